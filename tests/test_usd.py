"""OpenUSD splats, checked against plain pxr reads and writes, float64 references and PLY."""

import os
import warnings
import zipfile

import numpy as np
import pytest
from helpers import random_cloud
from pxr import Gf, Sdf, Usd, UsdGeom, UsdVol, Vt

from splatwright.core import SplatCloud
from splatwright.core import sh as shmod
from splatwright.io import SplatFileWarning, read_splats, usd, write_splats
from splatwright.io.common import SplatFileError
from splatwright.io.usd import pxr_stages, writer

# Parity of each 3DGS SH basis polynomial under (x, y, z) -> (x, -y, -z), worked out by hand:
# 1 | y z x | xy yz (2zz-xx-yy) xz (xx-yy) | y(3xx-yy) xyz y(..) z(..) x(..) z(xx-yy) x(xx-3yy)
FLIP_SIGNS = np.array([1, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)
# ... and of the nine degree-4 ones, m = -4..4: xy(xx-yy), yz(3xx-yy), xy(7zz-1), yz(7zz-3), 35z^4-30z^2+3,
# xz(7zz-3), (xx-yy)(7zz-1), xz(xx-3yy), x^4-6xxyy+y^4
FLIP_SIGNS_4 = np.concatenate([FLIP_SIGNS, np.float32([-1, 1, -1, 1, 1, -1, 1, -1, 1])])
FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh")


def hard_cloud(n=64, degree=3, seed=3):
    """Random splats plus the hard cases: huge and tiny scales, saturated logits, far positions,
    zero, tiny and non-unit quaternions."""
    c = random_cloud(n, sh_degree=degree, seed=seed)
    rng = np.random.default_rng(seed)
    c.log_scales[:, 0] = np.log(np.geomspace(1e-7, 1e4, n))
    c.opacity_logits[:4] = [1e4, -1e4, 30.0, -30.0]
    c.positions[4] = [1e6, -1e6, 2.5e5]
    c.rotations[5] = 0.0
    c.rotations[6] = [1e-30, 0, 0, 1e-30]
    c.rotations[7] = rng.normal(size=4) * 1e3
    return c


def assert_same(a, b):
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def attr_values(path, prim_path="/Splats", time=Usd.TimeCode.Default()):
    """Every authored attribute of a prim as NumPy, read with plain pxr."""
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath(prim_path)
    return {a.GetName(): np.asarray(a.Get(time)) for a in prim.GetAttributes() if a.HasAuthoredValue()}


def ulps(a, b):
    """Distance in float32 units in the last place."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    ia, ib = a.view(np.int32).astype(np.int64), b.view(np.int32).astype(np.int64)
    ia = np.where(ia < 0, -(ia & 0x7FFFFFFF), ia)
    ib = np.where(ib < 0, -(ib & 0x7FFFFFFF), ib)
    return np.abs(ia - ib)


# round trips --------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usdz", ".usd"])
def test_our_file_round_trips_exactly(tmp_path, ext):
    cloud = hard_cloud()
    first, second = tmp_path / f"a{ext}", tmp_path / f"b{ext}"
    write_splats(first, cloud)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # our own file reads without a single note
        back = read_splats(first)
    assert_same(back, cloud)
    write_splats(second, back)
    if ext != ".usdz":
        one, two = attr_values(first), attr_values(second)
        assert one.keys() == two.keys()
        for name in one:
            np.testing.assert_array_equal(one[name], two[name], err_msg=name)


def test_foreign_file_round_trips_within_one_ulp(tmp_path):
    """USD -> model -> USD for a file we did not write (no exact logits/log scales stored)."""
    rng = np.random.default_rng(7)
    n = 300
    scales = np.geomspace(1e-7, 1e4, 3 * n).reshape(n, 3).astype(np.float32)
    opacities = np.concatenate([[0.0, 1.0, 1e-30, 0.5], rng.uniform(0, 1, n - 4)]).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    positions = rng.normal(0, 100, (n, 3)).astype(np.float32)
    coeffs = rng.normal(0, 0.5, (n * 9, 3)).astype(np.float32)
    src = tmp_path / "foreign.usda"
    stage = Usd.Stage.CreateNew(str(src))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    splat = UsdVol.ParticleField3DGaussianSplat.Define(stage, "/Splats")
    splat.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(positions))
    splat.CreateOrientationsAttr(Vt.QuatfArray.FromNumpy(quats))
    splat.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(scales))
    splat.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(opacities))
    splat.CreateRadianceSphericalHarmonicsDegreeAttr(2)
    splat.CreateRadianceSphericalHarmonicsCoefficientsAttr(Vt.Vec3fArray.FromNumpy(coeffs))
    stage.GetRootLayer().Save()
    out = tmp_path / "out.usda"
    usd.write(out, usd.read(src, axes="RUB", unmarked="stage"), axes="RUB", exact=False)
    got = attr_values(out)
    np.testing.assert_array_equal(got["positions"], positions)
    np.testing.assert_array_equal(got["orientations"], quats)
    np.testing.assert_array_equal(got["radiance:sphericalHarmonicsCoefficients"], coeffs)
    assert ulps(got["scales"], scales).max() <= 1
    assert ulps(got["opacities"], opacities).max() <= 1
    # an edited cloud no longer matches what was read: its values come from the model, not the file
    edited = usd.read(src, axes="RUB", unmarked="stage")
    edited.log_scales[0] += 1
    usd.write(out, edited, axes="RUB")
    np.testing.assert_allclose(attr_values(out)["scales"][0], scales[0] * np.e, rtol=1e-6)


def test_ply_to_usd_to_ply_within_two_ulps(tmp_path):
    cloud = hard_cloud(200)
    cloud.extras["nx"] = np.linspace(-1, 1, 200).astype(np.float32)
    cloud.extras["ny"] = np.zeros(200, np.float32)
    cloud.extras["nz"] = np.ones(200, np.float32)
    cloud.extras["label"] = np.arange(200, dtype=np.int16)
    write_splats(tmp_path / "a.ply", cloud)
    src = read_splats(tmp_path / "a.ply")
    write_splats(tmp_path / "b.usdc", src)
    write_splats(tmp_path / "c.ply", read_splats(tmp_path / "b.usdc"))
    back = read_splats(tmp_path / "c.ply")
    for name in FIELDS:
        assert ulps(getattr(back, name), getattr(src, name)).max() <= 2, name
    for key in ("nx", "label"):
        np.testing.assert_array_equal(back.extras[key], src.extras[key])
        assert back.extras[key].dtype == src.extras[key].dtype


# what the file says, read with plain pxr -----------------------------------------------------------


def test_plain_pxr_sees_every_attribute_as_the_schema_defines_it(tmp_path):
    cloud = random_cloud(40, sh_degree=3, seed=11)
    path = tmp_path / "s.usda"
    usd.write(path, cloud)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Splats")
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetTypeName() == "ParticleField3DGaussianSplat" and UsdVol.ParticleField3DGaussianSplat(prim)
    schema = Usd.SchemaRegistry().FindConcretePrimDefinition("ParticleField3DGaussianSplat")
    n, k = len(cloud), 16
    expected_len = {
        "positions": n,
        "orientations": n,
        "scales": n,
        "opacities": n,
        "radiance:sphericalHarmonicsCoefficients": n * k,
        "extent": 2,
    }
    for name, length in expected_len.items():
        attr = prim.GetAttribute(name)
        definition = schema.GetAttributeDefinition(name)
        assert attr.GetTypeName() == definition.GetTypeName(), name
        assert attr.GetVariability() == definition.GetVariability() and not attr.IsCustom(), name
        assert len(attr.Get()) == length, name
    degree = prim.GetAttribute("radiance:sphericalHarmonicsDegree")
    assert degree.GetVariability() == Sdf.VariabilityUniform and degree.Get() == 3
    for name in ("positionsh", "orientationsh", "scalesh", "opacitiesh"):
        assert not prim.GetAttribute(name).HasAuthoredValue()
    # meaning, as the reference converters write it: the PLY's coordinates, normalised w-first
    # Gf.Quatf, linear scales and opacities, particle-major SH with primvar metadata
    np.testing.assert_array_equal(np.asarray(prim.GetAttribute("positions").Get()), cloud.positions)
    quats = prim.GetAttribute("orientations").Get()
    unit = cloud.rotations / np.linalg.norm(cloud.rotations.astype(np.float64), axis=1, keepdims=True)
    for i in (0, 17, 39):
        q = quats[i]
        np.testing.assert_allclose([q.GetReal(), *q.GetImaginary()], unit[i], atol=1e-7)
    np.testing.assert_array_equal(
        np.asarray(prim.GetAttribute("scales").Get()), np.exp(cloud.log_scales.astype(np.float64)).astype(np.float32)
    )
    sigmoid64 = 1 / (1 + np.exp(-cloud.opacity_logits.astype(np.float64)))
    np.testing.assert_array_equal(np.asarray(prim.GetAttribute("opacities").Get()), sigmoid64.astype(np.float32))
    sh_attr = prim.GetAttribute("radiance:sphericalHarmonicsCoefficients")
    np.testing.assert_array_equal(np.asarray(sh_attr.Get()).reshape(n, k, 3), cloud.sh)
    assert sh_attr.GetMetadata("interpolation") == "vertex" and sh_attr.GetMetadata("elementSize") == k
    # a transform stands the y-down capture upright in the Y-up stage: a half turn about X
    assert list(prim.GetAttribute("xformOpOrder").Get()) == ["xformOp:transform:upright"]
    world = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    np.testing.assert_array_equal(world, np.diag([1.0, -1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(np.asarray(prim.GetAttribute("splatwright:rotations").Get()), cloud.rotations)
    # the exact logits and log scales are custom attributes in our own namespace
    for name, values in (
        ("splatwright:opacityLogits", cloud.opacity_logits),
        ("splatwright:logScales", cloud.log_scales),
    ):
        attr = prim.GetAttribute(name)
        assert attr.IsCustom()
        np.testing.assert_array_equal(np.asarray(attr.Get()), values)


def test_extent_holds_every_visible_pixel_and_is_tight(tmp_path):
    """Brute force: points on each splat's alpha = 1/255 ellipsoid lie inside the extent, and the
    extreme ones touch it."""
    cloud = random_cloud(30, sh_degree=0, seed=5)
    cloud.opacity_logits[:] = np.linspace(-3, 8, 30)
    cloud.rotations[-3:] = [[0, 0, 0, 0], [1e-30, 3e-30, 0, 1e-30], [2e30, 0, -1e30, 5e29]]
    cloud.log_scales[-3:] = [[np.log(1e4), -4, -4], [-9, 0.5, -16], [0, -3, 1]]
    path = tmp_path / "e.usda"
    usd.write(path, cloud, axes="RUB")
    lo, hi = np.asarray(attr_values(path)["extent"], np.float64)
    rng = np.random.default_rng(1)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    reach_lo, reach_hi = np.full(3, np.inf), np.full(3, -np.inf)
    for i in range(len(cloud)):
        o = 1 / (1 + np.exp(-float(cloud.opacity_logits[i])))
        if o * 255 <= 1:
            pts = cloud.positions[i : i + 1].astype(np.float64)
        else:
            q = cloud.rotations[i].astype(np.float64)
            w, x, y, z = q / np.linalg.norm(q) if q.any() else (1, 0, 0, 0)
            r = np.array(
                [
                    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                ]
            )
            radius = np.sqrt(2 * np.log(255 * o))
            pts = cloud.positions[i] + radius * (u * np.exp(cloud.log_scales[i].astype(np.float64))) @ r.T
        reach_lo, reach_hi = np.minimum(reach_lo, pts.min(0)), np.maximum(reach_hi, pts.max(0))
    assert (lo <= reach_lo).all() and (hi >= reach_hi).all()
    span = hi - lo
    assert (reach_lo - lo < 0.01 * span).all() and (hi - reach_hi < 0.01 * span).all()


def test_without_the_schema_class_the_file_is_the_same(tmp_path, monkeypatch):
    cloud = random_cloud(20, sh_degree=2, seed=2)
    with_schema, without = tmp_path / "schema.usda", tmp_path / "generic.usda"
    usd.write(with_schema, cloud)
    monkeypatch.delattr(UsdVol, "ParticleField3DGaussianSplat")
    assert pxr_stages._schema_class() is None
    usd.write(without, cloud)
    assert without.read_text() == with_schema.read_text()
    assert_same(usd.read(without), cloud)


# stages written by others -------------------------------------------------------------------------


def _define_splats(stage, path, cloud):
    """A ParticleField3DGaussianSplat authored with plain pxr from a cloud's values as they are."""
    splat = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
    splat.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(cloud.positions))
    splat.CreateOrientationsAttr(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(cloud.rotations[:, [1, 2, 3, 0]])))
    splat.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(np.exp(cloud.log_scales).astype(np.float32)))
    splat.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(cloud.opacities.astype(np.float32)))
    splat.CreateRadianceSphericalHarmonicsDegreeAttr(cloud.sh_degree)
    splat.CreateRadianceSphericalHarmonicsCoefficientsAttr(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(cloud.sh.reshape(-1, 3)))
    )
    return splat


