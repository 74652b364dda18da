"""Readers for formats users bring from other tools: mkkellogg's `.ksplat`, PlayCanvas's streamed SOG
(`lod-meta.json`) and XGRIDS's LCC2 (`.lcc2`).

No tool writes `.ksplat` outside a browser, so the tests write it themselves (`write_ksplat`, below,
from the layout GaussianSplats3D's SplatBuffer documents in its code: its bucketing, rounding and
clamping) and splat-transform 3.10.2 reads the same files: both readings must agree, and match the
source within each compression level's quantisation. splat-transform writes streamed SOG on the CPU,
so those files are theirs; hostile variants are built from our own SOG writer. LCC2 scenes are built
to XGRIDS's white paper from our SOG and SPZ writers, and splat-transform reads them too.
"""

import json
import os
import struct
import time
import warnings

import numpy as np
import pytest
from helpers import random_cloud, skip_platform
from interop import matched, splat_transform
from test_io_fuzz import SMALL_PEAK, outcome, peak_bytes

from splatwright.cli import main
from splatwright.core import SplatCloud
from splatwright.core import sh as shmod
from splatwright.core.splats import sigmoid
from splatwright.io import (
    FORMATS,
    SplatFileError,
    SplatFileWarning,
    format_of,
    ksplat,
    lcc2,
    read_splats,
    sog_streamed,
    write_splats,
)

LEVELS = [0, 1, 2]
DEGREES = [0, 1, 2, 3]
BLOCK = 5.0  # GaussianSplats3D's default bucket block size and capacity
CAPACITY = 256


def assert_same_splats(got, want, position=1e-5, opacity=1e-4):
    """Two readers' decodings of one file (in the same order): equal up to float32 round-off (opacity
    1e-4 for the ends, which readers clamp differently: logit(1e-6) or logit(1e-7))."""
    assert len(got) == len(want) and got.sh_degree == want.sh_degree
    np.testing.assert_allclose(got.positions, want.positions, rtol=1e-6, atol=position)
    np.testing.assert_allclose(got.log_scales, want.log_scales, atol=1e-5)
    np.testing.assert_allclose(got.opacities, want.opacities, atol=opacity)
    np.testing.assert_allclose(got.sh, want.sh, atol=1e-5)
    np.testing.assert_allclose(
        got.unit_rotations * np.sign((got.unit_rotations * want.unit_rotations).sum(1))[:, None],
        want.unit_rotations,
        atol=1e-5,
    )


# a small .ksplat writer, as GaussianSplats3D's SplatBuffer writes ----------------------------------


def _buckets(positions, block, capacity):
    """GaussianSplats3D's bucketing: splats binned into a grid of `block`-sized cells from the
    minimum corner; a cell's splats fill buckets of `capacity` in order. (full bucket members,
    partly filled bucket members, each bucket's centre)."""
    low = positions.min(axis=0)
    cells = np.floor((positions - low) / block).astype(np.int64)
    full, partial = [], []
    for cell in np.unique(cells, axis=0):
        members = np.flatnonzero((cells == cell).all(axis=1))
        for start in range(0, len(members), capacity):
            group = members[start : start + capacity]
            (full if len(group) == capacity else partial).append((group, cell * block + low + block / 2))
    ordered = full + partial
    return ordered, len(full), [len(g) for g, _ in partial]


def _section(cloud, level, sh_range, block, capacity):
    """(section header bytes, section data bytes) of one section."""
    n, degree = len(cloud), cloud.sh_degree
    rest = cloud.sh[:, 1:].astype(np.float64)
    stored = np.concatenate(
        [rest[:, b * b - 1 : (b + 1) ** 2 - 1].transpose(0, 2, 1).reshape(n, -1) for b in range(1, degree + 1)]
        or [np.zeros((n, 0))],
        axis=1,
    )
    wide, sh_type = ("<f4", "<f4") if level == 0 else ("<f2", "<f2" if level == 1 else "u1")
    fields = [("position", "<f4" if level == 0 else "<u2", 3), ("scale", wide, 3), ("rotation", wide, 4)]
    fields += [("rgba", "u1", 4)] + ([("sh", sh_type, stored.shape[1])] if degree else [])
    rec = np.zeros(n, fields)
    rgba = np.column_stack([shmod.dc_to_rgb(cloud.sh[:, 0]), sigmoid(cloud.opacity_logits)]) * 255
    rec["rgba"] = np.clip(np.floor(rgba), 0, 255)
    q = cloud.rotations.astype(np.float64)
    rec["rotation"] = q / np.linalg.norm(q, axis=1, keepdims=True)
    rec["scale"] = np.exp(cloud.log_scales.astype(np.float64))
    if degree:
        if level == 2:
            low, high = sh_range
            rec["sh"] = np.clip(np.floor((np.clip(stored, low, high) - low) / (high - low) * 255), 0, 255)
        else:
            rec["sh"] = stored
    buckets, full, partial_lengths = ([], 0, []) if level == 0 else _buckets(cloud.positions, block, capacity)
    storage = b""
    if level == 0:
        rec["position"] = cloud.positions
    else:
        span = 32767
        order = np.concatenate([g for g, _ in buckets])
        centres = np.array([c for _, c in buckets], np.float32)
        centre_of = np.repeat(np.arange(len(buckets)), [len(g) for g, _ in buckets])
        delta = cloud.positions[order].astype(np.float64) - centres[centre_of]
        rec = rec[order]
        rec["position"] = np.clip(np.round(delta * (span / (block / 2))) + span, 0, 2 * span + 1)
        storage = np.array(partial_lengths, "<u4").tobytes() + centres.astype("<f4").tobytes()
    header = bytearray(1024)  # splats, capacity, bucket capacity and count, block size, bytes per bucket,
    # (2 spare bytes), position range, section bytes, full and partly filled buckets, SH degree
    buckets_of = (capacity, len(buckets), block, 12, 32767) if level else (0, 0, 0.0, 0, 0)
    partial = (full, len(partial_lengths)) if level else (0, 0)
    size = len(storage) + rec.nbytes
    struct.pack_into("<IIIIfHxxIIIIH", header, 0, n, n, *buckets_of, size, *partial, degree)
    return bytes(header), storage + rec.tobytes()


