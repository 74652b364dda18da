"""Hostile input files: what a reader must refuse, and how.

Each test builds a file that once got through (or took the machine down) and checks the refusal:
a SplatFileError naming the file and the problem, before anything large is allocated or decoded.
Files read only from where the user pointed (an OBJ's folder, a stage's package or folder); images,
SPZ payloads and crate layers beyond stated limits are refused from their headers; every value that
is not finite, or overflows once activated, goes through the non-finite policy in every format.
"""

import json
import re
import struct
import time
import warnings
import zlib

import numpy as np
import pytest
from helpers import random_cloud
from test_io_fuzz import SMALL_PEAK, outcome, peak_bytes, ply_ascii

from splatwright.cli import main
from splatwright.core.splats import MAX_LOG_SCALE, MAX_MAGNITUDE
from splatwright.io import SplatFileError, SplatFileWarning, image, mesh, read_splats, splat, spz, usd, write_splats
from splatwright.io.policy import MAX_IMAGE_PIXELS, MAX_TEXT_LAYER_BYTES, SPZ_MAX_BYTES, SPZ_MAX_RATIO, SPZ_RATIO_FLOOR


@pytest.fixture(params=["pxr", "text"])
def usd_reader(request, monkeypatch):
    """Read OpenUSD through pxr and through the text-layer reader used where pxr is missing."""
    if request.param == "text":
        monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    return request.param


def usda_text(tmp_path, cloud):
    usd.write(tmp_path / "base.usda", cloud)
    return (tmp_path / "base.usda").read_text()


def quiet_read(path, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)
        return read_splats(path, **options)


# the non-finite policy covers every value, as read and once activated -------------------------


def test_limits_are_where_float32_overflows():
    def squares(x):  # |v|^2 of a float32 vector (x, x, x), as float32 arithmetic gives it
        v = np.full(3, x, np.float32)
        with np.errstate(over="ignore"):
            return np.float32(v @ v)

    assert np.isfinite(squares(MAX_MAGNITUDE)) and not np.isfinite(squares(MAX_MAGNITUDE * 1.01))
    with np.errstate(over="ignore"):
        assert np.isfinite(np.float32(np.exp(MAX_LOG_SCALE))) and not np.isfinite(
            np.float32(np.exp(MAX_LOG_SCALE + 0.01))
        )


def planted(n=12):
    """A cloud with one bad value per kind in its own splat: {kind: splat index}."""
    cloud = random_cloud(n, sh_degree=1, seed=2)
    cloud.extras = {"weight": np.linspace(0, 1, n).astype(np.float32), "label": np.arange(n, dtype=np.int32)}
    cloud.log_scales[1, 0] = 1e30  # exp() is inf
    cloud.positions[3, 2] = 3e38  # finite float32, its square is not
    cloud.rotations[5, 1] = -np.inf
    cloud.extras["weight"][7] = np.inf
    cloud.extras["weight"][8] = np.nan
    return cloud, {"log_scales": [1], "positions": [3], "rotations": [5], "extra 'weight'": [7, 8]}


def test_ply_refuses_overflowing_and_extra_values_then_drops_exactly_them(tmp_path):
    cloud, bad = planted()
    with pytest.warns(SplatFileWarning, match="kept"):
        write_splats(tmp_path / "bad.ply", cloud, nonfinite="keep")
    path = tmp_path / "bad.ply"
    with pytest.raises(
        SplatFileError,
        match=r"bad.ply: 5 of 12 splats .*positions in 1, rotations in 1, "
        r"log_scales in 1, extra 'weight' in 2",
    ):
        read_splats(path)
    with pytest.warns(SplatFileWarning, match="5 of 12 splats"):
        dropped = read_splats(path, nonfinite="drop")
    keep = np.setdiff1d(np.arange(12), sum(bad.values(), []))
    assert np.array_equal(dropped.extras["label"], keep)
    assert np.array_equal(dropped.positions, cloud.positions[keep])
    with pytest.warns(SplatFileWarning, match="kept"):
        kept = read_splats(path, nonfinite="keep")
    assert sorted(kept.problems()) == sorted(f"{len(rows)} splats with non-finite {name}" for name, rows in bad.items())
    assert np.array_equal(np.flatnonzero(~kept.finite_mask()), sorted(sum(bad.values(), [])))


def test_ascii_ply_inf_in_an_extra_is_refused(tmp_path):
    data, names = ply_ascii(rows=3)
    data = data.replace(b"property float rot_3\n", b"property float rot_3\nproperty double temperature\n")
    head, body = data.split(b"end_header\n")
    rows = body.strip().split(b"\n")
    rows = [r + (b" inf" if i == 1 else b" 20.5") for i, r in enumerate(rows)]
    (tmp_path / "t.ply").write_bytes(head + b"end_header\n" + b"\n".join(rows) + b"\n")
    with pytest.raises(SplatFileError, match="t.ply: 1 of 3 splats .*extra 'temperature' in 1"):
        read_splats(tmp_path / "t.ply")


