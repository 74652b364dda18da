"""XGRIDS's first-generation LCC (`.lcc`): scenes written here from XGRIDS's white paper (meta.lcc,
index.bin, data.bin, shcoef.bin, environment.bin), read by us and by splat-transform 3.10.2 level by
level to the same splats, and by us to the source within the format's quantisation; hostile
indexes, files and folders are refused by name."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import skip_platform
from interop import assert_same_splats, splat_transform
from test_io_fuzz import SMALL_PEAK, outcome, peak_bytes
from test_new_readers import HOSTILE_VALUES, replaced, scalar_paths

from splatwright.core import SplatCloud
from splatwright.core import sh as shmod
from splatwright.core.splats import logit, sigmoid
from splatwright.io import READ_ONLY, SplatFileError, format_of, lcc2, read_splats, write_splats

NAMES = ("index.bin", "data.bin", "shcoef.bin", "environment.bin")


def source_cloud(n, degree, seed, spread=3.0):
    """Splats whose values the format holds: opacities and colours inside (0, 1), SH within +-1."""
    rng = np.random.default_rng(seed)
    sh = rng.uniform(-1, 1, (n, shmod.num_coeffs(degree), 3))
    sh[:, 0] = shmod.rgb_to_dc(rng.uniform(0.02, 0.98, (n, 3)))
    return SplatCloud(
        rng.normal(0, spread, (n, 3)),
        rng.normal(0, 1, (n, 4)),
        rng.uniform(-5, 0, (n, 3)),
        logit(rng.uniform(0.02, 0.98, n)),
        sh,
    )


def quantised(values, low, high, bits):
    return np.round((values - low) / (high - low) * ((1 << bits) - 1)).astype(np.uint32)


def pack_rotations(rotations):
    """The white paper's 32 bits of a quaternion: x, y, z, w less the largest (made positive), 10
    bits each from -sqrt(1/2)..sqrt(1/2), then the largest's index in the top 2 bits."""
    xyzw = rotations[:, [1, 2, 3, 0]] / np.linalg.norm(rotations, axis=1, keepdims=True)
    largest = np.abs(xyzw).argmax(axis=1)
    xyzw *= np.sign(xyzw[np.arange(len(xyzw)), largest])[:, None]
    packed = largest.astype(np.uint32) << 30
    for slot, row in enumerate(xyzw):
        rest = np.delete(row, largest[slot])
        codes = quantised(rest, -np.sqrt(0.5), np.sqrt(0.5), 10)
        packed[slot] |= codes[0] | (codes[1] << 10) | (codes[2] << 20)
    return packed


def records(cloud, scale_range):
    """data.bin's 32-byte records of a cloud (in the scene's axes)."""
    out = np.zeros((len(cloud), 32), np.uint8)
    out[:, 0:12] = cloud.positions.astype("<f4").view(np.uint8).reshape(-1, 12)
    rgb = shmod.dc_to_rgb(cloud.sh[:, 0])
    rgba = np.column_stack([rgb, sigmoid(cloud.opacity_logits)])
    out[:, 12:16] = np.round(rgba * 255).astype(np.uint8)
    scales = quantised(np.exp(cloud.log_scales.astype(np.float64)), *scale_range, 16).astype("<u2")
    out[:, 16:22] = scales.view(np.uint8).reshape(-1, 6)
    out[:, 22:26] = pack_rotations(cloud.rotations.astype(np.float64)).astype("<u4").view(np.uint8).reshape(-1, 4)
    return out


def sh_records(cloud, sh_range):
    """shcoef.bin's 64-byte records: fifteen words of 11/10/11 bits (r, g, b), one unused."""
    low, high = sh_range
    codes = [quantised(cloud.sh[:, 1:, c], low[c], high[c], bits) for c, bits in enumerate((11, 10, 11))]
    words = np.zeros((len(cloud), 16), "<u4")
    words[:, :15] = codes[0] | (codes[1] << 11) | (codes[2] << 21)
    return words.view(np.uint8).reshape(-1, 64)


def ranges(clouds):
    """The attributes' min and max (per axis) over the clouds."""
    scales = np.exp(np.concatenate([c.log_scales for c in clouds]).astype(np.float64))
    sh = np.concatenate([c.sh[:, 1:].reshape(-1, 3) for c in clouds])
    return (scales.min(0), scales.max(0)), (sh.min(0), sh.max(0)) if len(sh) else None