def write_ksplat(path, cloud, level, sections=1, block=BLOCK, capacity=CAPACITY, sh_range=None):
    """A .ksplat of `cloud` at a compression level, split into `sections` sections. Level 2's SH
    range is the SH's own (as GaussianSplats3D sets it) unless given."""
    if sh_range is None:
        sh_range = (float(cloud.sh[:, 1:].min()), float(cloud.sh[:, 1:].max())) if cloud.sh_degree else (0, 0)
    parts = [
        _section(piece, level, sh_range, block, capacity)
        for piece in np.array_split(np.arange(len(cloud)), sections)
        for piece in [cloud[piece]]
    ]
    header = bytearray(4096)  # version 0.1, sections (most, present), splats (most, present), level,
    # scene centre, SH range
    struct.pack_into("<BBxxIIIIHxx3fff", header, 0, 0, 1, sections, sections, len(cloud), len(cloud), level,
                     0, 0, 0, *sh_range)  # fmt: skip
    data = bytes(header) + b"".join(h for h, _ in parts) + b"".join(d for _, d in parts)
    with open(path, "wb") as f:
        f.write(data)
    return data


def quantisation(level, cloud, sh_range=None):
    """The largest error per field a level's storage allows (absolute; scales relative)."""
    half = 2.0**-11  # half float's relative step, rounded to nearest: half of it, plus round-off
    if sh_range is None:
        sh_range = (float(cloud.sh[:, 1:].min()), float(cloud.sh[:, 1:].max())) if cloud.sh_degree else (0, 0)
    sh_steps = {0: 1e-6, 1: half * float(np.abs(cloud.sh).max())}
    return {
        "position": 1e-6 if level == 0 else BLOCK / 2 / 32767 * 0.5 + 1e-6,
        "log_scale": 1e-6 if level == 0 else half,
        "rotation": 1e-6 if level == 0 else half,
        "sh": sh_steps[level] if level < 2 else (sh_range[1] - sh_range[0]) / 255,
    }


def check_quantised(got, want, level, sh_range=None):
    """`got` (read from a .ksplat of `want`, in any order) is `want` within the level's steps."""
    got = matched(got, want)
    steps = quantisation(level, want, sh_range)
    assert np.abs(got.positions - want.positions).max() <= steps["position"]
    assert np.abs(got.log_scales - want.log_scales).max() <= steps["log_scale"]
    unit = want.unit_rotations
    assert np.abs(got.rotations - unit).max() <= steps["rotation"]
    # colour and opacity: 8 bits, rounded down by the writer, so within one step below
    dc = shmod.dc_to_rgb(got.sh[:, 0]) - np.clip(shmod.dc_to_rgb(want.sh[:, 0]), 0, 1)
    assert dc.max() <= 1e-6 and dc.min() >= -1 / 255 - 1e-6
    alpha = got.opacities - sigmoid(want.opacity_logits)
    assert alpha.max() <= 1e-6 and alpha.min() >= -1 / 255 - 1e-6
    if want.sh_degree:
        rest = got.sh[:, 1:] - want.sh[:, 1:]
        assert np.abs(rest).max() <= steps["sh"] + 1e-6
        if level == 2:
            assert rest.max() <= 1e-6  # rounded down too
    return got


def ksplat_cloud(n=300, degree=3, seed=0, spread=4.0):
    """A random cloud spread over a few GaussianSplats3D buckets, SH within 8-bit colour's reach."""
    cloud = random_cloud(n, sh_degree=degree, seed=seed, spread=spread)
    cloud.sh[:, 0] = np.clip(cloud.sh[:, 0], -1.7, 1.7)
    return cloud


