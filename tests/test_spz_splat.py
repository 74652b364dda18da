"""SPZ and .splat: hand-built bytes from the format descriptions and closed-form quantisation bounds
(the peer tools reading and writing these files are in test_interop.py)."""

import gzip
import os
import struct
import sys

import numpy as np
import pytest
from helpers import random_cloud, rebuilt_rotation_bound

from splatwright.core import SplatCloud
from splatwright.core import sh as shmod
from splatwright.io import SplatFileWarning, read_splats, splat, spz, write_splats
from splatwright.io.common import SplatFileError

C0 = 0.28209479177387814
# Parity of the 16 SH basis polynomials under y -> -y, z -> -z (worked out by hand, see test_usd.py).
FLIP_SIGNS = np.array([1, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)


def in_range_cloud(n=400, degree=3, seed=0):
    """Random splats whose values all fit SPZ's byte ranges (so only rounding, no clamping)."""
    c = random_cloud(n, sh_degree=degree, seed=seed)
    c.sh[:, 1:] = np.clip(c.sh[:, 1:], -0.99, 0.99)
    c.sh[:, 0] = np.clip(c.sh[:, 0], -3.2, 3.2)
    return c


def angle_between(q1, q2):
    """Rotation angle (radians) between two quaternion arrays (any norm), w first."""
    a = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    b = q2 / np.linalg.norm(q2, axis=1, keepdims=True)
    return 2 * np.arccos(np.clip(np.abs((a * b).sum(axis=1)), 0, 1))


def v2_rotation_bound(want):
    """The largest turn SPZ v2's rotation bytes allow, per splat: x, y, z of the unit quaternion with
    w >= 0, each stored to half a step (1/255) of q * 127.5 + 127.5, w rebuilt from the norm."""
    return rebuilt_rotation_bound(want.unit_rotations, np.zeros(len(want), int), 1 / 255)


def spz_rotation_bound(version, want):
    """v2's per-splat bound, or the smallest-three's 0.25 degrees of v3 and later."""
    return v2_rotation_bound(want) if version == 2 else np.radians(0.25)


def check_spz_error(got, want, fractional_bits=12, rotation_bound=np.radians(0.25), sh=True):
    """Closed-form SPZ quantisation bounds (rounding to nearest in every field)."""
    assert len(got) == len(want)
    assert np.abs(got.positions - want.positions).max() <= 2.0 ** -(fractional_bits + 1) * 1.001
    assert np.abs(got.log_scales - want.log_scales).max() <= 1 / 32 + 1e-6
    assert np.abs(got.opacities - want.opacities).max() <= 0.5 / 255 + 1e-6
    assert np.abs(got.sh[:, 0] - want.sh[:, 0]).max() <= 0.5 / (0.15 * 255) + 1e-6
    if sh and want.sh_degree:
        err = np.abs(got.sh[:, 1:] - want.sh[:, 1:])
        assert err[:, :3].max() <= (4 + 0.5) / 128 + 1e-6  # 5 bits: buckets of 8 steps
        if want.sh_degree > 1:
            assert err[:, 3:].max() <= (8 + 0.5) / 128 + 1e-6  # 4 bits: buckets of 16 steps
    assert (angle_between(got.rotations, want.rotations) <= rotation_bound).all()


# SPZ against hand-built bytes ---------------------------------------------------------------------


def hand_built_v3():
    """Two splats encoded by hand from the SPZ description (RUB axes on disk), and the cloud (RDF) they
    stand for."""
    header = struct.pack("<IIIBBBB", 0x5053474E, 3, 2, 1, 12, 0, 0)
    # positions: RUB (1, 2.5, -0.25) and (-3, 0, 4) in 24-bit fixed point with 12 fractional bits
    fixed = [4096, 10240, -1024, -12288, 0, 16384]
    positions = b"".join(struct.pack("<i", v)[:3] for v in fixed)
    alphas = bytes([255, 51])  # opacities 1 and 0.2
    colors = bytes([128, 128, 128, 255, 0, 166])  # DC (x/255 - 0.5) / 0.15
    scales = bytes([160, 144, 176, 0, 255, 152])  # log scale x/16 - 10
    # rotations, smallest three: identity (largest = w, index 3) and a 90 degree turn about RUB x
    # (x = w = sqrt(1/2): largest is x, index 0; y, z, w follow as sign bit + 9 bits)
    identity = 3 << 30
    turn = (0 << 30) | (0 << 20) | (0 << 10) | 511
    rotations = struct.pack("<II", identity, turn)
    sh = bytes([128, 136, 120, 64, 192, 128, 128, 128, 128, 255, 0, 128][:9] * 2)
    raw = header + positions + alphas + colors + scales + rotations + sh
    flip = np.array([1, -1, -1])
    s = np.sqrt(0.5)
    rub_rot = np.array([[1, 0, 0, 0], [s, s, 0, 0]])  # w, x, y, z
    want_sh = np.zeros((2, 4, 3))
    want_sh[:, 1:] = ((np.array([128, 136, 120, 64, 192, 128, 128, 128, 128]) - 128) / 128).reshape(3, 3)
    want_sh[:, 0] = (np.array([[128, 128, 128], [255, 0, 166]]) / 255 - 0.5) / 0.15
    cloud = SplatCloud(
        positions=np.array([[1, 2.5, -0.25], [-3, 0, 4]]) * flip,
        rotations=rub_rot * np.array([1, 1, -1, -1]),
        log_scales=np.array([[160, 144, 176], [0, 255, 152]]) / 16 - 10,
        opacity_logits=np.log([1e7, 0.25]),  # 1 and 0.2 (0.2/0.8), see the check below
        sh=want_sh * FLIP_SIGNS[None, :4, None],
    )
    return raw, cloud


def test_reads_hand_built_v3(tmp_path):
    raw, want = hand_built_v3()
    path = tmp_path / "hand.spz"
    path.write_bytes(gzip.compress(raw))
    got = spz.read(path)
    np.testing.assert_array_equal(got.positions, want.positions.astype(np.float32))
    np.testing.assert_allclose(got.rotations, want.rotations, atol=1e-7)
    np.testing.assert_array_equal(got.log_scales, want.log_scales.astype(np.float32))
    np.testing.assert_allclose(got.opacities, [1 - 1e-7, 0.2], rtol=1e-6)
    np.testing.assert_allclose(got.sh, want.sh, atol=1e-6)
    raw_axes = spz.read(path, axes=None)
    np.testing.assert_array_equal(raw_axes.positions, [[1, 2.5, -0.25], [-3, 0, 4]])


def test_writes_the_hand_built_bytes(tmp_path):
    raw, cloud = hand_built_v3()
    cloud = cloud.replace(opacity_logits=np.float32([20.0, np.log(0.25)]))
    path = tmp_path / "ours.spz"
    spz.write(path, cloud, version=3)
    assert gzip.decompress(path.read_bytes()) == raw


def test_antialiased_flag_is_header_bit_0_both_ways(tmp_path):
    """The SPZ header's flags byte (offset 14): bit 0 says the splats were made for antialiased
    rendering; reading sets the cloud's flag, writing takes it from the cloud unless told."""
    raw, cloud = hand_built_v3()
    flagged = raw[:14] + bytes([1]) + raw[15:]
    (tmp_path / "aa.spz").write_bytes(gzip.compress(flagged))
    assert spz.read(tmp_path / "aa.spz").antialiased and not spz.read(write_raw(tmp_path, raw)).antialiased
    cloud = cloud.replace(opacity_logits=np.float32([20.0, np.log(0.25)]))
    for made_for, told, bit in [(True, None, 1), (False, None, 0), (True, False, 0), (False, True, 1)]:
        spz.write(tmp_path / "out.spz", cloud.replace(antialiased=made_for), version=3, antialiased=told)
        written = gzip.decompress((tmp_path / "out.spz").read_bytes())
        assert written[14] == bit and written[:14] + written[15:] == raw[:14] + raw[15:]


def write_raw(folder, raw):
    (folder / "plain.spz").write_bytes(gzip.compress(raw))
    return folder / "plain.spz"


def test_v2_rotations_keep_xyz_with_positive_w(tmp_path):
    cloud = in_range_cloud(300, degree=1, seed=4)
    path = tmp_path / "v2.spz"
    spz.write(path, cloud, version=2, axes=None)
    data = gzip.decompress(path.read_bytes())
    n = len(cloud)
    start = 16 + 9 * n + n + 3 * n + 3 * n
    stored = np.frombuffer(data[start : start + 3 * n], np.uint8).reshape(n, 3)
    q = cloud.rotations / np.linalg.norm(cloud.rotations, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1, 1)
    np.testing.assert_array_equal(stored, np.clip(np.rint(q[:, 1:] * 127.5 + 127.5), 0, 255))
    got = spz.read(path, axes=None)
    xyz = stored / 127.5 - 1
    np.testing.assert_allclose(got.rotations[:, 1:], xyz, atol=1e-6)
    np.testing.assert_allclose(got.rotations[:, 0], np.sqrt(np.maximum(0, 1 - (xyz**2).sum(1))), atol=2e-6)


@pytest.mark.parametrize("version", [2, 3, 4])
def test_round_trip_within_quantisation(tmp_path, version):
    cloud = in_range_cloud(500, degree=3, seed=version)
    path = tmp_path / f"v{version}.spz"
    spz.write(path, cloud, version=version)
    got = spz.read(path)
    check_spz_error(got, cloud, rotation_bound=spz_rotation_bound(version, cloud))
    if version == 2:  # x, y, z of the unit quaternion with w >= 0, each to half a step of 1/127.5
        unit = lambda q: q / np.linalg.norm(q, axis=1, keepdims=True) * np.where(q[:, :1] < 0, -1, 1)
        assert np.abs(unit(got.rotations)[:, 1:] - unit(cloud.rotations)[:, 1:]).max() <= 0.5 / 127.5 + 1e-6
    head = path.read_bytes()[:4]
    assert head == (b"NGSP" if version == 4 else b"\x1f\x8b\x08\x00")


def test_gzip_made_of_independent_chunks_is_one_valid_member(tmp_path, monkeypatch):
    cloud = in_range_cloud(2000, seed=5)
    spz.write(tmp_path / "one.spz", cloud)
    monkeypatch.setattr(spz, "GZIP_CHUNK", 4096)
    spz.write(tmp_path / "chunks.spz", cloud)
    one, chunks = (tmp_path / "one.spz").read_bytes(), (tmp_path / "chunks.spz").read_bytes()
    assert one != chunks and gzip.decompress(one) == gzip.decompress(chunks)  # Python's own gunzip
    check_spz_error(spz.read(tmp_path / "chunks.spz"), cloud)


def test_large_v4_uses_the_fast_level_and_decodes_the_same(tmp_path, monkeypatch):
    """Beyond GZIP_CHUNK of data v4 blocks are zstd level 1 frames: other bytes than level 12's,
    the same payload once decompressed (zstandard's own decoder) and the same splats read back."""
    zstandard = pytest.importorskip("zstandard")
    cloud = in_range_cloud(2000, seed=6)
    spz.write(tmp_path / "reference.spz", cloud, version=4)  # 130 kB of data: level 12
    monkeypatch.setattr(spz, "GZIP_CHUNK", 4096)
    spz.write(tmp_path / "fast.spz", cloud, version=4)
    spz.write(tmp_path / "level12.spz", cloud, version=4, level=12)
    reference, fast = (tmp_path / "reference.spz").read_bytes(), (tmp_path / "fast.spz").read_bytes()
    assert (tmp_path / "level12.spz").read_bytes() == reference and fast != reference

    def frames(data):
        count, toc = data[15], struct.unpack_from("<I", data, 16)[0]
        sizes = np.frombuffer(data[toc : toc + 16 * count], "<u8").reshape(-1, 2)
        at, out = toc + 16 * count, []
        for packed, _ in sizes:
            out.append(data[at : at + int(packed)])
            at += int(packed)
        return out

    for mine, theirs in zip(frames(fast), frames(reference), strict=True):
        assert zstandard.get_frame_parameters(mine).content_size == len(zstandard.decompress(theirs))
        assert zstandard.decompress(mine) == zstandard.decompress(theirs)
    got, want = spz.read(tmp_path / "fast.spz"), spz.read(tmp_path / "reference.spz")
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_hard_cases_are_clamped_and_reported(tmp_path):
    cloud = random_cloud(64, sh_degree=2, seed=9)
    cloud.log_scales[:, 0] = np.log(np.geomspace(1e-7, 1e4, 64))
    cloud.opacity_logits[:2] = [1e4, -1e4]
    cloud.positions[5] = [1500.0, -2047.0, 3.0]
    cloud.rotations[6] = 0
    path = tmp_path / "hard.spz"
    with pytest.warns(SplatFileWarning, match=r"log scales outside \[-10, 5.94\] clamped"):
        spz.write(path, cloud)
    got = spz.read(path)
    assert np.isfinite(got.positions).all() and np.isfinite(got.log_scales).all()
    np.testing.assert_allclose(
        got.log_scales[:, 0], np.clip(cloud.log_scales[:, 0], -10, 255 / 16 - 10), atol=1 / 32 + 1e-6
    )
    np.testing.assert_allclose(got.opacities[:2], [1, 0], atol=1e-6)
    np.testing.assert_allclose(got.rotations[6], [1, 0, 0, 0], atol=1e-6)  # zero -> identity
    far = cloud.copy()
    far.positions[0] = [1e6, -2e5, 3]
    with pytest.warns(SplatFileWarning, match=r"stored with 3 fractional bits \(resolution 0.125\)"):
        spz.write(path, far)
    got = spz.read(path)
    assert np.abs(got.positions - far.positions).max() <= 2.0**-4


# Parity of the nine degree-4 polynomials (m = -4..4: xy(xx-yy), yz(3xx-yy), xy(7zz-1), yz(7zz-3),
# 35z^4-30z^2+3, xz(7zz-3), (xx-yy)(7zz-1), xz(xx-3yy), x^4-6xxyy+y^4) under y -> -y, z -> -z, as
# Niantic's converter applies them: its table gives the last (even in y and z) the sign of y.
NIANTIC_FLIP_4 = np.array([-1, 1, -1, 1, 1, -1, 1, -1, -1], np.float32)


def degree_4_bytes(n):
    """A v3 payload of n splats at SH degree 4 (as Niantic's writer makes for any version) whose SH
    bytes count 0, 1, 2, ... coefficient by coefficient, channel fastest."""
    header = struct.pack("<IIIBBBB", 0x5053474E, 3, n, 4, 12, 0, 0)
    body = bytes(9 * n) + bytes([200] * n) + bytes([128] * 3 * n) + bytes([100] * 3 * n)
    return header + body + struct.pack("<III", *(3 << 30,) * n) + bytes(range(24 * 3)) * n


def test_sh_degree_4_files_are_read_whole(tmp_path):
    path = tmp_path / "d4.spz"
    path.write_bytes(gzip.compress(degree_4_bytes(3)))
    got = spz.read(path, axes=None)
    assert got.sh_degree == 4 and got.sh.shape == (3, 25, 3)
    np.testing.assert_allclose(got.sh[0, 1:].reshape(-1), (np.arange(72) - 128) / 128)
    flipped = spz.read(path)  # RUB -> RDF: signs only
    signs = np.concatenate([FLIP_SIGNS[1:], NIANTIC_FLIP_4])
    np.testing.assert_array_equal(flipped.sh[:, 1:], got.sh[:, 1:] * signs[None, :, None])


def v4_blocks(raw):
    """The raw attribute blocks of a v4 file (positions, alphas, colours, scales, rotations[, SH]),
    from its header and table of contents."""
    import zstandard

    magic, version, n, degree, bits, flags, streams, toc = struct.unpack_from("<IIIBBBBI", raw)
    assert (magic, version) == (0x5053474E, 4)
    sizes = np.frombuffer(raw, "<u8", 2 * streams, toc).reshape(streams, 2)
    at, blocks = toc + 16 * streams, []
    for packed, unpacked in sizes.tolist():
        blocks.append(zstandard.ZstdDecompressor().decompress(raw[at : at + packed], max_output_size=unpacked))
        at += packed
    return degree, blocks


def test_degree_4_is_written_as_v4_with_four_bit_buckets(tmp_path):
    """SPZ stores degree 4 from v4 on: write() picks v4 for it, and the fourth band's bytes are
    round(128 x) + 128 to the middle of a 16-step bucket (4 bits, like bands 2 and 3), 72 per splat,
    coefficient-major; read back within half a bucket."""
    cloud = in_range_cloud(300, degree=4, seed=44)
    path = tmp_path / "d4.spz"
    spz.write(path, cloud)
    degree, blocks = v4_blocks(path.read_bytes())
    assert degree == 4 and len(blocks) == 6 and len(blocks[5]) == 300 * 72
    stored = np.frombuffer(blocks[5], np.uint8).reshape(300, 24, 3)
    x = cloud.sh[:, 16:].astype(np.float64) * NIANTIC_FLIP_4[None, :, None]  # RDF -> RUB
    q = np.trunc(x * 128 + np.copysign(0.5, x)) + 128  # C's round()
    np.testing.assert_array_equal(stored[:, 15:], np.clip((q + 8) // 16 * 16, 0, 255))
    got = spz.read(path)
    assert got.sh_degree == 4
    check_spz_error(got, cloud)
    assert np.abs(got.sh[:, 16:] - cloud.sh[:, 16:]).max() <= (8 + 0.5) / 128 + 1e-6
    # without the flip, the same bytes in the file's own axes
    spz.write(tmp_path / "raw.spz", cloud, axes=None)
    raw = np.frombuffer(v4_blocks((tmp_path / "raw.spz").read_bytes())[1][5], np.uint8).reshape(300, 24, 3)
    flips = NIANTIC_FLIP_4 != 1
    np.testing.assert_array_equal(raw[:, 15:][:, ~flips], stored[:, 15:][:, ~flips])


@pytest.mark.parametrize("version", [2, 3])
def test_versions_before_4_reduce_degree_4_to_3_and_say_so(tmp_path, version):
    cloud = in_range_cloud(200, degree=4, seed=45)
    path = tmp_path / "d3.spz"
    with pytest.warns(SplatFileWarning, match=f"SPZ v{version}.*SH degree 4 reduced to 3"):
        spz.write(path, cloud, version=version)
    header = struct.unpack_from("<IIIBBBB", gzip.decompress(path.read_bytes()))
    assert header[1:4] == (version, 200, 3)
    got = spz.read(path)
    assert got.sh_degree == 3
    check_spz_error(got, cloud.with_sh_degree(3), rotation_bound=spz_rotation_bound(version, cloud))
    assert spz.uncompressed_size(200, 4, version) == spz.uncompressed_size(200, 3, version)


def test_bad_spz_files(tmp_path, monkeypatch):
    good = tmp_path / "good.spz"
    spz.write(good, in_range_cloud(100))
    raw = gzip.decompress(good.read_bytes())

    def expect(data, problem, name="bad.spz"):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(SplatFileError, match=problem) as info:
            spz.read(path)
        assert str(path) in str(info.value)

    expect(good.read_bytes()[:300], "truncated")
    expect(b"PK\x03\x04" + bytes(40), "not an SPZ file")
    expect(gzip.compress(struct.pack("<I", 0x12345678) + raw[4:]), "magic 0x12345678")
    expect(gzip.compress(raw[:4] + struct.pack("<I", 9) + raw[8:]), "version 9 is not supported")
    expect(gzip.compress(raw[:4] + struct.pack("<I", 1) + raw[8:]), "version 1 is not supported")
    expect(gzip.compress(raw[:8] + struct.pack("<I", 101) + raw[12:]), "truncated: .* 101 splats")
    expect(gzip.compress(raw[:8] + struct.pack("<I", 99) + raw[12:]), "beyond the data the header describes")
    expect(gzip.compress(raw[:12] + bytes([7]) + raw[13:]), "SH degree 7")
    v4 = tmp_path / "good4.spz"
    spz.write(v4, in_range_cloud(100), version=4)
    data4 = v4.read_bytes()
    expect(data4[:40], "bad v4 table of contents")
    expect(data4[:-50], "truncated: the sh stream runs past the end")
    corrupt = bytearray(data4)
    corrupt[140:150] = bytes(10)
    expect(bytes(corrupt), "corrupt zstd")
    monkeypatch.setitem(sys.modules, "zstandard", None)
    expect(data4, "needs the zstandard package")
    with pytest.raises(SplatFileError, match="needs the zstandard package"):
        spz.write(tmp_path / "no.spz", in_range_cloud(5), version=4)
    assert not (tmp_path / "no.spz").exists()


def test_failed_spz_write_leaves_the_old_file(tmp_path):
    path = tmp_path / "keep.spz"
    spz.write(path, in_range_cloud(10))
    before = path.read_bytes()
    too_far = in_range_cloud(10)
    too_far.positions[2] = [1e7, 0, 0]
    with pytest.raises(SplatFileError, match="do not fit SPZ's 24-bit fixed point"):
        spz.write(path, too_far)
    with pytest.raises(SplatFileError, match="non-finite"):
        spz.write(path, too_far.replace(positions=np.full((10, 3), np.nan)))
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["keep.spz"]


# .splat -------------------------------------------------------------------------------------------


def test_splat_bytes_follow_the_layout(tmp_path):
    cloud = SplatCloud.from_activated(
        positions=[[1.5, -2.0, 3.25]],
        rotations=[[0.0, 0.0, 2.0, 0.0]],
        scales=[[0.5, 0.25, 2.0]],
        opacities=[0.4],
        colors=[[1.0, 0.6, 0.0]],
    )
    path = tmp_path / "one.splat"
    splat.write(path, cloud)
    data = path.read_bytes()
    assert len(data) == 32
    assert struct.unpack("<6f", data[:24]) == (1.5, -2.0, 3.25, 0.5, 0.25, 2.0)
    assert list(data[24:28]) == [255, 153, 0, 102]  # 0.6 * 255 = 153, 0.4 * 255 = 102
    assert list(data[28:32]) == [128, 128, 255, 128]  # (0, 0, 1, 0) * 128 + 128, clamped
    got = splat.read(path)
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_array_equal(got.log_scales, cloud.log_scales)
    np.testing.assert_allclose(got.rotations, [[0, 0, 127 / 128, 0]])
    np.testing.assert_allclose(got.opacities, [102 / 255], rtol=1e-6)
    np.testing.assert_allclose(shmod.dc_to_rgb(got.sh[:, 0]), [[1, 0.6, 0]], atol=1e-6)


def test_splat_round_trip_within_quantisation(tmp_path):
    cloud = random_cloud(300, sh_degree=2, seed=3)
    cloud.sh[:, 0] = shmod.rgb_to_dc(np.random.default_rng(1).uniform(0, 1, (300, 3)))
    path = tmp_path / "r.splat"
    with pytest.warns(SplatFileWarning, match="DC colour only; SH degree 2"):
        write_splats(path, cloud)
    got = read_splats(path)
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_allclose(got.scales, cloud.scales, rtol=1e-6)
    assert np.abs(got.opacities - cloud.opacities).max() <= 0.5 / 255 + 1e-6
    assert np.abs(shmod.dc_to_rgb(got.sh[:, 0]) - shmod.dc_to_rgb(cloud.sh[:, 0])).max() <= 0.5 / 255 + 1e-6
    # splat-transform decodes rotation bytes as b / 127.5 - 1 rather than (b - 128) / 128: half a
    # step more per component than our own reader, hence 2 degrees rather than 1
    assert angle_between(got.rotations, cloud.rotations).max() <= np.radians(2.0)
    assert got.sh_degree == 0


def test_bad_splat_files(tmp_path):
    path = tmp_path / "cut.splat"
    path.write_bytes(bytes(70))
    with pytest.raises(SplatFileError, match="cut.splat: 70 bytes is not a whole number of 32-byte splats"):
        splat.read(path)
    empty = tmp_path / "empty.splat"
    empty.write_bytes(b"")
    assert len(splat.read(empty)) == 0
    record = bytearray(32)
    record[0:24] = struct.pack("<6f", np.nan, 0, 0, 1, 1, 1)
    (tmp_path / "nan.splat").write_bytes(bytes(record))
    with pytest.raises(SplatFileError, match="non-finite"):
        splat.read(tmp_path / "nan.splat")
    with pytest.warns(SplatFileWarning, match="1 of 1 splats have non-finite values"):
        assert len(splat.read(tmp_path / "nan.splat", nonfinite="drop")) == 0


def test_the_v2_rotation_bound_is_tight_and_holds(tmp_path):
    """What v2's bytes do to many quaternions, small w included: never past the per-splat bound, and the
    bound not loose by more than a few times where it matters (the worst splat comes within half of it)."""
    cloud = in_range_cloud(4000, degree=0, seed=5)
    q = np.random.default_rng(6).normal(size=(4000, 4))
    q[:1000, 0] *= 1e-3  # w near zero: where v2 loses most
    cloud = cloud.replace(rotations=q.astype(np.float32))
    write_splats(tmp_path / "v2.spz", cloud, version=2)
    angles, bound = angle_between(read_splats(tmp_path / "v2.spz").rotations, cloud.rotations), v2_rotation_bound(cloud)
    assert (angles <= bound).all()
    assert angles.max() > 0.5 * bound[np.argmax(angles)] and np.degrees(angles.max()) > 2
