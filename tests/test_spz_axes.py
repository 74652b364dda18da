"""SPZ axes: the coordinate-system record (0xADBE0003), each of its 16 axis systems turned into the
model's RDF axes against a brute-force float64 turn, RUB without a record, the spz_axes option (API
and command line), and Niantic's library (@adobe/spz) reading and writing the record."""

import contextlib
import gzip
import json
import struct
import warnings

import numpy as np
import pytest
from test_spz_splat import check_spz_error, in_range_cloud

from splatwright.cli import main
from splatwright.core import sh as shmod
from splatwright.io import SplatFileWarning, ply, read_splats, spz, write_splats
from splatwright.io.spz_axes import from_model, to_model

RECORD = 0xADBE0003
# Niantic's CoordinateSystem enum (splat-types.h), values 1..16
NIANTIC_CODES = "LDB RDB LUB RUB LDF RDF LUF RUF LFD RFD LFU RFU LBD RBD LBU RBU".split()
# where each letter points in the model's RDF axes (x right, y down, z front)
LETTER = {"R": (1, 0, 0), "L": (-1, 0, 0), "D": (0, 1, 0), "U": (0, -1, 0), "F": (0, 0, 1), "B": (0, 0, -1)}


def letters_matrix(name):
    """M with M @ v the RDF coordinates of values v stored in `name` axes."""
    return np.array([LETTER[c] for c in name], float).T


def covariances(cloud):
    """float64 covariances R S^2 R^T from the unit quaternions and scales."""
    w, x, y, z = cloud.unit_rotations.astype(np.float64).T
    r = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)
    s2 = np.exp(2 * cloud.log_scales.astype(np.float64))
    return np.einsum("nij,nj,nkj->nik", r, s2, r)


def refit_sh(sh, m):
    """Brute force: the SH whose colour function at d is the given one's at M^T d, by evaluating the
    given coefficients on many directions and fitting by least squares."""
    directions = np.random.default_rng(0).normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    degree = shmod.degree_of(sh.shape[1])
    values = np.einsum("dk,nkc->dnc", shmod.basis(directions @ m, degree), sh.astype(np.float64))
    fitted = np.linalg.lstsq(shmod.basis(directions, degree), values.reshape(len(directions), -1), rcond=None)[0]
    return fitted.reshape(sh.shape[1], len(sh), 3).transpose(1, 0, 2)


def reference_turn(stored, name):
    """float64 positions, covariances and SH in RDF of values stored in `name` axes; Niantic's
    library keeps the m = +4 coefficient of degree 4 negated in files whose vertical axis says Up."""
    m = letters_matrix(name)
    sh = stored.sh.astype(np.float64)
    if "U" in name and sh.shape[1] == 25:
        sh[:, 24] *= -1
    return stored.positions @ m.T, m @ covariances(stored) @ m.T, refit_sh(sh, m)


def check_turned(got, stored, name, atol=2e-6):
    positions, covs, sh = reference_turn(stored, name)
    np.testing.assert_array_equal(got.positions, positions.astype(np.float32))  # only moves and signs
    np.testing.assert_allclose(covariances(got), covs, atol=atol * np.abs(covs).max())
    np.testing.assert_allclose(got.sh, sh, atol=atol)
    np.testing.assert_array_equal(got.opacity_logits, stored.opacity_logits)


def test_the_systems_are_niantics_and_half_are_mirrors():
    assert [spz.axes_code(name) for name in NIANTIC_CODES] == list(range(1, 17))
    dets = [np.linalg.det(letters_matrix(name)) for name in NIANTIC_CODES]
    assert sorted(np.round(dets)) == [-1] * 8 + [1] * 8  # reflections change the handedness


@pytest.mark.parametrize("name", NIANTIC_CODES)
def test_each_system_turns_like_the_brute_force(name):
    stored = in_range_cloud(60, degree=4, seed=NIANTIC_CODES.index(name))
    got = to_model(stored, name)
    check_turned(got, stored, name)
    assert got.rotations.dtype == np.float32 and np.linalg.det(covariances(got)).min() > 0
    back = from_model(got, name)  # writing turns back
    np.testing.assert_array_equal(back.positions, stored.positions)
    np.testing.assert_allclose(covariances(back), covariances(stored), atol=1e-6 * np.abs(covariances(stored)).max())
    np.testing.assert_allclose(back.sh, stored.sh, atol=2e-6)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_lower_degrees_turn_too(degree):
    stored = in_range_cloud(40, degree=degree, seed=degree)
    for name in ("RFU", "LDB", "RBU"):
        check_turned(to_model(stored, name), stored, name)


