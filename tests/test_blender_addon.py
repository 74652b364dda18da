"""The Blender extension, headless: built into a zip, installed into a temporary user repository
and enabled as Blender does it, then driven by one worker process.

The worker is this file run as a script (a pytest process imports bpy once, and
BLENDER_USER_RESOURCES must be set before that). It performs every Blender-side step, saving what
it exported, rendered and read back through Blender's own API into a work folder plus results.json.
The tests below judge those outputs against references computed here without Blender: the source
files read by splatwright.io, float64 covariances and SH colours, Blender's own camera projection
(world_to_camera_view) and the core renderer.
"""

import warnings

import numpy as np
import pytest
from blender_session import MODULE, blender_fixture
from helpers import check_transformed, format_errors, read
from workers.addon import (
    ANIM_OFFSET,
    DEFAULT_AXES,
    EXACT,
    FORMAT_CLOUD,
    LOG_SCALE,
    MENUS,
    NATIVE_BASE,
    NATIVE_ROTATION,
    NATIVE_SCALE,
    NATIVE_SH,
    OPACITY,
    RENDER_CASES,
    ROTATION,
    SH,
    WORLD_COLOR,
)

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version: ~5-15 s


def _native(blender):
    """Whether new splat objects are Blender's own Gaussian-splat point clouds in this version (5.3 on)."""
    return blender.version_tuple >= (5, 3)


def _random_cloud(n, degree, seed, spread=1.0):
    from splatwright.core import SplatCloud

    rng = np.random.default_rng(seed)
    return SplatCloud(
        rng.normal(0, spread, (n, 3)),
        rng.normal(size=(n, 4)) * rng.uniform(0.5, 2, (n, 1)),
        rng.uniform(-4, -1.5, (n, 3)),
        rng.normal(0, 2, n),
        rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)),
    )


