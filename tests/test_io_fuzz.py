"""Every file reader against damaged files.

Each format starts from a small valid file written by our own writer (or a hand-written text file
for OBJ, MTL and URDF), then systematic damage is derived from it with seeded randomness: the
empty file, truncation at many offsets, flipped bits and overwritten words in the header and in the
body, counts that lie (off by one, huge), wrong magic and version, non-UTF-8 and binary garbage in
text, NaN and Inf. Every case must end in one of two ways: a SplatFileError whose message names
the file, or a correct read. Correct means finite values (or the non-finite policy fired), and
for raw binary bodies (PLY, .splat) exactly the values the damaged bytes hold, decoded here with
NumPy. Header counts that claim more than the file holds must fail before any large allocation
(peak traced memory stays small).
"""

import gzip
import io
import struct
import time
import tracemalloc
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud
from splatwright.core.splats import FIELDS, MAX_LOG_SCALE, MAX_MAGNITUDE
from splatwright.io import (
    SplatFileError,
    SplatFileWarning,
    compressed_ply,
    exr,
    gltf,
    image,
    mesh,
    ply,
    read_splats,
    sog,
    splat,
    spz,
    urdf,
    usd,
)
from splatwright.io.exr_plain import read_plain_exr

SMALL_PEAK = 64 << 20  # bytes: a refused header claim must not allocate more than this


# the two allowed outcomes ------------------------------------------------------------------------