def _covariances64(cloud):
    q = cloud.rotations.astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        1,
    ).reshape(-1, 3, 3)
    rs = r * np.exp(cloud.log_scales.astype(np.float64))[:, None, :]
    return rs @ rs.transpose(0, 2, 1)


def test_transforms_units_and_up_axis_are_applied(tmp_path):
    """Z-up centimetre stage, a parent Xform and two splat prims (rigid+uniform scale, and a shear);
    a mesh and a plain point cloud are skipped with a note."""
    rng = np.random.default_rng(4)
    a_cloud, b_cloud = random_cloud(25, 2, seed=8), random_cloud(15, 1, seed=9)
    a_cloud.rotations /= np.linalg.norm(a_cloud.rotations, axis=1, keepdims=True)
    b_cloud.rotations /= np.linalg.norm(b_cloud.rotations, axis=1, keepdims=True)
    parent = np.eye(4)
    parent[:3, 3] = [10, -20, 30]
    angle = 0.7
    spin = np.eye(4)
    spin[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    spin[:3, :3] *= 2.5
    shear = np.eye(4)
    shear[:3, :3] = [[2.0, 0.5, 0], [0, 1.0, 0], [0, 0, 0.25]]
    path = tmp_path / "scene.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    # USD matrices act on row vectors: author the transpose of our column-vector matrices
    UsdGeom.Xform.Define(stage, "/World").AddTransformOp().Set(Gf.Matrix4d(parent.T.tolist()))
    for name, cloud, m in (("A", a_cloud, spin), ("B", b_cloud, shear)):
        _define_splats(stage, f"/World/{name}", cloud).AddTransformOp().Set(Gf.Matrix4d(m.T.tolist()))
    UsdGeom.Mesh.Define(stage, "/World/Ground")
    UsdGeom.Points.Define(stage, "/World/Cloud").CreatePointsAttr([(0, 0, 0)])
    stage.GetRootLayer().Save()

    with pytest.warns(SplatFileWarning) as caught:
        prims = usd.read_stage(path, unmarked="stage")  # the values are Z-up stage geometry
    text = " ".join(str(w.message) for w in caught)
    assert "Mesh x1 (/World/Ground)" in text and "Points x1 (/World/Cloud)" in text
    assert "/World/B: its transform stretches unevenly" in text and "/World/A: its" not in text
    assert [p.path for p in prims] == ["/World/A", "/World/B"]

    to_rdf = np.diag([1.0, -1.0, -1.0]) @ np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]]) * 0.01
    for prim, cloud, m in zip(prims, (a_cloud, b_cloud), (spin, shear)):
        world = parent @ m
        a = to_rdf @ world[:3, :3]
        expected = (cloud.positions.astype(np.float64) @ world[:3, :3].T + world[:3, 3]) @ to_rdf.T
        np.testing.assert_allclose(prim.cloud.positions, expected, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(prim.cloud.covariances(), a @ _covariances64(cloud) @ a.T, rtol=1e-4, atol=1e-9)
        np.testing.assert_allclose(prim.anisotropy, np.linalg.cond(m[:3, :3]) - 1, rtol=1e-9)
    # the similarity keeps colours exact: seen along R d, the new SH give the old colour along d
    rotation = to_rdf @ (parent @ spin)[:3, :3] / (0.01 * 2.5)
    d = rng.normal(size=(len(a_cloud), 3))
    np.testing.assert_allclose(shmod.colors(prims[0].cloud.sh, d @ rotation.T), shmod.colors(a_cloud.sh, d), atol=2e-5)
    # read() concatenates both prims (the lower SH degree zero-padded)
    with pytest.warns(SplatFileWarning):
        everything = usd.read(path, unmarked="stage")
    assert len(everything) == 40 and everything.sh_degree == 2
    np.testing.assert_array_equal(everything.positions[25:], prims[1].cloud.positions)


def test_axes_and_units_can_be_kept(tmp_path):
    cloud = random_cloud(10, 0, seed=1)
    path = tmp_path / "cm.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    _define_splats(stage, "/S", cloud)
    stage.GetRootLayer().Save()
    with pytest.warns(SplatFileWarning, match="metersPerUnit is not authored; USD's fallback of 0.01"):
        scaled = usd.read(path, axes="RUB", unmarked="stage")
    np.testing.assert_allclose(scaled.positions[:, 1], cloud.positions[:, 2] * 0.01, rtol=1e-6)
    kept = usd.read(path, axes=None, meters_per_unit=None)
    np.testing.assert_array_equal(kept.positions, cloud.positions)


def test_adobe_points_convention(tmp_path):
    """UsdGeomPoints as Adobe's PLY file-format plugin writes splats: widths are 2 sigma, displayColor
    the clamped DC colour, fRest channel-major."""
    cloud = random_cloud(12, sh_degree=3, seed=6)
    cloud.sh[:, 0] = shmod.rgb_to_dc(np.random.default_rng(2).uniform(0, 1, (12, 3)))
    sigma = np.exp(cloud.log_scales.astype(np.float64))
    unit = cloud.rotations / np.linalg.norm(cloud.rotations, axis=1, keepdims=True)
    path = tmp_path / "adobe.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    points = UsdGeom.Points.Define(stage, "/ply/points")
    points.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(cloud.positions))
    points.CreateWidthsAttr(Vt.FloatArray.FromNumpy((2 * sigma[:, 0]).astype(np.float32)))
    api = UsdGeom.PrimvarsAPI(points)

    def primvar(name, type_name, values, interpolation=UsdGeom.Tokens.vertex):
        api.CreatePrimvar(name, type_name, interpolation).Set(values)

    primvar("widths1", Sdf.ValueTypeNames.FloatArray, Vt.FloatArray.FromNumpy((2 * sigma[:, 1]).astype(np.float32)))
    primvar("widths2", Sdf.ValueTypeNames.FloatArray, Vt.FloatArray.FromNumpy((2 * sigma[:, 2]).astype(np.float32)))
    primvar(
        "rot",
        Sdf.ValueTypeNames.QuatfArray,
        Vt.QuatfArray.FromNumpy(np.ascontiguousarray(unit[:, [1, 2, 3, 0]]).astype(np.float32)),
    )
    primvar(
        "displayOpacity", Sdf.ValueTypeNames.FloatArray, Vt.FloatArray.FromNumpy(cloud.opacities.astype(np.float32))
    )
    primvar(
        "displayColor",
        Sdf.ValueTypeNames.Color3fArray,
        Vt.Vec3fArray.FromNumpy(shmod.dc_to_rgb(cloud.sh[:, 0]).astype(np.float32)),
    )
    rest = cloud.sh[:, 1:].transpose(0, 2, 1).reshape(12, 45)  # PLY f_rest order
    for i in range(45):
        primvar(f"fRest{i}", Sdf.ValueTypeNames.FloatArray, Vt.FloatArray.FromNumpy(np.ascontiguousarray(rest[:, i])))
    primvar(
        "clipping", Sdf.ValueTypeNames.Float3Array, Vt.Vec3fArray([(-2, -2, -2), (2, 2, 2)]), UsdGeom.Tokens.constant
    )
    stage.GetRootLayer().Save()
    with pytest.warns(SplatFileWarning, match="clipping box"):
        (prim,) = usd.read_stage(path, axes="RUB")
    assert prim.source.startswith("Points")
    got = prim.cloud
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_allclose(got.scales, sigma, rtol=1e-6)
    np.testing.assert_allclose(got.rotations, unit, atol=1e-7)
    np.testing.assert_allclose(got.opacities, cloud.opacities, rtol=1e-5)
    np.testing.assert_allclose(got.sh[:, 0], cloud.sh[:, 0], atol=1e-5)
    np.testing.assert_array_equal(got.sh[:, 1:], cloud.sh[:, 1:])


