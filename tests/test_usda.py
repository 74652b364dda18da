"""OpenUSD where OpenUSD's Python module is missing (Blender 4.2 bundles none): io/usd's text
stage implementation, checked against usd-core reading what it writes and writing what it reads."""

import math

import numpy as np
import pytest
from helpers import random_cloud
from pxr import Gf, Sdf, Usd, UsdGeom
from test_usd import _define_splats, blender_points, hard_cloud

from splatwright.io import SplatFileError, SplatFileWarning, usd


@pytest.fixture
def without_pxr(monkeypatch):
    """io/usd as it runs where `import pxr` fails: the text stage implementation."""
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)


def extras_cloud(n=40, degree=3, seed=5):
    cloud = hard_cloud(n, degree, seed)
    rng = np.random.default_rng(seed)
    cloud.extras.update(
        label=rng.integers(0, 255, n).astype(np.uint8),
        feature=rng.normal(size=(n, 2)).astype(np.float32),
        keep=rng.random(n) > 0.5,
        part=rng.integers(-300, 300, n).astype(np.int16),
        weight=rng.random(n),
    )
    return cloud


def moved(cloud, k):
    out = cloud.copy() if hasattr(cloud, "copy") else cloud.transformed(np.eye(4))
    out.positions = cloud.positions + np.float32(k)
    out.opacity_logits = cloud.opacity_logits - np.float32(k)
    return out


CASES = {
    "exact": lambda p: usd.write(p, extras_cloud()),
    "half": lambda p: usd.write(p, random_cloud(30, 2, seed=2), half=True, half_positions=True),
    "y-up": lambda p: usd.write(p, random_cloud(30, 1, seed=3), layout="y-up", exact=False),
    "sh4": lambda p: usd.write(p, extras_cloud(degree=4)),
    "sh4-y-up": lambda p: usd.write(p, random_cloud(20, 4, seed=8), layout="y-up", exact=False),
    "antialiased": lambda p: usd.write(p, random_cloud(12, 2, seed=7).replace(antialiased=True)),
    "frames": lambda p: usd.write_frames(p, (moved(extras_cloud(), k) for k in range(3)), times=[1, 2, 5], fps=30),
    "stage": lambda p: usd.write_stage(
        p,
        {"/World/A": random_cloud(9, 0, seed=4), "/World/B": [random_cloud(7, 3, seed=5), random_cloud(7, 3, seed=6)]},
        times=[0, 1],
    ),
}


def _plain(value):
    if isinstance(value, (Gf.Matrix4d,)):
        return np.array(value)
    if hasattr(value, "__len__") and not isinstance(value, str):
        return np.array(value) if len(value) and not isinstance(value[0], str) else list(value)
    return value


def _same(a, b):
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.shape == b.shape
            and a.dtype == b.dtype
            and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        )
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return a == b


def layer_contents(path):
    """Everything usd-core sees in a file: the stage's metadata, and per prim its type and each
    attribute's type, variability, custom flag, primvar metadata, custom data, default and samples."""
    stage = Usd.Stage.Open(str(path))
    layer = stage.GetRootLayer()
    out = {
        "meta": {
            key: layer.GetPrimAtPath("/").GetInfo(key) if layer.GetPrimAtPath("/").HasInfo(key) else None
            for key in (
                "upAxis",
                "metersPerUnit",
                "defaultPrim",
                "startTimeCode",
                "endTimeCode",
                "timeCodesPerSecond",
                "framesPerSecond",
            )
        }
    }
    for prim in stage.Traverse():
        attrs = {}
        for a in prim.GetAuthoredAttributes():
            attrs[a.GetName()] = (
                str(a.GetTypeName()),
                str(a.GetVariability()),
                a.IsCustom(),
                a.GetMetadata("interpolation"),
                a.GetMetadata("elementSize"),
                dict(a.GetCustomData()),
                _plain(a.Get(Usd.TimeCode.Default())),
                {t: _plain(a.Get(t)) for t in a.GetTimeSamples()},
            )
        out[str(prim.GetPath())] = (str(prim.GetTypeName()), attrs)
    return out


