"""Every format both ways against independent tools, installed from their registries on first use
(see tests/interop.py): values equal, or within the format's quantisation, at SH degrees 0..3. Which
tool reads and writes what, at which version: docs/formats.md, "Interop with other tools". Tools
reorder splats when they write (splat-transform and spz-js into Morton order), so splats are compared
in any order (interop.matched pairs them by centre). Each tool runs once per format for every degree
(module fixtures batching its jobs); splat-transform's command line once per file.
"""

import io
import json
import zipfile

import numpy as np
import pytest
from helpers import random_cloud, rebuilt_rotation_bound
from interop import (
    assert_same_splats,
    batch,
    batch_in,
    cloud_from_arrays,
    cloud_from_niantic,
    cloud_from_ply_properties,
    load_arrays,
    load_json,
    matched,
    niantic_arrays,
    node,
    ply_arrays,
    ply_properties,
    python,
    save_arrays,
    save_json,
    splat_transform,
)
from test_spz_splat import FLIP_SIGNS, check_spz_error, in_range_cloud, spz_rotation_bound, v2_rotation_bound

from splatwright.core import material
from splatwright.io import read_splats, spz, usd, write_splats

pytestmark = pytest.mark.slow
DEGREES = [0, 1, 2, 3]
# SPZ in the PLY's axes (RDF), with no turn to SPZ's RUB: how splat-transform 3.10.2, gsply and spz-js
# store it (our files so written name the axes in a coordinate-system record)
SPZ_RDF = {"spz_axes": "rdf"}


def check_spz(got, want, **bounds):
    """`got` (in any order) is `want` within SPZ's quantisation (test_spz_splat.check_spz_error)."""
    check_spz_error(matched(got, want), want, **bounds)


def turned_yz(cloud):
    """The cloud seen with y and z reversed (a half turn about x): positions and the quaternion's y, z
    negated, each SH coefficient by its parity (test_spz_splat.FLIP_SIGNS, worked out by hand)."""
    signs = FLIP_SIGNS[: cloud.sh.shape[1], None]
    return cloud.replace(
        positions=cloud.positions * np.float32([1, -1, -1]),
        rotations=cloud.rotations * np.float32([1, 1, -1, -1]),
        sh=cloud.sh * signs,
    )


# PLY -----------------------------------------------------------------------------------------------


def ply_cloud(degree):
    return random_cloud(200, sh_degree=degree, seed=degree)


@pytest.fixture(scope="module")
def ply_work(tmp_path_factory):
    """Our PLY of each SH degree (in folders d0..d3) read, and the tools' own written, by one run of
    each tool (splat-transform: one per file)."""
    work, folders = tmp_path_factory.mktemp("ply"), [f"d{d}" for d in DEGREES]
    for degree, folder in zip(DEGREES, folders, strict=True):
        cloud = ply_cloud(degree)
        (work / folder).mkdir()
        write_splats(work / folder / "ours.ply", cloud)
        save_arrays(work / folder / "cloud.npz", **ply_arrays(cloud))
        save_json(work / folder / "cloud.json", **niantic_arrays(cloud))
        save_arrays(work / folder / "props.npz", **dict(reversed(ply_properties(cloud).items())))
        splat_transform(work / folder / "ours.ply", work / folder / "splat-transform.ply")
    python(
        "gsply",
        "gsply_tool.py",
        *batch_in(folders, ["read-ply", "{}/ours.ply", "{}/g.npz"], ["write-ply", "{}/cloud.npz", "{}/gsply.ply"]),
        cwd=work,
    )
    node(
        "spz_js.mjs",
        *batch_in(folders, ["read-ply", "{}/ours.ply", "{}/js.json"], ["write-ply", "{}/cloud.json", "{}/spz-js.ply"]),
        cwd=work,
    )
    python(
        "plyfile",
        "plyfile_tool.py",
        *batch_in(
            folders,
            ["read", "{}/ours.ply", "{}/plyfile.npz"],
            ["write", "{}/props.npz", "{}/plyfile-ascii.ply", "ascii"],
            ["write", "{}/props.npz", "{}/plyfile-big-endian.ply", "binary_big_endian"],
        ),
        cwd=work,
    )
    return work


