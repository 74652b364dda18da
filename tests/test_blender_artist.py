"""The artist's tools, headless in every Blender of the version matrix: the Splats panel and the
extension's preferences, export options through the export operators and the `splatwright` command
(each file read back here by splatwright.io and, for OpenUSD, by OpenUSD itself), the modal jobs of
Check Collisions and Mesh to Splats stepped and cancelled (the scene as it was), and rigid-bone
detection on pose matrices of a real armature against a float64 reference.
"""

import gzip
import struct
import warnings

import numpy as np
import pytest
from blender_session import MODULE, blender_fixture
from helpers import covariances, random_cloud
from workers.artist import CHAIN, OPTIONS_CLOUD, PANEL_CLOUD, POSES, PREFERRED, SCALED_BONE

from splatwright.core.skinning import RIGID_TOLERANCE, Binding, BonePose, skin
from splatwright.io import read_splats

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version

blender = blender_fixture("workers.artist")
EPS32 = float(np.finfo(np.float32).eps)


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_splats(path)


def _source(count, degree, seed):
    """The cloud the worker imported (its random_cloud) as the default axes leave it in a file."""
    return random_cloud(count, degree, seed)


def spz_header(path):
    """(version, count, SH degree, bytes of data before compression) of an SPZ file."""
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        payload = gzip.decompress(raw)
        _, version, count, degree = struct.unpack("<IIIB", payload[:13])
        return version, count, degree, len(payload)
    _, version, count, degree, _, _, streams, toc = struct.unpack("<IIIBBBBI", raw[:20])
    sizes = [struct.unpack("<QQ", raw[toc + 16 * i : toc + 16 * i + 16])[1] for i in range(streams)]
    return version, count, degree, sum(sizes)


def usd_types(path):
    """{attribute name: type name} of the splat prim, as OpenUSD itself reads the file."""
    Usd = pytest.importorskip("pxr.Usd")
    stage = Usd.Stage.Open(str(path))
    prim = next(p for p in stage.Traverse() if p.GetTypeName() == "ParticleField3DGaussianSplat")
    return {a.GetName(): str(a.GetTypeName()) for a in prim.GetAttributes() if a.IsAuthored()}


# panel and preferences -------------------------------------------------------------------------------


def test_panels_and_preferences_are_registered(blender):
    res = blender.step("install")
    assert res["panels"] == [True, True]
    assert res["panel_spaces"] == [["PROPERTIES", "WINDOW", "", "object"], ["VIEW_3D", "UI", "Splats", ""]]
    assert res["preferences_idname"] == MODULE  # Blender finds an extension's preferences by package
    assert res["defaults"] == {"export_format": "ply", "sh_degree": "KEEP", "spz_version": "3", "use_half": False}


def test_panel_polls_only_for_splat_objects(blender):
    polls = blender.step("install")["polls"]
    assert polls["Cube"] == [False, False]
    assert polls["Camera"] == [False, False]
    assert polls["poll"] == [True, True]
    if blender.version_tuple >= (4, 5):  # Blender's own splat point clouds
        assert polls["native"] == [True, True]
        assert polls["native_stats"] == [30, 2, 4 * 30 * (3 + 4 + 3 + 1 + 3 * 9)]


def test_panel_draws_the_numbers_display_settings_and_existing_operators(blender):
    res = blender.step("panel_draw")
    labels = res["labels"]
    form = "Blender point cloud" if blender.version_tuple >= (5, 3) else "splat mesh"  # what import makes
    assert labels[0] == f"123 splats, SH degree 1 ({form})"
    assert labels[1] == f"Memory: {4 * 123 * (3 + 4 + 3 + 1 + 12) / 1024:.1f} KiB"
    assert res["marked_labels"] == labels[:1] + ["Made for antialiased rendering"] + labels[1:]
    from splatwright.io import ply

    assert f"    PLY: {ply.file_size(123, 1) / 1024:.1f} KiB" in labels
    assert f"    .splat: {123 * 32 / 1024:.1f} KiB" in labels
    props = [c for c in res["checks"] if c[0] == "prop"]
    # the display modifier's settings: a splat mesh has them; Blender draws native splats itself
    assert [c[1] for c in props] == (
        [] if form == "Blender point cloud" else ["Radius Scale", "Min Opacity", "Display Ratio"]
    ) + ["Relight"]
    assert all(ok for _, _, ok in res["checks"]), res["checks"]
    operators = {c[1] for c in res["checks"] if c[0] != "prop"}
    assert operators == {
        "splat.export_file",
        "splat.export_animation",
        "splat.apply_transform",
        "splat.join",
        "splat.convert_form",
        "splat.bind_armature",
        "splat.check_collisions",
        "splat.bind_proxy",
        "splat.crop",
        "splat.prune",
        "splat.grade",
        "splat.reduce_sh",
        "splat.clear_cleanup",
        "splat.estimate_normals",
    }
    assert "Clean-up: none" in labels
    material = labels[labels.index("Material") :][:5]
    assert material == [
        "Material",
        "    Albedo: none",
        "    Normals: none",
        "    Roughness: default 0.5",
        "    Metallic: default 0",
    ]