# .ksplat ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("degree", DEGREES)
def test_ksplat_reads_every_level_and_degree_within_its_quantisation(tmp_path, level, degree):
    cloud = ksplat_cloud(degree=degree, seed=10 * level + degree)
    write_ksplat(tmp_path / "a.ksplat", cloud, level, sections=2, capacity=16)
    got = read_splats(tmp_path / "a.ksplat")
    assert len(got) == len(cloud) and got.sh_degree == degree
    check_quantised(got, cloud, level)


def test_ksplat_level_0_is_exact_and_in_file_order(tmp_path):
    cloud = ksplat_cloud(degree=2, seed=3)
    write_ksplat(tmp_path / "a.ksplat", cloud, 0)
    got = read_splats(tmp_path / "a.ksplat")
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_array_equal(got.sh[:, 1:], cloud.sh[:, 1:])
    np.testing.assert_allclose(got.rotations, cloud.unit_rotations, atol=1e-7)


def test_ksplat_sh_bands_land_where_the_ply_has_them(tmp_path):
    """One coefficient set at a time: the reader puts each stored SH value at the model's
    (coefficient, channel) it came from (GaussianSplats3D: band by band, channel-major)."""
    cloud = ksplat_cloud(n=45, degree=3, seed=4)
    cloud.sh[:, 1:] = 0
    for i in range(45):
        cloud.sh[i, 1 + i // 3, i % 3] = 1.0
    write_ksplat(tmp_path / "a.ksplat", cloud, 1)
    got = matched(read_splats(tmp_path / "a.ksplat"), cloud)
    np.testing.assert_array_equal(got.sh[:, 1:], cloud.sh[:, 1:])
    assert list(ksplat.stored_sh_order(1)) == [0, 3, 6, 1, 4, 7, 2, 5, 8]


def test_ksplat_sh_range_of_zero_means_the_default(tmp_path):
    cloud = ksplat_cloud(n=50, degree=1, seed=5)
    cloud.sh[:, 1:] = np.clip(cloud.sh[:, 1:], -1.5, 1.5)
    data = bytearray(write_ksplat(tmp_path / "a.ksplat", cloud, 2, sh_range=(-1.5, 1.5)))
    struct.pack_into("<ff", data, 36, 0.0, 0.0)  # GaussianSplats3D reads 0 as -1.5 / 1.5
    (tmp_path / "a.ksplat").write_bytes(bytes(data))
    check_quantised(read_splats(tmp_path / "a.ksplat"), cloud, 2, sh_range=(-1.5, 1.5))


@pytest.mark.slow
@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("degree", DEGREES)
def test_ksplat_splat_transform_reads_what_we_read(tmp_path, level, degree):
    """splat-transform 3.10.2 converts our test .ksplat to PLY: its decoding and ours agree to float32
    round-off, and both are the source within the level's quantisation."""
    # 148 splats a section: the second section's buckets start on a 4-byte boundary at every level
    # (splat-transform, like GaussianSplats3D, views them as a Float32Array, which must be aligned)
    cloud = ksplat_cloud(n=296, degree=degree, seed=20 + 10 * level + degree)
    write_ksplat(tmp_path / "a.ksplat", cloud, level, sections=2, capacity=32)
    ours = read_splats(tmp_path / "a.ksplat")
    splat_transform(tmp_path / "a.ksplat", tmp_path / "theirs.ply")
    theirs = matched(read_splats(tmp_path / "theirs.ply"), ours)
    assert_same_splats(theirs, ours)
    check_quantised(theirs, cloud, level)


def ksplat_file(tmp_path, level=1, degree=1, n=40):
    """(path, bytes) of a valid little .ksplat: two sections of 20 splats, each in one cell (two full
    buckets of 8 and a partly filled one of 4)."""
    path = tmp_path / "x.ksplat"
    cloud = ksplat_cloud(n=n, degree=degree, seed=7)
    return path, bytearray(write_ksplat(path, cloud, level, sections=2, block=100.0, capacity=8))


SECTION_AT = ksplat.HEADER_BYTES  # the first section header


@pytest.mark.parametrize(
    "offset, value, fmt, problem",
    [
        (4, 0xFFFFFFFF, "<I", "claims 4294967295 sections, more than the file's"),
        (SECTION_AT + 4, 0xFFFFFFFF, "<I", r"section 0 claims 4294967295 splats and \d+ buckets, beyond the file"),
        (SECTION_AT, 0xFFFFFFFF, "<I", "section 0 claims 4294967295 splats in room for 20"),
        (SECTION_AT + 12, 0x7FFFFFFF, "<I", "section 0 claims 20 splats and 2147483647 buckets, beyond the file"),
        (SECTION_AT + 36, 0x7FFFFFFF, "<I", "section 0 claims 20 splats and .* buckets, beyond the file"),
        (SECTION_AT + 32, 1000, "<I", "1000 full and .* partly filled buckets of 8 do not fit"),
        (SECTION_AT + 8, 0, "<I", "full and .* partly filled buckets of 0 do not fit"),
        (SECTION_AT + 20, 16, "<H", "section 0 stores 16 bytes per bucket, not 12"),
        (SECTION_AT + 40, 9, "<H", "section 0 claims SH degree 9"),
        (16, 41, "<I", "the header claims 41 splats, its sections hold 40"),
        (20, 3, "<H", "compression level 3"),
        (0, 1, "<B", r"\.ksplat version 1\.1"),
    ],
)
def test_hostile_ksplat_counts_are_refused_before_allocating(tmp_path, offset, value, fmt, problem):
    path, data = ksplat_file(tmp_path)
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))
    assert len(data) < 1 << 20
    started = time.perf_counter()
    assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
    assert time.perf_counter() - started < 2.0  # refused from the header (generous: no bomb)
    with pytest.raises(SplatFileError, match=rf"x\.ksplat: .*({problem})"):
        read_splats(path)