@pytest.mark.parametrize("degree", DEGREES)
def test_ply_both_ways(ply_work, degree):
    """Every tool reads our PLY's values bit for bit, and writes values we read bit for bit (plyfile
    in ASCII and big-endian too, properties in reverse order, positions as doubles)."""
    cloud, work = ply_cloud(degree), ply_work / f"d{degree}"
    plyfile_read = load_arrays(work / "plyfile.npz")
    names = list(ply_properties(cloud))
    assert list(plyfile_read["names"]) == names[:3] + ["nx", "ny", "nz"] + names[3:]
    readings = {
        "gsply": cloud_from_arrays(load_arrays(work / "g.npz")),
        "spz-js": cloud_from_niantic(load_json(work / "js.json")),
        "plyfile": cloud_from_ply_properties(plyfile_read),
    }
    for name in ("splat-transform", "gsply", "spz-js", "plyfile-ascii", "plyfile-big-endian"):
        readings[f"our reading of {name}'s"] = read_splats(work / f"{name}.ply")
    for name, got in readings.items():
        got = matched(got, cloud)
        for field in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(got, field), getattr(cloud, field), err_msg=f"{name}: {field}")


# compressed PLY ------------------------------------------------------------------------------------


def compressed_cloud(degree):
    cloud = random_cloud(600, sh_degree=degree, seed=20 + degree)
    cloud.sh[:, 1:] = np.clip(cloud.sh[:, 1:], -3.9, 3.9)
    return cloud


@pytest.fixture(scope="module")
def compressed_work(tmp_path_factory):
    """Our compressed PLY of each SH degree (in folders d0..d3) read, and the tools' own written and
    read, by one run of each tool (splat-transform: one per file)."""
    work, folders = tmp_path_factory.mktemp("compressed"), [f"d{d}" for d in DEGREES]
    for degree, folder in zip(DEGREES, folders, strict=True):
        cloud, here = compressed_cloud(degree), work / folder
        here.mkdir()
        write_splats(here / "src.ply", cloud)
        write_splats(here / "ours.compressed.ply", cloud)
        save_arrays(here / "cloud.npz", **ply_arrays(cloud))
        save_json(here / "cloud.json", **niantic_arrays(cloud))
        splat_transform(here / "src.ply", here / "st.compressed.ply")
        splat_transform(here / "ours.compressed.ply", here / "a.ply")  # their decoding of ours
        splat_transform(here / "st.compressed.ply", here / "b.ply")  # and of their own
    python(
        "gsply",
        "gsply_tool.py",
        *batch_in(
            folders,
            ["read-ply", "{}/ours.compressed.ply", "{}/g.npz"],
            ["write-compressed", "{}/cloud.npz", "{}/gs.compressed.ply"],
            ["read-ply", "{}/gs.compressed.ply", "{}/gs.npz"],
        ),
        cwd=work,
    )
    node(
        "spz_js.mjs",
        *batch_in(
            folders,
            ["read-compressed", "{}/ours.compressed.ply", "{}/js.json"],
            ["write-compressed", "{}/cloud.json", "{}/js.compressed.ply"],
            ["read-compressed", "{}/js.compressed.ply", "{}/js-theirs.json"],
        ),
        cwd=work,
    )
    return work