@pytest.mark.parametrize("version", [2, 3, 4])
@pytest.mark.parametrize("name", ["RUB", "RDF", "RFU", "LDB", "RBU"])
def test_the_reader_turns_by_the_record(tmp_path, version, name):
    """Values stored as they are with a record naming `name`: read() turns them as the brute force."""
    stored = in_range_cloud(50, degree=3 if version < 4 else 4, seed=version)
    path = tmp_path / "x.spz"
    with no_warning():
        spz.write(path, stored, version=version, axes=None, spz_axes=name)
    raw, facts = spz.read(path, axes=None), {}
    got = spz.read(path, facts=facts)
    assert facts["axes"] == name and facts["axes_record"] == (None if version < 4 and name == "RUB" else name)
    check_turned(got, raw, name)


@contextlib.contextmanager
def no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


def _v4_parts(raw):
    magic, version, n, degree, bits, flags, streams, toc = struct.unpack_from("<IIIBBBBI", raw)
    return flags, toc, raw[32:toc]


def test_every_v4_names_its_axes(tmp_path):
    cloud = in_range_cloud(30, degree=1, seed=3)
    for axes, code in [(None, 4), ("rub", 4), ("rdf", 6), ("RFU", 12)]:
        spz.write(tmp_path / "x.spz", cloud, version=4, spz_axes=axes)
        flags, toc, records = _v4_parts((tmp_path / "x.spz").read_bytes())
        assert flags & 0x2 and toc == 44 and records == struct.pack("<III", RECORD, 4, code)
    spz.write(tmp_path / "x.spz", cloud, version=4, axes=None)  # values of unknown axes: no record
    assert _v4_parts((tmp_path / "x.spz").read_bytes()) == (0, 32, b"")


def test_v2_v3_record_only_where_not_rub_after_the_blocks(tmp_path):
    cloud = in_range_cloud(30, degree=1, seed=4)
    blocks = 30 * (9 + 1 + 3 + 3 + 4 + 9)
    spz.write(tmp_path / "rub.spz", cloud, version=3)
    plain = gzip.decompress((tmp_path / "rub.spz").read_bytes())
    assert len(plain) == 16 + blocks and plain[14] == 0
    spz.write(tmp_path / "rdf.spz", cloud, version=3, spz_axes="rdf")
    tagged = gzip.decompress((tmp_path / "rdf.spz").read_bytes())
    assert tagged[14] == 0x2 and tagged[16 + blocks :] == struct.pack("<III", RECORD, 4, 6)
    # the RDF file's blocks hold the model's values: the RUB file's with y and z flipped
    assert (
        tagged[16:25] != plain[16:25]
        and spz.read(tmp_path / "rdf.spz", axes=None).positions[0, 0]
        == (spz.read(tmp_path / "rub.spz", axes=None).positions[0, 0])
    )
    check_spz_error(spz.read(tmp_path / "rdf.spz"), cloud)


def test_a_record_before_the_blocks_is_read_too(tmp_path):
    """Adobe's first writers put v2/v3 records right after the header."""
    cloud = in_range_cloud(20, degree=0, seed=5)
    spz.write(tmp_path / "tail.spz", cloud, version=3, spz_axes="rdf")
    tail = gzip.decompress((tmp_path / "tail.spz").read_bytes())
    head = tail[:16] + tail[-12:] + tail[16:-12]
    (tmp_path / "head.spz").write_bytes(gzip.compress(head))
    facts = {}
    got = spz.read(tmp_path / "head.spz", facts=facts)
    assert facts["axes_record"] == "RDF"
    np.testing.assert_array_equal(got.positions, spz.read(tmp_path / "tail.spz").positions)


def test_without_a_record_rub(tmp_path):
    """No record (or one without flag 0x2, which Niantic's library ignores too): SPZ's documented RUB."""
    cloud = in_range_cloud(40, degree=4, seed=6)
    spz.write(tmp_path / "x.spz", cloud, version=4, spz_axes="rdf")
    raw = bytearray((tmp_path / "x.spz").read_bytes())
    raw[14] &= ~0x2
    (tmp_path / "unflagged.spz").write_bytes(raw)
    facts = {}
    got = spz.read(tmp_path / "unflagged.spz", facts=facts)
    assert facts == {**facts, "axes": "RUB", "axes_record": None}
    check_turned(got, spz.read(tmp_path / "unflagged.spz", axes=None), "RUB")