def _write_inputs(work):
    """Every file the worker reads, written with splatwright.io (the formats under test elsewhere)."""
    from splatwright.io import write_splats

    a = _random_cloud(300, 3, 0)
    a.extras["nx"] = np.linspace(-1, 1, 300, dtype=np.float32)  # kept: PLY normals that are not all zero
    a.extras["ny"] = np.zeros(300, np.float32)
    a.extras["nz"] = np.ones(300, np.float32)
    a.extras["segment"] = (np.arange(300) % 7).astype(np.uint8)
    write_splats(work / "a.ply", a)
    write_splats(work / "b.ply", _random_cloud(120, 1, 1))
    fmt = _random_cloud(*FORMAT_CLOUD)
    for name in ("fmt.usda", "fmt.spz", "fmt.splat"):
        write_splats(work / name, fmt)
    scene = _random_cloud(250, 3, 3, spread=0.5)
    scene.log_scales[:] = np.random.default_rng(4).uniform(-3.2, -1.8, scene.log_scales.shape)
    scene.opacity_logits[:] = np.random.default_rng(5).normal(1.0, 1.5, len(scene))
    write_splats(work / "scene.ply", scene)
    write_splats(work / "scene_aa.ply", scene.replace(antialiased=True))
    np.save(work / "scene_positions.npy", scene.positions.astype(np.float64))
    (work / "garbage.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n" + bytes(200))
    full = (work / "a.ply").read_bytes()
    (work / "truncated.ply").write_bytes(full[: len(full) // 2])
    (work / "wrong_ext.xyz").write_bytes(b"1 2 3\n")
    (work / "not_3dgs.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n0 0 0\n"
    )
    bad = _random_cloud(50, 0, 6)
    bad.positions[3, 1] = np.nan
    bad.opacity_logits[7] = np.inf
    write_splats(work / "nan.ply", bad, nonfinite="keep")


def _write_inputs_quietly(work):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _write_inputs(work)


blender = blender_fixture("workers.addon", _write_inputs_quietly)


# install, import, export -------------------------------------------------------------------------


def test_install_enables_operators_engine_and_menus(blender):
    res = blender.step("install")
    assert MODULE in res["addons"]
    assert res["operators"] == [True, True]
    assert res["engine"]
    assert res["menus"] == MENUS


def test_import_ply_stores_documented_attributes_upright(blender):
    res = blender.step("import_ply")
    source = read(blender.work / "a.ply")
    d = np.load(blender.out / "import_a.npz")
    assert res["count"] == len(source)
    np.testing.assert_array_equal(d["position"], source.positions)
    if _native(blender):
        # Blender's own splats, drawn by Blender: linear scales, DC + activated opacity, SH rest by index
        assert res["type"] == "POINTCLOUD" and res["marker"] == "GAUSSIAN_SPLAT" and res["modifiers"] == []
        np.testing.assert_array_equal(d[NATIVE_ROTATION], source.rotations)
        np.testing.assert_allclose(d[NATIVE_SCALE], np.exp(source.log_scales.astype(np.float64)), rtol=2.5e-7)
        np.testing.assert_array_equal(d[NATIVE_BASE][:, :3], source.sh[:, 0])
        np.testing.assert_allclose(
            d[NATIVE_BASE][:, 3], 1 / (1 + np.exp(-source.opacity_logits.astype(np.float64))), rtol=2.5e-7, atol=1e-12
        )
        np.testing.assert_array_equal(d[EXACT[0]], source.log_scales)  # kept exactly beside them
        np.testing.assert_array_equal(d[EXACT[1]][:, 0], source.opacity_logits)
        for k in range(1, 16):
            np.testing.assert_array_equal(d[f"{NATIVE_SH}{k - 1}"], source.sh[:, k])
        assert f"{NATIVE_SH}15" not in d and not any(name.startswith("splat_") and "extra" not in name for name in d)
    else:
        assert res["type"] == "MESH" and res["marker"] is True
        assert res["modifiers"] == ["Splatwright Display"]
        np.testing.assert_array_equal(d[ROTATION], source.rotations)
        np.testing.assert_array_equal(d[LOG_SCALE], source.log_scales)
        np.testing.assert_array_equal(d[OPACITY][:, 0], source.opacity_logits)
        for k in range(16):
            np.testing.assert_array_equal(d[f"{SH}{k}"], source.sh[:, k])
        assert f"{SH}16" not in d
    np.testing.assert_array_equal(d["splat_extra_nx"][:, 0], source.extras["nx"])
    np.testing.assert_array_equal(d["splat_extra_segment"][:, 0], source.extras["segment"])
    # upright: the file's -Y (up in a COLMAP capture) is Blender's +Z, its +Z (forward) is Blender's +Y
    np.testing.assert_allclose(d["matrix_world"], DEFAULT_AXES, atol=1e-7)
    np.testing.assert_allclose(res["identity_matrix"], np.eye(4), atol=0)
    assert res["selected"] == [res["active"]]


def test_import_of_several_files_at_once(blender):
    res = blender.step("import_ply")
    assert res["multi"] == [120, 300] and res["multi_selected"] == 2


def test_import_while_another_object_is_in_edit_mode(blender):
    res = blender.step("import_ply")["in_edit_mode"]
    assert res == {"result": ["FINISHED"], "error": None, "count": 120}


def test_ply_import_export_is_lossless(blender):
    assert blender.step("import_ply")["export"]["error"] is None
    assert (blender.out / "a_roundtrip.ply").read_bytes() == (blender.work / "a.ply").read_bytes()


@pytest.mark.parametrize("name", ["fmt.usda", "fmt.spz", "fmt.splat"])
def test_each_format_imports_and_exports(blender, name):
    res = blender.step("formats")
    assert res[name]["export"]["error"] is None
    source, back = read(blender.work / name), read(blender.out / ("re_" + name))
    assert res[name]["count"] == len(source) == len(back)
    # Every reader hands the core its 3DGS axes (the USD reader turns Y-up stages into them), so one
    # default stands every format upright.
    np.testing.assert_allclose(res[name]["matrix_world"], DEFAULT_AXES, atol=1e-7)
    # Blender writes back what it read: re-encoding the decoded splats may lose no more than the
    # first encoding of the original cloud did (zero for lossless formats)
    first = format_errors(read(blender.work / name), _random_cloud(*FORMAT_CLOUD))
    second = format_errors(back, source)
    for key, value in second.items():
        assert value <= max(2 * first[key], 1e-6), (key, value, first[key])


def test_openusd_written_in_blender_reads_in_usd_core_as_the_schema(blender):
    """The extension authors through Blender's bundled pxr, whose UsdVol lacks the splat schema class,
    or, in a Blender without pxr (4.2), as a text layer of its own; usd-core (this process) must see
    a ParticleField3DGaussianSplat with the values written either way."""
    from pxr import Usd, UsdVol

    res = blender.step("formats")
    assert res["fmt.usda"]["export"]["error"] is None
    stage = Usd.Stage.Open(str(blender.out / "re_fmt.usda"))
    prims = [p for p in stage.Traverse() if p.GetTypeName() == "ParticleField3DGaussianSplat"]
    assert len(prims) == 1
    field = UsdVol.ParticleField3DGaussianSplat(prims[0])
    assert field and len(field.GetPositionsAttr().Get()) == FORMAT_CLOUD[0]
    assert field.GetRadianceSphericalHarmonicsDegreeAttr().Get() == FORMAT_CLOUD[1]


def test_export_axes_are_the_inverse_convention(blender):
    res = blender.step("export_axes")
    assert res["export"]["error"] is None
    source, result = read(blender.work / "a.ply"), read(blender.out / "a_blender_axes.ply")
    # exporting with forward Y / up Z writes Blender's own coordinates: the default import matrix applied
    check_transformed(source, result, DEFAULT_AXES, sh_rotation=DEFAULT_AXES[:3, :3])


def test_export_reflects_deleted_vertices_and_object_transform(blender):
    res = blender.step("edits")
    assert res["export"]["error"] is None and res["export_stretched"]["error"] is None
    source = read(blender.work / "a.ply")
    edited = read(blender.out / "edited.ply")
    kept = np.array(res["kept"])
    assert len(edited) == len(kept)
    total = np.linalg.inv(DEFAULT_AXES) @ np.array(res["matrix_world"])
    rotation = total[:3, :3] / 1.5
    check_transformed(source[kept], edited, total, sh_rotation=rotation)
    np.testing.assert_array_equal(edited.extras["segment"], source.extras["segment"][kept])
    stretched = read(blender.out / "stretched.ply")
    total = np.linalg.inv(DEFAULT_AXES) @ np.array(res["stretched_matrix_world"])
    check_transformed(source, stretched, total)


def test_apply_splat_transform_bakes_the_object_transform(blender):
    res = blender.step("edits")
    assert res["apply"]["error"] is None and res["export_applied"]["error"] is None
    np.testing.assert_allclose(res["applied_matrix"], np.eye(4), atol=0)
    edited, applied = read(blender.out / "edited.ply"), read(blender.out / "applied.ply")
    # baked once into the data, then exported through the default axes: the same splats
    kept = np.array(res["kept"])
    total = np.linalg.inv(DEFAULT_AXES) @ np.array(res["matrix_world"])
    check_transformed(read(blender.work / "a.ply")[kept], applied, total, sh_rotation=total[:3, :3] / 1.5)
    np.testing.assert_allclose(applied.positions, edited.positions, atol=1e-5)


def test_export_of_joined_objects(blender):
    res = blender.step("join")
    assert res["export"]["error"] is None
    assert len(res["objects"]) == 2  # the Cube and the joined splat object
    a, b = read(blender.work / "a.ply"), read(blender.out / "joined.ply")
    b_src = read(blender.work / "b.ply")
    assert len(b) == len(a) + len(b_src)
    head, tail = b[: len(a)], b[len(a) :]
    for name in ("positions", "rotations", "log_scales", "opacity_logits"):
        np.testing.assert_array_equal(getattr(head, name), getattr(a, name))
    np.testing.assert_array_equal(head.sh, a.sh)
    # b moved by (1, 2, 3) in Blender: in file axes that is (1, -3, 2)
    np.testing.assert_allclose(tail.positions, b_src.positions + [1.0, -3.0, 2.0], atol=1e-6)
    np.testing.assert_array_equal(tail.rotations, b_src.rotations)
    np.testing.assert_array_equal(tail.sh[:, :4], b_src.sh)  # degree 1 joined into degree 3:
    assert not tail.sh[:, 4:].any()  # zero-padded, same colours


def test_join_splats_keeps_every_splat_in_world_space(blender):
    res = blender.step("join")
    assert res["join_splats"]["error"] is None and res["export_splats"]["error"] is None
    assert len(res["splat_objects"]) == 1
    a, b = read(blender.work / "a.ply"), read(blender.work / "b.ply")
    joined = read(blender.out / "joined_splats.ply")
    to_file = np.linalg.inv(DEFAULT_AXES)
    # Independent reference: each source transformed on its own by its world matrix.
    for part, src, world in ((joined[: len(a)], a, res["world_a"]), (joined[len(a) :], b, res["world_b"])):
        total = to_file @ np.array(world)
        u, _, vt = np.linalg.svd(total[:3, :3])  # SH turn with the polar rotation U V^T
        check_transformed(src, part, total, sh_rotation=u @ vt)


def test_export_selected_visible_and_all(blender):
    res = blender.step("selected_only")
    a, b = read(blender.work / "a.ply"), read(blender.work / "b.ply")
    assert all(res[k]["error"] is None for k in ("selected", "visible", "all"))
    assert len(read(blender.out / "selected.ply")) == len(b)
    assert len(read(blender.out / "visible.ply")) == len(b)
    assert len(read(blender.out / "all.ply")) == len(a) + len(b)


# errors --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, words",
    [
        ("garbage.ply", ["garbage.ply", "truncated"]),
        ("truncated.ply", ["truncated.ply", "truncated"]),
        ("wrong_ext.xyz", ["wrong_ext.xyz", ".xyz"]),
        ("missing.ply", ["missing.ply", "no such file"]),
        ("nan.ply", ["nan.ply", "non-finite"]),
        ("not_3dgs.ply", ["not_3dgs.ply", "f_dc_0"]),
        ("good and bad together", ["truncated.ply", "truncated"]),
    ],
)
def test_bad_files_report_and_leave_scene_unchanged(blender, name, words):
    case = blender.step("bad_inputs")[name]
    assert case["result"] == ["CANCELLED"]
    for word in words:
        assert word.lower() in case["error"].lower(), case["error"]
    assert case["unchanged"]


def test_non_finite_splats_are_dropped_by_default(blender):
    case = blender.step("bad_inputs")["nan.ply dropped"]
    assert case == {"count": 48, "added": 1}


@pytest.mark.parametrize(
    "name, words",
    [
        ("non-splat selection", ["no splat objects selected", "'Cube' (MESH)"]),
        ("empty selection", ["nothing is selected"]),
        ("missing attribute", ["no '{rotation}' point attribute"]),  # the form's rotation attribute
        ("unknown extension", ["never4.xyz", "unknown splat file extension"]),
    ],
)
def test_wrong_objects_report_and_write_nothing(blender, name, words):
    res = blender.step("wrong_objects")
    rotation = NATIVE_ROTATION if _native(blender) else ROTATION
    words = [word.format(rotation=rotation) for word in words]
    assert res[name]["result"] == ["CANCELLED"]
    for word in words:
        assert word in res[name]["error"], res[name]["error"]
    assert res["written"] == []


# viewport display ------------------------------------------------------------------------------------


def test_viewport_display_points_sized_by_scale(blender):
    res = blender.step("display")
    source = read(blender.work / "a.ply")
    size = np.load(blender.out / "display_size.npy")
    if _native(blender):
        # Blender draws its own Gaussian splats: every splat, sized by its scales; no display of ours
        assert res["pointclouds"] == 1 and res["type"] == "GAUSSIAN_SPLAT" and res["count"] == len(source)
        assert res["modifiers"] == [] and not res["added"] and "Splatwright Splat" not in res["material"]
        np.testing.assert_allclose(size, source.scales, rtol=1e-5)
        return
    assert res["pointclouds"] == 1 and res["material"] == ["Splatwright Splat"]
    assert res["modifiers"] == ["Splatwright Display"] and res["added"]
    assert res["show_render"] is False
    visible = source.opacities > 0.05
    assert res["count"] == int(visible.sum())
    n, half = int(visible.sum()), res["half_count"][0]
    assert abs(half - n / 2) < 4 * np.sqrt(n / 4)  # Display Ratio 0.5 keeps about half
    np.testing.assert_allclose(np.sort(size[:, 0]), np.sort(source.scales.max(axis=1)[visible]), rtol=1e-5)


# render engine -----------------------------------------------------------------------------------------


def _core_camera(rec):
    from splatwright.core.camera import Camera

    x, y, pct = rec["resolution"]
    w, h = x * pct // 100, y * pct // 100
    lens = {
        k: rec[k]
        for k in (
            "lens",
            "sensor_width",
            "sensor_height",
            "sensor_fit",
            "shift_x",
            "shift_y",
            "type",
            "ortho_scale",
            "pixel_aspect_x",
            "pixel_aspect_y",
        )
    }
    return Camera.from_blender(
        np.array(rec["matrix_world"]), w, h, clip_start=rec["clip_start"], clip_end=rec["clip_end"], **lens
    )


def _core_image(cloud, rec, transparent):
    from splatwright.core.color import linear_to_srgb
    from splatwright.core.render import render

    background = None if transparent else linear_to_srgb(np.array(WORLD_COLOR))
    return render(cloud, _core_camera(rec), background=background)


def _png(path):
    from PIL import Image

    return np.asarray(Image.open(path), dtype=np.float64) / 255.0


@pytest.mark.parametrize("case", list(RENDER_CASES))
def test_camera_matches_blender_projection(blender, case):
    rec = blender.step("render")[case]
    cam = _core_camera(rec)
    points = np.load(blender.work / "scene_positions.npy")
    pixels, depth = cam.project(points)
    u, v, z = np.array(rec["projection"]).T
    np.testing.assert_allclose(pixels[:, 0], u * cam.width, atol=1e-3)
    np.testing.assert_allclose(pixels[:, 1], (1 - v) * cam.height, atol=1e-3)
    np.testing.assert_allclose(depth, z, atol=1e-4)


@pytest.mark.parametrize("case", list(RENDER_CASES))
def test_render_png_matches_core_renderer(blender, case):
    rec = blender.step("render")[case]
    transparent = RENDER_CASES[case]["transparent"]
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent)
    png = _png(blender.out / f"render_{case}.png")
    assert png.shape == (*image.color.shape[:2], 4 if transparent else 3)
    assert image.alpha.max() > 0.5 and image.alpha.min() < 0.5  # the cloud is in frame, not filling it
    if transparent:
        np.testing.assert_allclose(png[..., 3], image.alpha, atol=1 / 255)
        seen = image.alpha > 0.05  # straight colour is defined where there is alpha
        straight = np.clip(image.color / np.maximum(image.alpha, 1e-12)[..., None], 0, 1)
        assert np.abs(png[..., :3][seen] - straight[seen]).max() <= 1 / 255
    else:
        assert np.abs(png - np.clip(image.color, 0, 1)).max() <= 1 / 255  # 8 bits hold 0..1