def test_splat_format_refuses_scales_and_positions_that_overflow(tmp_path):
    cloud = random_cloud(6, sh_degree=0, seed=1)
    splat.write(tmp_path / "ok.splat", cloud)
    data = bytearray((tmp_path / "ok.splat").read_bytes())
    records = np.frombuffer(data, np.float32).reshape(6, 8)
    records[2, 3] = np.inf  # a linear scale
    records[4, 0] = -3e38  # a position
    (tmp_path / "bad.splat").write_bytes(bytes(data))
    with pytest.raises(SplatFileError, match=r"bad.splat: 2 of 6 splats .*positions in 1.*log_scales in 1"):
        read_splats(tmp_path / "bad.splat")
    with pytest.warns(SplatFileWarning):
        assert len(read_splats(tmp_path / "bad.splat", nonfinite="drop")) == 4


def test_usd_primvars_and_positions_go_through_the_policy(tmp_path, usd_reader):
    cloud = random_cloud(4, sh_degree=0, seed=3)
    cloud.extras = {"weight": np.array([1, 2, 3, 4], np.float32)}
    text = usda_text(tmp_path, cloud)
    bad = re.sub(r"(primvars:weight = \[)[^\]]*", r"\g<1>1, inf, 3, nan", text)
    assert bad != text
    (tmp_path / "inf.usda").write_text(bad)
    with pytest.raises(SplatFileError, match=r"inf.usda:/Splats: 2 of 4 splats .*extra 'weight' in 2"):
        usd.read(tmp_path / "inf.usda")
    far = re.sub(r"(point3f\[\] positions = \[\()[^,]+", r"\g<1>3e38", text, count=1)
    assert far != text
    (tmp_path / "far.usda").write_text(far)  # float32 holds 3e38; its square overflows
    with pytest.raises(SplatFileError, match=r"far.usda:/Splats: 1 of 4 splats .*positions in 1"):
        usd.read(tmp_path / "far.usda")


def test_info_json_is_strict_json_for_hostile_values(tmp_path, capsys):
    cloud, _ = planted()
    with pytest.warns(SplatFileWarning, match="kept"):
        write_splats(tmp_path / "bad.ply", cloud, nonfinite="keep")
    assert main(["info", str(tmp_path / "bad.ply"), "--json"]) == 0

    def refuse(token):
        raise AssertionError(f"info --json wrote {token}, which is not JSON")

    info = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert info["non_finite_splats"] == 5 and info["count"] == 12
    finite = np.setdiff1d(np.arange(12), [1, 3, 5, 7, 8])
    assert info["bbox_max"] == cloud.positions[finite].astype(np.float64).max(axis=0).tolist()
    assert info["scale"]["max"] == pytest.approx(np.exp(cloud.log_scales[finite].astype(np.float64)).max(), rel=1e-12)


# ASCII PLY rows, extras named like our fields, OpenUSD stage metadata and transforms ----------


def test_ascii_ply_blank_line_among_rows(tmp_path):
    data, _ = ply_ascii(rows=3)
    head, body = data.split(b"end_header\n")
    rows = body.split(b"\n")
    cases = {
        "extra_blank": rows[0] + b"\n\n" + b"\n".join(rows[1:]),  # 4 lines for 3 rows
        "blank_instead": rows[0] + b"\n  \n" + rows[2] + b"\n",  # count right, a row blank
        "leading_blank": b"\n" + b"\n".join(rows[:2]) + b"\n",
    }
    for label, lines in cases.items():
        path = tmp_path / f"{label}.ply"
        path.write_bytes(head + b"end_header\n" + lines)
        with pytest.raises(SplatFileError, match=f"{label}.ply: data line [12] .* is blank"):
            read_splats(path)
    (tmp_path / "trailing.ply").write_bytes(data + b"\n\n")  # blank lines at the end: fine
    assert len(read_splats(tmp_path / "trailing.ply")) == 3


@pytest.mark.parametrize("name", ["core", "x_0", "positions", "sh", "opacity_logits", "extras"])
def test_extras_named_like_our_own_fields_read_and_write(tmp_path, name):
    cloud = random_cloud(5, sh_degree=1, seed=6)
    cloud.extras = {name: np.arange(5, dtype=np.float32) * 1.5}
    for ext in (".ply", ".usda"):
        path = tmp_path / f"named{ext}"
        write_splats(path, cloud)
        back = quiet_read(path)
        assert np.array_equal(back.extras[name], cloud.extras[name]), ext
        assert np.array_equal(back.positions, cloud.positions), ext
        write_splats(tmp_path / f"again{ext}", back)
        assert np.array_equal(quiet_read(tmp_path / f"again{ext}").extras[name], cloud.extras[name])