@pytest.mark.parametrize("degree", DEGREES)
def test_compressed_ply_both_ways(compressed_work, degree):
    """Each tool's decoding of our file is ours; each tool's file decodes the same for it and for us,
    and is the source within the layout's quantisation."""
    cloud, work = compressed_cloud(degree), compressed_work / f"d{degree}"
    ours = read_splats(work / "ours.compressed.ply")
    # spz-js decodes SH bytes b as 8 b / 255 - 4 where we and splat-transform take the bucket's centre,
    # 8 (b + 0.5) / 256 - 4 (at most 1/64 apart), and its reader (1.2.5) fills the SH bands of degrees
    # 1 and 2 from the wrong places (its loop over colour channels stops at the SH degree): there it is
    # compared without them
    spz_js = dict(sh=1 / 64 + 1e-6)
    spz_js_view = (lambda c: c) if degree in (0, 3) else (lambda c: c.with_sh_degree(0))  # noqa: E731
    # they read ours
    assert_same_splats(read_splats(work / "a.ply", nonfinite="keep"), ours)
    assert_same_splats(cloud_from_arrays(load_arrays(work / "g.npz")), ours)
    assert_same_splats(spz_js_view(cloud_from_niantic(load_json(work / "js.json"))), spz_js_view(ours), **spz_js)
    # theirs, read by us: what they read in it, and the source within the layout's quantisation
    theirs = {
        "st": read_splats(work / "b.ply", nonfinite="keep"),
        "gs": cloud_from_arrays(load_arrays(work / "gs.npz")),
    }
    for name, their_reading in theirs.items():
        got = read_splats(work / f"{name}.compressed.ply")
        assert_same_splats(got, their_reading)
        check_compressed_error(matched(got, cloud), cloud)
    got = read_splats(work / "js.compressed.ply")
    assert_same_splats(spz_js_view(got), spz_js_view(cloud_from_niantic(load_json(work / "js-theirs.json"))), **spz_js)
    check_compressed_error(matched(got, cloud), cloud)


def check_compressed_error(got, want):
    """Bounds of the compressed layout: 10-11 bits of each chunk's range (at most the cloud's),
    8 bits of colour range and opacity, SH bytes of 1/32 (truncated by spz-js: a whole step)."""
    span = lambda a: a.max(axis=0) - a.min(axis=0)  # noqa: E731
    assert (np.abs(got.positions - want.positions) <= span(want.positions) / 2046 + 1e-6).all()
    assert (np.abs(got.log_scales - want.log_scales) <= span(want.log_scales) / 2046 + 1e-5).all()
    assert np.abs(got.opacities - want.opacities).max() <= 0.5 / 255 + 1e-6
    if want.sh_degree:
        assert np.abs(got.sh[:, 1:] - want.sh[:, 1:]).max() <= 1 / 32 + 1e-6


# SPZ ------------------------------------------------------------------------------------------------


SPZ_CASES = [(version, degree) for version in (2, 3, 4) for degree in DEGREES]


def spz_cloud(version, degree, seed=0):
    return in_range_cloud(300, degree=degree, seed=seed + 10 * version + degree)


@pytest.fixture(scope="module")
def niantic_work(tmp_path_factory):
    """Niantic's library writing each version and degree (in folders v2d0..v4d3) and reading ours,
    in one run."""
    work, jobs = tmp_path_factory.mktemp("niantic"), []
    for version, degree in SPZ_CASES:
        here = work / f"v{version}d{degree}"
        here.mkdir()
        cloud = spz_cloud(version, degree)
        save_json(here / "cloud.json", **niantic_arrays(cloud))
        spz.write(here / "ours.spz", cloud, version=version)
        jobs += [
            ["write", here / "cloud.json", here / "theirs.spz", version],
            ["read", here / "ours.spz", here / "back.json"],
        ]
    node("adobe_spz.mjs", *batch(*jobs))
    return work