@pytest.mark.parametrize("case", list(RENDER_CASES))
def test_render_exr_is_scene_linear_with_depth(blender, case):
    import OpenEXR

    from splatwright.core.color import srgb_to_linear

    rec = blender.step("render")[case]
    transparent = RENDER_CASES[case]["transparent"]
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent)
    with OpenEXR.File(str(blender.out / f"render_{case}.exr")) as exr:
        channels = {name: ch.pixels for part in exr.parts for name, ch in part.channels.items()}
    rgba = channels["ViewLayer.Combined"]
    alpha = image.alpha if transparent else np.ones_like(image.alpha)
    straight = np.where(alpha[..., None] > 0, image.color / np.maximum(alpha, 1e-12)[..., None], 0)
    # float32 rounding only (the engine renders in a camera-centred frame, the reference in the world's)
    np.testing.assert_allclose(rgba[..., :3], srgb_to_linear(straight) * alpha[..., None], atol=2e-5)
    np.testing.assert_allclose(rgba[..., 3], alpha, atol=1e-6)
    depth = channels["ViewLayer.Depth.Z"]
    hit = np.isfinite(image.depth) & (image.alpha > 0)
    np.testing.assert_allclose(depth[hit], image.depth[hit], rtol=1e-5)
    assert (depth[~hit] == 1e10).all()


