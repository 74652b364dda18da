"""The NumPy-only reader of uncompressed EXR (io/exr_plain.py) against files written by the OpenEXR
library: single and multi-part, float and half channels, both line orders; compressed, tiled and
damaged files refused by name."""

import numpy as np
import OpenEXR
import pytest

from splatwright.io import SplatFileError
from splatwright.io.exr_plain import read_plain_exr

HEAD = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}


def channels(seed=0, h=9, w=7):
    rng = np.random.default_rng(seed)
    return {
        "V.Combined.R": rng.normal(size=(h, w)).astype(np.float32),
        "V.Combined.A": rng.uniform(size=(h, w)).astype(np.float16),
        "V.Depth.Z": np.full((h, w), 1e10, np.float32),
    }


@pytest.mark.parametrize("order", [OpenEXR.INCREASING_Y, OpenEXR.DECREASING_Y], ids=["increasing", "decreasing"])
def test_single_part_in_either_line_order(tmp_path, order):
    want = channels()
    OpenEXR.File(dict(HEAD, lineOrder=order), dict(want)).write(str(tmp_path / "a.exr"))  # File takes the arrays over
    got = read_plain_exr(tmp_path / "a.exr")
    assert sorted(got) == sorted(want)
    for name, values in want.items():
        assert got[name].dtype == np.float32
        np.testing.assert_array_equal(got[name], values.astype(np.float32))


def test_multi_part_one_pass_per_part(tmp_path):
    parts = [OpenEXR.Part(dict(HEAD, name=f"p{i}"), {k: v}) for i, (k, v) in enumerate(channels(1).items())]
    OpenEXR.File(parts).write(str(tmp_path / "m.exr"))
    got = read_plain_exr(tmp_path / "m.exr")
    for name, values in channels(1).items():
        np.testing.assert_array_equal(got[name], values.astype(np.float32))


def tiles(size):
    description = OpenEXR.TileDescription()
    description.xSize = description.ySize = size
    return description


@pytest.mark.parametrize(
    "make, words",
    [
        (
            lambda p: OpenEXR.File(dict(HEAD, compression=OpenEXR.ZIP_COMPRESSION), channels()).write(str(p)),
            ["compressed", "uncompressed"],
        ),
        (
            lambda p: OpenEXR.File(
                {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.tiledimage, "tiles": tiles(4)}, channels()
            ).write(str(p)),
            ["tiled"],
        ),
        (lambda p: p.write_bytes(b"\x76\x2f\x31\x01\x02\x00\x00\x00channels\x00chl"), ["truncated"]),
        (lambda p: p.write_bytes(b"PNG not EXR"), ["not an OpenEXR file"]),
    ],
)
def test_other_files_are_refused_by_name(tmp_path, make, words):
    path = tmp_path / "bad.exr"
    make(path)
    with pytest.raises(SplatFileError) as err:
        read_plain_exr(path)
    assert "bad.exr" in str(err.value)
    for word in words:
        assert word in str(err.value)


def test_a_cut_file_is_refused(tmp_path):
    OpenEXR.File(HEAD, channels()).write(str(tmp_path / "a.exr"))
    data = (tmp_path / "a.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) - 40])
    with pytest.raises(SplatFileError, match="does not fit the file"):
        read_plain_exr(tmp_path / "cut.exr")