def write_lcc(folder, levels, environment=None, units=3, name="meta.lcc", capitalised=False, **overrides):
    """An LCC scene of `levels` (finest first; SH degree 3 makes it "Quality", 0 "Portable"): each
    level split into `units` cells; data.bin holds the cells one after another, each its levels
    coarsest first, so the offsets jump about; `overrides` replace top-level fields of meta.lcc."""
    quality = levels[0].sh_degree == 3
    total = len(levels)
    scale_range, sh_range = ranges(levels)
    pieces = [np.array_split(np.arange(len(cloud)), units) for cloud in levels]
    data, sh, index = bytearray(), bytearray(), bytearray()
    for unit in range(units):
        entry = [np.uint32(unit | (unit << 16)).tobytes()]
        runs = {}
        for level in reversed(range(total)):
            part = levels[level][pieces[level][unit]]
            runs[level] = (len(part), len(data))
            data += records(part, scale_range).tobytes()
            if quality:
                sh += sh_records(part, sh_range).tobytes()
        for level in range(total):
            count, offset = runs[level]
            entry.append(np.array([count], "<u4").tobytes() + np.array([offset], "<u8").tobytes())
            entry.append(np.array([count * 32], "<u4").tobytes())
        index += b"".join(entry)
    # the white paper's example lists a shcoef range for "Portable" scenes too (splat-transform needs it)
    sh_range = sh_range or (np.zeros(3), np.zeros(3))
    attributes = [
        {"name": "scale", "min": scale_range[0].tolist(), "max": scale_range[1].tolist()},
        {"name": "shcoef", "min": sh_range[0].tolist(), "max": sh_range[1].tolist()},
    ]
    files = {"index.bin": index, "data.bin": data, "shcoef.bin": sh if quality else None}
    if environment is not None:
        env_scale, env_sh = ranges([environment])
        attributes.append({"name": "envscale", "min": env_scale[0].tolist(), "max": env_scale[1].tolist()})
        env = records(environment, env_scale)
        if quality:
            attributes.append({"name": "envshcoef", "min": env_sh[0].tolist(), "max": env_sh[1].tolist()})
            env = np.concatenate([env, sh_records(environment, env_sh)], axis=1)
        files["environment.bin"] = env.tobytes()
    for file, content in files.items():
        if content is not None:
            (folder / (file.capitalize() if capitalised else file)).write_bytes(bytes(content))
    meta = {
        "version": "5.0",
        "totalSplats": sum(len(c) for c in levels),
        "totalLevel": total,
        "cellLengthX": 10.0,
        "cellLengthY": 10.0,
        "indexDataSize": 4 + 16 * total,
        "splats": [len(c) for c in levels],
        "encoding": "COMPRESS",
        "fileType": "Quality" if quality else "Portable",
        "attributes": attributes,
    }
    path = folder / name
    path.write_text(json.dumps({**meta, **overrides}))
    return path


def scene_clouds(degree=3):
    """Level 0 (90 splats), level 1 (30), level 2 (9) and an environment (12, far out)."""
    levels = [source_cloud(n, degree, seed) for n, seed in ((90, 1), (30, 2), (9, 3))]
    return levels, source_cloud(12, degree, 4, spread=40.0)


def check_quantised(got, source):
    """Our reading against the source, turned to the PLY's axes, within LCC's quantisation."""
    want = source.transformed(lcc2.TO_PLY)
    assert len(got) == len(want) and got.sh_degree == want.sh_degree
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-5)  # float32, as written
    # source_cloud's scales lie in (0, 1], so the 16-bit ranges' steps are below 1/65535
    np.testing.assert_allclose(got.scales, want.scales, atol=0.51 / 65535, rtol=1e-6)
    np.testing.assert_allclose(got.opacities, want.opacities, atol=0.51 / 255)
    np.testing.assert_allclose(shmod.dc_to_rgb(got.sh[:, 0]), shmod.dc_to_rgb(want.sh[:, 0]), atol=0.51 / 255)
    if source.sh_degree:
        # the turn mixes a band's coefficients: a band of 2l+1 errors of half a step each, at most
        # sqrt(7) half steps in one coefficient of band 3 (green has 10 bits, red and blue 11)
        spread = float(np.ptp(source.sh[:, 1:].reshape(-1, 3), axis=0).max())
        np.testing.assert_allclose(got.sh[:, 1:], want.sh[:, 1:], atol=spread * 0.5 * np.sqrt(7) / 1023 + 1e-6)
    cos = np.abs((got.unit_rotations * want.unit_rotations).sum(axis=1))
    assert np.degrees(2 * np.arccos(np.minimum(cos, 1))).max() < 0.3  # 10 bits over +-sqrt(1/2)


