"""Every format both ways against independent tools, installed from their registries on first use
(see tests/interop.py): values equal, or within the format's quantisation, at SH degrees 0..3.

| format | they read ours | we read theirs |
| SPZ v2/v3/v4 | Niantic's library (@adobe/spz), gsply | Niantic's library (byte-identical), gsply |
Further rows sit with their formats below.
"""

import numpy as np
import pytest
from helpers import random_cloud, rebuilt_rotation_bound
from interop import (
    cloud_from_arrays,
    load_arrays,
    load_json,
    matched,
    node,
    ply_arrays,
    python,
    save_arrays,
    save_json,
    splat_transform,
)
from test_spz_splat import check_spz_error, in_range_cloud, spz_rotation_bound

from splatwright.core import SplatCloud
from splatwright.io import read_splats, spz, usd, write_splats

pytestmark = pytest.mark.slow
DEGREES = [0, 1, 2, 3]


# SPZ ------------------------------------------------------------------------------------------------


def niantic_arrays(cloud):
    """The reference library's GaussianCloud fields (RDF, like the model): xyzw quaternions, SH
    coefficient-major with the channel fastest."""
    n, k = len(cloud), cloud.sh.shape[1]
    return dict(
        numPoints=n,
        shDegree=cloud.sh_degree,
        positions=cloud.positions,
        scales=cloud.log_scales,
        rotations=cloud.rotations[:, [1, 2, 3, 0]],
        alphas=cloud.opacity_logits,
        colors=cloud.sh[:, 0],
        sh=cloud.sh[:, 1:].reshape(n, 3 * (k - 1)),
    )


def cloud_from_niantic(a):
    n, k = int(a["numPoints"]), (int(a["shDegree"]) + 1) ** 2
    xyzw = np.asarray(a["rotations"], np.float32).reshape(n, 4)
    sh = np.concatenate([np.reshape(a["colors"], (n, 1, 3)), np.reshape(a["sh"], (n, k - 1, 3))], axis=1)
    return SplatCloud(
        np.reshape(a["positions"], (n, 3)),
        xyzw[:, [3, 0, 1, 2]],
        np.reshape(a["scales"], (n, 3)),
        np.reshape(a["alphas"], n),
        sh,
    )


@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_niantic_both_ways_and_byte_identical(tmp_path, version, degree):
    cloud = in_range_cloud(300, degree=degree, seed=10 * version + degree)
    save_json(tmp_path / "cloud.json", **niantic_arrays(cloud))
    node("adobe_spz.mjs", "write", tmp_path / "cloud.json", tmp_path / "theirs.spz", version)
    spz.write(tmp_path / "ours.spz", cloud, version=version)
    assert (tmp_path / "ours.spz").read_bytes() == (tmp_path / "theirs.spz").read_bytes()
    rotation_bound = spz_rotation_bound(version, cloud)
    check_spz_error(read_splats(tmp_path / "theirs.spz"), cloud, rotation_bound=rotation_bound)
    node("adobe_spz.mjs", "read", tmp_path / "ours.spz", tmp_path / "back.json")
    check_spz_error(cloud_from_niantic(load_json(tmp_path / "back.json")), cloud, rotation_bound=rotation_bound)
    if version == 2:  # v2 keeps x, y, z of the quaternion with w >= 0: compare those
        ours, theirs = read_splats(tmp_path / "ours.spz"), cloud_from_niantic(load_json(tmp_path / "back.json"))
        np.testing.assert_allclose(theirs.rotations, ours.rotations, atol=2e-5)  # w from float32 sqrt


def test_spz_rounding_ties_go_away_from_zero(tmp_path):
    """Values exactly halfway between two steps: Niantic rounds them away from zero (C's round)."""
    cloud = in_range_cloud(8, degree=1, seed=3)
    cloud.positions[:] = (np.arange(24).reshape(8, 3) - 12 + 0.5) / 4096  # every one a tie
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
    if degree:  # 8-bit SH: half a step of 1/128
        assert np.abs(got.sh[:, 1:] - cloud.sh[:, 1:]).max() <= 0.5 / 128 + 1e-6