@pytest.mark.parametrize(("version", "degree"), SPZ_CASES)
def test_spz_niantic_both_ways_and_byte_identical(niantic_work, version, degree):
    cloud, work = spz_cloud(version, degree), niantic_work / f"v{version}d{degree}"
    assert (work / "ours.spz").read_bytes() == (work / "theirs.spz").read_bytes()
    rotation_bound = spz_rotation_bound(version, cloud)
    check_spz(read_splats(work / "theirs.spz"), cloud, rotation_bound=rotation_bound)
    theirs = cloud_from_niantic(load_json(work / "back.json"))
    check_spz(theirs, cloud, rotation_bound=rotation_bound)
    if version == 2:  # v2 keeps x, y, z of the quaternion with w >= 0: compare those
        np.testing.assert_allclose(theirs.rotations, read_splats(work / "ours.spz").rotations, atol=2e-5)


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
def test_spz_splat_transform_in_ply_axes_both_ways_and_byte_identical(tmp_path, degree):
    """splat-transform 3.10.2 takes SPZ's values for the PLY's axes (no turn from SPZ's RUB; it reads
    no axes record), and writes v4 by default: our SPZ written with spz_axes="rdf" opens in it as
    its PLY source (within SPZ's quantisation, versions 2 to 4), and its SPZ (v3, v4: Niantic's code
    inside) read with spz_axes="rdf" is its source, in our writer's very bytes."""
    cloud = in_range_cloud(300, degree=degree, seed=20 + degree)
    cloud.opacity_logits[0] = 10.0  # alpha byte 255: a finite logit from their decoder (2.7.1 gave inf)
    write_splats(tmp_path / "src.ply", cloud)
    for version in (2, 3, 4):
        spz.write(tmp_path / f"ours{version}.spz", cloud, version=version, **SPZ_RDF)
        splat_transform(tmp_path / f"ours{version}.spz", tmp_path / f"back{version}.ply")
        back = read_splats(tmp_path / f"back{version}.ply")
        check_spz(back, cloud, rotation_bound=spz_rotation_bound(version, cloud))
    splat_transform(tmp_path / "src.ply", tmp_path / "theirs4.spz")  # no --spz-version: v4
    splat_transform(tmp_path / "src.ply", "--spz-version", 3, tmp_path / "theirs3.spz")
    for version in (3, 4):
        theirs = (tmp_path / f"theirs{version}.spz").read_bytes()
        assert spz.decode("theirs.spz", theirs)[1]["version"] == version
        check_spz(spz.read(tmp_path / f"theirs{version}.spz", **SPZ_RDF), cloud)
        # the values as given (axes=None: no turn, no axes record) are its bytes
        spz.write(tmp_path / "plain.spz", cloud, version=version, axes=None)
        assert theirs == (tmp_path / "plain.spz").read_bytes()


def test_spz_splat_transform_default_axes_turn_y_and_z(tmp_path):
    """Our default SPZ holds SPZ's RUB axes, which splat-transform 3.10.2 takes for the PLY's: it turns
    our file into a PLY with y and z reversed (exactly), and its own SPZ of a PLY, read as SPZ says,
    is that PLY reversed so. This fails the day splat-transform turns SPZ's axes."""
    cloud = in_range_cloud(300, degree=3, seed=29)
    write_splats(tmp_path / "src.ply", cloud)
    spz.write(tmp_path / "ours.spz", cloud)
    splat_transform(tmp_path / "ours.spz", tmp_path / "back.ply")
    splat_transform(tmp_path / "src.ply", tmp_path / "theirs.spz")
    ours = read_splats(tmp_path / "ours.spz")
    back = matched(read_splats(tmp_path / "back.ply", nonfinite="keep"), turned_yz(ours))
    np.testing.assert_array_equal(back.positions, ours.positions * np.float32([1, -1, -1]))
    np.testing.assert_array_equal(back.sh[:, 1:], ours.sh[:, 1:] * FLIP_SIGNS[1:16, None])
    assert_same_splats(back, turned_yz(ours))
    check_spz(read_splats(tmp_path / "theirs.spz"), turned_yz(cloud))


GSPLY_SPZ_CASES = [(version, degree) for version in (3, 4) for degree in DEGREES]


@pytest.fixture(scope="module")
def gsply_spz_work(tmp_path_factory):
    """gsply reading our SPZ (in the PLY's axes) and writing its own, for v3/v4 at each degree (in
    folders v3d0..v4d3), in one run."""
    work, jobs = tmp_path_factory.mktemp("gsply-spz"), []
    for version, degree in GSPLY_SPZ_CASES:
        here = work / f"v{version}d{degree}"
        here.mkdir()
        cloud = spz_cloud(version, degree, seed=100)
        spz.write(here / "ours.spz", cloud, version=version, **SPZ_RDF)
        save_arrays(here / "cloud.npz", **ply_arrays(cloud))
        jobs += [
            ["read-spz", here / "ours.spz", here / "back.npz"],
            ["write-spz", here / "cloud.npz", here / "theirs.spz", version],
        ]
    python("gsply", "gsply_tool.py", *batch(*jobs))
    return work