def test_hostile_ksplat_partial_buckets_shorter_than_the_section(tmp_path):
    path, data = ksplat_file(tmp_path)
    partial = struct.unpack_from("<I", data, SECTION_AT + 36)[0]
    assert partial > 0
    start = ksplat.HEADER_BYTES + 2 * ksplat.SECTION_HEADER_BYTES  # section 0's partial lengths
    for i in range(partial):
        struct.pack_into("<I", data, start + 4 * i, 0)
    path.write_bytes(bytes(data))
    with pytest.raises(SplatFileError, match=r"section 0 holds 20 splats, more than its buckets"):
        read_splats(path)


@pytest.mark.parametrize("size", [0, 100, ksplat.HEADER_BYTES, ksplat.HEADER_BYTES + 2048 + 50])
def test_truncated_ksplat_is_refused(tmp_path, size):
    path, data = ksplat_file(tmp_path)
    path.write_bytes(bytes(data[:size]))
    with pytest.raises(
        SplatFileError, match=r"x\.ksplat: .*(shorter than a \.ksplat header|beyond the file|more than the file)"
    ):
        read_splats(path)


def test_every_prefix_and_word_of_a_ksplat_reads_or_is_refused_by_name(tmp_path):
    """Sweep: each header word overwritten with extremes, and the file cut at every 97th byte."""
    path, data = ksplat_file(tmp_path, level=2, degree=2)
    header_words = list(range(0, 48, 4)) + [SECTION_AT + o for o in range(0, 44, 4)]
    for offset in header_words:
        for value in (0, 1, 0x7FFF, 0xFFFFFFFF):
            bad = bytearray(data)
            struct.pack_into("<I", bad, offset, value)
            path.write_bytes(bytes(bad))
            outcome(ksplat.read, path, nonfinite="keep")
    for size in range(0, len(data), 97):
        path.write_bytes(bytes(data[:size]))
        assert outcome(ksplat.read, path) is None


# streamed SOG ---------------------------------------------------------------------------------------


def streamed_sources(tmp_path):
    """Three PLYs for splat-transform to stack: level 0 (300 splats), level 1 (a coarser 100) and an
    environment (50, far out)."""
    fine = random_cloud(300, sh_degree=1, seed=30, spread=2.0)
    coarse = random_cloud(100, sh_degree=1, seed=31, spread=2.0)
    env = random_cloud(50, sh_degree=1, seed=32, spread=20.0)
    for name, cloud in (("fine", fine), ("coarse", coarse), ("env", env)):
        write_splats(tmp_path / f"{name}.ply", cloud)
    return fine, coarse, env


@pytest.fixture(scope="module")
def streamed(tmp_path_factory):
    """splat-transform's streamed SOG (on the CPU) of streamed_sources: small chunks, so the tree
    nests and each level spans several units."""
    folder = tmp_path_factory.mktemp("streamed")
    fine, coarse, env = streamed_sources(folder)
    out = folder / "scene" / "lod-meta.json"
    splat_transform(
        "-g", "cpu", folder / "fine.ply", "-l", "0", folder / "coarse.ply", "-l", "1", folder / "env.ply", "-l", "-1",
        "--lod-chunk-count", "0", "--lod-chunk-extent", "2", "--lod-chunk-min", "0", out,
    )  # fmt: skip
    return out, fine, coarse, env


def check_sog_error(got, want):
    """`got` (SOG-decoded `want`, any order) within SOG's quantisation: a 16-bit step of the log
    positions, 8-bit opacity and quaternions, 256-entry codebooks for scales and colours (the SH
    palette is compared through splat-transform's own decoding)."""
    got = matched(got, want)
    logs = np.sign(want.positions) * np.log1p(np.abs(want.positions))
    step = np.ptp(logs, axis=0) / 65535 * (np.abs(want.positions) + 1)
    assert (np.abs(got.positions - want.positions) <= step * 1.01).all()
    assert np.abs(got.opacities - want.opacities).max() <= 1 / 255
    assert np.abs(got.log_scales - want.log_scales).max() < 0.05
    assert np.abs(got.sh[:, 0] - want.sh[:, 0]).max() < 0.02
    cos = np.abs((got.unit_rotations * want.unit_rotations).sum(axis=1))
    assert np.degrees(2 * np.arccos(np.clip(cos, 0, 1))).max() < 2.0