# the same file decoded by them and by us ---------------------------------------------------------------


def assert_same_splats(got, want, position=1e-6, scale=1e-5, opacity=1e-4, sh=1e-5, angle_deg=0.01):
    """Two decodings of one file: equal up to float32 round-off (the tolerances, absolute; opacity
    1e-4 for the ends, which tools clamp differently: 0, 1e-7, sigmoid(-10))."""
    assert len(got) == len(want) and got.sh_degree == want.sh_degree
    np.testing.assert_allclose(got.positions, want.positions, rtol=1e-6, atol=position)
    np.testing.assert_allclose(got.log_scales, want.log_scales, atol=scale)
    np.testing.assert_allclose(got.opacities, want.opacities, atol=opacity)
    np.testing.assert_allclose(got.sh, want.sh, atol=sh)
    cos = np.abs((got.unit_rotations * want.unit_rotations).sum(axis=1))
    assert np.degrees(2 * np.arccos(np.clip(cos, 0, 1))).max() <= angle_deg


def assert_same_covariances(got, want, rtol=1e-5):
    """The same Gaussians: R S^2 R^T agrees (a quaternion times a half turn about a scale axis is
    another quaternion for the same ellipsoid, which is how tools differ in turning axes)."""
    g, w = got.covariances().astype(np.float64), want.covariances().astype(np.float64)
    size = np.abs(w).max(axis=(1, 2), keepdims=True)
    assert (np.abs(g - w) <= rtol * size).all()


def transform_ply(tmp_path, source, name):
    """splat-transform's own decoding of `source`, as the PLY it writes, read back."""
    splat_transform(source, tmp_path / name)
    return read_splats(tmp_path / name, nonfinite="keep")


# PLY -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", DEGREES)
def test_ply_splat_transform_and_gsply_both_ways(tmp_path, degree):
    cloud = random_cloud(200, sh_degree=degree, seed=degree)
    write_splats(tmp_path / "ours.ply", cloud)
    back = transform_ply(tmp_path, tmp_path / "ours.ply", "theirs.ply")  # they read ours, write theirs
    for got in (back, read_splats(tmp_path / "theirs.ply")):
        np.testing.assert_array_equal(got.positions, cloud.positions)
        np.testing.assert_array_equal(got.sh, cloud.sh)
        np.testing.assert_array_equal(got.rotations, cloud.rotations)
        np.testing.assert_array_equal(got.log_scales, cloud.log_scales)
        np.testing.assert_array_equal(got.opacity_logits, cloud.opacity_logits)
    python("gsply", "gsply_tool.py", "read-ply", tmp_path / "ours.ply", tmp_path / "g.npz")
    got = cloud_from_arrays(load_arrays(tmp_path / "g.npz"))
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_array_equal(got.sh, cloud.sh)