@pytest.mark.slow
@pytest.mark.parametrize("degree", [3, 0])
def test_lcc_splat_transform_reads_what_we_read(tmp_path, degree):
    """splat-transform 3.10.2 reads the scene ("Quality" with SH, "Portable" without) to the splats we
    read, level by level and in any order, within float32; ours is the source within quantisation."""
    levels, environment = scene_clouds(degree)
    path = write_lcc(tmp_path, levels, environment)
    for level, source in enumerate(levels):
        ours = read_splats(path, levels=level, environment=False)
        check_quantised(ours, source)
        splat_transform(path, "-L", str(level), tmp_path / "theirs.ply")
        assert_same_splats(read_splats(tmp_path / "theirs.ply"), ours, position=1e-5)
    splat_transform(path, tmp_path / "default.ply")  # one level, the finest; no environment
    assert_same_splats(read_splats(tmp_path / "default.ply"), read_splats(path, environment=False), position=1e-5)


def test_lcc_levels_and_environment(tmp_path):
    levels, environment = scene_clouds()
    path = write_lcc(tmp_path, levels, environment)
    check_quantised(read_splats(path), SplatCloud.concatenate([levels[0], environment]))
    check_quantised(read_splats(path, levels="all", environment=False), SplatCloud.concatenate(levels))
    check_quantised(read_splats(path, levels=[-1, 1], environment=False), SplatCloud.concatenate(levels[:0:-1]))
    with pytest.raises(SplatFileError, match=r"meta\.lcc: has 3 levels of detail .* level 3 asked for"):
        read_splats(path, levels=3)


def test_lcc_files_named_as_the_white_paper_writes_them(tmp_path):
    levels, environment = scene_clouds(degree=0)
    path = write_lcc(tmp_path, levels, environment, capitalised=True, name="scene.lcc")
    assert (tmp_path / "Index.bin").exists() and (tmp_path / "Environment.bin").exists()
    check_quantised(read_splats(path), SplatCloud.concatenate([levels[0], environment]))


def test_lcc_dispatches_and_is_read_only(tmp_path):
    assert format_of("x/meta.LCC") == "lcc" and format_of("x/scene.lcc2") == "lcc2" and "lcc" in READ_ONLY
    with pytest.raises(SplatFileError, match=r"meta\.lcc: Splatwright reads this format but does not write it"):
        write_splats(tmp_path / "meta.lcc", source_cloud(3, 0, 0))