def outcome(read, path, *args, **options):
    """(result, warnings) of a read that succeeded, or None after a SplatFileError naming the file;
    any other exception fails the test."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result = read(path, *args, **options)
        except SplatFileError as exc:
            assert Path(path).name in str(exc), f"error does not name the file: {exc}"
            return None
    return result, [w for w in caught if issubclass(w.category, SplatFileWarning)]


def finite_cloud(cloud):
    assert isinstance(cloud, SplatCloud)
    return all(np.isfinite(getattr(cloud, name)).all() for name in FIELDS)


def check_splat_read(read, path):
    """Default policy: an error or a finite cloud. nonfinite='keep': an error, a finite cloud, or
    non-finite values with a warning saying so."""
    got = outcome(read, path)
    if got is not None:
        assert finite_cloud(got[0])
    kept = outcome(read, path, nonfinite="keep")
    if kept is not None and not finite_cloud(kept[0]):
        assert any("non-finite" in str(w.message) for w in kept[1])
    return got[0] if got else None


# systematic damage --------------------------------------------------------------------------------


def damaged(data, header_len, seed, flips=24):
    """(label, bytes): empty, truncated at many offsets, flipped bits and words overwritten with
    0xFF or 0x00 in header and body, random garbage of the same length, trailing junk."""
    rng = np.random.default_rng(seed)
    n = len(data)
    yield "empty", b""
    yield "magic", b"\x00" + data[1:]
    cuts = {1, 2, 4, 8, 16, header_len - 1, header_len, header_len + 1, n // 2, n - 1}
    cuts |= set(rng.integers(1, n, 8).tolist())
    for cut in sorted(c for c in cuts if 0 < c < n):
        yield f"cut{cut}", data[:cut]
    for i in range(flips):
        at = int(rng.integers(0, header_len if i % 2 else n))
        flipped = bytearray(data)
        flipped[at] ^= 1 << int(rng.integers(0, 8))
        yield f"flip{at}", bytes(flipped)
    for i in range(flips // 3):
        at = int(rng.integers(0, header_len if i % 2 else n))
        for word in (b"\xff" * 4, b"\x00" * 4):
            yield f"word{at}", (data[:at] + word + data[at + 4 :])[:n]
    yield "garbage", rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    yield "trailing", data + b"\x00" * 7


def write_case(folder, label, ext, data):
    path = Path(folder) / f"bad_{label}{ext}"
    path.write_bytes(data)
    return path


def peak_bytes(fn, *args):
    """Peak traced memory of fn(*args) (NumPy and Python buffers both report to tracemalloc)."""
    tracemalloc.start()
    try:
        fn(*args)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


# PLY ------------------------------------------------------------------------------------------------


def ply_bytes(tmp_path, n=40, degree=1):
    path = tmp_path / "valid.ply"
    ply.write(path, random_cloud(n, sh_degree=degree, seed=3))
    data = path.read_bytes()
    return data, data.index(b"end_header\n") + len(b"end_header\n")


def test_ply_binary_damage(tmp_path):
    data, header_len = ply_bytes(tmp_path)
    names = ply.layout_names(1)
    reads = 0
    for label, bad in damaged(data, header_len, seed=1):
        path = write_case(tmp_path, label, ".ply", bad)
        cloud = check_splat_read(read_splats, path)
        if cloud is None or bad[:header_len] != data[:header_len]:
            continue
        # the header is intact: the cloud holds exactly what the damaged body says
        body = np.frombuffer(bad[header_len:], [(name, "<f4") for name in names])
        assert np.array_equal(cloud.positions, np.stack([body["x"], body["y"], body["z"]], 1))
        assert np.array_equal(cloud.opacity_logits, body["opacity"])
        assert np.array_equal(cloud.rotations, np.stack([body[f"rot_{i}"] for i in range(4)], 1))
        assert np.array_equal(cloud.sh[:, 0], np.stack([body[f"f_dc_{i}"] for i in range(3)], 1))
        reads += 1
    assert reads >= 5  # enough harmless body damage was read back and compared


@pytest.mark.parametrize("count", ["39", "41", "0", str(1 << 40), str(10**30)])
def test_ply_counts_that_lie(tmp_path, count):
    data, header_len = ply_bytes(tmp_path)
    bad = data.replace(b"element vertex 40\n", f"element vertex {count}\n".encode())
    path = write_case(tmp_path, f"count{count}", ".ply", bad)
    assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
    assert outcome(read_splats, path) is None


def ply_ascii(rows=3, types=None):
    """An ASCII 3DGS PLY (degree 0) with some property types changed."""
    names = ply.layout_names(0)
    types = types or {}
    values = np.random.default_rng(0).normal(size=(rows, len(names)))
    head = ["ply", "format ascii 1.0", f"element vertex {rows}"]
    head += [f"property {types.get(n, 'float')} {n}" for n in names] + ["end_header"]
    body = [
        " ".join(f"{v:.5f}" if types.get(n, "float") == "float" else "1" for n, v in zip(names, row)) for row in values
    ]
    return ("\n".join(head + body) + "\n").encode(), names


def test_ply_ascii_damage(tmp_path):
    data, _ = ply_ascii()
    header_len = data.index(b"end_header\n") + len(b"end_header\n")
    for label, bad in damaged(data, header_len, seed=2):
        check_splat_read(read_splats, write_case(tmp_path, label, ".ply", bad))


def test_ply_ascii_bad_values(tmp_path):
    data, names = ply_ascii(types={"nx": "uchar", "ny": "int"})
    first = data.index(b"end_header\n") + len(b"end_header\n")
    head, rows = data[:first], data[first:].split(b"\n")

    def with_value(column, text):
        row = rows[1].split(b" ")
        row[column] = text
        return head + b"\n".join(rows[:1] + [b" ".join(row)] + rows[2:])

    nx, ny = names.index("nx"), names.index("ny")
    cases = {
        "nan": with_value(0, b"nan"),
        "inf": with_value(1, b"-inf"),
        "beyond_float32": with_value(2, b"1e39"),
        "uchar_300": with_value(nx, b"300"),
        "uchar_negative": with_value(nx, b"-1"),
        "int_fraction": with_value(ny, b"1.5"),
        "int_overflow": with_value(ny, b"99999999999"),
        "word": with_value(0, b"zero"),
        "short_row": head + rows[0] + b"\n1 2 3\n" + b"\n".join(rows[2:]),
        "non_utf8_body": data[: first + 5] + b"\xff\xfe" + data[first + 5 :],
        "non_utf8_header": data[:20] + b"\xc3\x28" + data[20:],
        "count_huge": data.replace(b"element vertex 3", b"element vertex 1099511627776"),
        "count_short": data.replace(b"element vertex 3", b"element vertex 2"),
        "version": data.replace(b"format ascii 1.0", b"format ascii 2.0"),
        "no_opacity": data.replace(b"property float opacity\n", b""),
        "list_vertex": data.replace(b"property float x\n", b"property list uchar float x\n"),
        "f_rest_01": data.replace(
            b"property float f_dc_2\n",
            b"property float f_dc_2\n" + b"".join(f"property float f_rest_{i:02d}\n".encode() for i in range(9)),
        ),
        "repeated_other": data.replace(
            b"element vertex", b"element face 0\nproperty int a\nproperty int a\nelement vertex"
        ),
    }
    for label, bad in cases.items():
        path = write_case(tmp_path, label, ".ply", bad)
        got = outcome(read_splats, path)
        assert got is None, f"{label}: read without an error"
    # the integer checks name the property and the value
    with pytest.raises(SplatFileError, match=r"uchar property 'nx' holds 300.0, not an integer in 0..255"):
        read_splats(tmp_path / "bad_uchar_300.ply")
    with pytest.raises(SplatFileError, match=r"face element repeats properties \['a'\]"):
        read_splats(tmp_path / "bad_repeated_other.ply")
    # in-range integers still read exactly
    good = outcome(read_splats, write_case(tmp_path, "ints", ".ply", with_value(nx, b"255")))
    assert good is not None and good[0].extras["nx"][1] == 255


# .splat -----------------------------------------------------------------------------------------


def test_splat_damage_reads_the_damaged_bytes(tmp_path):
    path = tmp_path / "valid.splat"
    splat.write(path, random_cloud(30, sh_degree=0, seed=4))
    data = path.read_bytes()
    compared = 0
    for label, bad in damaged(data, 32, seed=3):
        cloud = check_splat_read(read_splats, write_case(tmp_path, label, ".splat", bad))
        if cloud is None:  # refused: a partial record, or values the non-finite rule refuses
            floats = np.frombuffer(bad[: len(bad) // 32 * 32], "<f4").reshape(-1, 8)[:, :6].astype(np.float64)
            with np.errstate(divide="ignore", over="ignore"):
                assert (
                    len(bad) % 32
                    or not np.isfinite(floats).all()
                    or (np.abs(floats[:, :3]) > MAX_MAGNITUDE).any()
                    or (np.log(np.abs(floats[:, 3:])) > MAX_LOG_SCALE).any()
                )
            continue
        records = np.frombuffer(bad, [("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("q", "u1", 4)])
        assert np.array_equal(cloud.positions, records["p"])
        assert np.array_equal(cloud.rotations, (records["q"].astype(np.float32) - 128) / 128)
        with np.errstate(divide="ignore"):
            logs = np.log(np.abs(records["s"].astype(np.float64)))
        ok = np.isfinite(logs)
        assert np.array_equal(cloud.log_scales[ok], logs[ok].astype(np.float32))  # zero scales: see io/common
        compared += 1
    assert compared >= 10


# SPZ --------------------------------------------------------------------------------------------


def spz_bytes(tmp_path, version):
    path = tmp_path / f"valid{version}.spz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)
        spz.write(path, random_cloud(30, sh_degree=2, seed=5), version=version)
    return path.read_bytes()


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_damage(tmp_path, version):
    data = spz_bytes(tmp_path, version)
    header_len = spz.V4_HEADER.size + 16 * 6 if version == 4 else 10
    for label, bad in damaged(data, header_len, seed=version):
        check_splat_read(read_splats, write_case(tmp_path, label, ".spz", bad))


@pytest.mark.parametrize("version", [2, 3])
def test_spz_payload_damage_and_lying_headers(tmp_path, version):
    """Damage inside the gzip stream (recompressed, so it decompresses) reaches the decoder."""
    payload = gzip.decompress(spz_bytes(tmp_path, version))
    fields = dict(
        zip(["magic", "version", "count", "degree", "bits", "flags", "reserved"], spz.HEADER.unpack_from(payload))
    )

    def header(**changes):
        return gzip.compress(spz.HEADER.pack(*{**fields, **changes}.values()) + payload[16:])

    cases = {
        "count_short": header(count=29),
        "count_long": header(count=31),
        "count_zero": header(count=0),
        "count_max": header(count=spz.MAX_POINTS),
        "count_2_32": header(count=0xFFFFFFFF),
        "degree_up": header(degree=3),
        "degree_9": header(degree=9),
        "bits_30": header(bits=30),
        "version_1": header(version=1),
        "version_4": header(version=4),
        "version_9": header(version=9),
        "magic": header(magic=0x12345678),
        "flags": header(flags=0xFF),
        "gzip_twice": gzip.compress(gzip.compress(payload)),
    }
    for label, bad in damaged(payload, 16, seed=10 + version):
        cases[f"inner_{label}"] = gzip.compress(bad)
    for label, bad in cases.items():
        check_splat_read(read_splats, write_case(tmp_path, label, ".spz", bad))
    assert outcome(read_splats, tmp_path / "bad_count_short.spz") is None


def test_spz_claims_beyond_the_file_fail_before_allocating(tmp_path):
    # gzip: 2^28 splats (17 GB) claimed by 100 kB of deflated zeros (deflate expands at most 1032:1)
    head = spz.HEADER.pack(spz.MAGIC, 3, spz.MAX_POINTS, 3, 12, 0, 0)
    claim = write_case(tmp_path, "gzip_claim", ".spz", gzip.compress(head + bytes(2 * SMALL_PEAK), 1))
    # zstd: a frame whose own header declares 1 GiB (zstandard would allocate that up front)
    data = spz_bytes(tmp_path, 4)
    magic, version, n, degree, bits, flags, streams, toc = spz.V4_HEADER.unpack_from(data)
    frame = struct.pack("<IB", 0xFD2FB528, 0xE0) + struct.pack("<Q", 1 << 30) + b"\x01\x00\x00"
    table = b"".join(struct.pack("<QQ", len(frame), 0) for _ in range(streams))
    empty = spz.V4_HEADER.pack(magic, version, 0, degree, bits, flags, streams, toc)
    declared = write_case(
        tmp_path, "zstd_declared", ".spz", empty + data[spz.V4_HEADER.size : toc] + table + frame * streams
    )
    # v4 table of contents with sizes near 2^64
    wrap = bytearray(data)
    struct.pack_into("<Q", wrap, toc, (1 << 64) - 8)
    wrapped = write_case(tmp_path, "toc_wrap", ".spz", bytes(wrap))
    for path in (claim, declared, wrapped):
        assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
        assert outcome(read_splats, path) is None
    with pytest.raises(SplatFileError, match="more than a .*-byte gzip file can hold"):
        read_splats(claim)
    with pytest.raises(SplatFileError, match="positions stream declares 1073741824 bytes"):
        read_splats(declared)


# OpenUSD ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usdz"])
def test_usd_damage(tmp_path, ext):
    path = tmp_path / f"valid{ext}"
    usd.write(path, random_cloud(20, sh_degree=1, seed=6))
    data = path.read_bytes()
    for label, bad in damaged(data, 200 if ext == ".usda" else 88, seed=20, flips=12):
        got = outcome(read_splats, write_case(tmp_path, label, ext, bad))
        if got is not None:
            assert finite_cloud(got[0])


USDA = """#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Y"
)

