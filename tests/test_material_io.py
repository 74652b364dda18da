"""The material extras (core.material) through the file formats: PLY, OpenUSD (every layout, with
OpenUSD's module and with the text writer) and glTF keep them, the formats without extras drop them
with one warning naming them."""

import json
import warnings

import numpy as np
import pytest
from helpers import random_cloud

from splatwright import io as sio
from splatwright.core import material as mat
from splatwright.io import gltf, usd
from splatwright.io.spz import flip_axes


def material_cloud(n=40, seed=1):
    rng = np.random.default_rng(seed)
    return mat.with_material(
        random_cloud(n, sh_degree=1, seed=seed),
        albedo=rng.uniform(0, 1, (n, 3)),
        normals=rng.normal(size=(n, 3)),
        roughness=rng.uniform(0, 1, n),
        metallic=rng.uniform(0, 1, n),
    )


def assert_same_material(got, want, atol=0.0):
    assert mat.has_material(got)
    assert got.extras[mat.ALBEDO].shape == (len(want), 3)
    for read in (mat.albedo, mat.normals, mat.roughness, mat.metallic):
        np.testing.assert_allclose(read(got), read(want), rtol=0, atol=atol)


def test_ply_keeps_the_material(tmp_path):
    cloud = material_cloud()
    sio.write_splats(tmp_path / "m.ply", cloud)
    back = sio.read_splats(tmp_path / "m.ply")
    assert_same_material(back, cloud)
    assert sorted(back.extras) == sorted(mat.KEYS)
    np.testing.assert_array_equal(back.positions, cloud.positions)


@pytest.mark.parametrize("implementation", ["pxr", "text"])
@pytest.mark.parametrize("layout", ["upright", "y-up", "as-is"])
@pytest.mark.parametrize("ext", ["usda", "usdz"])
def test_openusd_keeps_the_material_in_every_layout(tmp_path, monkeypatch, implementation, layout, ext):
    if implementation == "text":
        monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    elif usd.stages.PXR is None:
        pytest.skip("OpenUSD's module is not installed")
    cloud = material_cloud()
    path = tmp_path / f"m.{ext}"
    sio.write_splats(path, cloud, layout=layout)
    back = sio.read_splats(path)
    # The normals come back in the axes the positions come back in (a y-up file, whose values are
    # turned and which carries no upright transform, reads as a capture: y and z reversed).
    signs = np.array([1.0, -1.0, -1.0]) if layout == "y-up" else np.ones(3)
    np.testing.assert_allclose(back.positions, cloud.positions * signs, atol=1e-6)
    assert_same_material(back, mat.with_material(cloud, normals=mat.normals(cloud) * signs), atol=1e-7)


def test_axis_flips_turn_normals_like_positions():
    cloud = material_cloud()
    flipped = flip_axes(cloud, [-1, 1, -1])
    np.testing.assert_allclose(mat.normals(flipped), mat.normals(cloud) * [-1, 1, -1])
    np.testing.assert_array_equal(mat.albedo(flipped), mat.albedo(cloud))


@pytest.mark.parametrize("ext", ["spz", "splat", "sog", "compressed.ply"])
def test_formats_without_extras_warn_once_naming_the_dropped_ones(tmp_path, ext):
    cloud = material_cloud()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sio.write_splats(tmp_path / f"m.{ext}", cloud)
    dropped = [str(w.message) for w in caught if "not written" in str(w.message)]
    assert len(dropped) == 1, [str(w.message) for w in caught]
    assert all(repr(key) in dropped[0] for key in mat.KEYS)
    back = sio.read_splats(tmp_path / f"m.{ext}")
    assert not mat.has_material(back) and len(back) == len(cloud)