def test_schema_length_rules(tmp_path):
    """Too long: truncated; too short or missing: the schema's defaults; each noted."""
    cloud = random_cloud(6, sh_degree=1, seed=3)
    path = tmp_path / "lengths.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    splat = UsdVol.ParticleField3DGaussianSplat.Define(stage, "/S")
    splat.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(cloud.positions))
    long_quats = np.tile(np.float32([0, 0, 0.6, 0.8]), (9, 1))
    splat.CreateOrientationsAttr(Vt.QuatfArray.FromNumpy(long_quats))
    splat.CreateScalesAttr(Vt.Vec3fArray([(1, 2, 3)]))
    splat.CreateRadianceSphericalHarmonicsDegreeAttr(2)
    splat.CreateRadianceSphericalHarmonicsCoefficientsAttr(Vt.Vec3fArray.FromNumpy(np.ones((20, 3), np.float32)))
    splat.CreateScaleshAttr(Vt.Vec3hArray.FromNumpy(np.full((6, 3), 0.5, np.float16)))
    stage.GetRootLayer().Save()
    with pytest.warns(SplatFileWarning) as caught:
        got = usd.read(path, axes="RUB", unmarked="stage")
    text = str(caught[0].message)
    assert "orientations has 9 entries for 6 particles; truncated" in text
    assert "scales has 1 entries for 6 particles; ignored" in text
    assert "opacities not authored" in text and "needed for degree 2" in text
    np.testing.assert_array_equal(got.rotations, np.tile(np.float32([0.8, 0, 0, 0.6]), (6, 1)))
    np.testing.assert_array_equal(got.scales, np.ones((6, 3)))  # the float attribute wins, then 1
    np.testing.assert_allclose(got.opacities, 1, atol=1e-6)
    assert got.sh_degree == 0 and not got.sh.any()