def test_blender_import_dialog_offers_lcc_and_export_does_not():
    """The extension's file filters (in a child process: importing them imports bpy)."""
    script = (
        "from splatwright.splat_addon.files import import_export as d; "
        "print(d.FILTER_GLOB); print(d.EXPORT_FILTER_GLOB); print(d.IMPORT_MENU_LABEL)"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    imports, exports, label = done.stdout.splitlines()[-3:]
    assert {"*.lcc", "*.lcc2"} <= set(imports.split(";")) and "*.lcc" not in exports.split(";")
    assert ".lcc)" in label


def small_scene(folder, degree=3, environment=True):
    levels = [source_cloud(8, degree, 5), source_cloud(4, degree, 6)]
    return write_lcc(folder, levels, source_cloud(3, degree, 7) if environment else None, units=2)


def patch_index(folder, unit, level, count=None, offset=None, total=2):
    """Overwrite one index entry's count and/or offset."""
    index = bytearray((folder / "index.bin").read_bytes())
    at = unit * (4 + 16 * total) + 4 + 16 * level
    if count is not None:
        index[at : at + 4] = np.array([count], "<u4").tobytes()
    if offset is not None:
        index[at + 4 : at + 12] = np.array([offset], "<u8").tobytes()
    (folder / "index.bin").write_bytes(bytes(index))


@pytest.mark.parametrize(
    "count, offset, problem",
    [
        (0xFFFFFFFF, None, r"4294967295 splats at byte \d+ of data\.bin overlap another run or lie beyond its"),
        (None, 1 << 63, r"splats at byte 9223372036854775808 of data\.bin overlap another run or lie beyond"),
        (None, (1 << 64) - 1, r"of data\.bin overlap another run or lie beyond"),
        (6, None, r"overlap another run or lie beyond"),  # runs into the next level's splats
        (None, 0, r"overlap another run|names one run of data\.bin twice"),
    ],
)
def test_hostile_lcc_counts_and_offsets_are_refused_before_allocating(tmp_path, count, offset, problem):
    path = small_scene(tmp_path)
    patch_index(tmp_path, unit=1, level=0, count=count, offset=offset)
    assert peak_bytes(lambda: outcome(read_splats, path, levels="all")) < SMALL_PEAK
    with pytest.raises(SplatFileError, match=rf"meta\.lcc: index\.bin: .*({problem})"):
        read_splats(path, levels="all")


@pytest.mark.parametrize(
    "file, keep, problem",
    [
        ("index.bin", -1, r"index\.bin's \d+ bytes are not whole entries of 36 \(2 levels\)"),
        ("data.bin", -1, r"lie beyond its \d+ bytes"),
        ("shcoef.bin", -64, r"shcoef\.bin's \d+ bytes end before the SH"),
        ("environment.bin", -1, r"environment\.bin's \d+ bytes are not whole splats of 96"),
    ],
)
def test_truncated_lcc_files_are_refused(tmp_path, file, keep, problem):
    path = small_scene(tmp_path)
    (tmp_path / file).write_bytes((tmp_path / file).read_bytes()[:keep])
    with pytest.raises(SplatFileError, match=rf"meta\.lcc: .*{problem}"):
        read_splats(path, levels="all")


def test_every_prefix_of_every_lcc_file_reads_or_is_refused_by_name(tmp_path):
    path = small_scene(tmp_path)
    for name in NAMES:
        whole = (tmp_path / name).read_bytes()
        for size in range(0, len(whole), 7):
            (tmp_path / name).write_bytes(whole[:size])
            outcome(read_splats, path, levels="all", nonfinite="keep")
        (tmp_path / name).write_bytes(whole)


@pytest.mark.parametrize(
    "overrides, problem",
    [
        ({"totalLevel": 0}, r"totalLevel must be a whole number from 1 to 64"),
        ({"totalLevel": 1 << 40}, r"totalLevel must be a whole number from 1 to 64"),
        ({"totalLevel": 3}, r"index\.bin's 72 bytes are not whole entries of 52 \(3 levels\)"),
        ({"attributes": {}}, r"attributes must be a list of objects"),
        ({"attributes": []}, r"the attributes give no 'scale' range"),
        ({"attributes": [{"name": "scale", "min": [0, 0, 0], "max": [1, 1, 1]}]}, r"give no 'shcoef' range"),
        ({"attributes": [{"name": "scale", "min": [0, 0], "max": [1, 1, 1]}]}, r"'scale' attribute's min and max"),
    ],
)  # fmt: skip
def test_hostile_lcc_index_is_refused_by_name(tmp_path, overrides, problem):
    path = small_scene(tmp_path)
    document = {**json.loads(path.read_text()), **overrides}
    path.write_text(json.dumps(document))
    with pytest.raises(SplatFileError, match=rf"meta\.lcc: .*{problem}"):
        read_splats(path, levels="all")


def test_every_meta_lcc_value_replaced_reads_or_is_refused_by_name(tmp_path):
    path = small_scene(tmp_path)
    document = json.loads(path.read_text())
    for at in scalar_paths(document):
        for value in HOSTILE_VALUES:
            path.write_text(json.dumps(replaced(document, at, value)))
            outcome(read_splats, path, levels="all", nonfinite="keep")


def test_lcc_data_outside_its_folder_only_with_allow_outside(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    small_scene(outside)
    folder = tmp_path / "scene"
    folder.mkdir()
    path = small_scene(folder)
    try:
        (folder / "data.bin").unlink()
        os.symlink(outside / "data.bin", folder / "data.bin")
    except OSError:
        skip_platform("cannot make symbolic links here")
    with pytest.raises(SplatFileError, match=r"meta\.lcc: LCC data file 'data\.bin' is not a readable file under"):
        read_splats(path)
    assert len(read_splats(path, allow_outside=True, levels="all")) == 15


def test_lcc_data_file_that_is_a_fifo_is_refused_unopened(tmp_path):
    if not hasattr(os, "mkfifo"):
        skip_platform("this platform has no FIFOs")
    path = small_scene(tmp_path)
    for name in ("environment.bin", "shcoef.bin"):
        (tmp_path / name).unlink()
        os.mkfifo(tmp_path / name)
        with pytest.raises(SplatFileError, match=rf"meta\.lcc: LCC data file '{name}' is not a readable file"):
            read_splats(path)
        (tmp_path / name).unlink()
        (tmp_path / name).write_bytes(b"")


def test_missing_index_is_refused_and_missing_environment_is_none(tmp_path):
    path = small_scene(tmp_path, environment=False)
    assert len(read_splats(path)) == 8
    (tmp_path / "index.bin").unlink()
    with pytest.raises(SplatFileError, match=r"meta\.lcc: LCC data file 'index\.bin' is not a readable file"):
        read_splats(path)