@pytest.mark.parametrize("units", ["-1", "0", "-0.01", "inf", "nan"])
def test_usd_meters_per_unit_must_be_positive(tmp_path, usd_reader, units):
    text = usda_text(tmp_path, random_cloud(3, sh_degree=0))
    (tmp_path / "units.usda").write_text(text.replace("metersPerUnit = 1", f"metersPerUnit = {units}"))
    with pytest.raises(SplatFileError, match=r"units.usda: metersPerUnit .*: it must be a positive, finite"):
        usd.read(tmp_path / "units.usda")


@pytest.mark.parametrize("axis", ["X", "y", "-Z", ""])
def test_usd_up_axis_is_y_or_z(tmp_path, usd_reader, axis):
    text = usda_text(tmp_path, random_cloud(3, sh_degree=0))
    (tmp_path / "axis.usda").write_text(text.replace('upAxis = "Y"', f'upAxis = "{axis}"'))
    with pytest.raises(SplatFileError, match=f"axis.usda: upAxis '{axis}': an OpenUSD stage is Y-up or Z-up"):
        usd.read(tmp_path / "axis.usda")
    (tmp_path / "z.usda").write_text(text.replace('upAxis = "Y"', 'upAxis = "Z"'))
    assert len(quiet_read(tmp_path / "z.usda")) == 3  # the valid ones still read


@pytest.mark.parametrize("value", ["(nan, 0, 0, 1)", "(1, inf, 0, 0)"])
def test_usd_non_finite_orient_op_is_refused_by_name(tmp_path, usd_reader, value):
    text = usda_text(tmp_path, random_cloud(3, sh_degree=0))
    order = 'uniform token[] xformOpOrder = ["xformOp:transform:upright"]'
    assert order in text
    (tmp_path / "orient.usda").write_text(
        text.replace(
            order,
            f"quatf xformOp:orient = {value}\n    "
            'uniform token[] xformOpOrder = ["xformOp:orient", '
            '"xformOp:transform:upright"]',
        )
    )
    with pytest.raises(SplatFileError, match=r"orient.usda: /Splats: its transform ops xformOp:orient hold NaN or Inf"):
        usd.read(tmp_path / "orient.usda")


# files are read only from where the user pointed ----------------------------------------------

TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl a\nf 1/1 2/2 3/3\n"


def model_folder(tmp_path):
    """tmp_path/secret/ holds a real MTL and texture outside the model's folder tmp_path/model/."""
    secret, model = tmp_path / "secret", tmp_path / "model"
    secret.mkdir()
    model.mkdir()
    (secret / "s.mtl").write_text("newmtl a\nKd 0.9 0.9 0.9\n")
    image.write_image(secret / "s.png", np.full((2, 2, 3), 0.25))
    return model, secret