def test_view_transform_is_applied_to_the_linear_result(blender):
    blender.step("render")
    standard, agx = _png(blender.out / "render_persp.png"), _png(blender.out / "render_persp_agx.png")
    assert np.abs(standard - agx).max() > 0.05  # AgX tone-maps; the exact match needs Standard


def test_splats_made_for_antialiased_rendering_render_and_export_so(blender):
    from splatwright.core import SplatCloud
    from splatwright.io import spz

    res = blender.step("render_antialiased")
    made = read(blender.work / "scene_aa.ply")
    assert made.antialiased and res["marked"] and not res["export"]["error"]
    image = _core_image(made, res["alone"], transparent=False)  # its own mode by default
    classic = _core_image(made.replace(antialiased=False), res["alone"], transparent=False)
    png = _png(blender.out / "render_aa.png")
    assert np.abs(png - np.clip(image.color, 0, 1)).max() <= 1 / 255
    assert np.abs(png - np.clip(classic.color, 0, 1)).max() > 4 / 255  # the modes differ here
    assert spz.read(blender.out / "aa.spz").antialiased
    assert not res["export_usd"]["error"] and read(blender.out / "aa.usd").antialiased
    both = SplatCloud.concatenate([made.replace(antialiased=False), read(blender.work / "b.ply")])
    mixed = _core_image(both, res["mixed"], transparent=False)
    assert np.abs(_png(blender.out / "render_aa_mixed.png") - np.clip(mixed.color, 0, 1)).max() <= 1 / 255
    assert not res["mixed_export"]["error"] and not spz.read(blender.out / "mixed.spz").antialiased
    assert "made for classic rendering" in res["join"]["error"] and res["join"]["result"] == ["CANCELLED"]
    assert len(res["after_join"]) == 2  # nothing joined, nothing lost


