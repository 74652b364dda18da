"""The Blender extension against wrong and bad input, headless, with the extension installed from its
zip as in test_blender_addon.py.

Every operator (import, export, apply transform, join, animated export, collisions, binding, mesh to
splats), the render engine and the `--command splatwright` handler meet broken splat objects (NaN
values, no splats, each attribute deleted, a wrong attribute type, a zero or NaN transform), objects
of the wrong type, bad paths and files, degenerate meshes, armatures and cameras. A refusal must
cancel with a message naming the problem and leave the scene (objects, meshes, transforms, every
attribute's bytes) and the disk as they were; what is accepted must give a correct, finite result,
judged against references outside the code under test (splat files read back, Blender's own
Armature modifier, a render of the same splats without the broken ones).
"""

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import random_cloud, read
from workers.bad_input import RENDER_SIZE, WRONG_KINDS, N

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version: ~3 s


def _native(blender):
    """Whether new splat objects are Blender's own Gaussian-splat point clouds in this version (5.3 on)."""
    return blender.version_tuple >= (5, 3)


def _type_name(blender):
    """How messages name the type of a splat object this version makes."""
    return "pointcloud" if _native(blender) else "mesh"


def _write_inputs(work):
    from splatwright.io import write_splats

    write_splats(work / "empty.ply", random_cloud(0, sh_degree=1))
    write_splats(work / "cloud.ply", random_cloud(N, sh_degree=1))
    full = (work / "cloud.ply").read_bytes()
    (work / "truncated.ply").write_bytes(full[: len(full) * 2 // 3])
    (work / "cloud.xyz").write_bytes(full)
    import struct

    cloud = random_cloud(N, sh_degree=1)
    write_splats(work / "damaged.usdc", cloud)  # written by usd-core's pxr, outside Blender
    crate = bytearray((work / "damaged.usdc").read_bytes())
    at = crate.find(cloud.positions.astype("<f4").tobytes()) - 8
    struct.pack_into("<Q", crate, at, 1 << 28)  # the positions' count: 3.2 GB to OpenUSD
    (work / "damaged.usdc").write_bytes(bytes(crate))
    for folder in ("folder.ply", "folder.blend", "read_only"):
        (work / folder).mkdir()
    (work / "read_only").chmod(0o555)


blender = blender_fixture("workers.bad_input", _write_inputs)


def assert_refused(case, *words):
    """Cancelled with an error holding `words`, the scene exactly as it was, the frame restored."""
    assert case["result"] == ["CANCELLED"], case
    assert case["error"] is not None and "Traceback" not in case["error"], case["error"]
    for word in words:
        assert word in case["error"], case["error"]
    assert case["unchanged"], case
    assert case["frame"] == 1


def test_every_operator_is_exercised(blender):
    """A new operator fails this until its bad input is tested: here, or (clean-up and proxy binding)
    in test_blender_artist_tools.py's refusal tests, or (Estimate Normals) in test_blender_normals.py."""
    assert blender.step("install")["operators"] == [
        "SPLAT_OT_apply_transform",
        "SPLAT_OT_bind_armature",
        "SPLAT_OT_bind_proxy",
        "SPLAT_OT_check_collisions",
        "SPLAT_OT_clear_cleanup",
        "SPLAT_OT_convert_form",
        "SPLAT_OT_crop",
        "SPLAT_OT_estimate_normals",
        "SPLAT_OT_export_animation",
        "SPLAT_OT_export_file",
        "SPLAT_OT_from_mesh",
        "SPLAT_OT_grade",
        "SPLAT_OT_import_file",
        "SPLAT_OT_join",
        "SPLAT_OT_prune",
        "SPLAT_OT_reduce_sh",
    ]


# broken splat objects --------------------------------------------------------------------------------

# defect -> what the refusal says, for a splat mesh and for a native cloud (see workers.bad_input.DEFECT_ATTRIBUTES)
MISSING = {
    "mesh": dict(
        no_rotation="no 'splat_rotation' point attribute",
        no_scale="no 'splat_log_scale' point attribute",
        no_opacity="no 'splat_opacity_logit' point attribute",
        no_first_sh="missing [0]",
        no_middle_sh="missing [2]",
        int_opacity="'splat_opacity_logit' is INT on POINT, expected FLOAT",
    ),
    "native": dict(
        no_rotation="no 'rotation' point attribute",
        no_scale="no 'scale' point attribute",
        no_opacity="no 'radiance:base' point attribute",
        no_first_sh="missing [0]",
        no_middle_sh="missing [1]",
        int_opacity="'radiance:base' is INT on POINT, expected FLOAT4",
    ),
}
READERS = (
    "export",
    "apply",
    "join_into_good",
    "join_good_into",
    "anim_ply",
    "anim_usd",
    "collide",
    "bind",
    "convert",
    "render",
)


@pytest.mark.parametrize("defect", sorted(MISSING["mesh"]))
@pytest.mark.parametrize("operation", READERS)
def test_missing_or_wrong_attributes_are_refused_by_name(blender, defect, operation):
    case = blender.step("defects")[f"{defect} {operation}"]
    assert_refused(case, f"'{defect}'", MISSING["native" if _native(blender) else "mesh"][defect])
    assert case["written"] == []


@pytest.mark.parametrize(
    "defect, words",
    [
        ("zero_scale", ["'zero_scale'", "singular"]),
        ("nan_location", ["'nan_location'", "NaN or Inf"]),
    ],
)
@pytest.mark.parametrize("operation", ["export", "apply", "join_into_good", "anim_ply", "anim_usd", "collide"])
def test_degenerate_transforms_are_refused_by_name(blender, defect, words, operation):
    case = blender.step("defects")[f"{defect} {operation}"]
    assert_refused(case, *words)
    assert case["written"] == []


@pytest.mark.parametrize(
    "defect, words",
    [("zero_scale", ["'zero_scale'", "zero scale"]), ("nan_location", ["'nan_location'", "NaN or Inf"])],
)
def test_joining_into_a_degenerate_transform_is_refused(blender, defect, words):
    assert_refused(blender.step("defects")[f"{defect} join_good_into"], *words)


def test_a_nan_transform_binds_and_renders_nothing(blender):
    d = blender.step("defects")
    assert_refused(d["nan_location bind"], "'nan_location'", f"{N} splat centres are NaN")
    assert_refused(d["nan_location render"], "'nan_location'", "NaN or Inf")
    assert d["nan_location render"]["written"] == []


def test_a_zero_scale_object_renders_as_nothing(blender):
    from splatwright.io.exr import read_exr

    case = blender.step("defects")["zero_scale render"]
    assert case["result"] == ["FINISHED"]
    alpha = read_exr(blender.out / "zero_scale_render.exr")["A"]
    assert alpha.shape == RENDER_SIZE[::-1] and np.all(alpha == 0)


@pytest.mark.parametrize(
    "operation, words",
    [
        (
            "export",
            [
                "nan_values_export.ply",
                "3 of 40 splats have non-finite values",
                "positions in 1",
                "opacity_logits in 1",
                "sh in 1",
            ],
        ),
        ("anim_ply", ["nan_values_anim_ply_0001.ply", "non-finite"]),
        ("anim_usd", ["nan_values_anim_usd.usd", "non-finite"]),
        ("collide", ["frame 1", "2 splats of 'nan_values'", "NaN"]),
        ("bind", ["'nan_values'", "1 splat centres are NaN"]),
    ],
)
def test_nan_values_never_reach_a_file_or_a_binding(blender, operation, words):
    case = blender.step("defects")[f"nan_values {operation}"]
    assert_refused(case, *words)
    assert case["written"] == []


def test_nan_splats_are_left_out_of_a_render(blender):
    from splatwright.io.exr import read_exr

    d = blender.step("defects")
    assert d["nan_values render"]["result"] == ["FINISHED"] and d["finite render"]["result"] == ["FINISHED"]
    image = read_exr(blender.out / "nan_values_render.exr")
    reference = read_exr(blender.out / "finite_render.exr")  # the 37 finite splats alone
    assert reference["A"].max() > 0.3  # the splats are in view
    for channel in "RGBA":
        assert np.isfinite(image[channel]).all()
        np.testing.assert_allclose(image[channel], reference[channel], rtol=0, atol=1e-6)


def test_an_empty_splat_object_is_a_valid_empty_cloud(blender):
    from splatwright.io.exr import read_exr

    d = blender.step("defects")
    for operation in ("export", "apply", "anim_ply", "anim_usd", "collide", "render"):
        assert d[f"empty {operation}"]["result"] == ["FINISHED"], (operation, d[f"empty {operation}"])
    assert len(read(blender.out / "empty_export.ply")) == 0
    assert [len(read(blender.out / f"empty_anim_ply_000{f}.ply")) for f in (1, 2)] == [0, 0]
    assert len(read(blender.out / "empty_anim_usd.usd")) == 0
    assert np.all(read_exr(blender.out / "empty_render.exr")["A"] == 0)
    joined = d["empty join_good_into"]
    assert joined["result"] == ["FINISHED"] and joined["count"] == N and "good" not in joined["objects"]
    assert_refused(d["empty join_into_good"], "nothing to join", "empty")
    assert_refused(d["empty bind"], "'empty' has no splats to bind")


# objects of the wrong type ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", WRONG_KINDS)
def test_wrong_objects_are_refused_or_hidden(blender, kind):
    d = blender.step("wrong_objects")
    name = {
        "camera": "'Camera' (CAMERA)",
        "empty_object": "'Empty' (EMPTY)",
        "curve": "'Curve' (CURVE)",
        "armature": "'NoBones' (ARMATURE)",
        "plain_mesh": "'Plain' (MESH)",
        "nothing": "nothing is selected",
    }[kind]
    assert_refused(d[f"{kind} export"], name)
    assert_refused(d[f"{kind} anim"], name)
    for op in ("apply", "join"):  # poll() hides them: no splat object is active
        assert_refused(d[f"{kind} {op}"], "poll() failed")
    if kind != "plain_mesh":
        assert_refused(d[f"{kind} from_mesh"], "nothing is selected" if kind == "nothing" else "no mesh objects")
    assert_refused(d[f"{kind} bind onto splats"], f"'good' is {_type_name(blender)}, not an armature")
    assert_refused(d[f"{kind} convert"], "no selected splat objects")
    assert d[f"{kind} written"] == []
    if kind == "nothing":
        assert_refused(d[f"{kind} bind"], "no splat objects to bind")
        assert_refused(d[f"{kind} join into splats"], "select the splat objects to join")
        return
    short = name.split(" (")[0]
    assert_refused(d[f"{kind} bind"], "no splat objects to bind", short)
    assert_refused(d[f"{kind} join into splats"], "not splat objects", short.strip("'"))
    assert_refused(d[f"{kind} collide"], short, "is not a splat object")


# files and paths -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, words",
    [
        ("import truncated.ply", ["truncated.ply"]),
        ("import missing.ply", ["missing.ply", "no such file"]),
        ("import cloud.xyz", ["cloud.xyz", "unknown splat file extension"]),
        ("import folder.ply", ["folder.ply"]),
        ("import damaged.usdc", ["damaged.usdc"]),
        ("import nothing", ["no file to import"]),
        ("export missing folder", ["nowhere", "x.ply"]),
        ("export a folder", ["folder.ply", "is a folder"]),
        ("export no extension", ["noext", "unknown splat file extension"]),
        ("export NaN over a file", ["precious.ply", "non-finite"]),
    ],
)
def test_bad_paths_and_files_are_refused(blender, name, words):
    assert_refused(blender.step("files")[name], *words)


def test_export_can_drop_invalid_splats(blender):
    """Asked to, export leaves out exactly the splats that hold NaN/Inf and says how many."""
    case = blender.step("files")["export NaN dropped"]
    assert case["result"] == ["FINISHED"], case
    source = random_cloud(N, sh_degree=1, seed=3)  # as Worker.defective("nan_values") made it
    finite = np.ones(N, bool)
    finite[[3, 5, 7]] = False  # the splats it gave NaN or Inf
    got = read(blender.out / "dropped.ply")
    np.testing.assert_array_equal(got.opacity_logits, source.opacity_logits[finite])
    np.testing.assert_array_equal(got.log_scales, source.log_scales[finite])


def test_a_failed_export_keeps_the_file_it_would_replace(blender):
    assert blender.step("files")["precious kept"] is True
    assert (blender.out / "precious.ply").read_bytes() == b"precious"


def test_an_empty_file_imports_as_an_empty_splat_object(blender):
    case = blender.step("files")["import empty.ply contents"]
    assert case["result"] == ["FINISHED"] and case["count"] == 0
    if _native(blender):
        assert {"position", "rotation", "scale", "radiance:base", "radiance:sh_0", "radiance:sh_2"} <= set(
            case["attributes"]
        )
    else:
        assert {
            "position",
            "splat_rotation",
            "splat_log_scale",
            "splat_opacity_logit",
            "splat_sh_0",
            "splat_sh_3",
        } <= set(case["attributes"])
    assert case["export"]["result"] == ["FINISHED"]
    header = (blender.out / "empty_again.ply").read_bytes().split(b"end_header")[0]
    assert b"element vertex 0" in header and b"f_rest_8" in header
    assert len(read(blender.out / "empty_again.ply")) == 0


def test_a_sequence_that_fails_at_a_frame_changes_no_file(blender):
    d = blender.step("animation_files")
    assert_refused(d["nan at frame 2"], "frame 2", "'moving'", "NaN or Inf")
    assert d["nan at frame 2 files"] == ["shot_0001.ply"]  # no new frame, no temporary file
    assert d["old frame kept"] is True
    assert_refused(d["nan at frame 2 usd"], "frame 2", "'moving'")
    assert_refused(d["folder in the way"], "shot_0002.ply", "folder")
    assert d["folder in the way files"] == ["shot_0001.ply", "shot_0002.ply"]
    assert (blender.out / "seq" / "shot_0001.ply").read_bytes() == b"old frame 1"


def test_binary_openusd_needs_blenders_pxr_and_says_so(blender):
    """Blender 4.2 bundles no OpenUSD module: .usd, .usda and .usdz are written as text layers there,
    and .usdc is refused by name; from 4.4 on Blender's own pxr writes it."""
    files = blender.step("files")
    case = files["export binary usd"]
    if files["has pxr"]:
        assert case["result"] == ["FINISHED"] and case["written"], case
        assert (blender.out / "binary.usdc").read_bytes().startswith(b"PXR-USDC")
    else:
        assert blender.version_tuple < (4, 4)
        assert_refused(case, "binary.usdc", "pxr", "write .usda, .usd or .usdz")
        assert not case["written"]


@pytest.mark.parametrize(
    "name",
    ["export ro.ply", "export ro.usd", "export ro.spz", "export ro.splat", "animation ro_####.ply", "animation ro.usd"],
)
def test_a_read_only_folder_is_refused(blender, name):
    assert_refused(blender.step("read_only")[name], blender.step("read_only")["folder"], "ermission denied")


@pytest.mark.parametrize(
    "name, words",
    [
        ("export", ["ermission denied"]),
        ("render", ["cannot save", "ro_0001.png"]),
        ("from-mesh", ["ro.ply", "ermission denied"]),
        ("from-mesh blend", ["ro.blend"]),
        ("collide json", ["ro.json", "ermission denied"]),
    ],
)
def test_cli_jobs_into_a_read_only_folder_fail_cleanly(blender, name, words):
    run = blender.step("read_only")[f"cli {name}"]
    assert run["code"] == 1 and run["new_objects"] == 0, run
    assert "Traceback" not in run["stderr"] and "internal error" not in run["stderr"]
    for word in words:
        assert word in run["stderr"], run["stderr"]
    assert blender.step("read_only")["written"] == []


# meshes, rigs, cameras -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, words",
    [
        ("no_vertices", ["'no_vertices' has no faces", "0 vertices"]),
        ("edges_only", ["'edges_only' has no faces"]),
        ("nan_faces", ["'nan_faces'", "no face with positive area"]),
    ],
)
def test_meshes_without_a_surface_are_refused(blender, name, words):
    assert_refused(blender.step("from_mesh")[name], *words)


