"""Clean-up, grading and binding captured splats through a proxy mesh, headless in every Blender of
the version matrix (the worker is tests/workers/artist_tools.py). The edits are judged against the
unedited splats Blender shows, with independent references computed here: ray parity for the mesh
crop, the box's own inequality, the SH colour formula for grading, and, for the proxy binding, a
float64 brute-force nearest point, Blender's own posed proxy mesh, linear blend skinning by the
bone matrices Blender reports and, for the distance falloff, Blender's Armature modifier posing a
plain mesh of the same points with the same vertex groups and mask."""

import math

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import skip_platform
from test_cleanup import parity_inside
from test_proxy import ericson
from workers.artist_tools import FADE_SPAN, FALLOFF_START, FAR, GRADE, MAX_DISTANCE, NEAR, tube_mesh

from splatwright.core import cleanup
from splatwright.core.camera import Camera
from splatwright.core.economy import contributions
from splatwright.core.splats import SplatCloud

pytestmark = [pytest.mark.blender, pytest.mark.slow]

blender = blender_fixture("workers.artist_tools")


def test_operators_and_edit_hook_are_registered(blender):
    res = blender.step("install")
    assert all(res["operators"].values()), res["operators"]
    assert res["edits"] == ["apply_settings"]


# clean-up -------------------------------------------------------------------------------------------


def cleanup_result(blender, form):
    res = blender.step(f"cleanup_{form.lower()}")
    if res.get("skipped"):
        skip_platform(f"Blender {blender.version} makes no native splats from Python")
    return res, blender.npz(f"cleanup_{form}")


def rows(a):
    return {tuple(r) for r in np.round(np.asarray(a, np.float64), 5)}


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_crop_to_an_empty_box_keeps_the_splats_inside_it(blender, form):
    res, d = cleanup_result(blender, form)
    assert res["crop_box"]["result"] == ["FINISHED"]
    assert res["settings"] == {"crop": {"volume": "CropBox", "invert": False}}
    before = d["before_positions"].astype(np.float64)
    local = (before - d["box_matrix"][:3, 3]) @ np.linalg.inv(d["box_matrix"][:3, :3]).T
    inside = (np.abs(local) <= 1.0).all(axis=1)
    assert 20 < inside.sum() < len(before) - 20
    np.testing.assert_allclose(d["crop_box_positions"], before[inside], atol=1e-5)
    report = res["crop_box"]["report"]
    assert (report["splats_before"], report["splats_after"]) == (len(before), int(inside.sum()))
    assert report["bytes_after"] == int(inside.sum()) * 4 * (14 + 3 * 16)
    assert 0 < report["psnr"] < 60 and report["views"] == 6
    assert res["crop_box"]["exported"] == inside.sum()  # baked on export
    assert res["cleared_export"] == len(before)  # and cleared again


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_crop_to_a_closed_mesh_follows_ray_parity(blender, form):
    res, d = cleanup_result(blender, form)
    assert res["crop_mesh"]["result"] == ["FINISHED"]
    before = d["before_positions"].astype(np.float64)
    inside = np.array([parity_inside(p, d["torus_vertices"], d["torus_triangles"]) for p in before])
    assert 20 < inside.sum() < len(before) - 20
    np.testing.assert_allclose(d["crop_mesh_positions"], before[~inside], atol=1e-5)  # inverted
    assert res["crop_mesh"]["exported"] == (~inside).sum()


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_prune_by_opacity_and_size(blender, form):
    res, d = cleanup_result(blender, form)
    before = d["before_positions"]
    opaque = 1 / (1 + np.exp(-d["before_opacity"].astype(np.float64))) >= 0.6
    np.testing.assert_allclose(d["opacity_positions"], before[opaque], atol=1e-6)
    scale = abs(np.linalg.det(np.array(res["matrix"])[:3, :3])) ** (1 / 3)
    # sizes in world units: the object's scale is in the world cloud's log-scales already
    largest = np.exp(d["before_log_scales"].astype(np.float64).max(axis=1))
    assert scale == pytest.approx(1.2)
    sized = (largest >= 0.05) & (largest <= 0.25)
    assert 0 < sized.sum() < len(before)
    assert rows(d["size_positions"]) == rows(before[sized])
    assert res["size"]["report"]["splats_after"] == sized.sum()


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_grade_turns_every_sh_band(blender, form):
    res, d = cleanup_result(blender, form)
    assert res["grade"]["result"] == ["FINISHED"]
    m = cleanup.grade_matrix(**GRADE)
    expected = d["before_sh"].astype(np.float64) @ m.T
    expected[:, 0] += (m - np.eye(3)) @ np.full(3, 0.5) / 0.28209479177387814
    np.testing.assert_allclose(d["grade_sh"], expected, atol=2e-5)
    np.testing.assert_array_equal(d["grade_positions"], d["before_positions"])
    report = res["grade"]["report"]
    assert report["splats_after"] == report["splats_before"] and report["psnr"] < 40


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_reduce_sh_keeps_the_lower_bands(blender, form):
    res, d = cleanup_result(blender, form)
    np.testing.assert_array_equal(d["reduce_sh_sh"], d["before_sh"][:, :4])
    report = res["reduce_sh"]["report"]
    assert report["bytes_after"] == report["splats_after"] * 4 * (14 + 3 * 4)
    assert report["bytes_before"] == report["splats_before"] * 4 * (14 + 3 * 16)
    assert 10 < report["psnr"] < 80