@pytest.mark.parametrize(("version", "degree"), GSPLY_SPZ_CASES)
def test_spz_gsply_both_ways(gsply_spz_work, version, degree):
    """gsply stores the PLY's values in SPZ without turning them to SPZ's RUB axes (and with full
    8-bit SH): compared in the file's own axes."""
    cloud, work = spz_cloud(version, degree, seed=100), gsply_spz_work / f"v{version}d{degree}"
    check_spz(cloud_from_arrays(load_arrays(work / "back.npz")), cloud)
    got = spz.read(work / "theirs.spz", **SPZ_RDF)
    check_spz(got, cloud, sh=False)
    if degree:  # 8-bit SH: half a step of 1/128
        assert np.abs(matched(got, cloud).sh[:, 1:] - cloud.sh[:, 1:]).max() <= 0.5 / 128 + 1e-6


def spz_js_cloud(degree):
    return in_range_cloud(300, degree=degree, seed=200 + degree)


@pytest.fixture(scope="module")
def spz_js_work(tmp_path_factory):
    """spz-js reading our SPZ v2 and writing and reading its own, at each degree (folders d0..d3), in
    one run. It refuses a file holding anything after the SH block, so an axes record too: ours is
    written with the values as given (axes=None), the model's RDF, and no record."""
    work, folders = tmp_path_factory.mktemp("spz-js"), [f"d{d}" for d in DEGREES]
    for degree, folder in zip(DEGREES, folders, strict=True):
        (work / folder).mkdir()
        spz.write(work / folder / "ours.spz", spz_js_cloud(degree), version=2, axes=None)
        save_json(work / folder / "cloud.json", **niantic_arrays(spz_js_cloud(degree)))
    node(
        "spz_js.mjs",
        *batch_in(
            folders,
            ["read-spz", "{}/ours.spz", "{}/back.json"],
            ["write-spz", "{}/cloud.json", "{}/theirs.spz"],
            ["read-spz", "{}/theirs.spz", "{}/theirs.json"],
        ),
        cwd=work,
    )
    return work


@pytest.mark.parametrize("degree", DEGREES)
def test_spz_spz_js_both_ways(spz_js_work, degree):
    """spz-js reads SPZ v1/v2 and writes v2, in the PLY's axes (no turn to RUB)."""
    cloud, work = spz_js_cloud(degree), spz_js_work / f"d{degree}"
    bound = v2_rotation_bound(cloud)
    check_spz(cloud_from_niantic(load_json(work / "back.json")), cloud, rotation_bound=bound)
    got = spz.read(work / "theirs.spz", **SPZ_RDF)
    assert spz.decode("theirs.spz", (work / "theirs.spz").read_bytes())[1]["version"] == 2
    check_spz(got, cloud, rotation_bound=bound)
    assert_same_splats(got, cloud_from_niantic(load_json(work / "theirs.json")), angle_deg=0.05)


# the same file decoded by them and by us ---------------------------------------------------------------


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


# SOG -----------------------------------------------------------------------------------------------


def sog_cloud(degree):
    return random_cloud(500, sh_degree=degree, seed=30 + degree)


def their_sog(work):
    """Where splat-transform's SOG of a degree's folder is: bundled at odd degrees, loose at even."""
    return work / "theirs.sog" if int(work.name[1:]) % 2 else work / "theirs" / "meta.json"


@pytest.fixture(scope="module")
def sog_work(tmp_path_factory):
    """Our SOG of each SH degree (in folders d0..d3), bundled and loose, and splat-transform's SOG
    (bundled or loose in turn); splat-transform's decoding of each as a PLY (a1: our .sog, a2: our
    loose one, b: its own), gsply's of ours in one run."""
    work, folders = tmp_path_factory.mktemp("sog"), [f"d{d}" for d in DEGREES]
    for degree, folder in zip(DEGREES, folders, strict=True):
        cloud, here = sog_cloud(degree), work / folder
        (here / "loose").mkdir(parents=True)
        write_splats(here / "src.ply", cloud)
        write_splats(here / "ours.sog", cloud)
        write_splats(here / "loose" / "meta.json", cloud)
        their_sog(here).parent.mkdir(exist_ok=True)
        splat_transform("-g", "cpu", here / "src.ply", their_sog(here))
        for source, name in ((here / "ours.sog", "a1.ply"), (here / "loose" / "meta.json", "a2.ply")):
            splat_transform(source, here / name)
        splat_transform(their_sog(here), here / "b.ply")
    python("gsply", "gsply_tool.py", *batch_in(folders, ["read-sog", "{}/ours.sog", "{}/g.npz"]), cwd=work)
    return work