@pytest.mark.parametrize("name", ["no bones", "no deforming bones"])
def test_armatures_without_deforming_bones_are_refused(blender, name):
    assert_refused(blender.step("rigs")[name], f"armature '{name}' has no deforming bones")


def test_source_groups_that_match_no_bone_fall_back_with_a_warning(blender):
    case = blender.step("rigs")["groups match no bone"]
    assert case["source"] == "bones"
    assert len(case["warnings"]) == 1 and "'Skin'" in case["warnings"][0] and "no vertex group" in case["warnings"][0]
    assert case["groups"] == ["Lower", "Upper"]


def test_groups_that_match_no_bone_stay_put_as_in_blender(blender):
    case = blender.step("rigs")["bones renamed"]
    assert case["result"] == ["FINISHED"]
    d = blender.npz("renamed")
    # Export follows what Blender shows: its own Armature modifier's result on a splat mesh (Blender
    # renamed the vertex groups with the bones), or the native splats as drawn, which keep their bind
    # pose (their splat_weight:<bone> attributes now match no bone)
    if _native(blender):
        np.testing.assert_allclose(d["blender_co"], d["rest_co"], atol=1e-6)
    expected = d["blender_co"].astype(np.float64) @ d["matrix_world"][:3, :3].T + d["matrix_world"][:3, 3]
    got = read(blender.out / "renamed.ply").positions
    np.testing.assert_allclose(got, expected, atol=1e-6)