def test_panel_numbers_are_the_written_files(blender):
    res = blender.step("panel_numbers")
    count, degree, _ = PANEL_CLOUD
    out = blender.out
    for stats in res["stats"].values():
        assert stats["count"] == count and stats["sh_degree"] == degree
        source = _source(*PANEL_CLOUD)
        assert stats["memory"] == sum(
            getattr(source, f).nbytes for f in ("positions", "rotations", "log_scales", "opacity_logits", "sh")
        )
    assert all(r["error"] is None for r in res["exports"].values()), res["exports"]
    sizes = res["stats"]["3_False"]["sizes"]
    assert sizes["ply"] == (out / "size.ply").stat().st_size
    assert sizes["splat"] == (out / "size.splat").stat().st_size
    for version in (2, 3, 4):
        path = out / f"size_v{version}.spz"
        written_version, written_count, written_degree, data = spz_header(path)
        assert (written_version, written_count, written_degree) == (version, count, degree)
        assert res["stats"][f"{version}_False"]["sizes"]["spz"] == data  # the data the file compresses
        assert path.stat().st_size < data
    if res["pxr"]:  # crate files: the arrays plus ~1.4 kB of structure
        for name, half in (("size.usdc", False), ("size_half.usdc", True)):
            data = res["stats"][f"3_{half}"]["sizes"]["usd"]
            assert 0 <= (out / name).stat().st_size - data <= 2048, name
    assert res["stats"]["3_True"]["sizes"]["usd"] < 0.6 * res["stats"]["3_False"]["sizes"]["usd"]


# export options ------------------------------------------------------------------------------------------


def test_export_options_through_the_operator(blender):
    res = blender.step("export_options")
    assert all(r["error"] is None for r in res.values()), res
    out, source = blender.out, _source(*OPTIONS_CLOUD)
    full = _read(out / "keep.ply")
    assert len(full) == len(source) and full.sh_degree == 3
    np.testing.assert_array_equal(full.sh, source.sh)  # default axes: the file comes back as it was
    reduced = _read(out / "degree1.ply")
    assert reduced.sh_degree == 1
    np.testing.assert_array_equal(reduced.sh, source.sh[:, :4])
    np.testing.assert_array_equal(reduced.positions, source.positions)
    assert spz_header(out / "degree0.spz")[:3] == (4, len(source), 0)
    assert spz_header(out / "v2.spz")[:3] == (2, len(source), 3)
    assert spz_header(out / "v4.spz")[:3] == (4, len(source), 3)
    kept = source.opacities >= 0.6
    pruned = _read(out / "pruned.ply")
    assert 0 < len(pruned) == kept.sum() < len(source)
    np.testing.assert_array_equal(pruned.positions, source.positions[kept])
    ignored = _read(out / "ignored.ply")  # SPZ version and half floats do not apply to PLY
    assert len(ignored) == kept.sum() and ignored.sh_degree == 1


def test_half_floats_for_openusd(blender):
    blender.step("export_options")
    out, source = blender.out, _source(*OPTIONS_CLOUD)
    half, full = usd_types(out / "half.usda"), usd_types(out / "full.usda")
    assert half["orientationsh"] == "quath[]" and half["opacitiesh"] == "half[]" and "orientations" not in half
    assert full["orientations"] == "quatf[]" and "orientationsh" not in full
    back = _read(out / "half.usda")
    assert len(back) == len(source)
    np.testing.assert_allclose(back.opacities, source.opacities, atol=1e-3)
    assert not np.array_equal(back.opacities, _read(out / "full.usda").opacities)