def ParticleField3DGaussianSplat "Splats"
{
    point3f[] positions = [(0, 0, 1), (1, 0, 1), (0, 1, 1)]
    quatf[] orientations = [(1, 0, 0, 0), (0.5, 0.5, 0.5, 0.5), (0, 1, 0, 0)]
    float3[] scales = [(0.1, 0.2, 0.3), (0.1, 0.1, 0.1), (1, 2, 3)]
    float[] opacities = [0.5, 0.25, 1]
    uniform int radiance:sphericalHarmonicsDegree = 0
    float3[] radiance:sphericalHarmonicsCoefficients = [(0.1, 0.2, 0.3), (0, 0, 0), (-1, 1, 0)]
}
"""

POSITIONS = "point3f[] positions = [(0, 0, 1), (1, 0, 1), (0, 1, 1)]"
DEGREE = "uniform int radiance:sphericalHarmonicsDegree = 0"
PRIM = 'def ParticleField3DGaussianSplat "Splats"\n{\n'
USDA_BAD = {
    "positions_float": (POSITIONS, "float[] positions = [1, 2, 3, 4, 5, 6, 7]"),
    "positions_strings": (POSITIONS, 'string[] positions = ["a", "b", "c"]'),
    "positions_scalar": (POSITIONS, "float positions = 3"),
    "positions_nan": (POSITIONS, "point3f[] positions = [(nan, 0, 1), (1, 0, 1), (0, 1, 1)]"),
    "orientations_float": ("quatf[] orientations", "float[] orientations"),
    "scales_matrix": (
        "float3[] scales = [(0.1, 0.2, 0.3), (0.1, 0.1, 0.1), (1, 2, 3)]",
        "matrix4d scales = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))",
    ),
    "scales_bool": ("float3[] scales = [(0.1, 0.2, 0.3), (0.1, 0.1, 0.1), (1, 2, 3)]", "bool[] scales = [1, 0, 1]"),
    "opacities_vectors": ("float[] opacities = [0.5, 0.25, 1]", "float3[] opacities = [(1, 2, 3)]"),
    "opacities_inf": ("float[] opacities = [0.5, 0.25, 1]", "float[] opacities = [inf, 0.25, 1]"),
    "degree_string": (DEGREE, 'uniform string radiance:sphericalHarmonicsDegree = "two"'),
    "degree_fraction": (DEGREE, "uniform float radiance:sphericalHarmonicsDegree = 1.5"),
    "degree_negative": (DEGREE, "uniform int radiance:sphericalHarmonicsDegree = -1"),
    "degree_array": (DEGREE, "uniform int[] radiance:sphericalHarmonicsDegree = [1, 2]"),
    "sh_floats": (
        "float3[] radiance:sphericalHarmonicsCoefficients",
        "float[] radiance:sphericalHarmonicsCoefficients",
    ),
    "logits_strings": ("}\n", 'custom string[] splatwright:opacityLogits = ["a", "b", "c"]\n}\n'),
    "log_scales_floats": ("}\n", "custom float[] splatwright:logScales = [1, 2, 3, 4]\n}\n"),
    "translate_nan": (
        PRIM,
        PRIM + 'double3 xformOp:translate = (nan, 0, 0)\nuniform token[] xformOpOrder = ["xformOp:translate"]\n',
    ),
    "scale_zero": (
        PRIM,
        PRIM + 'double3 xformOp:scale = (0, 0, 0)\nuniform token[] xformOpOrder = ["xformOp:scale"]\n',
    ),
    "scale_huge": (
        PRIM,
        PRIM + 'double3 xformOp:scale = (1e300, 1e300, 1e300)\nuniform token[] xformOpOrder = ["xformOp:scale"]\n',
    ),
    "meters_nan": ("metersPerUnit = 1", "metersPerUnit = nan"),
    "meters_zero": ("metersPerUnit = 1", "metersPerUnit = 0"),
    "latin1": ('"Splats"', '"Spl\xe9ts"'),
    "version": ("#usda 1.0", "#usda 99.0"),
    "adobe_widths_strings": (
        PRIM,
        'def Points "P"\n{\npoint3f[] points = [(0, 0, 0)]\n'
        'string[] primvars:widths1 = ["a"]\nfloat[] primvars:widths2 = [1]\n'
        "quatf[] primvars:rot = [(1, 0, 0, 0)]\n}\n" + PRIM,
    ),
    "adobe_colour_floats": (
        PRIM,
        'def Points "P"\n{\npoint3f[] points = [(0, 0, 0)]\n'
        "float[] primvars:widths1 = [1]\nfloat[] primvars:widths2 = [1]\n"
        "quatf[] primvars:rot = [(1, 0, 0, 0)]\n"
        "float[] primvars:displayColor = [1, 2, 3, 4]\n}\n" + PRIM,
    ),
}


def test_usd_malformed_attributes(tmp_path):
    for label, (old, new) in USDA_BAD.items():
        assert old in USDA, label
        path = tmp_path / f"bad_{label}.usda"
        path.write_bytes(USDA.replace(old, new, 1).encode("latin-1"))
        got = outcome(read_splats, path)
        assert got is None, f"{label}: read without an error"
    with pytest.raises(
        SplatFileError,
        match=r"/Splats: positions holds a FloatArray \(float32, shape \(7,\)\), "
        "expected an array of 3-component vectors",
    ):
        read_splats(tmp_path / "bad_positions_float.usda")
    with pytest.raises(SplatFileError, match="radiance:sphericalHarmonicsDegree is 'two', expected an int >= 0"):
        read_splats(tmp_path / "bad_degree_string.usda")
    # the valid original still reads, with the values it states
    good = tmp_path / "good.usda"
    good.write_text(USDA)
    cloud = usd.read(good, axes=None)
    assert np.array_equal(cloud.positions, [[0, 0, 1], [1, 0, 1], [0, 1, 1]])
    assert np.allclose(cloud.opacities, [0.5, 0.25, 1 - 1e-7], rtol=0, atol=1e-6)


def test_usd_extra_dtype_custom_data(tmp_path):
    """The narrow-int marker on an extra's primvar is obeyed only where the values fit it."""
    from pxr import Usd

    cloud = random_cloud(4, sh_degree=0, seed=7)
    cloud.extras["label"] = np.array([1, -2, 3, 100], np.int8)
    path = tmp_path / "extras.usda"
    usd.write(path, cloud)
    assert usd.read(path).extras["label"].dtype == np.int8
    for label, marker, values in [("unknown", "garbage", None), ("not_str", 5, None), ("too_small", "int8", 1000)]:
        stage = Usd.Stage.Open(str(path))
        attr = stage.GetPrimAtPath("/Splats").GetAttribute("primvars:label")
        attr.SetCustomDataByKey(usd.DTYPE_KEY, marker)
        if values is not None:
            attr.Set([values] * 4)
        bad = tmp_path / f"bad_{label}.usda"
        stage.GetRootLayer().Export(str(bad))
        got = outcome(read_splats, bad)
        assert got is not None and got[0].extras["label"].dtype == np.int32
        assert any("does not fit" in str(w.message) for w in got[1])