@pytest.mark.slow
def test_streamed_sog_from_splat_transform_reads_finest_all_or_one_level(streamed, tmp_path):
    meta_path, fine, coarse, env = streamed
    meta = json.loads(meta_path.read_text())
    assert meta["counts"] == [300, 100] and len(meta["filenames"]) > 2 and "children" in meta["tree"]
    finest = read_splats(meta_path)  # the default: level 0 and the environment
    assert len(finest) == 350 and finest.sh_degree == 1
    check_sog_error(finest, SplatCloud.concatenate([fine, env]))
    check_sog_error(read_splats(meta_path, levels=1, environment=False), coarse)
    check_sog_error(read_splats(meta_path, levels=[-1], environment=False), coarse)
    check_sog_error(read_splats(meta_path, levels="finest", environment=False), fine)
    everything = read_splats(meta_path, levels="all")
    check_sog_error(everything, SplatCloud.concatenate([fine, coarse, env]))
    assert len(everything) == 450
    # splat-transform's own reading of its file, level by level (without the environment), as PLY
    for level in (0, 1):
        splat_transform(meta_path, "-L", str(level), tmp_path / "theirs.ply")
        ours = read_splats(meta_path, levels=level, environment=False)
        assert_same_splats(matched(read_splats(tmp_path / "theirs.ply"), ours), ours)


def write_streamed(folder, clouds, meta=None, names=None):
    """A streamed SOG built from our SOG writer: one unit per level (`<level>_0/meta.json`), a tree
    of one leaf per unit; `meta` entries override the generated ones."""
    names = names or [f"{level}_0/meta.json" for level in range(len(clouds))]
    for name, cloud in zip(names, clouds, strict=True):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        write_splats(folder / name, cloud, order=None)
    leaf = {str(level): {"file": level, "offset": 0, "count": len(c)} for level, c in enumerate(clouds)}
    content = {
        "version": 1,
        "count": sum(len(c) for c in clouds),
        "counts": [len(c) for c in clouds],
        "lodLevels": len(clouds),
        "filenames": names,
        "tree": {"children": [{"lods": leaf}]},
        **(meta or {}),
    }
    path = folder / "lod-meta.json"
    path.write_text(json.dumps(content))
    return path


def test_streamed_sog_built_from_our_units_keeps_offsets(tmp_path):
    """A leaf's offset and count select that run of the unit: two leaves splitting one unit give
    back the unit in order."""
    fine, coarse = random_cloud(40, sh_degree=0, seed=40), random_cloud(10, sh_degree=0, seed=41)
    leaves = [
        {"lods": {"0": {"file": 0, "offset": 25, "count": 15}, "1": {"file": 1, "offset": 0, "count": 10}}},
        {"lods": {"0": {"file": 0, "offset": 0, "count": 25}}},
    ]
    path = write_streamed(tmp_path, [fine, coarse], {"tree": {"children": leaves}})
    got = read_splats(path)
    unit = read_splats(tmp_path / "0_0" / "meta.json")
    np.testing.assert_array_equal(got.positions, unit.positions)
    check_sog_error(got, fine)
    assert format_of(path) == "sog_streamed" and format_of(tmp_path / "0_0" / "meta.json") == "sog"