def test_animation_export_options(blender):
    res = blender.step("animation_options")
    assert res["seq"]["error"] is None and res["usd"]["error"] is None
    assert res["frame"] == 2
    source = _source(*OPTIONS_CLOUD)
    kept = int((source.opacities >= 0.6).sum())
    for frame in (1, 2, 3):
        assert spz_header(blender.out / f"anim_{frame:04d}.spz")[:3] == (4, kept, 1)
    types = usd_types(blender.out / "anim.usda")
    assert types["scalesh"] == "half3[]"
    from splatwright.io import usd

    frames = usd.read_frames(blender.out / "anim.usda")
    assert [t for t, _ in frames] == [1.0, 2.0, 3.0]
    assert all(c.sh_degree == 0 and len(c) == len(source) for _, c in frames)


def test_export_options_through_the_command(blender):
    """Files per frame for every format but OpenUSD: name_0001.ext (see animation.frame_path)."""
    res = blender.step("command_options")
    out, source = blender.out, _source(*OPTIONS_CLOUD)
    assert res["cmd_wrong.ply"] == 1 and res["cmd_wrong_half.spz"] == 1 and res["cmd_bad_prune.ply"] == 1
    assert not any(
        (out / n).exists() for n in ("cmd_wrong_0001.ply", "cmd_wrong_half_0001.spz", "cmd_bad_prune_0001.ply")
    )
    assert res["cmd_degree1.ply"] == 0
    reduced = _read(out / "cmd_degree1_0001.ply")
    np.testing.assert_array_equal(reduced.sh, source.sh[:, :4])
    kept = int((source.opacities >= 0.6).sum())
    assert spz_header(out / "cmd_v2_0001.spz")[:3] == (2, kept, 3)
    assert spz_header(out / "cmd_v4_0001.spz")[:3] == (4, len(source), 0)
    types = usd_types(out / "cmd_half.usda")
    assert types["radiance:sphericalHarmonicsCoefficientsh"] == "half3[]"
    assert _read(out / "cmd_half.usda").sh_degree == 2


def test_unset_options_come_from_the_preferences(blender):
    res = blender.step("preferences_defaults")
    assert all(r["error"] is None for k, r in res.items() if k.startswith("op_"))
    assert res["cmd_spz"] == res["cmd_noext"] == res["cmd_override"] == 0
    out, source = blender.out, _source(*OPTIONS_CLOUD)
    assert spz_header(out / "prefs.spz")[:3] == (int(PREFERRED["spz_version"]), len(source), 2)
    assert _read(out / "prefs.ply").sh_degree == 2
    assert "orientationsh" in usd_types(out / "prefs.usda")
    assert _read(out / "prefs_override.ply").sh_degree == 3  # given explicitly: the operator's value
    assert spz_header(out / "prefs_cmd_0001.spz")[:3] == (2, len(source), 2)
    assert spz_header(out / "prefs_noext_0001.spz")[:3] == (2, len(source), 2)  # the preferred format's extension
    assert spz_header(out / "prefs_cmd3_0001.spz")[:3] == (3, len(source), 3)


# modal jobs ----------------------------------------------------------------------------------------------


def test_collision_job_cancelled_midway_leaves_the_scene_as_it_was(blender):
    res = blender.step("collide_job")
    assert res["stepped"] == [True, True, True, True]
    assert res["mid_frame"] == 4  # the job really moved through the frames
    assert res["after"] == res["before"]  # frame 5, objects, attributes, earlier contacts
    assert res["done"] == 9 and res["frame_end"] == 5


def test_collision_job_run_through_matches_the_direct_check_and_the_operator(blender):
    res = blender.step("collide_job")
    assert res["stepped_report"] == res["direct"]
    assert res["operator"]["error"] is None
    assert res["direct"]["contact_frames"] and len(res["direct"]["contact_frames"]) < 9
    contact = np.array(res["contact_a"])
    assert contact.max() > 0 and np.all(np.isin(np.round(contact * 9), np.arange(10)))