# compressed PLY ------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", DEGREES)
def test_compressed_ply_both_ways(tmp_path, degree):
    cloud = random_cloud(600, sh_degree=degree, seed=20 + degree)
    cloud.sh[:, 1:] = np.clip(cloud.sh[:, 1:], -3.9, 3.9)
    write_splats(tmp_path / "src.ply", cloud)
    write_splats(tmp_path / "ours.compressed.ply", cloud)
    ours = read_splats(tmp_path / "ours.compressed.ply")
    assert_same_splats(transform_ply(tmp_path, tmp_path / "ours.compressed.ply", "a.ply"), ours)
    python("gsply", "gsply_tool.py", "read-ply", tmp_path / "ours.compressed.ply", tmp_path / "g.npz")
    assert_same_splats(cloud_from_arrays(load_arrays(tmp_path / "g.npz")), ours)
    # theirs: splat-transform (Morton order) and gsply, read by us, against their own decoding
    splat_transform(tmp_path / "src.ply", tmp_path / "st.compressed.ply")
    assert_same_splats(
        read_splats(tmp_path / "st.compressed.ply"), transform_ply(tmp_path, tmp_path / "st.compressed.ply", "b.ply")
    )
    save_arrays(tmp_path / "cloud.npz", **ply_arrays(cloud))
    python("gsply", "gsply_tool.py", "write-compressed", tmp_path / "cloud.npz", tmp_path / "gs.compressed.ply")
    python("gsply", "gsply_tool.py", "read-ply", tmp_path / "gs.compressed.ply", tmp_path / "gs.npz")
    assert_same_splats(read_splats(tmp_path / "gs.compressed.ply"), cloud_from_arrays(load_arrays(tmp_path / "gs.npz")))
    # and what they wrote is the input within the format's quantisation
    check_compressed_error(matched(read_splats(tmp_path / "st.compressed.ply"), cloud), cloud)


def check_compressed_error(got, want):
    """Bounds of the compressed layout: 10-11 bits of each chunk's range (at most the cloud's),
    8 bits of colour range and opacity, SH bytes of 1/32."""
    span = lambda a: a.max(axis=0) - a.min(axis=0)  # noqa: E731
    assert (np.abs(got.positions - want.positions) <= span(want.positions) / 2046 + 1e-6).all()
    assert (np.abs(got.log_scales - want.log_scales) <= span(want.log_scales) / 2046 + 1e-5).all()
    assert np.abs(got.opacities - want.opacities).max() <= 0.5 / 255 + 1e-6
    if want.sh_degree:
        assert np.abs(got.sh[:, 1:] - want.sh[:, 1:]).max() <= 1 / 32 + 1e-6


# SOG -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", DEGREES)
def test_sog_both_ways(tmp_path, degree):
    cloud = random_cloud(500, sh_degree=degree, seed=30 + degree)
    write_splats(tmp_path / "src.ply", cloud)
    write_splats(tmp_path / "ours.sog", cloud)
    (tmp_path / "loose").mkdir()
    write_splats(tmp_path / "loose" / "meta.json", cloud)
    ours = read_splats(tmp_path / "ours.sog")
    assert_same_splats(read_splats(tmp_path / "loose" / "meta.json"), ours, position=0, scale=0, opacity=0, sh=0)
    for source in (tmp_path / "ours.sog", tmp_path / "loose" / "meta.json"):
        assert_same_splats(transform_ply(tmp_path, source, "a.ply"), ours)
    python("gsply", "gsply_tool.py", "read-sog", tmp_path / "ours.sog", tmp_path / "g.npz")
    assert_same_splats(cloud_from_arrays(load_arrays(tmp_path / "g.npz")), ours)
    splat_transform("-g", "cpu", tmp_path / "src.ply", tmp_path / "theirs.sog")
    theirs = read_splats(tmp_path / "theirs.sog")
    assert_same_splats(theirs, transform_ply(tmp_path, tmp_path / "theirs.sog", "b.ply"))
    # what they wrote is the input within SOG's quantisation: log-scales and DC colours are the nearest
    # entries of the 256-entry codebooks their file carries, rotations within the 8-bit smallest-three's
    # bound (the SH palette they cluster is compared through splat-transform's own decoding, above)
    got, books = matched(theirs, cloud), sog_codebooks(tmp_path / "theirs.sog")
    assert_same_splats(
        got.with_sh_degree(0).replace(sh=cloud.sh[:, :1], log_scales=cloud.log_scales, rotations=cloud.rotations),
        cloud.with_sh_degree(0),
        position=2e-4,
        scale=0,
        opacity=1 / 255,
        sh=0,
        angle_deg=1e-5,
    )
    nearest = np.abs(cloud.log_scales[..., None] - books["scales"]).min(axis=-1)
    assert (np.abs(got.log_scales - cloud.log_scales) <= nearest + 1e-6).all()
    # splat-transform 2.7.1 gives the odd splat (1-2 of 500 when it writes SH bands) the codebook's first
    # colour on all three channels; every other DC colour is the nearest entry
    nearest = np.abs(cloud.sh[:, 0, :, None] - books["sh0"]).min(axis=-1)
    within = (np.abs(got.sh[:, 0] - cloud.sh[:, 0]) <= nearest + 1e-6).all(axis=1)
    assert (~within).sum() <= len(cloud) // 100 and (got.sh[~within, 0] == np.float32(books["sh0"][0])).all()
    # rotations: three components to 8 bits, the largest rebuilt; theirs reach 1.75 half steps (not
    # rounded to nearest), so the bound allows a whole step
    unit = cloud.unit_rotations
    bound = rebuilt_rotation_bound(unit, np.abs(unit).argmax(axis=1), np.sqrt(2) / 255)
    cos = np.abs((got.unit_rotations * unit).sum(axis=1))
    assert (2 * np.arccos(np.clip(cos, 0, 1)) <= bound).all()