@pytest.mark.parametrize(
    "meta, problem",
    [
        ({"counts": [40, 11]}, r"claims \[40, 11\] splats per level, its tree holds \[40, 10\]"),
        ({"tree": {"lods": {"0": {"file": 0, "offset": 30, "count": 20}}}, "counts": None},
         r"splats 30 to 50 of '0_0/meta.json' overlap another reference or lie beyond its 40 splats"),
        ({"tree": {"lods": {"0": {"file": 0, "offset": 0, "count": 1 << 40}}}, "counts": None},
         r"splats 0 to 1099511627776 of '0_0/meta.json'"),
        ({"tree": {"lods": {"0": {"file": 5, "offset": 0, "count": 1}}}, "counts": None}, r"file index below 2"),
        ({"tree": {"lods": {"7": {"file": 0, "offset": 0, "count": 1}}}, "counts": None},
         r"level '7' .* not one of its 2"),
        ({"tree": {"lods": {"0": {"file": 0, "offset": -1, "count": 1}}}, "counts": None}, r"whole-number offset"),
        ({"tree": {"lods": {"0": {"file": 0, "offset": 2**60, "count": 1}}}, "counts": None}, r"whole-number offset"),
        ({"tree": {"lods": {"0": {"file": 0, "offset": 0, "count": 1.5}}}, "counts": None}, r"whole-number offset"),
        ({"tree": {"children": [{"lods": {"0": {"file": 0, "offset": 0, "count": 40}}}] * 2}, "counts": None},
         r"overlap another reference"),
        ({"tree": {"children": "x"}}, r"children must be a list"),
        ({"tree": []}, r"tree must be an object"),
        ({"lodLevels": 0}, r"lodLevels must be a positive whole number"),
        ({"version": 2}, r"streamed SOG version 2"),
        ({"filenames": ["lod-meta.json", "1_0/meta.json"]}, r"SOG unit 'lod-meta.json' is not a SOG"),
        ({"filenames": ["../outside/meta.json", "1_0/meta.json"]},
         r"SOG unit '../outside/meta.json' is not a readable file under"),
        ({"filenames": ["/etc/passwd.sog", "1_0/meta.json"]}, r"SOG unit '/etc/passwd.sog' is not a readable file"),
        ({"filenames": ["0_0/meta.json", "1_0/scene.ply"]}, r"SOG unit '1_0/scene.ply' is not a SOG"),
        ({"environment": "../outside/meta.json"}, r"environment '../outside/meta.json' is not a readable file"),
    ],
)  # fmt: skip
def test_hostile_streamed_sog_is_refused_by_name(tmp_path, meta, problem):
    (tmp_path / "outside").mkdir()
    write_splats(tmp_path / "outside" / "meta.json", random_cloud(5, sh_degree=0, seed=1))
    folder = tmp_path / "scene"
    folder.mkdir()
    clouds = [random_cloud(40, sh_degree=0, seed=42), random_cloud(10, sh_degree=0, seed=43)]
    path = write_streamed(folder, clouds)
    content = {**json.loads(path.read_text()), **meta}
    content = {k: v for k, v in content.items() if v is not None}
    path.write_text(json.dumps(content))
    with pytest.raises(SplatFileError, match=rf"lod-meta\.json: .*{problem}"):
        read_splats(path, levels="all")


def test_streamed_sog_before_versioning_reads(tmp_path):
    """Files written before splat-transform stamped `version`, `count` and `counts` read as well."""
    clouds = [random_cloud(40, sh_degree=1, seed=49), random_cloud(10, sh_degree=1, seed=50)]
    path = write_streamed(tmp_path, clouds)
    content = {k: v for k, v in json.loads(path.read_text()).items() if k not in ("version", "count", "counts")}
    path.write_text(json.dumps(content))
    check_sog_error(read_splats(path, levels="all"), SplatCloud.concatenate(clouds))


def test_streamed_sog_leaves_sharing_a_unit_come_back_in_unit_order(tmp_path):
    unit = random_cloud(2000, sh_degree=0, seed=47)
    leaves = [{"lods": {"0": {"file": 0, "offset": i, "count": 1}}} for i in reversed(range(2000))]
    path = write_streamed(tmp_path, [unit], {"tree": {"children": leaves}})
    np.testing.assert_array_equal(read_splats(path).positions, read_splats(tmp_path / "0_0" / "meta.json").positions)


def test_lod_meta_beyond_the_limit_is_refused_unparsed(tmp_path, monkeypatch):
    path = write_streamed(tmp_path, [random_cloud(40, sh_degree=0, seed=48)])
    monkeypatch.setattr(sog_streamed, "MAX_META_BYTES", path.stat().st_size - 1)
    with pytest.raises(SplatFileError, match=r"lod-meta\.json: lod-meta\.json beyond 0 MiB is refused"):
        read_splats(path)


def test_streamed_sog_outside_its_folder_only_with_allow_outside(tmp_path):
    (tmp_path / "outside").mkdir()
    write_splats(tmp_path / "outside" / "meta.json", random_cloud(5, sh_degree=0, seed=1))
    folder = tmp_path / "scene"
    folder.mkdir()
    path = write_streamed(folder, [random_cloud(40, sh_degree=0, seed=44)], {"environment": "../outside/meta.json"})
    with pytest.raises(SplatFileError, match="is not a readable file under"):
        read_splats(path)
    assert len(read_splats(path, allow_outside=True)) == 45
    assert len(read_splats(path, environment=False)) == 40


def test_streamed_sog_unit_that_is_a_fifo_is_refused_unopened(tmp_path):
    if not hasattr(os, "mkfifo"):
        skip_platform("this platform has no FIFOs")
    path = write_streamed(tmp_path, [random_cloud(40, sh_degree=0, seed=45)])
    os.mkfifo(tmp_path / "fifo.sog")
    content = {**json.loads(path.read_text()), "filenames": ["fifo.sog"]}
    path.write_text(json.dumps(content))
    with pytest.raises(SplatFileError, match="SOG unit 'fifo.sog' is not a readable file"):
        read_splats(path)


def nested_tree(depth):
    """The text of a tree whose one leaf (40 splats of unit 0 at level 0) lies `depth` nodes down."""
    leaf = json.dumps({"lods": {"0": {"file": 0, "offset": 0, "count": 40}}})
    return '{"children": [' * depth + leaf + "]}" * depth