# animation, half precision ------------------------------------------------------------------------


def test_frames_are_time_samples_of_one_prim(tmp_path):
    frames = [random_cloud(50, 2, seed=s) for s in range(3)]
    path = tmp_path / "anim.usdc"
    usd.write_frames(path, frames, times=[1, 5, 9])
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetAttribute("positions").GetTimeSamples() == [1, 5, 9]
    assert prim.GetAttribute("extent").GetTimeSamples() == [1, 5, 9]
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1, 9)
    assert not stage.GetRootLayer().HasTimeCodesPerSecond()  # no rate given: players assume 24
    assert usd.time_codes(path) == [1, 5, 9]
    for (_time, got), want in zip(usd.read_frames(path), frames):
        assert_same(got, want)
    assert_same(usd.read(path, time=5), frames[1])
    assert_same(usd.read(path), frames[0])  # default: the earliest sample
    with pytest.raises(SplatFileError, match="same splat count"):
        usd.write_frames(tmp_path / "bad.usdc", [frames[0], frames[1][:10]])


def test_frame_rate_is_written_for_players(tmp_path):
    path = tmp_path / "anim.usda"
    usd.write_frames(path, [random_cloud(5, 0, seed=s) for s in range(2)], fps=25)
    stage = Usd.Stage.Open(str(path))
    assert (stage.GetTimeCodesPerSecond(), stage.GetFramesPerSecond()) == (25, 25)
    for bad in (0, -24, float("nan")):
        with pytest.raises(ValueError, match="fps must be a positive number"):
            usd.write_frames(tmp_path / "bad.usda", [random_cloud(5, 0)], fps=bad)
    assert not (tmp_path / "bad.usda").exists()


