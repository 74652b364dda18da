"""File sizes computed from a splat count and SH degree by each writer's own layout (io.file_sizes,
what the Blender Splats panel shows), against the files those writers really write."""

import gzip
import struct
import warnings

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core.splats import FIELDS, memory_bytes
from splatwright.io import file_sizes, ply, splat, spz, usd, write_splats

CASES = [(1, 0), (333, 1), (1000, 2), (4097, 3)]


def _write(path, cloud, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_splats(path, cloud, **options)
    return path.stat().st_size


def _spz_data(path):
    """Bytes an SPZ file compresses: the gzip payload (v2/v3) or the streams' sizes in its contents (v4)."""
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        return len(gzip.decompress(raw))
    streams, toc = struct.unpack("<BI", raw[15:20])
    return sum(struct.unpack("<QQ", raw[toc + 16 * i : toc + 16 * i + 16])[1] for i in range(streams))


@pytest.mark.parametrize("count, degree", CASES)
def test_ply_and_splat_sizes_are_exact(tmp_path, count, degree):
    cloud = random_cloud(count, degree, seed=count)
    assert ply.file_size(count, degree) == _write(tmp_path / "a.ply", cloud)
    assert splat.file_size(count, degree) == _write(tmp_path / "a.splat", cloud)


@pytest.mark.parametrize("count, degree", CASES)
@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_size_is_the_data_it_compresses(tmp_path, count, degree, version):
    cloud = random_cloud(count, degree, seed=count)
    written = _write(tmp_path / "a.spz", cloud, version=version)
    assert spz.uncompressed_size(count, degree, version) == _spz_data(tmp_path / "a.spz")
    if count > 100:
        assert written < spz.uncompressed_size(count, degree, version)


@pytest.mark.parametrize("count, degree", CASES[1:])
@pytest.mark.parametrize("half", [False, True])
def test_usd_crate_size_is_its_arrays_and_a_little_structure(tmp_path, count, degree, half):
    if usd.stages.PXR is None:
        pytest.skip("OpenUSD's Python module (usd-core) is not installed")
    cloud = random_cloud(count, degree, seed=count)
    written = _write(tmp_path / "a.usdc", cloud, half=half)
    assert 0 <= written - usd.data_size(count, degree, half) <= 2048


def test_file_sizes_asks_each_format():
    sizes = file_sizes(1000, 3, spz_version=4, half=True)
    assert sizes == {
        "ply": ply.file_size(1000, 3),
        "spz": spz.uncompressed_size(1000, 3, 4),
        "splat": 32_000,
        "usd": usd.data_size(1000, 3, half=True),
    }


@pytest.mark.parametrize("count, degree", CASES)
def test_memory_is_the_clouds_arrays(count, degree):
    cloud = random_cloud(count, degree, seed=1)
    assert memory_bytes(count, degree) == sum(np.asarray(getattr(cloud, f)).nbytes for f in FIELDS)