def test_an_explicit_option_wins_with_a_warning_where_the_record_differs(tmp_path):
    cloud = in_range_cloud(40, degree=2, seed=7)
    path = tmp_path / "x.spz"
    spz.write(path, cloud, version=4, spz_axes="rdf")
    raw = spz.read(path, axes=None)
    with pytest.warns(SplatFileWarning, match="record says RDF; read as RUB, as asked"):
        as_rub = read_splats(path, spz_axes="rub")
    check_turned(as_rub, raw, "RUB")
    with no_warning():
        for told in ("rdf", "RDF", "auto", None):
            np.testing.assert_array_equal(read_splats(path, spz_axes=told).positions, raw.positions)
    with pytest.raises(ValueError, match="unknown SPZ axes 'up'"):
        spz.read(path, spz_axes="up")


@pytest.mark.parametrize(("code", "said"), [(0, "unspecified axes"), (17, "unknown axes 17")])
def test_a_record_naming_no_system_reads_as_rub(tmp_path, code, said):
    cloud = in_range_cloud(10, degree=0, seed=8)
    spz.write(tmp_path / "x.spz", cloud, version=4)
    raw = bytearray((tmp_path / "x.spz").read_bytes())
    raw[40:44] = struct.pack("<I", code)
    (tmp_path / "odd.spz").write_bytes(raw)
    with pytest.warns(SplatFileWarning, match=f"record says {said}; taken as no record"):
        got = spz.read(tmp_path / "odd.spz")
    np.testing.assert_array_equal(got.positions, spz.read(tmp_path / "x.spz").positions)


@pytest.mark.parametrize("version", [3, 4])
def test_written_in_rdf_reads_back_within_quantisation(tmp_path, version):
    cloud = in_range_cloud(200, degree=3, seed=9)
    write_splats(tmp_path / "x.spz", cloud, version=version, spz_axes="rdf")
    check_spz_error(read_splats(tmp_path / "x.spz"), cloud)
    # the stored values are the model's own: as splat-transform and gsply keep them
    check_spz_error(spz.read(tmp_path / "x.spz", axes=None), cloud)


# the command line ---------------------------------------------------------------------------------


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def wild(tmp_path):
    """An SPZ holding PLY's RDF values without saying so (as Niantic's converter long wrote them)."""
    cloud = in_range_cloud(80, degree=1, seed=10)
    spz.write(tmp_path / "wild.spz", cloud, version=3, axes=None)
    return tmp_path / "wild.spz", spz.read(tmp_path / "wild.spz", axes=None)


def test_cli_info_reports_the_axes_and_the_record(capsys, wild, tmp_path):
    path, _ = wild
    code, out, err = run(capsys, "info", path, "--json")
    assert code == 0, err
    info = json.loads(out)
    assert (info["spz_version"], info["spz_axes"], info["spz_axes_record"]) == (3, "RUB", None)
    code, out, _ = run(capsys, "info", path, "--json", "--spz-axes", "rdf")
    assert json.loads(out)["spz_axes"] == "RDF"
    spz.write(tmp_path / "tagged.spz", spz.read(path, spz_axes="rdf"), version=4)
    code, out, _ = run(capsys, "info", tmp_path / "tagged.spz")
    assert "spz_axes_record: RUB" in out
    code, out, _ = run(capsys, "info", tmp_path / "tagged.spz", "--json", "--spz-axes", "rdf")
    (warning,) = json.loads(out)["warnings"]
    assert code == 0 and "record says RUB; read as RDF, as asked" in warning