def test_nested_lod_meta_is_walked_without_recursion(tmp_path):
    path = write_streamed(tmp_path, [random_cloud(40, sh_degree=0, seed=46)])
    content = json.loads(path.read_text())
    path.write_text(json.dumps({**content, "tree": "@"}).replace('"@"', nested_tree(200)))
    assert len(read_splats(path)) == 40
    path.write_text(json.dumps({**content, "tree": "@"}).replace('"@"', nested_tree(100_000)))
    with pytest.raises(SplatFileError, match=r"lod-meta\.json: lod-meta\.json nests too deeply"):
        read_splats(path)


# XGRIDS LCC2 --------------------------------------------------------------------------------------


def lcc2_sources():
    """Level 0 (60 splats), level 1 (20) and an environment (10, far out)."""
    return (
        random_cloud(60, sh_degree=1, seed=70, spread=2.0),
        random_cloud(20, sh_degree=1, seed=71, spread=2.0),
        random_cloud(10, sh_degree=1, seed=72, spread=20.0),
    )


def write_lcc2(folder, kind=".sog", legacy=False, **overrides):
    """An LCC2 scene of lcc2_sources as XGRIDS's white paper lays it out: chunk files under data/3dgs,
    the root's one child holding level 1, its two children level 0 (one chunk file, split by start
    and count); `legacy`: the older field names. `overrides` replace top-level fields."""
    fine, coarse, env = lcc2_sources()
    names = [f"data/3dgs/{name}{kind}" for name in ("lod0", "lod1", "env")]
    for name, cloud in zip(names, (fine, coarse, env), strict=True):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        write_splats(folder / name, cloud, **({"order": None} if kind == ".sog" else {}))
    leaves = [
        {"id": "0-0-0", "data": {"3dgs": {"name": 0, "start": 0, "count": 25}}, "childNum": 0},
        {"id": "0-0-1", "data": {"3dgs": {"name": 0, "start": 25, "count": 35}}, "childNum": 0},
    ]
    node = {"id": "0-0", "data": {"3dgs": {"name": 1, "start": 0, "count": 20}}, "childNum": 2, "child": leaves}
    root = {"id": "0", "data": {"env": {"name": 2}}, "childNum": 1, "child": {"0": node}}
    if legacy:  # chunk names from the root, without their extension
        meta = {
            "total_splats": 80,
            "lod_3dgs_info": [20, 60],
            "lod_level": 2,
            "root": {**root, "files": ["/" + n.removesuffix(".sog") for n in names]},
        }
    else:
        meta = {
            "version": "0.0.3",
            "totalSplats": 80,
            "lodSplats": [60, 20],
            "totalLevels": 2,
            "splatType": kind,
            "root": {**root, "splatFiles": names},
        }
    path = folder / "scene.lcc2"
    path.write_text(json.dumps({**meta, **overrides}))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("kind, legacy", [(".sog", False), (".spz", False), (".sog", True)])
def test_lcc2_splat_transform_reads_what_we_read(tmp_path, kind, legacy):
    """splat-transform 3.10.2 reads an LCC2 scene built to the white paper (SOG or SPZ chunks, current
    or older field names) as we do, level by level; ours (every level and the environment) is the
    source turned from Z up to the PLY's axes, within SOG's quantisation."""
    path = write_lcc2(tmp_path, kind, legacy)
    for level in (0, 1):
        splat_transform(path, "-L", str(level), tmp_path / "theirs.ply")
        ours = read_splats(path, levels=level, environment=False)
        assert_same_splats(matched(read_splats(tmp_path / "theirs.ply"), ours), ours)
    splat_transform(path, tmp_path / "default.ply")  # a PLY holds one level: the finest, no environment
    ours = read_splats(path, environment=False)
    assert_same_splats(matched(read_splats(tmp_path / "default.ply"), ours), ours)
    if kind == ".sog":
        everything = SplatCloud.concatenate([cloud.transformed(lcc2.TO_PLY) for cloud in lcc2_sources()])
        check_sog_error(read_splats(path, levels="all"), everything)