@pytest.mark.parametrize("degree", DEGREES)
def test_sog_both_ways(sog_work, degree):
    """SOG version 2, which splat-transform 3.10.2 writes as .sog or loose beside a meta.json (with SH
    bands it needs `-g cpu` without a GPU): our files, bundled and loose, have the layout its writer
    makes and its reader expects, and it reads them as we do; gsply too. Its files read the same for
    us as for it, and are the source within SOG's quantisation."""
    cloud, work = sog_cloud(degree), sog_work / f"d{degree}"
    theirs_path = their_sog(work)
    (ours_meta, ours), (their_meta, theirs) = sog_files(work / "ours.sog"), sog_files(theirs_path)
    for meta, files in ((ours_meta, ours), sog_files(work / "loose" / "meta.json"), (their_meta, theirs)):
        check_sog_v2_layout(meta, files, len(cloud), degree)
    assert key_paths(ours_meta) == key_paths(their_meta)
    for name in FILES_PER_SPLAT:
        assert pixels(ours[name]).shape == pixels(theirs[name]).shape, name
    if degree:  # the palette's rows of 64 entries: as wide, as many rows as entries need
        assert pixels(ours["shN_centroids.webp"]).shape[1] == pixels(theirs["shN_centroids.webp"]).shape[1]

    ours = read_splats(work / "ours.sog")
    assert_same_splats(read_splats(work / "loose" / "meta.json"), ours, position=0, scale=0, opacity=0, sh=0)
    for name in ("a1.ply", "a2.ply"):
        assert_same_splats(read_splats(work / name, nonfinite="keep"), ours)
    assert_same_splats(cloud_from_arrays(load_arrays(work / "g.npz")), ours)
    theirs = read_splats(theirs_path)
    assert_same_splats(theirs, read_splats(work / "b.ply", nonfinite="keep"))
    # what they wrote is the input within SOG's quantisation: log-scales and DC colours are the nearest
    # entries of the 256-entry codebooks their file carries, rotations within the 8-bit smallest-three's
    # bound (the SH palette they cluster is compared through splat-transform's own decoding, above)
    got, books = matched(theirs, cloud), sog_codebooks(theirs_path)
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
    # splat-transform (2.7.1 to 3.10.2 alike) gives the odd splat (1-2 of 500 when it writes SH bands)
    # the codebook's first colour on all three channels; every other DC colour is the nearest entry
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
    meta, _ = sog_files(path)
    return {key: np.asarray(meta[key]["codebook"], np.float64) for key in ("scales", "sh0")}


# SOG version 2's layout, as PlayCanvas's specification states it and splat-transform 3.10.2's writer
# (writeSogSource) and reader (readSogSourceV2) implement it
FILES_PER_SPLAT = ["means_l.webp", "means_u.webp", "scales.webp", "quats.webp", "sh0.webp"]
SOG_FILES = {
    "means": ["means_l.webp", "means_u.webp"],
    "scales": ["scales.webp"],
    "quats": ["quats.webp"],
    "sh0": ["sh0.webp"],
    "shN": ["shN_centroids.webp", "shN_labels.webp"],
}


def sog_files(path):
    """A SOG's meta.json (parsed) and the bytes of its other files, from a .sog bundle or a loose
    meta.json."""
    if path.suffix == ".sog":
        with zipfile.ZipFile(path) as archive:
            files = {name: archive.read(name) for name in archive.namelist()}
    else:
        files = {p.name: p.read_bytes() for p in path.parent.iterdir()}
    return json.loads(files.pop("meta.json")), files