# OpenEXR ----------------------------------------------------------------------------------------


def test_exr_damage(tmp_path):
    rng = np.random.default_rng(8)
    for compression in ("zip", "none"):
        path = tmp_path / f"valid_{compression}.exr"
        exr.write_exr(path, {"R": rng.random((6, 5)), "Z": np.full((6, 5), np.inf)}, compression=compression)
        data = path.read_bytes()
        for label, bad in damaged(data, 300, seed=30):
            got = outcome(exr.read_exr, write_case(tmp_path, f"{compression}_{label}", ".exr", bad))
            if got is not None:
                assert not any(np.isnan(a).any() for a in got[0].values())


def test_exr_nan_policy(tmp_path):
    path = tmp_path / "nan.exr"
    exr.write_exr(path, {"R": np.zeros((2, 3)), "G": np.ones((2, 3))}, compression="none")
    data = bytearray(path.read_bytes())
    one = struct.pack("<f", 1.0)
    at = data.rindex(one)  # the last G pixel, stored as float32
    data[at : at + 4] = struct.pack("<f", np.nan)
    path.write_bytes(bytes(data))
    with pytest.raises(SplatFileError, match=r"nan.exr: channels hold NaN values \('G' 1\)"):
        exr.read_exr(path)
    with pytest.warns(SplatFileWarning, match="'G' 1"):
        kept = exr.read_exr(path, nan="keep")
    assert np.isnan(kept["G"]).sum() == 1 and (kept["R"] == 0).all()