def sog_codebooks(path):
    """The 256-entry codebooks (log-scales, DC colours) an .sog file's meta.json carries."""
    import json
    import zipfile

    with zipfile.ZipFile(path) as archive:
        meta = json.loads(archive.read("meta.json"))
    return {key: np.asarray(meta[key]["codebook"], np.float64) for key in ("scales", "sh0")}


# glTF ----------------------------------------------------------------------------------------------

GLTF_SH_SIGNS = np.float32([1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1])  # parity under x, y -> -x, -y


@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("ext", [".glb", ".gltf"])
def test_gltf_both_ways(tmp_path, degree, ext):
    cloud = random_cloud(200, sh_degree=degree, seed=40 + degree)
    write_splats(tmp_path / f"ours{ext}", cloud)
    node("gltf_read.mjs", tmp_path / f"ours{ext}", tmp_path / "read.json")
    read = load_json(tmp_path / "read.json")
    assert read["extension"]["kernel"] == "ellipse" and "KHR_gaussian_splatting" in read["extensionsUsed"]
    attributes = read["primitives"][0]
    unit = cloud.unit_rotations
    np.testing.assert_array_equal(np.float32(attributes["POSITION"]), cloud.positions * np.float32([-1, -1, 1]))
    np.testing.assert_allclose(
        attributes["KHR_gaussian_splatting:ROTATION"], unit[:, [1, 2, 3, 0]] * [-1, -1, 1, 1], atol=1e-6
    )
    np.testing.assert_allclose(attributes["KHR_gaussian_splatting:SCALE"], cloud.scales, rtol=1e-6)
    np.testing.assert_allclose(np.reshape(attributes["KHR_gaussian_splatting:OPACITY"], -1), cloud.opacities, atol=1e-7)
    for d in range(4):
        for c in range(2 * d + 1):
            name = f"KHR_gaussian_splatting:SH_DEGREE_{d}_COEF_{c}"
            assert (name in attributes) == (d <= degree)
            if d <= degree:
                np.testing.assert_array_equal(
                    np.float32(attributes[name]), cloud.sh[:, d * d + c] * GLTF_SH_SIGNS[d * d + c]
                )
    # theirs (splat-transform's .glb) against their own decoding of the PLY they read
    write_splats(tmp_path / "src.ply", cloud)
    splat_transform(tmp_path / "src.ply", tmp_path / "theirs.glb")
    theirs = read_splats(tmp_path / "theirs.glb")
    assert_same_splats(theirs.replace(rotations=cloud.rotations), cloud, position=0, scale=1e-6, opacity=1e-6, sh=0)
    assert_same_covariances(theirs, cloud)


# .splat --------------------------------------------------------------------------------------------