def test_unchanging_attributes_are_authored_once(tmp_path):
    """A rigid move changes positions and orientations only: opacities, scales and SH are written
    once, and every frame still reads back exactly. The SH change at the last frame backfills."""
    base = random_cloud(40, 1, seed=7)
    frames = []
    for t in range(4):
        c = base.copy()
        c.positions = c.positions + np.float32(0.1 * t)
        c.rotations = np.roll(c.rotations, t, axis=1)
        if t == 3:
            c.sh = c.sh * np.float32(0.5)
        frames.append(c)
    path = tmp_path / "rigid.usdc"
    usd.write_frames(path, frames, times=[10, 11, 12, 13])
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Splats")
    sampled = {a.GetName() for a in prim.GetAttributes() if a.GetTimeSamples()}
    assert sampled == {"positions", "orientations", "extent", usd.SH_COEFFS, usd.RAW_ROTATIONS}
    assert prim.GetAttribute("opacities").HasAuthoredValue()  # the one default value
    assert prim.GetAttribute(usd.SH_COEFFS).GetTimeSamples() == [10, 11, 12, 13]
    for (_time, got), want in zip(usd.read_frames(path), frames):
        assert_same(got, want)
    assert usd.time_codes(path) == [10, 11, 12, 13]


def test_frames_stream_from_a_generator(tmp_path):
    """Each cloud is authored before the next is asked for; a failure midway leaves no file."""
    asked = []

    def clouds(fail_at=None):
        for i in range(3):
            if i == fail_at:
                raise RuntimeError("the scene could not be evaluated")
            asked.append(i)
            yield random_cloud(20, 0, seed=i)

    usd.write_frames(tmp_path / "gen.usdc", clouds())  # times default to 0, 1, 2
    assert asked == [0, 1, 2] and usd.time_codes(tmp_path / "gen.usdc") == [0, 1, 2]
    assert_same(usd.read(tmp_path / "gen.usdc", time=2), random_cloud(20, 0, seed=2))
    with pytest.raises(RuntimeError, match="could not be evaluated"):
        usd.write_frames(tmp_path / "half.usdc", clouds(fail_at=2))
    assert list(tmp_path.iterdir()) == [tmp_path / "gen.usdc"]
    with pytest.raises(SplatFileError, match="more clouds than time codes"):
        usd.write_frames(tmp_path / "bad.usdc", clouds(), times=[1, 2])
    with pytest.raises(SplatFileError, match="more time codes than clouds"):
        usd.write_frames(tmp_path / "bad.usdc", clouds(), times=[1, 2, 3, 4])
    with pytest.raises(SplatFileError, match="no clouds to write"):
        usd.write_frames(tmp_path / "bad.usdc", [])
    assert list(tmp_path.iterdir()) == [tmp_path / "gen.usdc"]


def test_many_prims_animated_and_static_in_one_stage(tmp_path):
    static, frames = random_cloud(30, 3, seed=1), [random_cloud(12, 0, seed=s) for s in (2, 3)]
    path = tmp_path / "set.usdc"
    usd.write_stage(path, {"/World/rock": static, "/World/flag": frames}, times=[10, 20])
    stage = Usd.Stage.Open(str(path))
    assert stage.GetPrimAtPath("/World").GetTypeName() == "Xform"
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    at_20 = usd.read_stage(path, time=20)
    assert [p.path for p in at_20] == ["/World/rock", "/World/flag"]
    assert_same(at_20[0].cloud, static)
    assert_same(at_20[1].cloud, frames[1])
    assert usd.time_codes(path, "/World/rock") == [] and usd.time_codes(path) == [10, 20]
    ((t, only),) = usd.read_frames(path, "/World/rock")
    assert t is None
    assert_same(only, static)


def test_half_precision_is_an_economy_with_half_rounding(tmp_path):
    cloud = random_cloud(2000, 3, seed=12)
    full, half = tmp_path / "full.usdc", tmp_path / "half.usdc"
    usd.write(full, cloud)
    usd.write(half, cloud, half=True)
    values = attr_values(half)
    for name in ("orientations", "scales", "opacities", "radiance:sphericalHarmonicsCoefficients"):
        assert name not in values and values[name + "h"].dtype == np.float16
    stage = Usd.Stage.Open(str(half))
    assert stage.GetPrimAtPath("/Splats").GetAttribute("scalesh").GetTypeName() == Sdf.ValueTypeNames.Half3Array
    back = usd.read(half)
    np.testing.assert_array_equal(back.positions, cloud.positions)
    linear = np.exp(cloud.log_scales.astype(np.float64)).astype(np.float32)
    # the model keeps log scales, so linear values come back within float32 round-off of the halves
    np.testing.assert_allclose(back.scales, linear.astype(np.float16).astype(np.float64), rtol=3e-7)
    np.testing.assert_array_equal(
        back.sh,
        (cloud.sh * FLIP_SIGNS[None, :, None]).astype(np.float16).astype(np.float32) * FLIP_SIGNS[None, :, None],
    )
    assert os.path.getsize(half) < 0.55 * os.path.getsize(full)
    with pytest.raises(SplatFileError, match="exceed the half-float range"):
        usd.write(tmp_path / "big.usdc", cloud.replace(sh=cloud.sh * 1e6), half=True)
    assert not (tmp_path / "big.usdc").exists()