# images (mesh textures) -------------------------------------------------------------------------


def test_texture_image_damage(tmp_path):
    path = tmp_path / "valid.png"
    image.write_image(path, np.random.default_rng(9).random((6, 5, 3)))
    data = path.read_bytes()
    for label, bad in damaged(data, 33, seed=40):
        got = outcome(mesh.load_image, write_case(tmp_path, label, ".png", bad))
        if got is not None:
            assert got[0].shape == (6, 5, 3)
    # a header claiming 10^10 pixels (with a valid checksum) is refused, not decoded
    import zlib

    bomb = bytearray(data)
    bomb[16:24] = struct.pack(">II", 100_000, 100_000)
    bomb[29:33] = struct.pack(">I", zlib.crc32(bytes(bomb[12:29])))
    with pytest.raises(SplatFileError, match="bad_bomb.png: cannot read image"):
        mesh.load_image(write_case(tmp_path, "bomb", ".png", bytes(bomb)))


# OBJ and MTL ------------------------------------------------------------------------------------

OBJ = b"""mtllib m.mtl
v 0 0 0
v 1 0 0
v 0 1 0 0.5 0.5 0.5
vt 0 0
vt 1 0
vt 0 1
usemtl red
f 1/1 2/2 3/3
f -3 -2 -1
"""
MTL = b"newmtl red\nKd 0.8 0.1 0.1\nmap_Kd -o 0.1 0.2 -s 2 2 tex.png\n"