def test_prune_by_visibility_keeps_what_the_camera_path_sees(blender):
    res = blender.step("visibility")
    assert res["prune"]["result"] == ["FINISHED"] and res["frame"] == 1
    d = blender.npz("visibility")
    cloud = SplatCloud(
        positions=d["positions"],
        rotations=d["rotations"],
        log_scales=d["log_scales"],
        opacity_logits=d["opacity_logits"],
        sh=d["sh"],
    )
    # the renderer's own weights from the three frames' cameras (256 px on the long side), from Blender's matrices
    cameras = [
        Camera.from_blender(
            m,
            256,
            192,
            clip_start=float(d["clip"][0]),
            clip_end=float(d["clip"][1]),
            lens=float(d["lens"]),
            sensor_width=float(d["sensor"][0]),
            sensor_height=float(d["sensor"][1]),
        )
        for m in d["cameras"]
    ]
    expected = np.max([contributions(cloud, [c]) for c in cameras], axis=0)
    np.testing.assert_allclose(d["weights"], expected, atol=1e-6)
    kept = d["weights"] > 0.004
    assert 20 < kept.sum() < len(kept) - 20
    assert rows(d["kept"]) == rows(d["positions"][kept])
    # splats behind the camera in every frame (y < -4 here) are never seen
    behind = d["positions"][:, 1] < -4.0
    assert behind.any() and not kept[behind].any()
    assert res["report"]["splats_after"] == kept.sum()


def test_bad_clean_up_input_is_refused_and_changes_nothing(blender):
    res = blender.step("cleanup_refusals")
    expected = {
        "camera_volume": "cannot be a crop volume",
        "faceless_volume": "no faces",
        "missing_volume": "no object named 'Nowhere'",
        "not_splats": "not splat objects",
        "nothing": "no splat objects selected",
        "no_camera": "no camera",
        "sizes": "max size",
    }
    for name, words in expected.items():
        assert res[name]["result"] == ["CANCELLED"], name
        assert words in res[name]["error"], (name, res[name]["error"])
        assert res[name]["unchanged"], name


# binding through a proxy ----------------------------------------------------------------------------


def reference_nearest(points, verts, faces):
    """(triangle, barycentric, distance) of the nearest surface point, one point and triangle at a time."""
    out_t, out_b, out_d = [], [], []
    for p in points:
        best = (math.inf, None, None)
        for t, f in enumerate(faces):
            q = ericson(p, *verts[f])
            dist = np.linalg.norm(p - q)
            if dist < best[0]:
                best = (dist, t, q)
        a, b, c = verts[faces[best[1]]]
        bary = np.linalg.lstsq(np.stack([a, b, c], 1), best[2], rcond=None)[0]
        out_t.append(best[1])
        out_b.append(bary / bary.sum())
        out_d.append(best[0])
    return np.array(out_t), np.array(out_b), np.array(out_d)


@pytest.fixture(scope="module")
def proxy_case(blender):
    res = blender.step("proxy_bind")
    d = blender.npz("proxy_bind")
    tri, bary, dist = reference_nearest(d["rest"], d["proxy_rest"], d["triangles"])
    return res, d, tri, bary, dist


def test_splats_take_the_weights_of_the_nearest_surface_point(proxy_case):
    res, d, tri, bary, dist = proxy_case
    assert res["bind"]["result"] == ["FINISHED"]
    assert res["modifiers"][0] == "ARMATURE" and res["parent"] == "Rig"
    far = dist > 0.1
    assert far.sum() == FAR and not far[:NEAR].any()
    expected = np.einsum("nk,nkb->nb", bary, d["vertex_weights"][d["triangles"][tri]])
    for form in ("MESH", "NATIVE"):  # vertex groups; weight attributes of native splats
        if f"bound_{form}" in d:
            np.testing.assert_allclose(d[f"bound_{form}"], expected, atol=2e-6)  # far ones too: their mask is 0
    assert ((d["bound_MESH"] > 0).sum(axis=1) == 2).sum() > 50  # splats where the bones blend
    if "bound_NATIVE" in d:
        assert res["native"] == ["Rig", False, True]  # the armature property, the strength attribute


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_posed_splats_follow_the_posed_proxy_surface(proxy_case, form):
    res, d, tri, bary, dist = proxy_case
    if f"posed_{form}" not in d:
        skip_platform("this Blender makes no native splats from Python")
    posed = d[f"posed_{form}"].astype(np.float64)
    near = slice(0, NEAR)
    # Blender's posed proxy, at the same surface point
    surface = np.einsum("nk,nki->ni", bary, d["proxy_posed"][d["triangles"][tri]])
    gap = np.linalg.norm(posed[near] - surface[near], axis=1)
    assert np.abs(d["rest"][near] - posed[near]).max() > 0.5  # the pose moves them
    assert (gap <= dist[near] + 0.02).all(), gap.max()  # they stay on the skin
    # exactly linear blend skinning of each splat with its weights
    w = d[f"bound_{form}"]
    blended = np.einsum("nb,bij->nij", w[near], d["deform"])
    lbs = np.einsum("nij,nj->ni", blended[:, :3, :3], d["rest"][near]) + blended[:, :3, 3]
    np.testing.assert_allclose(posed[near], lbs, atol=1e-5)
    # far splats stay where they were
    np.testing.assert_allclose(posed[NEAR:], d["rest"][NEAR:], atol=1e-5)
    if form == "NATIVE":  # Blender draws them posed (the bones were posed by hand)
        np.testing.assert_allclose(d["drawn_NATIVE"], posed, rtol=0, atol=1e-5)