@pytest.mark.parametrize(
    "name, words",
    [
        ("empty as camera", ["'Rig Empty' is empty, not a camera object"]),
        ("splats as camera", ["'splats' is {type}, not a camera object"]),  # a splat object's type
        ("zero scale camera", ["'Camera'", "zero scale"]),
        ("nan camera", ["'Camera'", "NaN or Inf"]),
    ],
)
def test_cameras_the_engine_cannot_use_are_refused(blender, name, words):
    case = blender.step("cameras")[name]
    words = [word.format(type=_type_name(blender)) for word in words]
    assert case["result"] == ["CANCELLED"] and not case["image"]
    assert "internal error" not in case["error"]
    for word in words:
        assert word in case["error"], case["error"]
        assert word in case["cli"]["stderr"], case["cli"]["stderr"]
    assert case["cli"]["code"] == 1


def test_refused_renders_write_no_image(blender):
    assert blender.step("cameras")["written"] == []


# the command -------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, words",
    [
        ("psnr nan", ["--target-psnr", "nan"]),
        ("psnr negative", ["--target-psnr", "-3"]),
        ("no splats", ["max_splats must be at least 1"]),
        ("ply is a folder", ["folder.ply"]),
        ("blend is a folder", ["folder.blend"]),
        ("sigma inf", ["sigma", "finite", "inf"]),
        ("min opacity nan", ["minimum opacity", "nan"]),
        ("min opacity 2", ["minimum opacity", "between 0 and 1"]),
        ("export nan location", ["'nan_location'", "NaN or Inf"]),
        ("collide nan location", ["'nan_location'", "NaN or Inf"]),
    ],
)
def test_cli_refuses_bad_values_and_leaves_no_objects(blender, name, words):
    run = blender.step("cli")[name]
    assert run["code"] == 1, run
    assert "Traceback" not in run["stderr"] and "internal error" not in run["stderr"]
    for word in words:
        assert word in run["stderr"], run["stderr"]
    assert run["new_objects"] == 0


def test_cli_refusals_write_nothing(blender):
    res = blender.step("cli")
    assert res["written"] == [] and res["folders"] == [True, True]
