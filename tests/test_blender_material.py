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