@pytest.mark.parametrize("axes", ["RUB", "LUF", "RUF"])
def test_spz_axis_turns_move_normals_like_positions(axes):
    from splatwright.io import spz_axes

    cloud = material_cloud()
    turned = spz_axes.from_model(cloud, axes)
    m = spz_axes.axis_matrix(axes).T  # from_model's turn
    np.testing.assert_allclose(turned.positions, cloud.positions @ m.T, atol=1e-6)
    np.testing.assert_allclose(mat.normals(turned), mat.normals(cloud) @ m.T, atol=1e-7)
    np.testing.assert_allclose(mat.normals(spz_axes.to_model(turned, axes)), mat.normals(cloud), atol=1e-7)


@pytest.mark.parametrize("ext", ["glb", "gltf"])
def test_gltf_keeps_the_material_and_float_extras(tmp_path, ext):
    """Unit normals as glTF's NORMAL (in its axes: x and y reversed), the other float extras as
    `_<name>` attributes read back under their names; an integer extra, which no glTF attribute keeps,
    is left out with one warning naming it."""
    cloud = material_cloud()
    cloud.extras["confidence"] = np.linspace(0.0, 1.0, len(cloud))  # float64: read back as float32
    cloud.extras["segment"] = np.arange(len(cloud), dtype=np.int32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sio.write_splats(tmp_path / f"m.{ext}", cloud)
    dropped = [str(w.message) for w in caught if "not written" in str(w.message)]
    assert len(dropped) == 1 and "'segment'" in dropped[0] and "albedo" not in dropped[0]
    back = sio.read_splats(tmp_path / f"m.{ext}")
    assert_same_material(back, cloud)
    assert sorted(back.extras) == sorted([*mat.KEYS, "confidence"])
    np.testing.assert_array_equal(back.extras["confidence"], cloud.extras["confidence"].astype(np.float32))
    doc, binary = gltf.encode(cloud)
    attributes = doc["meshes"][0]["primitives"][0]["attributes"]
    assert {"NORMAL", "_albedo", "_roughness", "_metallic", "_confidence"} <= set(attributes)
    assert not {"_nx", "_ny", "_nz", "_segment"} & set(attributes)
    normal = doc["accessors"][attributes["NORMAL"]]
    view = doc["bufferViews"][normal["bufferView"]]
    stored = np.frombuffer(binary, "<f4", normal["count"] * 3, view["byteOffset"]).reshape(-1, 3)
    np.testing.assert_array_equal(stored, mat.normals(cloud) * np.float32([-1, -1, 1]))


def test_gltf_normals_turn_with_node_transforms_and_odd_ones_stay_extras(tmp_path):
    """A node's rotation turns the normals as it turns the positions; normals that are not unit
    vectors (a file's own, unnormalised) go as `_nx`, `_ny`, `_nz` and read back as they were."""
    cloud = material_cloud()
    doc, binary = gltf.encode(cloud)
    doc["nodes"][0]["rotation"] = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]  # 90 degrees about glTF's z
    doc["buffers"][0]["uri"] = "m.bin"
    (tmp_path / "m.bin").write_bytes(binary)
    (tmp_path / "m.gltf").write_text(json.dumps(doc))
    turned = sio.read_splats(tmp_path / "m.gltf")
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # the same turn in the model's axes
    np.testing.assert_allclose(turned.positions, cloud.positions @ quarter.T, atol=1e-6)
    np.testing.assert_allclose(mat.normals(turned), mat.normals(cloud) @ quarter.T, atol=1e-6)
    odd = cloud.replace(extras={**cloud.extras, "nx": cloud.extras["nx"] * 2.0})
    attributes = gltf.encode(odd)[0]["meshes"][0]["primitives"][0]["attributes"]
    assert "NORMAL" not in attributes and {"_nx", "_ny", "_nz"} <= set(attributes)
    sio.write_splats(tmp_path / "odd.glb", odd)
    back = sio.read_splats(tmp_path / "odd.glb")
    for name in ("nx", "ny", "nz"):
        np.testing.assert_array_equal(back.extras[name], odd.extras[name])