def test_mesh_to_splats_job_cancelled_midway_leaves_the_scene_as_it_was(blender):
    res = blender.step("from_mesh_job")
    assert res["steps"] == [True, True] and 0 < res["done"] < 1 and "dB" in res["label"]
    assert res["during"] == res["before"]  # the rest pose is back once the mesh is read
    assert res["after"] == res["before"]
    assert res["progress"] and res["progress"] == sorted(res["progress"]) and res["count"] > 0
    job = blender.npz("from_mesh_job")
    np.testing.assert_array_equal(job["stepped"], job["direct"])


# rigid bones at Blender's float32 precision --------------------------------------------------------------


@pytest.fixture(scope="module")
def armature(blender):
    res = blender.step("armature_matrices")
    arrays = blender.npz("armature")
    assert len(res["names"]) == CHAIN + 4 and arrays["poses"].shape == (POSES, CHAIN + 4, 4, 4)
    # Blender's matrices hold float32 values
    assert np.array_equal(arrays["poses"], arrays["poses"].astype(np.float32).astype(np.float64))
    return arrays["rest"], arrays["poses"]


def _stretch(deform):
    """The polar stretch of each deform matrix, by SVD in float64: max |S - I|."""
    u, s, vt = np.linalg.svd(deform[:, :3, :3])
    stretch = np.einsum("bji,bj,bjk->bik", vt, s, vt)
    return np.abs(stretch - np.eye(3)).max(axis=(1, 2)), stretch


def test_turned_bones_of_a_real_armature_are_rigid_and_a_scaled_one_is_not(armature):
    rest, poses = armature
    worst = 0.0
    for t, pose in enumerate(poses):
        bones = BonePose.from_blender(rest, pose)
        deviation, _ = _stretch(bones.deform)
        scaled = bones.derived["scales"]
        if t < len(poses) - 1:
            worst = max(worst, deviation.max())
            assert not scaled.any(), (
                f"pose {t}: bones {np.flatnonzero(scaled)} stretch {deviation.max() / EPS32:.1f} eps"
            )
        else:  # bone 3 scaled 1.001: it and the bones it carries
            assert scaled[SCALED_BONE]
            assert np.array_equal(scaled, deviation > 1e-4)
    assert 0 < worst < RIGID_TOLERANCE  # float32 rounding along a 12-bone chain


def _reference_covariances(cloud, binding, deform):
    """Float64 LBS covariances with every bone's exact stretch: R_polar(M) S_blend Sigma S_blend R^T."""
    _, stretch = _stretch(deform)
    w = binding.weights.astype(np.float64)
    w /= w.sum(axis=1, keepdims=True)
    blended = np.einsum("nk,nkij->nij", w, deform[binding.indices][:, :, :3, :3])
    s_blend = np.einsum("nk,nkij->nij", w, stretch[binding.indices])
    u, _, vt = np.linalg.svd(blended)
    m = (u @ vt) @ s_blend
    return m @ covariances(cloud.rotations, cloud.log_scales) @ np.swapaxes(m, 1, 2)


def test_skinning_with_blender_matrices_stays_within_float32_of_the_float64_reference(armature):
    rest, poses = armature
    cloud = random_cloud(3000, sh_degree=1, seed=9)
    rng = np.random.default_rng(10)
    bones = len(rest)
    binding = Binding.from_weights(
        np.stack([rng.choice(bones, 3, replace=False) for _ in range(len(cloud))]),
        rng.uniform(0.1, 1.0, (len(cloud), 3)),
    )
    for pose in poses[:-1:6]:
        bones_pose = BonePose.from_blender(rest, pose)
        deviation, _ = _stretch(bones_pose.deform)
        ours = skin(cloud, binding, bones_pose, "lbs")
        ref = _reference_covariances(cloud, binding, bones_pose.deform)
        mine = covariances(ours.rotations, ours.log_scales)
        rel = (np.abs(mine - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))).max()
        # dropping a stretch d changes a covariance by at most 2 d; the rest is float32 storage
        assert rel <= 2 * deviation.max() + 4 * EPS32, (rel / EPS32, deviation.max() / EPS32)
        assert rel < 1e-5