def test_splat_both_ways(tmp_path):
    cloud = random_cloud(300, sh_degree=0, seed=50)
    cloud.sh[:, 0] = np.clip(cloud.sh[:, 0], -1.7, 1.7)
    write_splats(tmp_path / "src.ply", cloud)
    python("ply2splat", "ply2splat_tool.py", tmp_path / "src.ply", tmp_path / "theirs.splat")
    theirs = read_splats(tmp_path / "theirs.splat")
    np.testing.assert_array_equal(theirs.positions, cloud.positions)
    np.testing.assert_allclose(theirs.scales, cloud.scales, rtol=1e-6)
    # ply2splat truncates colour and opacity to bytes (where we round): within one step
    assert np.abs(theirs.opacities - cloud.opacities).max() <= 1 / 255 + 1e-6
    assert np.abs(theirs.sh[:, 0] - cloud.sh[:, 0]).max() <= 1 / 255 / 0.28209479 + 1e-5
    cos = np.abs((theirs.unit_rotations * cloud.unit_rotations).sum(axis=1))
    assert np.degrees(2 * np.arccos(np.clip(cos, 0, 1))).max() <= 2.0
    write_splats(tmp_path / "ours.splat", cloud)
    assert_same_splats(
        transform_ply(tmp_path, tmp_path / "ours.splat", "a.ply"), read_splats(tmp_path / "ours.splat"), angle_deg=1.0
    )


# OpenUSD -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", DEGREES)
def test_usd_nvidia_converter_and_openusd_schema(tmp_path, degree):
    """NVIDIA's usd-convert-gsplat turns our PLY into OpenUSD: we read the PLY's values back. OpenUSD's
    own schema (in that environment, its own usd-core) reads our file: the values NVIDIA's converter
    writes for the same PLY, with the same metadata, and a transform standing the capture upright."""
    cloud = random_cloud(40, sh_degree=degree, seed=60 + degree)
    write_splats(tmp_path / "src.ply", cloud)
    python("nvidia", "-m", "usd_convert_gsplat", "-i", tmp_path / "src.ply", "-o", tmp_path / "nvidia.usda")
    theirs = read_splats(tmp_path / "nvidia.usda")  # no upright transform: capture values
    np.testing.assert_array_equal(theirs.positions, cloud.positions)
    np.testing.assert_allclose(theirs.sh, cloud.sh, atol=0)
    np.testing.assert_allclose(theirs.log_scales, cloud.log_scales, atol=2e-6)
    np.testing.assert_allclose(theirs.opacities, cloud.opacities, atol=1e-6)
    assert_same_covariances(theirs, cloud)
    # the same file taken in the stage's own axes comes back turned (what the file shows in a viewer)
    turned = usd.read(tmp_path / "nvidia.usda", unmarked="stage")
    np.testing.assert_array_equal(turned.positions, cloud.positions * np.float32([1, -1, -1]))

    write_splats(tmp_path / "ours.usda", cloud)
    python("nvidia", "openusd_read.py", tmp_path / "ours.usda", tmp_path / "ours.npz")
    python("nvidia", "openusd_read.py", tmp_path / "nvidia.usda", tmp_path / "nvidia.npz")
    ours, nvidia = load_arrays(tmp_path / "ours.npz"), load_arrays(tmp_path / "nvidia.npz")
    for name in ("positions", "sh", "degree", "element_size", "interpolation", "up_axis"):
        np.testing.assert_array_equal(ours[name], nvidia[name], err_msg=name)
    for name in ("orientations_xyzw", "scales", "opacities"):
        np.testing.assert_allclose(ours[name], nvidia[name], rtol=2e-7, atol=1e-7, err_msg=name)
    assert int(ours["element_size"]) == (degree + 1) ** 2 and str(ours["interpolation"]) == "vertex"
    np.testing.assert_array_equal(ours["to_world"], np.diag([1.0, -1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(nvidia["to_world"], np.eye(4))
