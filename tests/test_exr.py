"""EXR images: checked against OpenEXR's own reader and against the values written."""

import os

import numpy as np
import OpenEXR
import pytest

from splatwright.io.common import SplatFileError
from splatwright.io.exr import read_exr, write_exr


def _image(rng, h=7, w=5):
    return {
        "R": rng.uniform(0, 1, (h, w)),
        "G": rng.uniform(0, 1, (h, w)),
        "B": rng.uniform(0, 1, (h, w)),
        "A": rng.uniform(0, 1, (h, w)),
        "Z": rng.uniform(0.2, 1e4, (h, w)),
        "N.x": rng.normal(0, 1, (h, w)),
        "albedo.R": rng.uniform(0, 1, (h, w)),
    }


def _openexr_read(path):
    """Plain OpenEXR reading, independent of read_exr: name -> (pixels, pixel type name)."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {name: (c.pixels.copy(), str(c.type()).rsplit(".", 1)[-1]) for name, c in f.channels().items()}


def test_float32_channels_are_exact_in_openexr_and_back(tmp_path, rng):
    image = _image(rng)
    path = tmp_path / "beauty.exr"
    write_exr(path, image)
    seen = _openexr_read(path)
    assert set(seen) == set(image)
    for name, values in image.items():
        pixels, kind = seen[name]
        assert kind == "FLOAT" and pixels.dtype == np.float32 and pixels.shape == values.shape
        np.testing.assert_array_equal(pixels, values.astype(np.float32))
    back = read_exr(path)
    for name, values in image.items():
        assert back[name].dtype == np.float32
        np.testing.assert_array_equal(back[name], values.astype(np.float32))


def test_half_channels_round_to_nearest_half(tmp_path, rng):
    image = {k: v for k, v in _image(rng).items() if k != "Z"}
    image["Z"] = rng.uniform(0.2, 6e4, (7, 5))
    path = tmp_path / "half.exr"
    write_exr(path, image, half=True)
    seen = _openexr_read(path)
    for name, values in image.items():
        pixels, kind = seen[name]
        assert kind == "HALF" and pixels.dtype == np.float16
        # numpy's float32->float16 cast rounds to nearest even, as Imath::half does.
        np.testing.assert_array_equal(pixels, values.astype(np.float32).astype(np.float16))
        rel = np.abs(read_exr(path)[name] - values) / np.maximum(np.abs(values), 6.1e-5)
        assert rel.max() <= 2.0**-11 * 1.0001  # half keeps 11 significant bits


def test_one_by_one_and_infinite_depth(tmp_path):
    path = tmp_path / "px.exr"
    write_exr(path, {"R": [[0.25]], "Z": [[np.inf]]})
    back = read_exr(path)
    assert back["R"].shape == (1, 1) and back["R"][0, 0] == 0.25
    assert back["Z"][0, 0] == np.inf


@pytest.mark.parametrize("compression", ["none", "zip", "piz", "rle", "zips", "zstd"])
def test_lossless_compressions(tmp_path, rng, compression):
    image = _image(rng, 33, 17)
    path = tmp_path / f"{compression}.exr"
    write_exr(path, image, compression=compression)
    for name, values in read_exr(path).items():
        np.testing.assert_array_equal(values, image[name].astype(np.float32))


def test_reads_a_file_written_by_plain_openexr_with_rgba_grouping(tmp_path, rng):
    rgba = rng.uniform(0, 1, (4, 6, 4)).astype(np.float32)
    z = rng.uniform(1, 2, (4, 6)).astype(np.float16)
    path = str(tmp_path / "theirs.exr")
    OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGBA": rgba, "Z": z}).write(
        path
    )
    back = read_exr(path)
    assert set(back) == {"R", "G", "B", "A", "Z"}
    for i, c in enumerate("RGBA"):
        np.testing.assert_array_equal(back[c], rgba[..., i])
    np.testing.assert_array_equal(back["Z"], z.astype(np.float32))


@pytest.mark.parametrize(
    "channels, problem",
    [
        ({}, "no channels"),
        ({"R": np.zeros((2, 2)), "G": np.zeros((2, 3))}, "channel 'G' has shape (2, 3)"),
        ({"R": np.zeros((2, 2, 3))}, "channel 'R' has shape (2, 2, 3)"),
        ({"R": np.full((2, 2), np.nan)}, "channel 'R' holds 4 NaN"),
        ({"": np.zeros((2, 2))}, "channel name ''"),
        ({"R": np.array([["a", "b"]])}, "channel 'R' has dtype"),
    ],
)
def test_bad_channels_are_refused_and_leave_no_file(tmp_path, channels, problem):
    path = tmp_path / "bad.exr"
    with pytest.raises(SplatFileError, match=problem.replace("(", r"\(").replace(")", r"\)")) as info:
        write_exr(path, channels)
    assert str(path) in str(info.value)
    assert os.listdir(tmp_path) == []


def test_half_overflow_is_refused(tmp_path):
    with pytest.raises(SplatFileError, match="channel 'Z' holds 1 values beyond the half-float range"):
        write_exr(tmp_path / "z.exr", {"Z": [[1.0, 1e5]]}, half=True)
    write_exr(tmp_path / "z.exr", {"Z": [[1.0, 1e5]]})  # float32 holds it
    assert read_exr(tmp_path / "z.exr")["Z"][0, 1] == 1e5


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "keep.exr"
    write_exr(path, {"R": [[1.0]]})
    before = path.read_bytes()

    class Broken(OpenEXR.File):
        def write(self, filename):
            with open(filename, "wb") as f:
                f.write(b"v/1\x01 half written")
            raise RuntimeError("disk full")

    monkeypatch.setattr(OpenEXR, "File", Broken)
    with pytest.raises(SplatFileError, match="disk full"):
        write_exr(path, {"R": [[2.0]]})
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["keep.exr"]


def test_unreadable_files_name_the_problem(tmp_path, rng):
    with pytest.raises(SplatFileError, match="no such file"):
        read_exr(tmp_path / "missing.exr")
    wrong = tmp_path / "wrong.exr"
    wrong.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    with pytest.raises(SplatFileError, match="wrong magic"):
        read_exr(wrong)
    good = tmp_path / "good.exr"
    write_exr(good, _image(rng, 64, 64))
    cut = tmp_path / "cut.exr"
    cut.write_bytes(good.read_bytes()[:200])
    with pytest.raises(SplatFileError, match=str(cut)):
        read_exr(cut)