def test_render_near_clip_removes_splats(blender):
    rec = blender.step("render")["persp_vertical"]
    cloud = read(blender.work / "scene.ply")
    cam = _core_camera(rec)
    _, depth = cam.project(cloud.positions)
    assert 0 < (depth <= rec["clip_start"]).sum() < len(cloud)  # the case clips part of the cloud


def test_render_far_from_origin_keeps_precision(blender):
    rec = dict(blender.step("render_edges")["far"])
    # the same picture as the cloud at the origin seen from the same relative camera position
    camera = np.array(rec["matrix_world"])
    camera[:3, 3] -= np.array(rec["object_matrix"])[:3, 3]
    rec["matrix_world"] = camera.tolist()
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    assert image.alpha.max() > 0.5
    assert np.abs(_png(blender.out / "edge_far.png") - np.clip(image.color, 0, 1)).max() <= 1 / 255


def test_render_with_non_square_pixels(blender):
    rec = blender.step("render_edges")["aspect"]
    cam = _core_camera(rec)
    pixels, _ = cam.project(np.load(blender.work / "scene_positions.npy"))
    u, v, _ = np.array(rec["projection"]).T
    np.testing.assert_allclose(pixels, np.stack([u * cam.width, (1 - v) * cam.height], axis=1), atol=1e-3)
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    assert np.abs(_png(blender.out / "edge_aspect.png") - np.clip(image.color, 0, 1)).max() <= 1 / 255