@pytest.mark.parametrize(
    "overrides, problem",
    [
        ({"totalLevels": 1}, r"a node 2 deep holds splats, below its 1 levels"),
        ({"totalLevels": 0}, r"totalLevels must be a positive whole number"),
        ({"splatType": ".ply"}, r"splatType '.ply'; this reader takes .sog and .spz"),
        ({"splatType": [".sog"]}, r"splatType '\['.sog'\]'; this reader takes"),
        ({"root": []}, r"root must be an object listing its splatFiles"),
        ({"root": {"splatFiles": ["../outside/x.sog"], "child": [{"data": {"3dgs": {"name": 0, "count": 5}}}]}},
         r"SOG unit '../outside/x.sog' is not a readable file under|'../outside/x.sog' is not a readable file"),
        ({"root": {"splatFiles": ["data/3dgs/lod0.sog"], "child": [{"data": {"3dgs": {"name": 0, "count": 61}}}]}},
         r"splats 0 to 61 of 'data/3dgs/lod0.sog' overlap another reference or lie beyond its 60"),
        ({"root": {"splatFiles": ["data/3dgs/lod0.sog"], "child": [{"data": {"3dgs": {"name": 3, "count": 1}}}]}},
         r"needs a file index below 1"),
        ({"root": {"splatFiles": ["data/3dgs/lod0.sog"], "child": [{"data": {"3dgs": [0]}}]}},
         r"3dgs data must be an object"),
        ({"root": {"splatFiles": ["scene.lcc2"], "child": [{"data": {"3dgs": {"name": 0, "count": 1}}}]}},
         r"'scene.lcc2' is not a .sog file"),
        ({"root": {"splatFiles": ["data/3dgs/lod0.sog"], "data": {"env": {"name": 4}}}}, r"environment names no file"),
        ({"root": {"splatFiles": [], "child": "x"}}, r"child must be a list or an object of nodes"),
    ],
)  # fmt: skip
def test_hostile_lcc2_is_refused_by_name(tmp_path, overrides, problem):
    (tmp_path / "outside").mkdir()
    write_splats(tmp_path / "outside" / "x.sog", random_cloud(5, sh_degree=0, seed=1))
    folder = tmp_path / "scene"
    folder.mkdir()
    path = write_lcc2(folder, **overrides)
    with pytest.raises(SplatFileError, match=rf"scene\.lcc2: .*({problem})"):
        read_splats(path, levels="all")


HOSTILE_VALUES = [-1, 1 << 70, 1.5, "x", None, True, [], {}, [0], {"0": {}}]


def scalar_paths(value, at=()):
    """The key paths of every value in a JSON document, innermost last."""
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else []
    for key, child in children:
        yield from scalar_paths(child, (*at, key))
    if at:
        yield at


def replaced(document, at, value):
    copy = json.loads(json.dumps(document))
    parent = copy
    for key in at[:-1]:
        parent = parent[key]
    parent[at[-1]] = value
    return copy


@pytest.mark.parametrize("fmt", ["lcc2", "lod-meta"])
def test_every_index_value_replaced_reads_or_is_refused_by_name(tmp_path, fmt):
    """Each value of an LCC2 index or a lod-meta.json, in turn, replaced by numbers, strings, lists
    and objects it should not be: a read, or a SplatFileError naming the file; nothing else."""
    if fmt == "lcc2":
        path = write_lcc2(tmp_path, kind=".spz")
    else:
        clouds = [random_cloud(40, sh_degree=0, seed=51), random_cloud(10, sh_degree=0, seed=52)]
        path = write_streamed(tmp_path, clouds)
    document = json.loads(path.read_text())
    for at in scalar_paths(document):
        for value in HOSTILE_VALUES:
            path.write_text(json.dumps(replaced(document, at, value)))
            outcome(read_splats, path, levels="all", nonfinite="keep")


def test_lcc2_is_read_z_up_turned_to_the_ply_axes(tmp_path):
    path = write_lcc2(tmp_path)
    fine, _, env = lcc2_sources()
    unit = read_splats(tmp_path / "data" / "3dgs" / "lod0.sog")
    got = read_splats(path, environment=False)
    np.testing.assert_allclose(got.positions, unit.positions[:, [0, 2, 1]] * [1, -1, 1], atol=1e-6)
    check_sog_error(got, fine.transformed(lcc2.TO_PLY))
    assert len(read_splats(path)) == 70 and len(read_splats(path, levels=1, environment=False)) == 20


# dispatch, the command and the Blender dialog ------------------------------------------------------


def test_new_formats_dispatch_and_are_read_only(tmp_path):
    assert format_of("a.KSPLAT") == "ksplat" and format_of("x/lod-meta.json") == "sog_streamed"
    assert format_of("x/meta.json") == "sog"
    assert FORMATS[".ksplat"] == "ksplat"
    for name in ("out.ksplat", "lod-meta.json"):
        with pytest.raises(SplatFileError, match=rf"{name}: Splatwright reads this format but does not write it"):
            write_splats(tmp_path / name, random_cloud(3, sh_degree=0))
        assert not (tmp_path / name).exists()


def test_command_reads_ksplat(tmp_path, capsys):
    cloud = ksplat_cloud(n=60, degree=1, seed=8)
    write_ksplat(tmp_path / "a.ksplat", cloud, 1)
    assert main(["convert", str(tmp_path / "a.ksplat"), str(tmp_path / "b.ply"), "--no-check"]) == 0
    check_quantised(read_splats(tmp_path / "b.ply"), cloud, 1)
    assert main(["info", "--json", str(tmp_path / "a.ksplat")]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["format"] == "ksplat"


def test_ksplat_zero_scales_are_repaired_with_a_warning(tmp_path):
    cloud = ksplat_cloud(n=20, degree=0, seed=9)
    cloud.log_scales[0] = -30  # below half float's smallest: stored as 0 at level 1
    write_ksplat(tmp_path / "a.ksplat", cloud, 1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = read_splats(tmp_path / "a.ksplat")
    assert any("zero scales" in str(w.message) and issubclass(w.category, SplatFileWarning) for w in caught)
    assert np.isfinite(got.log_scales).all()