@pytest.mark.parametrize("ext", [".usda", ".usdz", ".usd"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_text_layers_hold_what_pxr_writes(tmp_path, monkeypatch, case, ext):
    """Written without pxr, usd-core reads the very prims, attributes, metadata and values it
    reads from the file pxr writes."""
    CASES[case](tmp_path / f"pxr{ext}")
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    CASES[case](tmp_path / f"text{ext}")
    monkeypatch.undo()
    want, got = layer_contents(tmp_path / f"pxr{ext}"), layer_contents(tmp_path / f"text{ext}")
    assert want.keys() == got.keys()
    for key in want:
        assert _same(want[key], got[key]), key


def test_usdz_packages_the_text_layer_as_openusd_requires(tmp_path, without_pxr):
    """OpenUSD's own zip reader: one file, stored uncompressed, its data 64-byte aligned."""
    usd.write(tmp_path / "a.usdz", random_cloud(20, 1, seed=1))
    package = Sdf.ZipFile.Open(str(tmp_path / "a.usdz"))
    (name,) = package.GetFileNames()
    info = package.GetFileInfo(name)
    assert name == "a.usda" and info.compressionMethod == 0 and info.dataOffset % 64 == 0
    assert bytes(package.GetFile(name)).startswith(b"#usda 1.0")


def _read_everything(path, **options):
    frames = usd.read_frames(path, **options)
    prims = usd.read_stage(path, **options)
    return frames, prims


def _assert_same_reading(a, b, exact=True):
    (frames_a, prims_a), (frames_b, prims_b) = a, b
    assert [t for t, _ in frames_a] == [t for t, _ in frames_b]
    assert [(p.path, p.source) for p in prims_a] == [(p.path, p.source) for p in prims_b]
    check = (
        np.testing.assert_array_equal
        if exact
        else (lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6))
    )
    for (_, x), (_, y) in zip(frames_a, frames_b):
        for field in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
            check(getattr(x, field), getattr(y, field))
        assert x.antialiased == y.antialiased
        assert x.extras.keys() == y.extras.keys()
        for key in x.extras:
            assert x.extras[key].dtype == y.extras[key].dtype
            np.testing.assert_array_equal(x.extras[key], y.extras[key])
    for p, q in zip(prims_a, prims_b):
        # float32 op values (quatf, float3 angles) reach float64 by slightly different routes in pxr
        np.testing.assert_allclose(p.to_world, q.to_world, rtol=0 if exact else 1e-6, atol=1e-12)


@pytest.mark.parametrize("case", sorted(CASES))
def test_text_reader_reads_what_pxr_writes_as_pxr_does(tmp_path, monkeypatch, case):
    path = tmp_path / "pxr.usda"
    CASES[case](path)
    want = _read_everything(path)
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    _assert_same_reading(want, _read_everything(path))


def test_splats_made_for_antialiased_rendering_are_marked_as_pxr_reads_it(tmp_path, monkeypatch):
    for writer in ("pxr", "text"):
        if writer == "text":
            monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
        CASES["antialiased"](tmp_path / f"{writer}.usda")
        monkeypatch.undo()
        stage = Usd.Stage.Open(str(tmp_path / f"{writer}.usda"))
        attr = stage.GetPrimAtPath("/Splats").GetAttribute("splatwright:antialiased")
        assert attr.IsCustom() and attr.Get() is True
        assert usd.read(tmp_path / f"{writer}.usda").antialiased
    usd.write(tmp_path / "classic.usda", random_cloud(12, 2, seed=7))
    stage = Usd.Stage.Open(str(tmp_path / "classic.usda"))
    assert not stage.GetPrimAtPath("/Splats").GetAttribute("splatwright:antialiased")
    assert not usd.read(tmp_path / "classic.usda").antialiased


def test_transform_ops_units_and_up_axis_read_as_pxr_reads_them(tmp_path, monkeypatch):
    """A Z-up centimetre stage, a parent Xform with a matrix op and splat prims with translate,
    rotateXYZ, orient, scale and inverted ops, one resetting the parents' transform."""
    path = tmp_path / "ops.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    parent = UsdGeom.Xform.Define(stage, "/World")
    parent.AddTransformOp().Set(Gf.Matrix4d(2.0).SetTranslateOnly(Gf.Vec3d(10, -20, 30)))
    a = _define_splats(stage, "/World/A", random_cloud(12, 2, seed=7))
    a.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    a.AddRotateXYZOp().Set(Gf.Vec3f(30, -45, 60))
    a.AddOrientOp().Set(Gf.Quatf(0.8, 0.36, 0.48, 0.0).GetNormalized())
    a.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    a.AddTranslateOp(opSuffix="pivot").Set(Gf.Vec3d(0.5, 0, 0))
    a.AddTranslateOp(opSuffix="pivot", isInverseOp=True)
    b = _define_splats(stage, "/World/B", random_cloud(8, 1, seed=8))
    b.SetResetXformStack(True)
    b.AddRotateZOp().Set(90.0)
    b.AddScaleOp().Set(Gf.Vec3f(1, 3, 0.5))
    stage.GetRootLayer().Save()
    options = dict(unmarked="stage")
    with pytest.warns(SplatFileWarning):
        want = _read_everything(path, **options)
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    with pytest.warns(SplatFileWarning):
        got = _read_everything(path, **options)
    _assert_same_reading(want, got, exact=False)


@pytest.mark.parametrize("quat_type, degree", [("float4", 3), ("quatf", 3), ("float4", 4)])
def test_blender_point_clouds_read_without_pxr(tmp_path, monkeypatch, quat_type, degree):
    path = tmp_path / "blender.usda"
    blender_points(path, random_cloud(20, sh_degree=degree, seed=12), quat_type)
    want = _read_everything(path)
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    _assert_same_reading(want, _read_everything(path))


def test_binary_layers_are_refused_by_name_without_pxr(tmp_path, monkeypatch):
    usd.write(tmp_path / "crate.usdc", random_cloud(5, 0))
    usd.write(tmp_path / "crate.usdz", random_cloud(5, 0))
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    for name in ("crate.usdc", "crate.usdz"):
        with pytest.raises(SplatFileError, match=r"binary \(crate\).*pxr"):
            usd.read(tmp_path / name)
    with pytest.raises(SplatFileError, match=r"\.usdc.*pxr.*write \.usda"):
        usd.write(tmp_path / "new.usdc", random_cloud(5, 0))
    assert not (tmp_path / "new.usdc").exists() and sorted(p.name for p in tmp_path.iterdir()) == [
        "crate.usdc",
        "crate.usdz",
    ]


@pytest.mark.parametrize("arc", ["references", "subLayers", "payload", "variantSet"])
def test_composition_is_refused_by_name_without_pxr(tmp_path, monkeypatch, arc):
    usd.write(tmp_path / "part.usda", random_cloud(5, 0))
    stage = Usd.Stage.CreateNew(str(tmp_path / "scene.usda"))
    prim = stage.DefinePrim("/Scene", "Xform")
    if arc == "references":
        prim.GetReferences().AddReference("./part.usda")
    elif arc == "payload":
        prim.GetPayloads().AddPayload("./part.usda")
    elif arc == "subLayers":
        stage.GetRootLayer().subLayerPaths.append("./part.usda")
    else:
        prim.GetVariantSets().AddVariantSet("look").AddVariant("red")
    stage.GetRootLayer().Save()
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    with pytest.raises(SplatFileError, match=arc.replace("variantSet", "variant") + r".*OpenUSD's Python module"):
        usd.read(tmp_path / "scene.usda")


def test_damaged_text_is_refused_with_its_line(tmp_path, without_pxr):
    path = tmp_path / "a.usda"
    usd.write_frames(path, [random_cloud(30, 2, seed=1), random_cloud(30, 2, seed=2)])
    text = path.read_text()
    for fraction in np.linspace(0.05, 0.98, 25):
        cut = tmp_path / "cut.usda"
        cut.write_text(text[: int(len(text) * fraction)])
        with pytest.raises(SplatFileError, match="line [0-9]+"):
            usd.read_frames(cut)
    lines = text.splitlines()
    row = next(i for i, line in enumerate(lines) if "positions.timeSamples" in line) + 1
    for bad in ("(0.5, 1.5, abc)", "(0.5, 1.5)", "(0.5, 1.5, 2.5, 3.5)"):
        broken = tmp_path / "broken.usda"
        broken.write_text("\n".join(lines[:row] + [lines[row].replace("[(", f"[{bad}, (", 1)] + lines[row + 1 :]))
        with pytest.raises(SplatFileError, match=f"line {row + 1}: .*point3f"):
            usd.read_frames(broken)
    (tmp_path / "b.usda").write_text("hello")
    with pytest.raises(SplatFileError, match="does not start with '#usda'"):
        usd.read(tmp_path / "b.usda")


def test_text_layer_keeps_non_finite_values_and_extremes(tmp_path, without_pxr):
    cloud = random_cloud(6, 1, seed=9)
    cloud.positions[0] = [np.inf, -np.inf, 3.4028235e38]
    cloud.positions[1] = [1e-45, -0.0, 1.1754944e-38]
    with pytest.warns(SplatFileWarning, match="non-finite"):
        usd.write(tmp_path / "x.usda", cloud, nonfinite="keep")
    with pytest.warns(SplatFileWarning, match="non-finite"):
        back = usd.read(tmp_path / "x.usda", nonfinite="keep")
    np.testing.assert_array_equal(back.positions, cloud.positions)
    assert np.signbit(back.positions[1, 1])


def test_both_stage_implementations_answer_the_whole_interface():
    """The readers and the writer reach stages only through stages.Stages; pxr is imported by the
    interface module (which asks whether it exists) and by its pxr implementation, nowhere else."""
    import ast
    from pathlib import Path

    stages = usd.stages
    assert stages.active is stages.PXR and {stages.PXR.name, stages.TEXT.name} == {"pxr", "text"}
    wanted = {name for name in vars(stages.Stages) if not name.startswith("_")} | {"name", "errors"}
    for impl in (stages.PXR, stages.TEXT):
        assert isinstance(impl, stages.Stages)
        assert not [name for name in wanted if not hasattr(impl, name)]
    io_root = Path(usd.__file__).resolve().parents[1]
    importing = set()
    for source in io_root.rglob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom) and not node.level
                else []
            )
            if any(n == "pxr" or n.startswith("pxr.") for n in names):
                importing.add(source.relative_to(io_root).as_posix())
    assert importing == {"usd/stages.py", "usd/pxr_stages.py"}