@pytest.mark.parametrize("name", ["wide", "narrow"])
def test_render_very_wide_and_very_narrow_lenses(blender, name):
    rec = blender.step("render_edges")[name]
    cam = _core_camera(rec)
    pixels, depth = cam.project(np.load(blender.work / "scene_positions.npy"))
    u, v, _ = np.array(rec["projection"]).T
    near = np.abs(pixels).max(axis=1) < 1e4  # beyond that, float32 in Blender's own math
    np.testing.assert_allclose(
        pixels[near], np.stack([u * cam.width, (1 - v) * cam.height], axis=1)[near], rtol=1e-5, atol=1e-3
    )
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    assert np.abs(_png(blender.out / f"edge_{name}.png") - np.clip(image.color, 0, 1)).max() <= 1 / 255


def test_render_one_pixel(blender):
    rec = blender.step("render_edges")["tiny"]
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    png = _png(blender.out / "edge_tiny.png")
    assert png.shape == (1, 1, 3)
    assert np.abs(png - np.clip(image.color, 0, 1)).max() <= 1 / 255


def test_hidden_splats_leave_the_world_colour(blender):
    from splatwright.core.color import linear_to_srgb

    blender.step("render_edges")
    png = _png(blender.out / "edge_hidden.png")
    assert np.abs(png - linear_to_srgb(np.array(WORLD_COLOR))).max() <= 1 / 255


def test_panoramic_camera_is_refused_clearly(blender):
    res = blender.step("render_edges")["panoramic"]
    assert "PANO" in res["error"] and "perspective and orthographic" in res["error"]


def test_animation_renders_each_frame(blender):
    res = blender.step("animation")
    assert res["frames"] == ["anim_0001.png", "anim_0002.png"]
    cloud = read(blender.work / "scene.ply")
    moved = cloud.replace(positions=cloud.positions + np.array(ANIM_OFFSET, np.float32))
    for frame, c in (("anim_0001.png", cloud), ("anim_0002.png", moved)):
        image = _core_image(c, res["camera"], transparent=False)
        assert np.abs(_png(blender.out / frame) - np.clip(image.color, 0, 1)).max() <= 1 / 255


# registration ------------------------------------------------------------------------------------------


def test_unregister_register_twice_leaves_nothing_behind(blender):
    res = blender.step("reregister")
    assert res["enabled"]["menus"] == MENUS
    assert res["enabled"]["operators"] and res["enabled"]["engine_panels"] > 10
    off = res["disabled"]
    assert off["menus"] == dict.fromkeys(MENUS, 0)
    assert off["engine_panels"] == 0 and off["types_left"] == []
    assert not off["engine"] and MODULE not in off["addons"]
    assert res["re_enabled_menus"] == MENUS
    # NumPy's huge-page advice is off while the extension is enabled, NumPy's default after it
    assert res["enabled"]["huge_pages"] is False and off["huge_pages"] is True