# bad input ------------------------------------------------------------------------------------------


def test_bad_files_raise_clear_errors(tmp_path):
    good = tmp_path / "good.usdc"
    usd.write(good, random_cloud(500, 3))
    cut = tmp_path / "cut.usdc"
    cut.write_bytes(good.read_bytes()[:5000])
    with pytest.raises(SplatFileError, match="cut.usdc: (OpenUSD cannot open it|crate table of contents lies outside)"):
        usd.read(cut)
    wrong = tmp_path / "wrong.usdc"
    wrong.write_text("#usda 1.0\n")
    with pytest.raises(SplatFileError, match="not a .usdc file"):
        usd.read(wrong)
    broken = tmp_path / "broken.usda"
    broken.write_text('#usda 1.0\ndef ParticleField3DGaussianSplat "S" {\n  point3f[] positions = [(1, 2\n')
    with pytest.raises(SplatFileError, match="broken.usda: OpenUSD cannot open it"):
        usd.read(broken)
    empty = tmp_path / "empty.usda"
    stage = Usd.Stage.CreateNew(str(empty))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.GetRootLayer().Save()
    with pytest.raises(SplatFileError, match="no ParticleField3DGaussianSplat prims"):
        usd.read(empty)


def test_failed_writes_leave_nothing_behind(tmp_path):
    path = tmp_path / "keep.usdc"
    usd.write(path, random_cloud(10, 0))
    before = path.read_bytes()
    bad = random_cloud(10, 0)
    bad.positions[3, 1] = np.nan
    with pytest.raises(SplatFileError, match="non-finite"):
        usd.write(path, bad)
    named = random_cloud(10, 0)
    named.extras["not a name"] = np.zeros(10)
    with pytest.raises(SplatFileError, match="extra 'not a name'"):
        usd.write(path, named)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["keep.usdc"]


def test_empty_cloud_and_usdz_package(tmp_path):
    path = tmp_path / "none.usdz"
    usd.write(path, SplatCloud.empty(1))
    with zipfile.ZipFile(path) as z:
        assert [i.filename for i in z.infolist()] == ["none.usdc"]
    back = usd.read(path)
    assert len(back) == 0 and back.sh_degree == 1


def test_stale_exact_values_give_way_to_edited_schema_values(tmp_path):
    """Another tool edits `opacities` and `scales` but not our exact copies: the edit wins, noted."""
    cloud = random_cloud(8, 0, seed=4)
    path = tmp_path / "edited.usda"
    usd.write(path, cloud)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Splats")
    opacities = np.asarray(prim.GetAttribute("opacities").Get()).copy()
    opacities[2] = 0.25
    prim.GetAttribute("opacities").Set(Vt.FloatArray.FromNumpy(opacities))
    scales = np.asarray(prim.GetAttribute("scales").Get()).copy()
    scales[5, 1] = 3.0
    prim.GetAttribute("scales").Set(Vt.Vec3fArray.FromNumpy(scales))
    stage.GetRootLayer().Save()
    with pytest.warns(SplatFileWarning, match="opacityLogits: 1 entries no longer match"):
        got = usd.read(path)
    np.testing.assert_allclose(got.opacities[2], 0.25, rtol=1e-6)
    np.testing.assert_allclose(
        got.scales[5], [np.exp(cloud.log_scales[5, 0]), 3.0, np.exp(cloud.log_scales[5, 2])], rtol=1e-6
    )
    untouched = np.setdiff1d(np.arange(8), [2])
    np.testing.assert_array_equal(got.opacity_logits[untouched], cloud.opacity_logits[untouched])


# the command line ---------------------------------------------------------------------------------

FORMATS = (".ply", ".usda", ".usdc", ".usdz", ".spz", ".splat")


def test_convert_every_pair_and_info_every_format(tmp_path, capsys):
    import json

    from splatwright.cli import main

    cloud = random_cloud(40, sh_degree=1, seed=21)
    cloud.sh[:, 1:] = np.clip(cloud.sh[:, 1:], -0.9, 0.9)
    write_splats(tmp_path / "src.ply", cloud)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)  # .splat drops SH, SPZ rounds: said elsewhere
        for a in FORMATS:
            assert main(["convert", str(tmp_path / "src.ply"), str(tmp_path / f"a{a}")]) == 0
            for b in FORMATS:
                out = tmp_path / f"{a[1:]}_to{b}"
                assert main(["convert", str(tmp_path / f"a{a}"), str(out)]) == 0
                got = read_splats(out)
                lossy = {".spz", ".splat"} & {a, b}
                tolerance = 2.0**-13 if ".spz" in lossy else 0.0
                assert np.abs(got.positions - cloud.positions).max() <= tolerance, (a, b)
                assert got.sh_degree == (0 if ".splat" in lossy else 1), (a, b)
            capsys.readouterr()
            assert main(["info", "--json", str(tmp_path / f"a{a}")]) == 0
            summary = json.loads(capsys.readouterr().out)
            assert summary["count"] == 40 and summary["format"] == {
                ".ply": "ply",
                ".spz": "spz",
                ".splat": "splat",
            }.get(a, "usd")
    assert main(["convert", str(tmp_path / "src.ply"), str(tmp_path / "v4.spz"), "--spz-version", "4"]) == 0
    assert (tmp_path / "v4.spz").read_bytes()[:8] == b"NGSP\x04\x00\x00\x00"
    assert main(["convert", str(tmp_path / "src.ply"), str(tmp_path / "h.usdc"), "--half"]) == 0
    assert "scalesh" in attr_values(tmp_path / "h.usdc")
    capsys.readouterr()
    assert main(["convert", str(tmp_path / "src.ply"), str(tmp_path / "x.ply"), "--half"]) == 2
    assert "--half needs an OpenUSD output" in capsys.readouterr().err
    assert not (tmp_path / "x.ply").exists()


