"""Every format both ways against independent tools, installed from their registries on first use
(see tests/interop.py): values equal, or within the format's quantisation, at SH degrees 0..3.

| format | they read ours | we read theirs |
| SPZ v2/v3/v4 | Niantic's library (@adobe/spz), gsply | Niantic's library (byte-identical), gsply |
Further rows sit with their formats below.
"""

import numpy as np
import pytest
from interop import (cloud_from_arrays, load_arrays, load_json, node, ply_arrays, python, save_arrays,
                     save_json)
from test_spz_splat import check_spz_error, in_range_cloud

from splatwright.core import SplatCloud
from splatwright.io import read_splats, spz, write_splats

pytestmark = pytest.mark.slow
DEGREES = [0, 1, 2, 3]


# SPZ ------------------------------------------------------------------------------------------------

def niantic_arrays(cloud):
    """The reference library's GaussianCloud fields (RDF, like the model): xyzw quaternions, SH
    coefficient-major with the channel fastest."""
    n, k = len(cloud), cloud.sh.shape[1]
    return dict(numPoints=n, shDegree=cloud.sh_degree, positions=cloud.positions, scales=cloud.log_scales,
                rotations=cloud.rotations[:, [1, 2, 3, 0]], alphas=cloud.opacity_logits, colors=cloud.sh[:, 0],
                sh=cloud.sh[:, 1:].reshape(n, 3 * (k - 1)))


def cloud_from_niantic(a):
    n, k = int(a["numPoints"]), (int(a["shDegree"]) + 1) ** 2
    xyzw = np.asarray(a["rotations"], np.float32).reshape(n, 4)
    sh = np.concatenate([np.reshape(a["colors"], (n, 1, 3)), np.reshape(a["sh"], (n, k - 1, 3))], axis=1)
    return SplatCloud(np.reshape(a["positions"], (n, 3)), xyzw[:, [3, 0, 1, 2]], np.reshape(a["scales"], (n, 3)),
                      np.reshape(a["alphas"], n), sh)


@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_niantic_both_ways_and_byte_identical(tmp_path, version, degree):
    cloud = in_range_cloud(300, degree=degree, seed=10 * version + degree)
    save_json(tmp_path / "cloud.json", **niantic_arrays(cloud))
    node("adobe_spz.mjs", "write", tmp_path / "cloud.json", tmp_path / "theirs.spz", version)
    spz.write(tmp_path / "ours.spz", cloud, version=version)
    assert (tmp_path / "ours.spz").read_bytes() == (tmp_path / "theirs.spz").read_bytes()
    rotation_bound = np.pi if version == 2 else np.radians(0.25)
    check_spz_error(read_splats(tmp_path / "theirs.spz"), cloud, rotation_bound=rotation_bound)
    node("adobe_spz.mjs", "read", tmp_path / "ours.spz", tmp_path / "back.json")
    check_spz_error(cloud_from_niantic(load_json(tmp_path / "back.json")), cloud, rotation_bound=rotation_bound)
    if version == 2:    # v2 keeps x, y, z of the quaternion with w >= 0: compare those
        ours, theirs = read_splats(tmp_path / "ours.spz"), cloud_from_niantic(load_json(tmp_path / "back.json"))
        np.testing.assert_allclose(theirs.rotations, ours.rotations, atol=2e-5)   # w from float32 sqrt


def test_spz_rounding_ties_go_away_from_zero(tmp_path):
    """Values exactly halfway between two steps: Niantic rounds them away from zero (C's round)."""
    cloud = in_range_cloud(8, degree=1, seed=3)
    cloud.positions[:] = (np.arange(24).reshape(8, 3) - 12 + 0.5) / 4096       # every one a tie
    cloud.log_scales[:] = (np.arange(24).reshape(8, 3) + 60.5) / 16 - 10
    save_json(tmp_path / "cloud.json", **niantic_arrays(cloud))
    node("adobe_spz.mjs", "write", tmp_path / "cloud.json", tmp_path / "theirs.spz", 4)
    spz.write(tmp_path / "ours.spz", cloud, version=4)
    assert (tmp_path / "ours.spz").read_bytes() == (tmp_path / "theirs.spz").read_bytes()
    got = spz.read(tmp_path / "ours.spz")
    np.testing.assert_array_equal(np.abs(got.positions * 4096), np.ceil(np.abs(cloud.positions * 4096)))


@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("version", [3, 4])
def test_spz_gsply_both_ways(tmp_path, version, degree):
    """gsply stores the PLY's values in SPZ without turning them to SPZ's RUB axes (and with full
    8-bit SH): compared in the file's own axes (axes=None)."""
    cloud = in_range_cloud(300, degree=degree, seed=100 + 10 * version + degree)
    spz.write(tmp_path / "ours.spz", cloud, version=version, axes=None)
    python("gsply", "gsply_tool.py", "read-spz", tmp_path / "ours.spz", tmp_path / "back.npz")
    check_spz_error(cloud_from_arrays(load_arrays(tmp_path / "back.npz")), cloud)
    save_arrays(tmp_path / "cloud.npz", **ply_arrays(cloud))
    python("gsply", "gsply_tool.py", "write-spz", tmp_path / "cloud.npz", tmp_path / "theirs.spz", version)
    got = spz.read(tmp_path / "theirs.spz", axes=None)
    check_spz_error(got, cloud, sh=False)
    if degree:       # 8-bit SH: half a step of 1/128
        assert np.abs(got.sh[:, 1:] - cloud.sh[:, 1:]).max() <= 0.5 / 128 + 1e-6