def pixels(webp):
    """A WebP image's pixels: (height, width, 4) uint8."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(webp)).convert("RGBA"))


def key_paths(tree, prefix=""):
    """Every key path of a JSON object but the free-form "asset" (generator name)."""
    if not isinstance(tree, dict):
        return set()
    paths = set()
    for key, value in tree.items():
        if key != "asset":
            paths |= {prefix + key} | key_paths(value, prefix + key + ".")
    return paths


def check_sog_v2_layout(meta, files, count, degree):
    assert meta["version"] == 2 and meta["count"] == count
    assert set(meta) - {"asset", "model"} == {"version", "count", *SOG_FILES} - (set() if degree else {"shN"})
    for key in meta.keys() & SOG_FILES.keys():
        assert meta[key]["files"] == SOG_FILES[key]
        for name in SOG_FILES[key]:  # lossless WebP (a VP8L chunk): lossy would change the values
            assert files[name][:4] == b"RIFF" and files[name][8:16] == b"WEBPVP8L", name
    assert len(meta["means"]["mins"]) == len(meta["means"]["maxs"]) == 3
    assert (np.asarray(meta["means"]["mins"]) <= meta["means"]["maxs"]).all()
    assert len(meta["scales"]["codebook"]) == len(meta["sh0"]["codebook"]) == 256
    # every per-splat image alike: one splat per pixel, row by row, as wide as splat-transform sizes them
    width = int(np.ceil(np.sqrt(count) / 4) * 4)
    names = FILES_PER_SPLAT + (["shN_labels.webp"] if degree else [])
    assert {pixels(files[name]).shape for name in names} == {(int(np.ceil(count / width / 4) * 4), width, 4)}
    quats = pixels(files["quats.webp"]).reshape(-1, 4)[:count]
    assert ((quats[:, 3] >= 252) & (quats[:, 3] <= 255)).all()  # 252 + the largest component's index
    if degree:
        shn = meta["shN"]
        assert shn["bands"] == degree and len(shn["codebook"]) == 256
        rows, width, _ = pixels(files["shN_centroids.webp"]).shape
        assert width == 64 * ((degree + 1) ** 2 - 1) and rows * 64 >= shn["count"]
        labels = pixels(files["shN_labels.webp"]).reshape(-1, 4)[:count].astype(int)
        assert (labels[:, 0] + 256 * labels[:, 1] < shn["count"]).all()


# glTF ----------------------------------------------------------------------------------------------

GLTF_SH_SIGNS = np.float32([1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1])  # parity under x, y -> -x, -y


def gltf_cloud(degree):
    return random_cloud(200, sh_degree=degree, seed=40 + degree)


def gltf_material(cloud):
    """`cloud` with a material (albedo, normals, roughness, metallic): the extras our glTF carries."""
    rng = np.random.default_rng(len(cloud))
    n = len(cloud)
    return material.with_material(
        cloud, albedo=rng.uniform(0, 1, (n, 3)), normals=rng.normal(size=(n, 3)), roughness=rng.uniform(0, 1, n),
        metallic=rng.uniform(0, 1, n),
    )  # fmt: skip


@pytest.fixture(scope="module")
def gltf_work(tmp_path_factory):
    """For each SH degree (folders d0..d3): glTF Transform reading our .glb and .gltf (one run), and
    splat-transform's .glb of our PLY."""
    work, folders = tmp_path_factory.mktemp("gltf"), [f"d{d}" for d in DEGREES]
    for degree, folder in zip(DEGREES, folders, strict=True):
        cloud, here = gltf_cloud(degree), work / folder
        here.mkdir()
        for ext in (".glb", ".gltf"):
            write_splats(here / f"ours{ext}", gltf_material(cloud))
        write_splats(here / "src.ply", cloud)
        splat_transform(here / "src.ply", here / "theirs.glb")
    jobs = [["{}/ours.glb", "{}/read.glb.json"], ["{}/ours.gltf", "{}/read.gltf.json"]]
    node("gltf_read.mjs", *batch_in(folders, *jobs), cwd=work)
    return work


@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("ext", [".glb", ".gltf"])
def test_gltf_both_ways(gltf_work, degree, ext):
    cloud, work = gltf_cloud(degree), gltf_work / f"d{degree}"
    read = load_json(work / f"read{ext}.json")
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
    # the material: unit normals as NORMAL in glTF's axes, the other parts as `_<name>` attributes
    lit = gltf_material(cloud)
    np.testing.assert_array_equal(np.float32(attributes["NORMAL"]), material.normals(lit) * np.float32([-1, -1, 1]))
    assert np.abs(np.linalg.norm(np.float64(attributes["NORMAL"]), axis=1) - 1).max() < 1e-6
    np.testing.assert_array_equal(np.float32(attributes["_albedo"]), material.albedo(lit))
    for name, part in (("_roughness", material.roughness(lit)), ("_metallic", material.metallic(lit))):
        np.testing.assert_array_equal(np.reshape(np.float32(attributes[name]), -1), part)
    # theirs (splat-transform's .glb of the PLY): the PLY's values, the same ellipsoids (the quaternion
    # may differ by a half turn about a scale axis)
    theirs = matched(read_splats(work / "theirs.glb"), cloud)
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


