"""Hostile input files: what a reader must refuse, and how.

Each test builds a file that once got through (or took the machine down) and checks the refusal:
a SplatFileError naming the file and the problem, before anything large is allocated or decoded.
Files read only from where the user pointed (an OBJ's folder, a stage's package or folder); images,
SPZ payloads and crate layers beyond stated limits are refused from their headers; every value that
is not finite, or overflows once activated, goes through the non-finite policy in every format.
"""

import json
import math
import re
import warnings

import numpy as np
import pytest
from helpers import random_cloud
from test_io_fuzz import SMALL_PEAK, outcome, peak_bytes, ply_ascii

from splatwright.cli import main
from splatwright.core.splats import MAX_LOG_SCALE, MAX_MAGNITUDE
from splatwright.io import SplatFileError, SplatFileWarning, ply, read_splats, splat, usd, write_splats


@pytest.fixture(params=["pxr", "text"])
def usd_reader(request, monkeypatch):
    """Read OpenUSD through pxr and through the text-layer reader used where pxr is missing."""
    if request.param == "text":
        monkeypatch.setattr(usd, "Usd", None)
    return request.param


def usda_text(tmp_path, cloud):
    usd.write(tmp_path / "base.usda", cloud)
    return (tmp_path / "base.usda").read_text()


def quiet_read(path, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)
        return read_splats(path, **options)


# 5. the non-finite policy covers every value, as read and once activated -------------------------

def test_limits_are_where_float32_overflows():
    def squares(x):                       # |v|^2 of a float32 vector (x, x, x), as float32 arithmetic gives it
        v = np.full(3, x, np.float32)
        with np.errstate(over="ignore"):
            return np.float32(v @ v)
    assert np.isfinite(squares(MAX_MAGNITUDE)) and not np.isfinite(squares(MAX_MAGNITUDE * 1.01))
    assert np.isfinite(squares(np.exp(MAX_LOG_SCALE))) and not np.isfinite(squares(np.exp(MAX_LOG_SCALE + 0.01)))


def planted(n=12):
    """A cloud with one bad value per kind in its own splat: {kind: splat index}."""
    cloud = random_cloud(n, sh_degree=1, seed=2)
    cloud.extras = {"weight": np.linspace(0, 1, n).astype(np.float32), "label": np.arange(n, dtype=np.int32)}
    cloud.log_scales[1, 0] = 1e30                # exp() is inf
    cloud.positions[3, 2] = 3e38                 # finite float32, its square is not
    cloud.rotations[5, 1] = -2e19
    cloud.extras["weight"][7] = np.inf
    cloud.extras["weight"][8] = np.nan
    return cloud, {"log_scales": [1], "positions": [3], "rotations": [5], "extra 'weight'": [7, 8]}


def test_ply_refuses_overflowing_and_extra_values_then_drops_exactly_them(tmp_path):
    cloud, bad = planted()
    write_splats(tmp_path / "bad.ply", cloud)            # the writer keeps them (they are finite floats or
    path = tmp_path / "bad.ply"                          # NaN/Inf in an extra); reading refuses them
    with pytest.raises(SplatFileError, match=r"bad.ply: 5 of 12 splats .*positions in 1, rotations in 1, "
                                             r"log_scales in 1, extra 'weight' in 2"):
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
    data = data.replace(b"property float rot_3\n",
                                                             b"property float rot_3\nproperty double temperature\n")
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
    records[2, 3] = 3e38              # a linear scale: its log is 88.6, its square inf
    records[4, 0] = -3e38             # a position
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
    (tmp_path / "far.usda").write_text(far)          # float32 holds 3e38; its square overflows
    with pytest.raises(SplatFileError, match=r"far.usda:/Splats: 1 of 4 splats .*positions in 1"):
        usd.read(tmp_path / "far.usda")


def test_info_json_is_strict_json_for_hostile_values(tmp_path, capsys):
    cloud, _ = planted()
    write_splats(tmp_path / "bad.ply", cloud)
    assert main(["info", str(tmp_path / "bad.ply"), "--json"]) == 0

    def refuse(token):
        raise AssertionError(f"info --json wrote {token}, which is not JSON")
    info = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert info["non_finite_splats"] == 5 and info["count"] == 12
    finite = np.setdiff1d(np.arange(12), [1, 3, 5, 7, 8])
    assert info["bbox_max"] == cloud.positions[finite].astype(np.float64).max(axis=0).tolist()
    assert info["scale"]["max"] == pytest.approx(np.exp(cloud.log_scales[finite].astype(np.float64)).max(), rel=1e-12)


# 6. smaller holes ---------------------------------------------------------------------------------

def test_ascii_ply_blank_line_among_rows(tmp_path):
    data, _ = ply_ascii(rows=3)
    head, body = data.split(b"end_header\n")
    rows = body.split(b"\n")
    cases = {"extra_blank": rows[0] + b"\n\n" + b"\n".join(rows[1:]),          # 4 lines for 3 rows
             "blank_instead": rows[0] + b"\n  \n" + rows[2] + b"\n",          # count right, a row blank
             "leading_blank": b"\n" + b"\n".join(rows[:2]) + b"\n"}
    for label, lines in cases.items():
        path = tmp_path / f"{label}.ply"
        path.write_bytes(head + b"end_header\n" + lines)
        with pytest.raises(SplatFileError, match=f"{label}.ply: data line [12] .* is blank"):
            read_splats(path)
    (tmp_path / "trailing.ply").write_bytes(data + b"\n\n")                 # blank lines at the end: fine
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
    assert len(quiet_read(tmp_path / "z.usda")) == 3                      # the valid ones still read


@pytest.mark.parametrize("value", ["(nan, 0, 0, 1)", "(1, inf, 0, 0)"])
def test_usd_non_finite_orient_op_is_refused_by_name(tmp_path, usd_reader, value):
    text = usda_text(tmp_path, random_cloud(3, sh_degree=0))
    order = 'uniform token[] xformOpOrder = ["xformOp:transform:upright"]'
    assert order in text
    (tmp_path / "orient.usda").write_text(text.replace(order, f"quatf xformOp:orient = {value}\n    "
                                                               'uniform token[] xformOpOrder = ["xformOp:orient", '
                                                               '"xformOp:transform:upright"]'))
    with pytest.raises(SplatFileError, match=r"orient.usda: /Splats: its transform ops xformOp:orient hold NaN or Inf"):
        usd.read(tmp_path / "orient.usda")