def read_with_warnings(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = mesh.read_mesh(path)
    return result, " | ".join(str(w.message) for w in caught)


@pytest.mark.parametrize("kind", ["absolute", "parent", "cwd", "symlink"])
def test_mtllib_outside_the_model_folder_is_refused_without_saying_if_it_exists(tmp_path, monkeypatch, kind):
    model, secret = model_folder(tmp_path)
    monkeypatch.chdir(secret)  # "s.mtl" exists relative to the working directory
    (model / "link.mtl").symlink_to(secret / "s.mtl")
    names = {
        "absolute": (str(secret / "s.mtl"), str(secret / "gone.mtl")),
        "parent": ("../secret/s.mtl", "../secret/gone.mtl"),
        "cwd": ("s.mtl", "gone.mtl"),
        "symlink": ("link.mtl", "link.mtl"),
    }[kind]
    messages = []
    for name in names:
        (model / "m.obj").write_text(f"mtllib {name}\n" + TRIANGLE)
        got, said = read_with_warnings(model / "m.obj")
        assert got.materials[0].base_color != (0.9, 0.9, 0.9)  # the outside file was not read
        messages.append(said.replace(name, "NAME"))
    if kind == "cwd":  # relative to the model's folder it is simply missing
        assert all("material library 'NAME' not found" in m for m in messages)
    else:
        assert "is outside the model's folder; only files in it and below are read" in messages[0]
        assert messages[0] == messages[1]  # same text whether the outside file exists or not


def test_textures_outside_the_model_folder_are_refused(tmp_path, monkeypatch):
    model, secret = model_folder(tmp_path)
    (model / "m.obj").write_text("mtllib m.mtl\n" + TRIANGLE)
    monkeypatch.chdir(secret)  # "s.png" exists relative to the working directory only
    (model / "m.mtl").write_text("newmtl a\nKd 0.1 0.2 0.3\nmap_Kd s.png\n")
    got, message = read_with_warnings(model / "m.obj")
    assert got.materials[0].texture is None and "texture 's.png' of material 'a' not found" in message
    said = []
    for name in (
        str(secret / "s.png"),
        str(secret / "none.png"),
        "../secret/s.png",
        "../secret/none.png",
        "/etc/passwd",
        "/etc/nothing-here",
    ):
        (model / "m.mtl").write_text(f"newmtl a\nKd 0.1 0.2 0.3\nmap_Kd {name}\n")
        got, message = read_with_warnings(model / "m.obj")
        assert got.materials[0].texture is None
        said.append(message.replace(name, "NAME"))
    assert said[0] == said[1] == said[2] == said[3] == said[4] == said[5]
    assert "texture of material 'a' 'NAME' is outside the model's folder" in said[0]
    # a texture in the folder (or a subfolder, or beside the MTL when the path was absolute) still reads
    (model / "tex").mkdir()
    image.write_image(model / "tex" / "t.png", np.full((2, 2, 3), 0.5))
    image.write_image(model / "s.png", np.full((3, 3, 3), 0.5))
    for name, shape in (
        ("tex/t.png", (2, 2, 3)),
        ("./tex/../tex/t.png", (2, 2, 3)),
        (str(secret / "s.png"), (3, 3, 3)),
    ):
        (model / "m.mtl").write_text(f"newmtl a\nmap_Kd {name}\n")
        got, message = read_with_warnings(model / "m.obj")
        assert got.materials[0].texture.shape == shape, name
    assert "read 's.png' beside the MTL instead" in message


def stage_with(tmp_path, arcs):
    """model/stage.usda composing `arcs` ("sub" | "ref" | "payload", asset path); a splat layer
    sits at model/in.usdc and tmp_path/out.usdc."""
    model = tmp_path / "model"
    model.mkdir(exist_ok=True)
    usd.write(model / "in.usdc", random_cloud(5, sh_degree=0, seed=1))
    usd.write(tmp_path / "out.usdc", random_cloud(7, sh_degree=0, seed=2))
    subs = [a for kind, a in arcs if kind == "sub"]
    head = '#usda 1.0\n(\n    metersPerUnit = 1\n    upAxis = "Y"\n'
    head += f"    subLayers = [{', '.join(f'@{a}@' for a in subs)}]\n)\n" if subs else ")\n"
    for i, (kind, asset) in enumerate(a for a in arcs if a[0] != "sub"):
        head += f'def "P{i}" (\n    prepend {"references" if kind == "ref" else "payload"} = @{asset}@\n)\n{{\n}}\n'
    (model / "stage.usda").write_text(head)
    return model / "stage.usda"


@pytest.mark.parametrize("kind", ["sub", "ref", "payload"])
def test_usd_composes_only_from_the_stage_folder(tmp_path, kind, capfd):
    inside_ok = stage_with(tmp_path, [(kind, "./in.usdc")])
    assert len(usd.read(inside_ok)) == 5
    messages = []
    for asset in ("../out.usdc", str(tmp_path / "out.usdc"), "../missing.usdc", "/etc/passwd", "/etc/nothing-here"):
        path = stage_with(tmp_path, [(kind, asset)])
        with pytest.raises(
            SplatFileError, match="stage.usda: refers to a layer: .* is outside the stage's folder"
        ) as exc:
            usd.read(path)
        messages.append(str(exc.value).replace(asset, "NAME"))
    assert len(set(messages)) == 1  # existing or not, outside is all it says
    # allowed explicitly, the outside layer is read; a missing one is an error, not a warning
    assert len(usd.read(stage_with(tmp_path, [(kind, "../out.usdc")]), allow_outside=True)) == 7
    for asset, allow in (("./gone.usda", False), ("../gone.usda", True)):
        with pytest.raises(
            SplatFileError, match="stage.usda: refers to the layer '.*gone.usda', which cannot be opened"
        ):
            usd.read(stage_with(tmp_path, [(kind, asset)]), allow_outside=allow)
    assert "Could not" not in capfd.readouterr().err  # OpenUSD never got to warn about it


def test_usd_layers_composed_by_composed_layers_are_checked_too(tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    (model / "deep").mkdir()
    usd.write(tmp_path / "out.usdc", random_cloud(7, sh_degree=0, seed=2))
    (model / "deep" / "mid.usda").write_text("#usda 1.0\n(\n    subLayers = [@../../out.usdc@]\n)\n")
    (model / "stage.usda").write_text("#usda 1.0\n(\n    subLayers = [@deep/mid.usda@]\n)\n")
    with pytest.raises(
        SplatFileError, match=r"stage.usda: layer .*mid.usda refers to a layer: '../../out.usdc' is outside"
    ):
        usd.read(model / "stage.usda")


def test_usd_references_inside_variants_are_checked_too(tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    usd.write(tmp_path / "out.usdc", random_cloud(7, sh_degree=0, seed=2))
    (model / "v.usda").write_text(
        '#usda 1.0\n(\n    metersPerUnit = 1\n)\ndef "W" (\n    variants = { string look = "far" }\n'
        '    prepend variantSets = "look"\n)\n{\n    variantSet "look" = {\n        "far" (\n'
        "            prepend references = @../out.usdc@\n        ) {\n        }\n    }\n}\n"
    )
    with pytest.raises(SplatFileError, match="v.usda: refers to a layer: '../out.usdc' is outside the stage's folder"):
        usd.read(model / "v.usda")
    assert len(usd.read(model / "v.usda", allow_outside=True)) == 7  # the variant does select it


def test_usdz_composes_only_from_its_own_package(tmp_path):
    from pxr import UsdUtils

    model = tmp_path / "model"
    model.mkdir()
    usd.write(model / "in.usdc", random_cloud(5, sh_degree=0, seed=1))
    (model / "root.usda").write_text("#usda 1.0\n(\n    subLayers = [@./in.usdc@]\n)\n")
    assert UsdUtils.CreateNewUsdzPackage(str(model / "root.usda"), str(model / "inside.usdz"))
    assert len(usd.read(model / "inside.usdz")) == 5
    # a package whose layer names a file beside the package (not in it) is refused
    import zipfile

    with zipfile.ZipFile(model / "beside.usdz", "w", zipfile.ZIP_STORED) as z:
        z.writestr("root.usda", "#usda 1.0\n(\n    subLayers = [@../in.usdc@]\n)\n")
    with pytest.raises(
        SplatFileError, match="beside.usdz: refers to a layer: '../in.usdc' is outside the stage's package"
    ):
        usd.read(model / "beside.usdz")


def test_usd_text_reader_refuses_composition_by_name(tmp_path, monkeypatch):
    for kind in ("sub", "ref", "payload"):
        path = stage_with(tmp_path, [(kind, "./in.usdc")])
        monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
        with pytest.raises(SplatFileError, match=r"stage.usda: .*uses composition \((subLayers|references|payload)\)"):
            usd.read(path)
        monkeypatch.undo()


# images beyond the size limit are refused from their header ------------------------------------


def png_header_only(width, height):
    """A PNG whose IHDR (with a valid CRC) claims width x height; the pixels are not there."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = lambda kind, data: struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b"")
    )


def jpeg_header_only(width, height):
    """A baseline JPEG start (SOI, SOF0 claiming width x height, 3 components) with no scan data."""
    sof = struct.pack(">BHHB", 8, height, width, 3) + b"\x01\x11\x00\x02\x11\x00\x03\x11\x00"
    return b"\xff\xd8" + b"\xff\xc0" + struct.pack(">H", len(sof) + 2) + sof + b"\xff\xd9"


@pytest.mark.parametrize("make, ext", [(png_header_only, ".png"), (jpeg_header_only, ".jpg")])
def test_a_12000_pixel_texture_is_refused_before_decoding(tmp_path, make, ext):
    from PIL import Image

    path = tmp_path / f"huge{ext}"
    path.write_bytes(make(12000, 12000))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        with Image.open(path) as img:  # the independent reading of the header
            assert img.size == (12000, 12000)
    assert peak_bytes(lambda: outcome(mesh.load_image, path)) < SMALL_PEAK
    with pytest.raises(
        SplatFileError,
        match=rf"huge{ext}: image of 12000 x 12000 pixels, more than the 67108864 "
        r"\(8192 x 8192\) textures may have",
    ):
        mesh.load_image(path)
    # the largest allowed texture still reads (8192 x 8192 would decode 192 MiB: its neighbour, small)
    ok = tmp_path / f"ok{ext}"
    assert MAX_IMAGE_PIXELS == 8192 * 8192
    image.write_image(tmp_path / "ok.png", np.zeros((4, 3, 3)))
    assert mesh.load_image(tmp_path / "ok.png").shape == (4, 3, 3)
    del ok


# SPZ decompression bombs ----------------------------------------------------------------------


def gzip_of_zeros(head, zero_bytes):
    """A gzip stream of `head` then `zero_bytes` zeros, made without holding or compressing them: one
    fully flushed deflate block of 1 MiB of zeros, repeated (the trailer's CRC does not matter here)."""
    c = zlib.compressobj(9, zlib.DEFLATED, 31)
    start = c.compress(head) + c.flush(zlib.Z_FULL_FLUSH)
    block = c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)
    return start + block * (zero_bytes >> 20) + c.flush()


def spz_v3_head(count, degree=0):
    return spz.HEADER.pack(spz.MAGIC, 3, count, degree, 12, 0, 0)


def test_spz_header_claims_beyond_the_stated_limits(tmp_path):
    assert (SPZ_MAX_BYTES, SPZ_MAX_RATIO, SPZ_RATIO_FLOOR) == (4 << 30, 64, 64 << 20)
    # 7.5 MB of real deflated zeros (about 7.7 GB inflated) under a header claiming 2^28 splats (5.4 GB
    # at SH degree 0: within deflate's 1032:1, so the old check let it inflate)
    bomb = tmp_path / "bomb.spz"
    bomb.write_bytes(gzip_of_zeros(spz_v3_head(spz.MAX_POINTS), 7500 << 20))
    assert 7.4e6 < bomb.stat().st_size < 7.9e6
    # 326 KB inflating to 16.7M valid splats (zeros decode to splats) - 1030:1
    dense = tmp_path / "dense.spz"
    dense.write_bytes(gzip_of_zeros(spz_v3_head(1 << 24), 20 << 24))
    assert 320e3 < dense.stat().st_size < 335e3
    # the same 7.5 MB claiming 150M splats (3 GB: under the absolute limit, 386x the file)
    under = tmp_path / "under.spz"
    under.write_bytes(gzip_of_zeros(spz_v3_head(150_000_000), 7500 << 20))
    ratio = "in a {size}-byte file: more than 64x its size, which no SPZ compresses to"
    cases = (
        (bomb, spz.MAX_POINTS, "more than the 4 GiB this reader decompresses"),
        (under, 150_000_000, ratio),
        (dense, 1 << 24, ratio),
    )
    for path, count, problem in cases:
        started = time.perf_counter()
        assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
        assert time.perf_counter() - started < 2.0  # refused from the header: nothing inflated
        problem = problem.format(size=path.stat().st_size)
        with pytest.raises(
            SplatFileError,
            match=re.escape(f"{path.name}: header claims {count} splats ({20 * count} data bytes)")
            + r",? "
            + re.escape(problem),
        ):
            read_splats(path)


def test_spz_within_the_limits_still_reads(tmp_path):
    # 64 MiB of zeros (3.3M splats) from 65 KB: at the floor, so inflated - to the end, where the CRC
    # this test did not compute is what fails
    n = (64 << 20) // 20
    path = tmp_path / "floor.spz"
    path.write_bytes(gzip_of_zeros(spz_v3_head(n), 64 << 20)[:-8] + struct.pack("<II", 0, 0))
    with pytest.raises(SplatFileError, match="floor.spz: corrupt gzip stream"):
        read_splats(path)
    # an honest file (compressed about 2x) reads back as written, to SPZ's precision
    honest = random_cloud(2000, sh_degree=2, seed=9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)
        spz.write(tmp_path / "honest.spz", honest)
        cloud = read_splats(tmp_path / "honest.spz")
    assert len(cloud) == 2000
    assert np.abs(cloud.positions - honest.positions).max() <= 0.5 / 4096 + 1e-6


def test_spz_inflates_a_piece_at_a_time(tmp_path, monkeypatch):
    """A stream that runs past what its header claims stops one piece past the claim, not at its end."""
    monkeypatch.setattr(spz, "STREAM_PIECE", 1 << 16)
    head = spz_v3_head(100)
    data = gzip_of_zeros(head, 8 << 20)  # 2000 bytes claimed, 8 MiB there
    d = zlib.decompressobj(31)
    assert d.decompress(data, spz.HEADER.size) == head
    out = spz._inflate(d, 2000 + spz.EXTENSION_ROOM + 1)
    assert len(out) == 2000 + spz.EXTENSION_ROOM + 1 and not d.eof
    (tmp_path / "long.spz").write_bytes(data)
    assert peak_bytes(lambda: outcome(read_splats, tmp_path / "long.spz")) < 4 << 20
    with pytest.raises(
        SplatFileError,
        match="long.spz: 8388608 bytes beyond the data the header describes|"
        r"long.spz: \d+ bytes beyond the data",
    ):
        read_splats(tmp_path / "long.spz")


def test_spz_v4_claims_beyond_the_ratio_are_refused_before_any_frame_is_read(tmp_path):
    zstandard = pytest.importorskip("zstandard")
    n = 5 << 20  # 100 MiB of degree-0 data
    sizes = [size for _, size in spz._block_sizes(n, 0, 4) if size]
    frames = []
    for size in sizes:
        c = zstandard.ZstdCompressor(level=1).compressobj()
        frames.append(
            b"".join(c.compress(bytes(1 << 20)) for _ in range(size >> 20))
            + c.compress(bytes(size & ((1 << 20) - 1)))
            + c.flush()
        )
    toc = spz.V4_HEADER.size
    table = b"".join(struct.pack("<QQ", len(f), size) for f, size in zip(frames, sizes))
    data = spz.V4_HEADER.pack(spz.MAGIC, 4, n, 0, 12, 0, len(frames), toc) + table + b"".join(frames)
    path = tmp_path / "zbomb.spz"
    path.write_bytes(data)
    assert len(data) < 50_000
    assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
    with pytest.raises(
        SplatFileError,
        match=rf"zbomb.spz: header claims {n} splats \({20 * n} data bytes\) "
        rf"in a {len(data)}-byte file: more than 64x",
    ):
        read_splats(path)


# damaged crate (.usdc) files ------------------------------------------------------------------

CRATE_SWEEP = r"""
import json, resource, struct, sys, warnings
from pathlib import Path
resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))    # an allocation of gigabytes fails loudly
from splatwright.io import SplatFileError, SplatFileWarning, usd
folder = Path(sys.argv[1])
outcomes = {}
for case in json.loads(sys.argv[2]):
    source, offset, value, width = case
    bad = bytearray((folder / source).read_bytes())
    bad[offset:offset + width] = value.to_bytes(8, "little")[:width]
    path = folder / f"bad_{source[:-5]}_{offset}_{value}_{width}.usdc"
    path.write_bytes(bytes(bad))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SplatFileWarning)
            usd.read(path, nonfinite="keep")
        outcomes[path.name] = "read"
    except SplatFileError as exc:
        outcomes[path.name] = "error" if path.name in str(exc) else f"unnamed: {exc}"
    except Exception as exc:
        outcomes[path.name] = f"{type(exc).__name__}: {exc}"[:300]
print(json.dumps(outcomes))
"""


def crate_6k(tmp_path):
    """A 6.5 KB .usdc of 42 splats (SH degree 1) and its positions' offset (found by their bytes)."""
    cloud = random_cloud(42, sh_degree=1, seed=6)
    usd.write(tmp_path / "valid.usdc", cloud)
    data = (tmp_path / "valid.usdc").read_bytes()
    at = data.find(cloud.positions.astype("<f4").tobytes())
    assert 6_400 < len(data) < 6_700 and at > 0
    assert struct.unpack_from("<Q", data, at - 8)[0] == 42  # the array's element count
    return data, at - 8


def test_a_crate_array_count_of_2_28_is_refused_before_openusd_allocates(tmp_path):
    data, count_at = crate_6k(tmp_path)
    bad = bytearray(data)
    struct.pack_into("<Q", bad, count_at, 1 << 28)  # 3.2 GB of point3f
    (tmp_path / "count.usdc").write_bytes(bytes(bad))
    started = time.perf_counter()
    assert peak_bytes(lambda: outcome(read_splats, tmp_path / "count.usdc")) < SMALL_PEAK
    assert time.perf_counter() - started < 1.0
    with pytest.raises(
        SplatFileError,
        match=r"count.usdc: crate file is corrupt: an array of type 24 at byte "
        rf"{count_at} claims 268435456 elements, more than the \d+ bytes",
    ):
        read_splats(tmp_path / "count.usdc")
    # the same crate layer inside a .usdz package (stored, as usdz requires)
    cloud = random_cloud(42, sh_degree=1, seed=6)
    usd.write(tmp_path / "packed.usdz", cloud)
    packed = bytearray((tmp_path / "packed.usdz").read_bytes())
    at = packed.find(cloud.positions.astype("<f4").tobytes()) - 8
    assert struct.unpack_from("<Q", packed, at)[0] == 42
    struct.pack_into("<Q", packed, at, 1 << 28)
    (tmp_path / "packed.usdz").write_bytes(bytes(packed))
    with pytest.raises(
        SplatFileError,
        match=r"packed.usdz: crate file is corrupt: an array of type 24 .* claims "
        "268435456 elements",
    ):
        read_splats(tmp_path / "packed.usdz")


def test_damaged_crate_words_give_a_named_error_or_a_read_never_a_crash(tmp_path):
    """Words of the 6.5 KB file overwritten with huge counts, in a child process (OpenUSD aborts the
    whole process on some damage: "Dereferenced an invalid SdfPrimSpec")."""
    import subprocess
    import sys

    data, count_at = crate_6k(tmp_path)
    toc = struct.unpack_from("<q", data, 16)[0]
    cloud = random_cloud(20, sh_degree=1, seed=6)  # and an animated file: time samples
    usd.write_frames(
        tmp_path / "anim.usdc",
        [cloud, cloud.replace(positions=cloud.positions + 1, opacity_logits=cloud.opacity_logits * 2)],
    )
    anim = (tmp_path / "anim.usdc").read_bytes()
    special = [
        (85, 1 << 28, 8),  # the pseudo-root's child list grows to 16 names: an abort before
        (count_at, 1 << 28, 8),
        (toc, 1 << 20, 8),
        (toc + 24, 1 << 40, 8),
    ]
    cases = [("valid.usdc", *case) for case in special]
    # fields pointed at values of another type: xformOpOrder a Variability, primChildren a float (TypeErrors before)
    cases += [("anim.usdc", 3733, 1 << 28, 8), ("anim.usdc", 3908, 1 << 28, 8)]
    cases += [("valid.usdc", at, 1 << 28, 8) for at in range(16, len(data) - 8, 136)]
    cases += [("valid.usdc", at, 0xFFFFFFFF, 4) for at in range(92, len(data) - 4, 400)]
    cases += [("anim.usdc", at, 1 << 28, 8) for at in range(40, len(anim) - 8, 200)]
    started = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-c", CRATE_SWEEP, str(tmp_path), json.dumps(cases)],
        capture_output=True,
        encoding="utf-8",
        errors="replace",
        timeout=120,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    outcomes = json.loads(run.stdout.strip().splitlines()[-1])
    assert len(outcomes) == len(cases)
    wrong = {name: what for name, what in outcomes.items() if what not in ("error", "read")}
    assert not wrong, wrong
    assert list(outcomes.values()).count("error") > 10
    for offset, value, width in special:
        assert outcomes[f"bad_valid_{offset}_{value}_{width}.usdc"] == "error"
    assert time.perf_counter() - started < 60


def test_openusd_errors_while_reading_values_become_named_errors(tmp_path, monkeypatch):
    """pxr parses lazily: an error raised after the stage opened is a SplatFileError too."""
    from pxr import Tf

    usd.write(tmp_path / "ok.usdc", random_cloud(3, sh_degree=0))

    def failing(*args, **kwargs):
        raise Tf.ErrorException(
            "Error in 'CrateFile::_UnpackValue' at line 1 in file crateFile.cpp : "
            "'Corrupt asset: exception thrown unpacking a value'"
        )

    monkeypatch.setattr(usd.stages.PXR, "world_matrices", lambda time: failing)
    with pytest.raises(
        SplatFileError,
        match=r"ok.usdc: OpenUSD cannot read it \(truncated or corrupt\?\): "
        "'Corrupt asset: exception thrown unpacking a value'",
    ):
        read_splats(tmp_path / "ok.usdc")
    with pytest.raises(SplatFileError, match="ok.usdc: OpenUSD cannot read it"):
        usd.read_frames(tmp_path / "ok.usdc")


def test_text_stages_beyond_the_stated_size_are_refused_before_parsing(tmp_path, monkeypatch):
    """Without pxr, OpenUSD text is parsed by NumPy: 1 GiB at most, and usdz roots must be stored."""
    monkeypatch.setattr(usd.stages, "active", usd.stages.TEXT)
    assert MAX_TEXT_LAYER_BYTES == 1 << 30
    big = tmp_path / "big.usda"
    with open(big, "wb") as f:  # sparse: 1 GiB + 1 byte, nothing really written
        f.write(b"#usda 1.0\n")
        f.truncate((1 << 30) + 1)
    started = time.perf_counter()
    assert peak_bytes(lambda: outcome(usd.read, big)) < SMALL_PEAK
    assert time.perf_counter() - started < 1.0
    with pytest.raises(SplatFileError, match=r"big.usda: a 1073741825-byte text layer, more than the 1024 MiB"):
        usd.read(big)
    # a usdz whose root layer is deflated (a zip bomb shape; usdz stores its files) is refused unread
    import zipfile

    with zipfile.ZipFile(tmp_path / "bomb.usdz", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("root.usda", "#usda 1.0\n" + " " * (64 << 20))
    assert (tmp_path / "bomb.usdz").stat().st_size < 1 << 20
    assert peak_bytes(lambda: outcome(usd.read, tmp_path / "bomb.usdz")) < 16 << 20
    with pytest.raises(SplatFileError, match="bomb.usdz: the .usdz package's 'root.usda' is compressed"):
        usd.read(tmp_path / "bomb.usdz")