def usd_cloud(degree):
    return in_range_cloud(40, degree=degree, seed=60 + degree)


@pytest.fixture(scope="module")
def usd_work(tmp_path_factory):
    """For each SH degree (folders d0..d3): NVIDIA's converter turning our PLY, and our SPZ v2 and v3
    in the PLY's axes, into OpenUSD; OpenUSD's schema reading our file and NVIDIA's; one run."""
    work, folders = tmp_path_factory.mktemp("usd"), [f"d{d}" for d in DEGREES]
    for degree, folder in zip(DEGREES, folders, strict=True):
        cloud, here = usd_cloud(degree), work / folder
        here.mkdir()
        write_splats(here / "src.ply", cloud)
        write_splats(here / "ours.usda", cloud)
        for version in (2, 3):
            spz.write(here / f"v{version}.spz", cloud, version=version, **SPZ_RDF)
    python(
        "nvidia",
        "nvidia_usd.py",
        *batch_in(
            folders,
            ["convert", "{}/src.ply", "{}/nvidia.usda"],
            ["convert", "{}/v2.spz", "{}/nvidia-v2.usda"],
            ["convert", "{}/v3.spz", "{}/nvidia-v3.usda"],
            ["read", "{}/ours.usda", "{}/ours.npz"],
            ["read", "{}/nvidia.usda", "{}/nvidia.npz"],
        ),
        cwd=work,
    )
    return work


@pytest.mark.parametrize("degree", DEGREES)
def test_usd_nvidia_converter_and_openusd_schema(usd_work, degree):
    """NVIDIA's usd-convert-gsplat turns our PLY into OpenUSD: we read the PLY's values back; and our
    SPZ (v2, v3; it reads them in the PLY's axes): we read them back within SPZ's quantisation.
    OpenUSD's own schema (in that environment, its own usd-core) reads our file: the values NVIDIA's
    converter writes for the same PLY, with the same metadata, and a transform standing the capture
    upright."""
    cloud, work = usd_cloud(degree), usd_work / f"d{degree}"
    theirs = read_splats(work / "nvidia.usda")  # no upright transform: capture values
    np.testing.assert_array_equal(theirs.positions, cloud.positions)
    np.testing.assert_allclose(theirs.sh, cloud.sh, atol=0)
    np.testing.assert_allclose(theirs.log_scales, cloud.log_scales, atol=2e-6)
    np.testing.assert_allclose(theirs.opacities, cloud.opacities, atol=1e-6)
    assert_same_covariances(theirs, cloud)
    for version in (2, 3):
        check_spz(
            read_splats(work / f"nvidia-v{version}.usda"), cloud, rotation_bound=spz_rotation_bound(version, cloud)
        )
    # the same file taken in the stage's own axes comes back turned (what the file shows in a viewer)
    turned = usd.read(work / "nvidia.usda", unmarked="stage")
    np.testing.assert_array_equal(turned.positions, cloud.positions * np.float32([1, -1, -1]))

    ours, nvidia = load_arrays(work / "ours.npz"), load_arrays(work / "nvidia.npz")
    for name in ("positions", "sh", "degree", "element_size", "interpolation", "up_axis"):
        np.testing.assert_array_equal(ours[name], nvidia[name], err_msg=name)
    for name in ("orientations_xyzw", "scales", "opacities"):
        np.testing.assert_allclose(ours[name], nvidia[name], rtol=2e-7, atol=1e-7, err_msg=name)
    assert int(ours["element_size"]) == (degree + 1) ** 2 and str(ours["interpolation"]) == "vertex"
    np.testing.assert_array_equal(ours["to_world"], np.diag([1.0, -1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(nvidia["to_world"], np.eye(4))