def test_far_splats_are_reported(proxy_case):
    res, d, tri, bary, dist = proxy_case
    if "native_far" not in res:
        skip_platform("this Blender makes no native splats from Python")
    far = res["native_far"]
    assert far["far"] == FAR and far["far_kept_still"]
    assert far["farthest"] == pytest.approx(dist.max(), abs=1e-6)
    assert far["mean_distance"] == pytest.approx(dist.mean(), abs=1e-6)


# distance falloff ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def falloff_case(blender):
    res = blender.step("proxy_falloff")
    d = blender.npz("proxy_falloff")
    verts, faces = tube_mesh()
    _, _, dist = reference_nearest(d["rest"], verts + np.array([0.2, 0.1, 0.0]), faces)
    return res, d, dist


def smoothstep_falloff(dist):
    s = np.clip((dist - FALLOFF_START) / (MAX_DISTANCE - FALLOFF_START), 0.0, 1.0)
    return 1.0 - 3.0 * s**2 + 2.0 * s**3


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_falloff_is_the_armature_modifiers_mask_group(falloff_case, mode):
    res, d, dist = falloff_case
    assert res[f"bind_{mode}"]["result"] == ["FINISHED"], res[f"bind_{mode}"]
    assert res[f"modifier_{mode}"] == ["ARMATURE", "splatwright_bind_strength", False, mode == "dqs"]
    np.testing.assert_allclose(d[f"strength_{mode}"], smoothstep_falloff(dist), atol=2e-6)
    if f"strength_NATIVE_{mode}" in d:  # native splats: the same weights and strength as attributes
        assert res[f"native_{mode}"] == ["Rig", mode == "dqs", True]
        np.testing.assert_allclose(d[f"strength_NATIVE_{mode}"], smoothstep_falloff(dist), atol=2e-6)
        np.testing.assert_allclose(d[f"bound_NATIVE_{mode}"], d[f"bound_{mode}"], atol=2e-6)
    near, far = dist <= FALLOFF_START, dist > MAX_DISTANCE
    fading = ~near & ~far
    assert near.sum() > 40 and far.sum() > 40 and fading.sum() > 80, (near.sum(), fading.sum(), far.sum())
    assert dist.max() > FADE_SPAN - 0.01


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_fading_splats_move_as_blenders_masked_modifier_moves_vertices(falloff_case, mode, form):
    res, d, dist = falloff_case
    if f"posed_{form}_{mode}" not in d:
        skip_platform("this Blender makes no native splats from Python")
    posed = d[f"posed_{form}_{mode}"].astype(np.float64)
    rest, full = d["rest"], d[f"blender_full_{mode}"]
    # Blender's own Armature modifier on a plain mesh of the same points, groups and mask
    np.testing.assert_allclose(posed, d[f"blender_masked_{mode}"], atol=1e-5)
    near, far = dist <= FALLOFF_START, dist > MAX_DISTANCE
    assert np.linalg.norm(full - rest, axis=1).min() > 0.01  # the pose moves every one
    np.testing.assert_allclose(posed[near], full[near], atol=1e-5)  # near ones follow fully
    np.testing.assert_allclose(posed[far], rest[far], atol=1e-6)  # far ones stay
    fraction = smoothstep_falloff(dist)[:, None]  # between: by the falloff
    np.testing.assert_allclose(posed, rest + fraction * (full - rest), atol=1e-5)
    if form == "NATIVE":  # as Blender draws them
        np.testing.assert_allclose(d[f"drawn_NATIVE_{mode}"], posed, rtol=0, atol=1e-5)


def test_bad_proxy_input_is_refused_and_changes_nothing(blender):
    res = blender.step("proxy_refusals")
    expected = {
        "camera": "not a rigged mesh",
        "splats_as_proxy": "a splat object",
        "faceless": "no faces",
        "no_armature": "no armature",
        "no_bones": "no deforming bones",
        "no_splats": "no splat objects",
        "missing": "no object named 'Nowhere'",
    }
    for name, words in expected.items():
        assert res[name]["result"] == ["CANCELLED"], name
        assert words in res[name]["error"], (name, res[name]["error"])
        assert res[name]["unchanged"], name