def finite_materials(materials):
    return all(
        np.isfinite(np.asarray(v, float)).all() for m in materials for v in (m.base_color, m.uv_offset, m.uv_scale)
    )


def finite_mesh(m):
    arrays = [m.vertices] + [a for a in (m.corner_uvs, m.corner_colors) if a is not None]
    return all(np.isfinite(a).all() for a in arrays) and finite_materials(m.materials)


def test_obj_and_mtl_damage(tmp_path):
    image.write_image(tmp_path / "tex.png", np.random.default_rng(0).random((4, 4, 3)))
    (tmp_path / "m.mtl").write_bytes(MTL)
    cases = dict(damaged(OBJ, 13, seed=50))
    cases.update(
        {
            "v_nan": OBJ.replace(b"v 1 0 0", b"v nan 0 0"),
            "v_inf": OBJ.replace(b"v 1 0 0", b"v 1e999 0 0"),
            "vt_nan": OBJ.replace(b"vt 1 0", b"vt nan 0"),
            "colour_nan": OBJ.replace(b"0.5 0.5 0.5", b"inf 0.5 0.5"),
            "binary": bytes(range(256)) * 4,
            "utf16": OBJ.decode().encode("utf-16"),
            "index_huge": OBJ.replace(b"f -3 -2 -1", b"f 1 2 99999999999999999999"),
            "index_zero": OBJ.replace(b"f -3 -2 -1", b"f 0 1 2"),
        }
    )
    for label, bad in cases.items():
        got = outcome(mesh.read_mesh, write_case(tmp_path, label, ".obj", bad))
        if got is not None:
            assert finite_mesh(got[0]), label
    for label in ("v_nan", "v_inf", "vt_nan", "colour_nan", "binary", "index_huge"):
        assert outcome(mesh.read_mesh, tmp_path / f"bad_{label}.obj") is None, label
    with pytest.raises(SplatFileError, match="bad_v_nan.obj: vertex 2 holds NaN or infinite values"):
        mesh.read_mesh(tmp_path / "bad_v_nan.obj")

    mtl_cases = dict(damaged(MTL, 10, seed=51))
    mtl_cases.update(
        {
            "kd_nan": MTL.replace(b"0.8", b"nan"),
            "kd_inf": MTL.replace(b"0.8", b"inf"),
            "offset_nan": MTL.replace(b"-o 0.1", b"-o nan"),
            "scale_inf": MTL.replace(b"-s 2", b"-s -inf"),
            "texture_not_image": MTL.replace(b"tex.png", b"m.mtl"),
            "binary": bytes(range(256)),
        }
    )
    for label, bad in mtl_cases.items():
        got = outcome(mesh.read_mtl, write_case(tmp_path, label, ".mtl", bad))
        if got is not None:
            assert finite_materials(got[0].values()), label
    for label in ("kd_nan", "kd_inf", "offset_nan", "scale_inf"):
        with pytest.raises(SplatFileError, match=f"bad_{label}.mtl: line 2|bad_{label}.mtl: line 3"):
            mesh.read_mtl(tmp_path / f"bad_{label}.mtl")


# URDF -------------------------------------------------------------------------------------------

URDF = b"""<?xml version="1.0"?>
<robot name="r">
 <link name="a"/>
 <link name="b"/>
 <joint name="j" type="revolute">
  <parent link="a"/><child link="b"/>
  <origin xyz="0 0 1" rpy="0 0 0.5"/>
  <axis xyz="0 0 1"/>
  <limit lower="-1" upper="1"/>
 </joint>
</robot>
"""


def test_urdf_damage(tmp_path):
    cases = dict(damaged(URDF, 40, seed=60))
    laughs = (
        b'<?xml version="1.0"?><!DOCTYPE r [<!ENTITY a "aaaaaaaaaa">'
        + b"".join(
            b'<!ENTITY %s "%s">' % (chr(98 + i).encode(), (b"&%s;" % chr(97 + i).encode()) * 10) for i in range(6)
        )
        + b']><robot name="&g;"><link name="a"/></robot>'
    )
    cases.update(
        {
            "limit_nan": URDF.replace(b'upper="1"', b'upper="nan"'),
            "binary": bytes(range(256)),
            "utf16": URDF.decode().replace('<?xml version="1.0"?>', "").encode("utf-16"),
            "latin1": URDF.replace(b'name="r"', b'name="\xe9"'),
            "laughs": laughs,
            "axis_zero": URDF.replace(b'<axis xyz="0 0 1"/>', b'<axis xyz="0 0 0"/>'),
            "axis_overflow": URDF.replace(b'<axis xyz="0 0 1"/>', b'<axis xyz="1e300 1e300 0"/>'),
            "self_parent": URDF.replace(b'<parent link="a"/>', b'<parent link="b"/>'),
        }
    )
    for label, bad in cases.items():
        got = outcome(urdf.read_urdf, write_case(tmp_path, label, ".urdf", bad))
        if got is not None:
            tree = got[0]
            assert np.isfinite(tree.origins).all() and np.isfinite(tree.axes).all()
            assert np.allclose(np.linalg.norm(tree.axes, axis=1), 1)
    for label in ("limit_nan", "binary", "laughs", "axis_zero", "axis_overflow", "self_parent"):
        assert outcome(urdf.read_urdf, tmp_path / f"bad_{label}.urdf") is None, label