def test_cli_convert_and_render_read_the_axes_asked(capsys, wild, tmp_path):
    path, values = wild
    code, _, err = run(capsys, "convert", path, tmp_path / "fixed.ply", "--spz-axes", "rdf", "--no-check")
    assert code == 0, err
    np.testing.assert_array_equal(ply.read(tmp_path / "fixed.ply").positions, values.positions)
    # SPZ to SPZ: read as RDF, written in the documented RUB (repairs the file)
    code, _, err = run(capsys, "convert", path, tmp_path / "fixed.spz", "--spz-axes", "rdf", "--no-check")
    assert code == 0, err
    check_spz_error(spz.read(tmp_path / "fixed.spz"), values, sh=False)
    # a PLY to an SPZ stored in RDF
    code, _, err = run(
        capsys, "convert", tmp_path / "fixed.ply", tmp_path / "rdf.spz", "--spz-axes", "rdf", "--no-check"
    )
    assert code == 0, err
    facts = {}
    spz.read(tmp_path / "rdf.spz", facts=facts)
    assert facts["axes_record"] == "RDF"
    images = []
    for source, extra in [(path, ["--spz-axes", "rdf"]), (tmp_path / "fixed.ply", [])]:
        out = tmp_path / f"{len(images)}.png"
        code, _, err = run(capsys, "render", source, "-o", out, "--width", 48, "--height", 32, *extra)
        assert code == 0, err
        images.append(out.read_bytes())
    assert images[0] == images[1]
    code, _, err = run(capsys, "render", tmp_path / "fixed.ply", "-o", tmp_path / "x.png", "--spz-axes", "rdf")
    assert code != 0 and "--spz-axes needs an SPZ file" in err
    code, _, err = run(capsys, "convert", tmp_path / "fixed.ply", tmp_path / "x.ply", "--spz-axes", "rdf")
    assert code != 0 and "--spz-axes needs an SPZ input or output" in err


# Niantic's library ---------------------------------------------------------------------------------


def niantic_reads(tmp_path, path):
    from interop import cloud_from_niantic, load_json, node

    node("adobe_spz.mjs", "read", path, tmp_path / "back.json")
    return cloud_from_niantic(load_json(tmp_path / "back.json"))


def agree(ours, theirs):
    np.testing.assert_allclose(ours.positions, theirs.positions, atol=1e-6)
    np.testing.assert_allclose(covariances(ours), covariances(theirs), atol=1e-6)
    np.testing.assert_allclose(ours.sh, theirs.sh, atol=3e-7)


# Niantic's conversion of these four flips before its quarter turn about x, landing a half turn about
# x from their letters
NIANTIC_HALF_TURNED = {"LFD", "RFD", "LBU", "RBU"}


@pytest.mark.slow
@pytest.mark.parametrize("name", NIANTIC_CODES)
def test_niantic_writes_every_system_and_both_read_it_alike(tmp_path, name):
    from interop import niantic_arrays, node, save_json

    cloud = in_range_cloud(100, degree=4, seed=11)
    save_json(tmp_path / "cloud.json", **niantic_arrays(cloud))
    node("adobe_spz.mjs", "write", tmp_path / "cloud.json", tmp_path / "theirs.spz", 4, name)
    facts = {}
    ours = spz.read(tmp_path / "theirs.spz", facts=facts)
    assert facts["axes_record"] == name
    theirs = niantic_reads(tmp_path, tmp_path / "theirs.spz")
    if name in NIANTIC_HALF_TURNED:
        half_turn = to_model(ours, "RUB")  # RUB's matrix is that half turn
        k = ours.sh.shape[1]
        half_turn.sh[:, 24:k] *= -1  # without the Up sign of coefficient 24: an exact half turn
        agree(half_turn, theirs)
    else:
        agree(ours, theirs)


@pytest.mark.slow
@pytest.mark.parametrize("version", [2, 3, 4])
def test_rdf_files_are_niantics_bytes(tmp_path, version):
    """Written in RDF, our files are the bytes Niantic's writer makes with an RDF record; its reader
    (whose WebAssembly build skips v2/v3 records) takes the v4 file as we do."""
    from interop import niantic_arrays, node, save_json

    cloud = in_range_cloud(100, degree=3, seed=12)
    save_json(tmp_path / "cloud.json", **niantic_arrays(cloud))
    node("adobe_spz.mjs", "write", tmp_path / "cloud.json", tmp_path / "theirs.spz", version, "RDF")
    spz.write(tmp_path / "ours.spz", cloud, version=version, spz_axes="rdf")
    assert (tmp_path / "ours.spz").read_bytes() == (tmp_path / "theirs.spz").read_bytes()
    if version == 4:
        agree(spz.read(tmp_path / "ours.spz"), niantic_reads(tmp_path, tmp_path / "ours.spz"))