# layouts, prims without the upright transform, Blender's point clouds ------------------------------


@pytest.mark.parametrize("layout", ["upright", "y-up", "as-is"])
def test_layouts_show_the_same_splats_or_say_how_they_differ(tmp_path, layout):
    """World space as OpenUSD computes it: upright and y-up show the capture Y-up (its -y up); as-is
    shows the PLY's values themselves. Each reads back as the cloud."""
    cloud = random_cloud(30, sh_degree=2, seed=5)
    path = tmp_path / f"{layout}.usda"
    usd.write(path, cloud, layout=layout)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Splats")
    world = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    local = np.asarray(prim.GetAttribute("positions").Get(), np.float64)
    shown = local @ world[:3, :3].T + world[:3, 3]
    flip = np.array([1, -1, -1])
    expected = cloud.positions * (1 if layout == "as-is" else flip)
    np.testing.assert_array_equal(shown, expected)
    unmarked = "capture" if layout != "y-up" else "stage"  # y-up values are stage geometry
    assert_same(usd.read(path, unmarked=unmarked), cloud)


def test_unmarked_prims_are_capture_coordinates_or_stage_geometry(tmp_path):
    """A prim as NVIDIA's converter writes it (PLY values, no transform, Y-up stage): by default its
    values come back as they are; unmarked="stage" takes them as Y-up geometry (flipped to RDF)."""
    cloud = random_cloud(12, sh_degree=1, seed=6)
    cloud.rotations /= np.linalg.norm(cloud.rotations, axis=1, keepdims=True)
    path = tmp_path / "plain.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    _define_splats(stage, "/P", cloud)
    stage.GetRootLayer().Save()
    got = usd.read(path)
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_array_equal(got.sh, cloud.sh)
    staged = usd.read(path, unmarked="stage")
    np.testing.assert_array_equal(staged.positions, cloud.positions * np.float32([1, -1, -1]))
    np.testing.assert_array_equal(staged.sh, cloud.sh * FLIP_SIGNS[None, :4, None])
    with pytest.raises(ValueError, match="unmarked must be one of"):
        usd.read(path, unmarked="sideways")


def blender_points(path, cloud, quat_type="float4"):
    """UsdGeomPoints as Blender 5.3's USD export writes splat point clouds (Z-up stage, object space
    positions, `rotation` w,x,y,z, linear `scale`, `radiance:base` = DC rgb + opacity,
    `radiance:sh_0..14` the higher coefficients in 3DGS order), authored with plain pxr."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    points = UsdGeom.Points.Define(stage, "/root/Splats")
    points.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(cloud.positions))
    api = UsdGeom.PrimvarsAPI(points)
    if quat_type == "float4":
        api.CreatePrimvar("rotation", Sdf.ValueTypeNames.Float4Array, UsdGeom.Tokens.vertex).Set(
            Vt.Vec4fArray.FromNumpy(np.ascontiguousarray(cloud.rotations))
        )
    else:
        api.CreatePrimvar("rotation", Sdf.ValueTypeNames.QuatfArray, UsdGeom.Tokens.vertex).Set(
            Vt.QuatfArray.FromNumpy(np.ascontiguousarray(cloud.rotations[:, [1, 2, 3, 0]]))
        )
    api.CreatePrimvar("scale", Sdf.ValueTypeNames.Float3Array, UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(cloud.scales.astype(np.float32))
    )
    base = np.column_stack([cloud.sh[:, 0], cloud.opacities]).astype(np.float32)
    api.CreatePrimvar("radiance:base", Sdf.ValueTypeNames.Float4Array, UsdGeom.Tokens.vertex).Set(
        Vt.Vec4fArray.FromNumpy(base)
    )
    for i in range(cloud.sh.shape[1] - 1):
        api.CreatePrimvar(f"radiance:sh_{i}", Sdf.ValueTypeNames.Float3Array, UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(cloud.sh[:, i + 1]))
        )
    stage.GetRootLayer().Save()


@pytest.mark.parametrize("quat_type, degree", [("float4", 3), ("quatf", 3), ("float4", 4)])
def test_blender_splat_point_clouds(tmp_path, quat_type, degree):
    """Blender 5.3 writes degree 4 as radiance:sh_0..23; the SH turn with the axes (Z-up to RDF is
    x, y, z -> x, -z, y: the colour seen from d in the file is the one seen from that d turned)."""
    cloud = random_cloud(20, sh_degree=degree, seed=12)
    path = tmp_path / "blender.usda"
    blender_points(path, cloud, quat_type)
    prims = usd.read_stage(path, axes=None)  # the stage's own (Blender's Z-up) axes
    assert prims[0].source == "Points (Blender splat primvars)"
    got = prims[0].cloud
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_array_equal(got.rotations, cloud.rotations)
    np.testing.assert_allclose(got.log_scales, cloud.log_scales, atol=1e-6)
    np.testing.assert_allclose(got.opacities, cloud.opacities, atol=1e-6)
    np.testing.assert_array_equal(got.sh, cloud.sh)
    # in the model's axes: Z-up turned to Y-up, then to 3DGS's y down (x, y, z) -> (x, -z, y)
    rdf = usd.read(path)
    np.testing.assert_allclose(rdf.positions, cloud.positions[:, [0, 2, 1]] * [1, -1, 1], atol=1e-6)
    assert rdf.sh_degree == degree
    d = np.random.default_rng(3).normal(size=(20, 3))
    np.testing.assert_allclose(
        shmod.evaluate(rdf.sh, d[:, [0, 2, 1]] * [1, -1, 1]), shmod.evaluate(cloud.sh, d), atol=2e-6
    )


def test_degree_4_is_25_coefficients_per_particle_as_the_schema_says(tmp_path):
    """radiance:sphericalHarmonicsDegree 4 and (4+1)^2 float3 per particle, particle-major, as plain pxr
    reads them; exact both ways; layout y-up turns them by each basis function's parity."""
    cloud = random_cloud(30, sh_degree=4, seed=14)
    path = tmp_path / "sh4.usdc"
    usd.write(path, cloud)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetAttribute("radiance:sphericalHarmonicsDegree").Get() == 4
    coefficients = prim.GetAttribute("radiance:sphericalHarmonicsCoefficients")
    assert coefficients.GetMetadata("elementSize") == 25
    np.testing.assert_array_equal(np.asarray(coefficients.Get()), cloud.sh.reshape(-1, 3))
    assert_same(read_splats(path), cloud)
    usd.write(tmp_path / "up.usda", cloud, layout="y-up", exact=False)
    values = attr_values(tmp_path / "up.usda")["radiance:sphericalHarmonicsCoefficients"]
    np.testing.assert_array_equal(values.reshape(30, 25, 3), cloud.sh * FLIP_SIGNS_4[None, :, None])
    np.testing.assert_array_equal(usd.read(tmp_path / "up.usda", unmarked="stage").sh, cloud.sh)