# missing paths, directories, unknown formats ----------------------------------------------------

READERS = {
    ".ply": ply.read,
    ".splat": splat.read,
    ".spz": spz.read,
    ".usda": usd.read,
    ".usdc": usd.read,
    ".usdz": usd.read,
    ".exr": exr.read_exr,
    ".png": mesh.load_image,
    ".obj": mesh.read_mesh,
    ".mtl": mesh.read_mtl,
    ".urdf": urdf.read_urdf,
}


@pytest.mark.parametrize("ext", sorted(READERS))
def test_missing_path_and_directory(tmp_path, ext):
    folder = tmp_path / f"folder{ext}"
    folder.mkdir()
    for path in (tmp_path / f"missing{ext}", folder):
        assert outcome(READERS[ext], path) is None
        if ext in (".ply", ".splat", ".spz", ".usda", ".usdc", ".usdz"):
            assert outcome(read_splats, path) is None


def test_read_splats_unknown_formats(tmp_path):
    for name in ("cloud.xyz", "cloud", "cloud.ply.bak", ".ply"):
        path = tmp_path / name
        path.write_bytes(b"ply\n")
        assert outcome(read_splats, path) is None
    upper = tmp_path / "CLOUD.SPLAT"
    splat.write(upper, random_cloud(2, sh_degree=0))
    assert len(read_splats(upper)) == 2


# a fuzz per reader --------------------------------------------------------------------------------
#
# Each reader meets seeded mutations of a file our own writer made: bits flipped, words overwritten
# with boundary values (0, -1, 2^31, lengths near 2^32), bytes cut, blocks deleted and repeated, the
# file cut short. Containers (zip, gzip) are opened and their members mutated, so the damage reaches
# the decoder and not only the checksum. Each case must end in a SplatFileError naming the file or a
# correct read: finite values in arrays of the right shapes. The cases are a fixed seeded sequence;
# a budget of seconds per reader stops it early on a slow machine (never before MIN_CASES).

FUZZ_CASES, MIN_CASES, FUZZ_SECONDS = 60, 15, 1.5
BOUNDARY_WORDS = [0, 1, 0xFF, 0x7F, 0x80, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 0xFFFFFFF0, 1 << 28]


def mutate(data, rng, kind, head):
    """One mutation of `data`, at an offset below `head`: 0 a flipped bit, 1 a boundary word, 2 cut
    short, 3 a block deleted, 4 a block repeated, 5 random bytes."""
    n, b = len(data), bytearray(data)
    at = int(rng.integers(0, max(1, min(n, head))))
    if kind == 0 and n:
        b[at] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:
        b[at : at + 4] = struct.pack("<I", int(rng.choice(BOUNDARY_WORDS)))[: max(0, min(4, n - at))]
    elif kind == 2:
        del b[int(rng.integers(0, max(1, n))) :]
    elif kind == 3:
        del b[at : at + int(rng.integers(1, 64))]
    elif kind == 4:
        b[at:at] = b[at : at + int(rng.integers(1, 64))] * int(rng.integers(1, 4))
    else:
        b[at : at + 8] = rng.integers(0, 256, 8, dtype=np.uint8).tobytes()[: max(0, min(8, n - at))]
    return bytes(b)


def mutations(data, rng, count, head=256):
    """`count` seeded mutations of `data`, every other one aimed at its first `head` bytes."""
    for i in range(count):
        yield f"m{i}k{i % 6}", mutate(data, rng, i % 6, head if i % 2 else len(data))


