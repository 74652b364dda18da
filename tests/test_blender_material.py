"""The material splats carry for relighting, in every Blender of the version matrix (the worker is
tests/workers/material.py): kept by splat objects of both forms, turned by the inverse transpose of a
stretched, mirrored world matrix, and made by Mesh to Splats from Principled BSDF values."""

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import skip_platform
from workers.material import FIRST, SECOND

pytestmark = [pytest.mark.blender, pytest.mark.slow]

blender = blender_fixture("workers.material")

KEYS = ("albedo", "normals", "roughness", "metallic")


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_both_forms_keep_the_material_and_turn_normals_with_the_object(blender, form):
    res = blender.step(f"forms_{form.lower()}")
    if res.get("skipped"):
        skip_platform(f"Blender {blender.version} makes no native splats from Python")
    assert res["skipped_extras"] == []
    assert {"albedo", "nx", "ny", "nz", "roughness", "metallic"} <= set(res["extras"])
    d = blender.npz(f"forms_{form}")
    for key in KEYS:
        np.testing.assert_allclose(d[f"own_{key}"], d[f"source_{key}"], rtol=0, atol=1e-7, err_msg=key)
    # World: n' = A^-T n / |A^-T n| for the object's linear part A (float64 closed form).
    a = d["matrix"][:3, :3]
    expected = d["source_normals"] @ np.linalg.inv(a)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(d["world_normals"], expected, atol=2e-6)
    np.testing.assert_allclose(d["world_albedo"], d["source_albedo"], atol=1e-7)


def test_mesh_to_splats_reads_the_principled_bsdf(blender):
    res = blender.step("convert")
    assert res["result"] == ["FINISHED"], res
    d = blender.npz("convert")
    face = d["source_triangle"].astype(int)
    assert set(np.unique(face)) == {0, 1}
    first = face == 0
    np.testing.assert_allclose(d["albedo"][first], np.tile(FIRST["base"], (first.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(d["albedo"][~first], np.tile(SECOND["base"], ((~first).sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(d["roughness"], np.where(first, FIRST["roughness"], 0.5), atol=1e-6)
    np.testing.assert_allclose(d["metallic"], np.where(first, FIRST["metallic"], SECOND["metallic"]), atol=1e-6)
    # Object space normals: each polygon's winding normal from its corners.
    corners = d["corners"][d["polygon_vertices"][face]]
    winding = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    np.testing.assert_allclose(d["normals"], winding / np.linalg.norm(winding, axis=1, keepdims=True), atol=1e-6)
    assert res["plain"]["result"] == ["FINISHED"]
    assert not {"albedo", "nx", "roughness", "metallic"} & set(res["plain_extras"])


def test_smooth_shading_interpolates_blenders_corner_normals(blender):
    res = blender.step("smooth")
    assert res["result"] == ["FINISHED"], res
    d = blender.npz("smooth")
    tri = d["source_triangle"].astype(int)
    expected = np.einsum("nk,nkc->nc", d["barycentric"].astype(np.float64), d["corner_normals"][tri])
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(d["normals"], expected, atol=2e-6)
    radial = d["positions"] / np.linalg.norm(d["positions"], axis=1, keepdims=True)
    assert np.median(np.einsum("ij,ij->i", d["normals"], radial)) > np.cos(np.radians(1.0))


def _turned(normals, matrix):
    """n A^-1 row-wise (A^-T n), renormalised: the closed form for normals under the linear part A."""
    out = normals @ np.linalg.inv(matrix[:3, :3])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_join_and_apply_transform_turn_the_normals(blender, form):
    res = blender.step(f"join_{form.lower()}")
    if res.get("skipped"):
        skip_platform(f"Blender {blender.version} makes no native splats from Python")
    assert res["join"]["result"] == ["FINISHED"] and res["apply"]["result"] == ["FINISHED"], res
    d = blender.npz(f"join_{form}")
    n = len(d["a_normals"])
    joined = d["join_normals"]
    assert joined.shape == (2 * n, 3)
    # The joined splats are A's as they were, then B's turned into A's space (in whichever order the
    # form joins them: matched by albedo).
    first_is_a = np.allclose(joined[:n], d["a_normals"], atol=1e-6)
    a_rows, b_rows = (slice(0, n), slice(n, None)) if first_is_a else (slice(n, None), slice(0, n))
    np.testing.assert_allclose(joined[a_rows], d["a_normals"], atol=1e-6)
    np.testing.assert_allclose(d["join_albedo"][b_rows], d["b_albedo"], atol=1e-7)
    np.testing.assert_allclose(joined[b_rows], _turned(d["b_normals"], d["to_target"]), atol=2e-6)
    # Apply Splat Transform bakes A's stretch into everything it holds.
    np.testing.assert_allclose(d["apply_normals"], _turned(joined, d["target_matrix"]), atol=2e-6)