def test_convert_axes_and_usd_input_options(tmp_path, capsys):
    from splatwright.cli import main

    cloud = random_cloud(20, sh_degree=1, seed=13)
    write_splats(tmp_path / "in.ply", cloud)
    for layout in ("upright", "y-up", "as-is"):
        assert main(["convert", str(tmp_path / "in.ply"), str(tmp_path / f"{layout}.usda"), "--axes", layout]) == 0
    positions = {
        layout: attr_values(tmp_path / f"{layout}.usda")["positions"] for layout in ("upright", "y-up", "as-is")
    }
    np.testing.assert_array_equal(positions["upright"], cloud.positions)
    np.testing.assert_array_equal(positions["as-is"], cloud.positions)
    np.testing.assert_array_equal(positions["y-up"], cloud.positions * np.float32([1, -1, -1]))
    assert main(["convert", str(tmp_path / "y-up.usda"), str(tmp_path / "back.ply"), "--usd-input", "stage"]) == 0
    np.testing.assert_array_equal(read_splats(tmp_path / "back.ply").positions, cloud.positions)
    assert main(["convert", str(tmp_path / "in.ply"), str(tmp_path / "x.ply"), "--axes", "y-up"]) == 2
    assert "--axes needs an OpenUSD output" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "in.ply"), str(tmp_path / "x.glb"), "--usd-input", "stage"]) == 2


def test_crate_counts_the_file_cannot_hold_are_refused_before_openusd_reads_them(tmp_path):
    """A flipped bit in a crate section's element count makes OpenUSD's reader size arrays by it
    (gigabytes, minutes): refused from the table of contents first."""
    import struct

    path = tmp_path / "ok.usdc"
    usd.write(path, random_cloud(20, sh_degree=1, seed=6))
    data = bytearray(path.read_bytes())
    toc = struct.unpack_from("<q", data, 16)[0]
    for i in range(struct.unpack_from("<Q", data, toc)[0]):
        name, start, _ = struct.unpack_from("<16sqq", data, toc + 8 + 32 * i)
        if name.rstrip(b"\0") == b"SPECS":
            struct.pack_into("<Q", data, start, 1 << 29)
    bad = tmp_path / "specs.usdc"
    bad.write_bytes(bytes(data))
    with pytest.raises(SplatFileError, match="crate section 'SPECS' claims 536870912 entries"):
        read_splats(bad)


def test_upright_transform_counts_where_pxr_does_not_know_the_schema(tmp_path):
    """Blender's bundled pxr has no ParticleField3DGaussianSplat: it does not count such prims as
    Xformable, so their own ops must be read directly (here a prim of a type no pxr knows)."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Xform.Define(stage, "/World").AddTranslateOp().Set((1, 2, 3))
    prim = stage.DefinePrim("/World/S", "SplatTypeUnknownHere")
    writer._upright_op(prim)
    assert not UsdGeom.Xformable(prim)  # as in a pxr without the schema
    expected = np.diag([1.0, -1.0, -1.0, 1.0])
    expected[:3, 3] = (1, 2, 3)
    np.testing.assert_array_equal(usd.stages.PXR.world_matrices(Usd.TimeCode.Default())(prim), expected)


def test_one_read_evaluates_a_parents_ops_once_for_all_its_children(tmp_path, monkeypatch):
    """A parent of many transform ops over many splat prims: one transform cache for the read (a
    cache per prim evaluated the parent's ops once per child: a 1 MB layer took 25 s), the same
    matrices as a cache per prim gives."""
    from splatwright.io.usd import pxr_stages

    stage = Usd.Stage.CreateNew(str(tmp_path / "many.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    parent = UsdGeom.Xform.Define(stage, "/A")
    for i in range(50):
        parent.AddTranslateOp(opSuffix=f"t{i}").Set((0.01, 0.0, 0.0))
    stage.GetRootLayer().Save()
    write_splats(tmp_path / "child.usda", random_cloud(3, sh_degree=0))
    for i in range(20):
        stage.DefinePrim(f"/A/c{i}").GetReferences().AddReference(str(tmp_path / "child.usda"))
    stage.GetRootLayer().Save()
    made = []

    class Counted(UsdGeom.XformCache):
        def __init__(self, *args):
            made.append(args)
            super().__init__(*args)

    monkeypatch.setattr(pxr_stages.UsdGeom, "XformCache", Counted)
    cloud = read_splats(tmp_path / "many.usda")
    assert len(made) == 1 and len(cloud) == 60
    shifted = read_splats(tmp_path / "child.usda").positions + [0.5, 0.0, 0.0]
    np.testing.assert_allclose(cloud.positions[:3], shifted, atol=1e-6)