def zip_members_mutated(data, rng, count):
    """Mutations of one member of a zip archive at a time, the archive rebuilt (stored) around it."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        members = {info.filename: archive.read(info) for info in archive.infolist()}
    names = sorted(members)
    for i in range(count):
        name, kind = names[i % len(names)], i % 6
        bad = mutate(members[name], rng, kind, 64 if i % 4 < 2 else len(members[name]))
        out = io.BytesIO()
        with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
            for other in names:
                archive.writestr(other, bad if other == name else members[other])
        yield f"{name}_{i}k{kind}", out.getvalue()


def gzip_payload_mutated(data, rng, count):
    for label, bad in mutations(gzip.decompress(data), rng, count, head=64):
        yield f"inner_{label}", gzip.compress(bad, 1)


def right_cloud(cloud):
    n = len(cloud)
    k = cloud.sh.shape[1] if cloud.sh.ndim == 3 else -1
    shapes = {
        "positions": (n, 3),
        "rotations": (n, 4),
        "log_scales": (n, 3),
        "opacity_logits": (n,),
        "sh": (n, k, 3),
    }
    for name, shape in shapes.items():
        assert getattr(cloud, name).shape == shape, (name, getattr(cloud, name).shape)
    assert k in (1, 4, 9, 16, 25)
    return finite_cloud(cloud)


def right_exr(channels):
    shapes = {a.shape for a in channels.values()}
    return len(shapes) == 1 and len(next(iter(shapes))) == 2 and all(a.dtype == np.float32 for a in channels.values())


def fuzz_cloud(n=24, degree=1):
    return random_cloud(n, sh_degree=degree, seed=70)


def written(tmp_path, name, write):
    path = tmp_path / "valid" / name
    path.parent.mkdir(exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)
        write(path)
    return path


def made_ply(tmp_path):
    return written(tmp_path, "v.ply", lambda p: ply.write(p, fuzz_cloud()))


def made_compressed(tmp_path):
    return written(tmp_path, "v.compressed.ply", lambda p: compressed_ply.write(p, fuzz_cloud(300)))


def made_spz(version):
    return lambda tmp_path: written(tmp_path, "v.spz", lambda p: spz.write(p, fuzz_cloud(), version=version))


def made_splat(tmp_path):
    return written(tmp_path, "v.splat", lambda p: splat.write(p, fuzz_cloud(degree=0)))


def made_sog(tmp_path):
    return written(tmp_path, "v.sog", lambda p: sog.write(p, fuzz_cloud()))


def made_glb(tmp_path):
    return written(tmp_path, "v.glb", lambda p: gltf.write(p, fuzz_cloud()))


def made_gltf(tmp_path):
    return written(tmp_path, "v.gltf", lambda p: gltf.write(p, fuzz_cloud()))


def made_usd(ext):
    return lambda tmp_path: written(tmp_path, f"v{ext}", lambda p: usd.write(p, fuzz_cloud()))


def made_exr(tmp_path):
    rng = np.random.default_rng(71)
    channels = {"V.Combined.R": rng.random((5, 4)), "V.Depth.Z": rng.random((5, 4))}
    return written(tmp_path, "v.exr", lambda p: exr.write_exr(p, channels, compression="none"))


def raw_and(extra):
    """Mutations of the whole file, then `extra`'s (of what is inside it)."""

    def cases(data, rng):
        yield from mutations(data, rng, FUZZ_CASES // 2)
        yield from extra(data, rng, FUZZ_CASES // 2)

    return cases


# reader id: (make the valid file, read, check a read, cases from the valid bytes)
FUZZED = {
    "ply": (made_ply, read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, head=1200)),
    "compressed_ply": (made_compressed, read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, 1500)),
    "spz2": (made_spz(2), read_splats, right_cloud, raw_and(gzip_payload_mutated)),
    "spz3": (made_spz(3), read_splats, right_cloud, raw_and(gzip_payload_mutated)),
    "spz4": (made_spz(4), read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, head=200)),
    "splat": (made_splat, read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES)),
    "sog": (made_sog, read_splats, right_cloud, raw_and(zip_members_mutated)),
    "glb": (made_glb, read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, head=1500)),
    "gltf": (made_gltf, read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, head=1500)),
    "usda": (made_usd(".usda"), read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, head=600)),
    "usdc": (made_usd(".usdc"), read_splats, right_cloud, lambda d, r: mutations(d, r, FUZZ_CASES, head=88)),
    "usdz": (made_usd(".usdz"), read_splats, right_cloud, raw_and(zip_members_mutated)),
    "exr_plain": (made_exr, read_plain_exr, right_exr, lambda d, r: mutations(d, r, FUZZ_CASES, head=400)),
}


def fuzz_cases(tmp_path, reader):
    """(the valid file, then (label, bytes) of each case in the seeded order)."""
    make, read, right, cases = FUZZED[reader]
    valid = make(tmp_path)
    return valid, cases(valid.read_bytes(), np.random.default_rng(sorted(FUZZED).index(reader) + 80))


@pytest.mark.parametrize("reader", sorted(FUZZED))
def test_reader_fuzz(tmp_path, reader):
    _, read, right, _ = FUZZED[reader]
    valid, cases = fuzz_cases(tmp_path, reader)
    got = outcome(read, valid)
    assert got is not None and right(got[0])  # the valid file reads
    start, done = time.monotonic(), 0
    for label, bad in cases:
        valid.write_bytes(bad)
        case = time.monotonic()
        got = outcome(read, valid)
        assert time.monotonic() - case < 5, f"{reader} {label}: a bomb?"  # generous: cases take milliseconds
        if got is not None:
            assert right(got[0]), f"{reader} {label}: a wrong read"
        done += 1
        if done >= MIN_CASES and time.monotonic() - start > FUZZ_SECONDS:
            break
    assert done >= MIN_CASES
