"""PLY: files built byte by byte here (not by io/ply.py) are read value for value; our own files
round-trip byte for byte and are read by plyfile; every kind of bad input names file and problem."""

import os
import struct
import warnings

import numpy as np
import plyfile
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud
from splatwright.io import SplatFileError, SplatFileWarning, ply, read_splats, write_splats

# An independent PLY writer -----------------------------------------------------------------------

CODES = {
    "char": "i1",
    "uchar": "u1",
    "short": "i2",
    "ushort": "u2",
    "int": "i4",
    "uint": "u4",
    "float": "f4",
    "double": "f8",
    "int8": "i1",
    "uint8": "u1",
    "int16": "i2",
    "uint16": "u2",
    "int32": "i4",
    "uint32": "u4",
    "float32": "f4",
    "float64": "f8",
}
ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">"}


def build_ply(vertex, types=None, fmt="binary_little_endian", count=None, before=(), after=(), newline="\n"):
    """PLY bytes for vertex columns {name: values} (file order = dict order), each of a PLY type
    (float unless `types` says otherwise). before/after: other elements as (name, props, rows) with
    props [(name, type)] or [(name, ("list", count type, item type))] and rows tuples of values."""
    types = types or {}
    n = len(next(iter(vertex.values())))
    elements = [*before, ("vertex", [(p, types.get(p, "float")) for p in vertex], None), *after]
    head = ["ply", f"format {fmt} 1.0", "comment built by test_ply"]
    for name, props, rows in elements:
        rows_stated = count if (name == "vertex" and count is not None) else (n if rows is None else len(rows))
        head.append(f"element {name} {rows_stated}")
        for p, t in props:
            head.append(f"property list {t[1]} {t[2]} {p}" if isinstance(t, tuple) else f"property {t} {p}")
    head.append("end_header")
    body = b""
    for _name, props, rows in elements:
        if rows is None:
            rows = list(zip(*vertex.values()))
        body += _element_bytes(props, rows, fmt)
    return (newline.join(head) + newline).encode("ascii") + body


def _element_bytes(props, rows, fmt):
    if fmt == "ascii":
        lines = []
        for row in rows:
            words = []
            for (_, t), v in zip(props, row):
                if isinstance(t, tuple):
                    words += [str(len(v))] + [_ascii(t[2], x) for x in v]
                else:
                    words.append(_ascii(t, v))
            lines.append(" ".join(words) + "\n")
        return "".join(lines).encode("ascii")
    e = ENDIAN[fmt]
    if not any(isinstance(t, tuple) for _, t in props):
        records = np.array(rows, dtype=[(p, e + CODES[t]) for p, t in props])
        return records.tobytes()
    out = b""
    for row in rows:
        for (_, t), v in zip(props, row):
            if isinstance(t, tuple):
                out += np.array(len(v), e + CODES[t[1]]).tobytes() + np.array(v, e + CODES[t[2]]).tobytes()
            else:
                out += np.array(v, e + CODES[t]).tobytes()
    return out


def _ascii(t, v):
    code = CODES[t]
    if code[0] == "f":
        return repr(float(np.float32(v))) if code == "f4" else repr(float(v))
    return str(int(v))


def gaussian_columns(n, degree, seed=0, normals=True, extras=True):
    """Vertex columns of a 3DGS file, values as float64, in the reference order (+ extras)."""
    rng = np.random.default_rng(seed)
    cols = {c: rng.normal(0, 2, n) for c in "xyz"}
    if normals:
        cols.update({c: rng.normal(0, 1, n) for c in ("nx", "ny", "nz")})
    cols.update({f"f_dc_{i}": rng.normal(0, 1, n) for i in range(3)})
    cols.update({f"f_rest_{i}": rng.normal(0, 0.3, n) for i in range(3 * ((degree + 1) ** 2 - 1))})
    cols["opacity"] = rng.normal(0, 3, n)
    cols.update({f"scale_{i}": rng.uniform(-6, 0, n) for i in range(3)})
    cols.update({f"rot_{i}": rng.normal(0, 1, n) for i in range(4)})
    if extras:
        cols["segment"] = rng.integers(0, 200, n)
        cols["confidence"] = rng.uniform(0, 1, n)
    return cols


def expected_fields(cols):
    """What a reader must produce, derived from the columns with the layout's rules spelled out."""

    def f32(names):
        with np.errstate(over="ignore"):  # doubles beyond float32 become inf, as in any reader
            return np.stack([np.asarray(cols[c], np.float64) for c in names], 1).astype(np.float32)

    m = sum(1 for c in cols if c.startswith("f_rest_"))
    k = m // 3 + 1
    sh = np.zeros((len(cols["x"]), k, 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = np.float32(cols[f"f_dc_{c}"])
        for j in range(k - 1):  # channel-major: f_rest[c*(K-1) + j] is channel c, coefficient j+1
            sh[:, 1 + j, c] = np.float32(cols[f"f_rest_{c * (k - 1) + j}"])
    return dict(
        positions=f32("xyz"),
        rotations=f32(["rot_0", "rot_1", "rot_2", "rot_3"]),
        log_scales=f32(["scale_0", "scale_1", "scale_2"]),
        opacity_logits=f32(["opacity"])[:, 0],
        sh=sh,
    )


def assert_fields(cloud, expected):
    for name, values in expected.items():
        np.testing.assert_array_equal(getattr(cloud, name), values, err_msg=name)
        assert getattr(cloud, name).dtype == np.float32


def write_bytes(tmp_path, data, name="in.ply"):
    path = tmp_path / name
    path.write_bytes(data)
    return path


# Round trips --------------------------------------------------------------------------------------


def cloud_with_extras(n, degree, seed=0):
    c = random_cloud(n, sh_degree=degree, seed=seed)
    rng = np.random.default_rng(seed + 1)
    c.extras = {
        "nx": rng.normal(size=n).astype(np.float32),
        "ny": np.zeros(n, np.float32),
        "nz": rng.normal(size=n).astype(np.float32),
        "segment": rng.integers(0, 255, n).astype(np.uint8),
        "weight": rng.normal(size=n),
        "id": rng.integers(-(2**31), 2**31 - 1, n).astype(np.int32),
        "tag": rng.integers(-100, 100, n).astype(np.int16),
    }
    return c


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_our_files_round_trip_byte_for_byte(tmp_path, degree):
    cloud = cloud_with_extras(300, degree, seed=degree)
    first, second = tmp_path / "a.ply", tmp_path / "b.ply"
    ply.write(first, cloud)
    back = ply.read(first)
    ply.write(second, back)
    assert first.read_bytes() == second.read_bytes()
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name))
    assert list(back.extras) == list(cloud.extras)
    for key, values in cloud.extras.items():
        assert back.extras[key].dtype == values.dtype
        np.testing.assert_array_equal(back.extras[key], values)


def test_plyfile_reads_our_file_in_the_reference_layout(tmp_path):
    cloud = cloud_with_extras(200, 3)
    path = tmp_path / "ours.ply"
    write_splats(path, cloud)
    data = plyfile.PlyData.read(str(path))
    assert not data.text and data.byte_order == "<"
    vertex = data["vertex"]
    names = list(vertex.data.dtype.names)
    assert names[:62] == (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert names[62:] == ["segment", "weight", "id", "tag"]
    assert all(vertex.data.dtype[i] == np.dtype("<f4") for i in range(62))
    assert [vertex.data.dtype[n] for n in names[62:]] == [
        np.dtype("u1"),
        np.dtype("<f8"),
        np.dtype("<i4"),
        np.dtype("<i2"),
    ]
    cols = {n: vertex[n] for n in names}
    assert_fields(cloud, expected_fields(cols))
    for key in ("nx", "ny", "nz", "segment", "weight", "id", "tag"):
        np.testing.assert_array_equal(vertex[key], cloud.extras[key])


def test_plyfile_reads_our_degree_4_file_with_72_f_rest(tmp_path):
    """SH degree 4 as Blender 5.3 and 3DGS trainers with sh_degree 4 write it: f_rest_0..71, channel-major."""
    cloud = random_cloud(150, sh_degree=4, seed=9)
    path = tmp_path / "sh4.ply"
    write_splats(path, cloud)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    names = list(vertex.data.dtype.names)
    assert names == (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(72)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert_fields(cloud, expected_fields({n: vertex[n] for n in names}))
    # f_rest_47 is channel 1 (green), coefficient 47 - 24 + 1 = 24: the m = 4 term of band 4
    np.testing.assert_array_equal(vertex["f_rest_47"], cloud.sh[:, 24, 1])
    back = read_splats(path)
    assert back.sh_degree == 4 and back.sh.shape == (150, 25, 3)
    np.testing.assert_array_equal(back.sh, cloud.sh)


def test_antialiased_splats_say_so_in_a_comment_other_readers_skip(tmp_path):
    cloud = cloud_with_extras(50, 1).replace(antialiased=True)
    write_splats(tmp_path / "aa.ply", cloud)
    data = plyfile.PlyData.read(str(tmp_path / "aa.ply"))
    assert [c.split()[0] for c in data.comments] == ["antialiased"]
    assert_fields(cloud, expected_fields({n: data["vertex"][n] for n in data["vertex"].data.dtype.names}))
    assert read_splats(tmp_path / "aa.ply").antialiased
    write_splats(tmp_path / "classic.ply", cloud.replace(antialiased=False))
    assert plyfile.PlyData.read(str(tmp_path / "classic.ply")).comments == []
    assert not read_splats(tmp_path / "classic.ply").antialiased
    other = plyfile.PlyData([data["vertex"]], text=True, comments=["antialiased, written by another tool"])
    other.write(str(tmp_path / "other.ply"))  # ASCII, the word with a comma: not ours
    assert not read_splats(tmp_path / "other.ply").antialiased
    plyfile.PlyData([data["vertex"]], text=True, comments=["antialiased"]).write(str(tmp_path / "text.ply"))
    assert read_splats(tmp_path / "text.ply").antialiased


def test_formats_that_cannot_record_antialiased_splats_warn(tmp_path):
    cloud = random_cloud(20, sh_degree=0).replace(antialiased=True)
    for name in ("x.splat", "x.glb"):
        with pytest.warns(SplatFileWarning, match="cannot record that the splats were made for antialiased"):
            write_splats(tmp_path / name, cloud)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_splats(tmp_path / "x.spz", cloud)
        write_splats(tmp_path / "y.splat", cloud.replace(antialiased=False))


def test_cloud_without_normals_gets_zero_normals_and_reads_back_without_them(tmp_path):
    cloud = random_cloud(50, sh_degree=1)
    path = tmp_path / "c.ply"
    ply.write(path, cloud)
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    for n in ("nx", "ny", "nz"):
        np.testing.assert_array_equal(vertex[n], 0.0)
    assert ply.read(path).extras == {}


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("ptype", ["float", "double"])
@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_hand_built_files_read_value_for_value(tmp_path, fmt, ptype, degree):
    rng = np.random.default_rng(degree)
    cols = gaussian_columns(40, degree, seed=degree, normals=bool(degree % 2))
    order = list(cols)
    if degree >= 2:  # any property order
        rng.shuffle(order)
    cols = {k: cols[k] for k in order}
    types = {k: ptype for k in cols} | {"segment": "uchar"}
    path = write_bytes(tmp_path, build_ply(cols, types, fmt))
    cloud = ply.read(path)
    assert_fields(cloud, expected_fields(cols))
    assert cloud.extras["segment"].dtype == np.uint8
    np.testing.assert_array_equal(cloud.extras["segment"], cols["segment"])
    assert cloud.extras["confidence"].dtype == (np.float64 if ptype == "double" else np.float32)
    np.testing.assert_array_equal(
        cloud.extras["confidence"], cols["confidence"].astype(cloud.extras["confidence"].dtype)
    )
    assert ("nx" in cloud.extras) == bool(degree % 2)
    # value for value through our writer and back
    ply.write(tmp_path / "out.ply", cloud)
    again = ply.read(tmp_path / "out.ply")
    assert_fields(again, expected_fields(cols))
    assert sorted(again.extras) == sorted(cloud.extras)  # normals move to their layout slot
    for key, values in cloud.extras.items():
        np.testing.assert_array_equal(again.extras[key], values)
        assert again.extras[key].dtype == values.dtype


def test_every_scalar_type_in_core_and_extra_properties(tmp_path):
    n = 30
    rng = np.random.default_rng(5)
    cols = gaussian_columns(n, 1, extras=False, normals=False)
    cols["x"] = rng.integers(-100, 100, n)
    cols["y"] = rng.integers(0, 255, n)
    cols["opacity"] = rng.integers(-3000, 3000, n)
    types = {"x": "int", "y": "uchar", "z": "double", "opacity": "short"}
    spans = {
        "char": (-128, 127),
        "uchar": (0, 255),
        "short": (-(2**15), 2**15 - 1),
        "ushort": (0, 2**16 - 1),
        "int": (-(2**31), 2**31 - 1),
        "uint": (0, 2**32 - 1),
    }
    for t, (lo, hi) in spans.items():
        cols[f"e_{t}"] = np.r_[lo, hi, rng.integers(lo, hi, n - 2, endpoint=True)]
        types[f"e_{t}"] = t
    cols["e_int8"], types["e_int8"] = rng.integers(-5, 5, n), "int8"
    cols["e_float64"], types["e_float64"] = rng.normal(size=n) * 1e200, "float64"
    for fmt in ("binary_big_endian", "ascii"):
        cloud = ply.read(write_bytes(tmp_path, build_ply(cols, types, fmt), f"{fmt}.ply"))
        assert_fields(cloud, expected_fields(cols))
        for t in spans:
            assert cloud.extras[f"e_{t}"].dtype == np.dtype(CODES[t])
            np.testing.assert_array_equal(cloud.extras[f"e_{t}"], cols[f"e_{t}"])
        np.testing.assert_array_equal(cloud.extras["e_float64"], cols["e_float64"])
        assert cloud.extras["e_float64"].dtype.isnative


def test_other_elements_before_and_after_the_vertices(tmp_path):
    cols = gaussian_columns(20, 1, normals=False, extras=False)
    camera = (
        "camera",
        [("fx", "float"), ("fy", "float"), ("width", "uint"), ("height", "uint")],
        [(500.0, 500.0, 640, 480), (300.0, 310.0, 320, 240)],
    )
    face = ("face", [("vertex_indices", ("list", "uchar", "int"))], [((0, 1, 2),), ((2, 3, 4, 5),)])
    for fmt in ("binary_little_endian", "binary_big_endian", "ascii"):
        for before, after in [((camera,), ()), ((), (camera, face)), ((camera,), (face,))]:
            path = write_bytes(tmp_path, build_ply(cols, fmt=fmt, before=before, after=after))
            assert_fields(ply.read(path), expected_fields(cols))
    # ASCII rows are lines, so even a list element before the vertices is skipped.
    path = write_bytes(tmp_path, build_ply(cols, fmt="ascii", before=(face,)))
    assert_fields(ply.read(path), expected_fields(cols))


def test_crlf_header_is_accepted(tmp_path):
    cols = gaussian_columns(10, 0, normals=False, extras=False)
    path = write_bytes(tmp_path, build_ply(cols, newline="\r\n"))
    assert_fields(ply.read(path), expected_fields(cols))


def test_2dgs_file_gets_a_flat_third_axis_and_says_so(tmp_path):
    cols = gaussian_columns(25, 2, extras=False)
    del cols["scale_2"]
    path = write_bytes(tmp_path, build_ply(cols))
    with pytest.warns(SplatFileWarning, match="2DGS.*flat"):
        cloud = ply.read(path)
    np.testing.assert_array_equal(
        cloud.log_scales[:, :2], np.stack([cols["scale_0"], cols["scale_1"]], 1).astype(np.float32)
    )
    np.testing.assert_array_equal(cloud.log_scales[:, 2], np.float32(np.log(1e-6)))
    assert np.all(cloud.scales[:, 2] < 1.01e-6) and np.all(cloud.scales[:, 2] > 0.99e-6)
    cov = cloud.covariances()  # flat but still a valid (invertible) covariance
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    ply.write(tmp_path / "3d.ply", cloud)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # written back as 3DGS: no warning on reading it
        np.testing.assert_array_equal(ply.read(tmp_path / "3d.ply").log_scales, cloud.log_scales)


def test_hard_values_survive_bit_for_bit(tmp_path):
    n = 8
    cloud = random_cloud(n, sh_degree=2, seed=3)
    cloud.positions[:] = [[1e6, -1e6, 3e6]] * n
    cloud.log_scales[:, 0] = np.log([1e-7, 1e4] * (n // 2))
    cloud.opacity_logits[:] = [1e4, -1e4, 0.0, -0.0, 1e-45, -1e-45, 3.4e38, -3.4e38]
    cloud.rotations[0] = 0.0
    cloud.rotations[1] = [1e-30, 0, 0, 0]
    ply.write(tmp_path / "hard.ply", cloud)
    back = ply.read(tmp_path / "hard.ply")
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        assert getattr(back, name).tobytes() == getattr(cloud, name).tobytes(), name
    assert any("zero rotation quaternion" in p for p in back.problems())


def test_empty_cloud_round_trips(tmp_path):
    for degree in (0, 3):
        ply.write(tmp_path / "e.ply", SplatCloud.empty(degree))
        back = ply.read(tmp_path / "e.ply")
        assert len(back) == 0 and back.sh_degree == degree


def test_many_chunks_on_several_threads_match_one_pass(tmp_path, monkeypatch):
    cloud = cloud_with_extras(1000, 3, seed=9)
    ply.write(tmp_path / "one.ply", cloud)
    monkeypatch.setattr(ply, "CHUNK_ROWS", 37)
    monkeypatch.setattr(ply, "PARALLEL_ROWS", 100)
    monkeypatch.setattr(ply, "WORKERS", 3)
    ply.write(tmp_path / "many.ply", cloud)
    assert (tmp_path / "one.ply").read_bytes() == (tmp_path / "many.ply").read_bytes()
    cols = gaussian_columns(1000, 3, seed=2)
    for fmt in ("binary_little_endian", "ascii"):
        path = write_bytes(tmp_path, build_ply(cols, {"segment": "uchar"}, fmt=fmt))
        cloud = ply.read(path)
        assert_fields(cloud, expected_fields(cols))
        np.testing.assert_array_equal(cloud.extras["nx"], np.float32(cols["nx"]))


def test_extras_of_other_dtypes_are_written_as_ply_types(tmp_path):
    n = 12
    cloud = random_cloud(n, sh_degree=0)
    cloud.extras = {
        "hit": np.arange(n) % 2 == 0,
        "tri": np.arange(n, dtype=np.int64) * 1000,
        "uv": np.arange(2 * n, dtype=np.float16).reshape(n, 2),
    }
    ply.write(tmp_path / "x.ply", cloud)
    vertex = plyfile.PlyData.read(str(tmp_path / "x.ply"))["vertex"]
    assert vertex.data.dtype["hit"] == np.uint8 and vertex.data.dtype["tri"] == np.dtype("<i4")
    np.testing.assert_array_equal(vertex["hit"], cloud.extras["hit"])
    np.testing.assert_array_equal(vertex["tri"], cloud.extras["tri"])
    np.testing.assert_array_equal(vertex["uv_1"], cloud.extras["uv"][:, 1])
    assert vertex.data.dtype["uv_0"] == np.dtype("<f4")


def test_read_splats_dispatches_to_ply(tmp_path):
    cloud = random_cloud(20, sh_degree=1)
    write_splats(tmp_path / "d.PLY", cloud)
    np.testing.assert_array_equal(read_splats(tmp_path / "d.PLY").sh, cloud.sh)


# Bad input ----------------------------------------------------------------------------------------


def raises_naming(path, *fragments):
    """pytest.raises for a SplatFileError whose message names `path` and every fragment."""

    class Check:
        def __enter__(self):
            self.ctx = pytest.raises(SplatFileError)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            handled = self.ctx.__exit__(*exc)
            message = str(self.info.value)
            assert str(path) in message, message
            for fragment in fragments:
                assert fragment in message, message
            return handled

    return Check()


def good_file_bytes(fmt="binary_little_endian", n=10, **kw):
    return build_ply(gaussian_columns(n, 1, extras=False), fmt=fmt, **kw)


def test_truncated_binary_data(tmp_path):
    data = good_file_bytes()
    path = write_bytes(tmp_path, data[:-7])
    with raises_naming(path, "truncated", "10 vertices"):
        ply.read(path)


def test_header_that_lies_about_the_count(tmp_path):
    too_many = write_bytes(tmp_path, good_file_bytes(count=11), "more.ply")
    with raises_naming(too_many, "truncated", "11 vertices"):
        ply.read(too_many)
    too_few = write_bytes(tmp_path, good_file_bytes(count=9), "fewer.ply")
    with raises_naming(too_few, "bytes beyond", "vertex count of 9"):
        ply.read(too_few)
    for count, words in ((11, "truncated"), (9, "data lines beyond")):
        path = write_bytes(tmp_path, good_file_bytes("ascii", count=count), f"a{count}.ply")
        with raises_naming(path, words):
            ply.read(path)


def test_ascii_row_with_a_missing_value(tmp_path):
    data = good_file_bytes("ascii").decode()
    head, body = data.split("end_header\n")
    lines = body.splitlines()
    lines[3] = " ".join(lines[3].split()[:-1])
    path = write_bytes(tmp_path, (head + "end_header\n" + "\n".join(lines) + "\n").encode())
    with raises_naming(path, "vertex data"):
        ply.read(path)
    path = write_bytes(tmp_path, data.replace(body.split()[5], "abc", 1).encode(), "word.ply")
    with raises_naming(path, "vertex data"):
        ply.read(path)


def test_missing_required_properties_are_named(tmp_path):
    cols = gaussian_columns(5, 0, extras=False)
    del cols["opacity"], cols["rot_2"], cols["f_dc_1"]
    path = write_bytes(tmp_path, build_ply(cols))
    with raises_naming(path, "f_dc_1", "opacity", "rot_2"):
        ply.read(path)


@pytest.mark.parametrize(
    "data, words",
    [
        (b"", "not a PLY file"),
        (b"\x89PNG\r\n\x1a\n" + bytes(100), "not a PLY file"),
        (b"plyx\nformat ascii 1.0\n", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no 'end_header'"),
        (b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n", "unsupported format"),
        (b"ply\nelement vertex 0\nproperty float x\nend_header\n", "no 'format' line"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "property before any element"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty half x\nend_header\n", "property TYPE NAME"),
        (b"ply\nformat ascii 1.0\nelement vertex -1\nend_header\n", "element NAME COUNT"),
        (
            b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n",
            "no 'vertex' element",
        ),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float x\nend_header\n", "repeats"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty list uchar float x\nend_header\n", "list properties"),
        (b"ply\nformat ascii 1.0\nwhatever\nend_header\n", "unknown keyword"),
        (b"ply\nformat ascii 1.0\ncomment \xff\nend_header\n", "not ASCII"),
    ],
)
def test_malformed_headers(tmp_path, data, words):
    path = write_bytes(tmp_path, data)
    with raises_naming(path, words):
        ply.read(path)


def test_list_element_before_vertices_in_binary(tmp_path):
    face = ("face", [("vertex_indices", ("list", "uchar", "int"))], [((0, 1, 2),)])
    path = write_bytes(tmp_path, good_file_bytes(before=(face,)))
    with raises_naming(path, "'face'", "before 'vertex'"):
        ply.read(path)


def test_wrong_number_or_numbering_of_f_rest(tmp_path):
    cols = gaussian_columns(5, 1, extras=False)
    cols["f_rest_9"] = cols["f_rest_0"]
    path = write_bytes(tmp_path, build_ply(cols), "ten.ply")
    with raises_naming(path, "10 f_rest properties"):
        ply.read(path)
    cols = gaussian_columns(5, 1, extras=False)
    cols["f_rest_11"] = cols.pop("f_rest_4")
    path = write_bytes(tmp_path, build_ply(cols), "gap.ply")
    with raises_naming(path, "without gaps", "f_rest_11"):
        ply.read(path)


def test_unwritable_folder(tmp_path):
    path = tmp_path / "no" / "such" / "folder.ply"
    with raises_naming(path, "cannot write"):
        ply.write(path, random_cloud(3, sh_degree=0))


def test_missing_file(tmp_path):
    with raises_naming(tmp_path / "nope.ply", "no such file"):
        read_splats(tmp_path / "nope.ply")
    with raises_naming(tmp_path / "nope.ply", "cannot read", "No such file"):
        ply.read(tmp_path / "nope.ply")


def nonfinite_columns():
    cols = gaussian_columns(10, 1, extras=False)
    cols["opacity"][2] = np.nan
    cols["x"][5] = np.inf
    cols["f_rest_7"][5] = -np.inf
    cols["rot_1"][7] = 1e300  # a double beyond float32
    return cols


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_non_finite_values_are_refused_by_default(tmp_path, fmt):
    types = {"rot_1": "double"}
    path = write_bytes(tmp_path, build_ply(nonfinite_columns(), types, fmt))
    with raises_naming(path, "3 of 10 splats", "positions in 1", "rotations in 1", "opacity_logits in 1", "sh in 1"):
        ply.read(path)
    with pytest.warns(SplatFileWarning, match="3 of 10 splats.*kept"):
        kept = ply.read(path, nonfinite="keep")
    assert len(kept) == 10 and np.isnan(kept.opacity_logits[2]) and np.isinf(kept.rotations[7, 1])
    assert any("non-finite opacity_logits" in p for p in kept.problems())
    with pytest.warns(SplatFileWarning, match="dropped"):
        dropped = ply.read(path, nonfinite="drop")
    expected = expected_fields(nonfinite_columns())
    keep = np.array([i not in (2, 5, 7) for i in range(10)])
    assert_fields(dropped, {k: v[keep] for k, v in expected.items()})
    with pytest.raises(ValueError, match="nonfinite must be"):
        ply.read(path, nonfinite="ignore")


def test_writing_non_finite_values_is_refused_and_leaves_nothing(tmp_path):
    cloud = random_cloud(10, sh_degree=1)
    cloud.sh[4, 2, 1] = np.nan
    path = tmp_path / "nan.ply"
    with raises_naming(path, "1 of 10 splats", "sh in 1"):
        ply.write(path, cloud)
    assert os.listdir(tmp_path) == []
    with pytest.warns(SplatFileWarning):
        ply.write(path, cloud, nonfinite="drop")
    assert len(ply.read(path)) == 9
    with pytest.warns(SplatFileWarning):
        ply.write(path, cloud, nonfinite="keep")
    with pytest.warns(SplatFileWarning):
        assert np.isnan(ply.read(path, nonfinite="keep").sh[4, 2, 1])


def test_failed_write_keeps_the_old_file_and_leaves_no_partial_one(tmp_path, monkeypatch):
    path = tmp_path / "scene.ply"
    ply.write(path, random_cloud(50, sh_degree=0))
    before = path.read_bytes()
    calls = []

    def fail_midway(fd, records, offset):
        calls.append(offset)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        os.pwrite(fd, records.view(np.uint8).tobytes(), offset)

    monkeypatch.setattr(ply, "_write_at", fail_midway)
    monkeypatch.setattr(ply, "CHUNK_ROWS", 10)
    with raises_naming(path, "cannot write", "No space left"):
        ply.write(path, random_cloud(100, sh_degree=3))
    assert len(calls) == 2
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["scene.ply"]


@pytest.mark.parametrize(
    "extras, words",
    [
        ({"opacity": np.zeros(4)}, "'opacity'"),
        ({"bad name": np.zeros(4)}, "'bad name'"),
        ({"f_rest_50": np.zeros(4)}, "'f_rest_50'"),
        ({"uv": np.zeros((4, 2)), "uv_1": np.zeros(4)}, "'uv_1'"),
        ({"big": np.array([0, 2**40, 0, 0], np.int64)}, "extra 'big' has dtype int64"),
        ({"obj": np.array(["a", "b", "c", "d"])}, "extra 'obj' has dtype <U1"),
        ({"nx": np.zeros((4, 2))}, "'nx' must hold one value per splat"),
    ],
)
def test_extras_that_cannot_be_written(tmp_path, extras, words):
    cloud = random_cloud(4, sh_degree=0)
    cloud.extras = extras
    path = tmp_path / "x.ply"
    with raises_naming(path, words):
        ply.write(path, cloud)
    assert not path.exists()


def test_struct_packed_reference_file(tmp_path):
    """One 3DGS vertex packed field by field with struct, as the reference writer lays it out."""
    values = list(range(1, 63))
    names = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
        + "".join(f"property float {n}\n" for n in names)
        + "end_header\n"
    )
    path = write_bytes(tmp_path, header.encode() + struct.pack("<62f", *values))
    cloud = ply.read(path)
    assert cloud.positions.tolist() == [[1, 2, 3]]
    assert cloud.extras["nx"].tolist() == [4]
    assert cloud.sh[0, 0].tolist() == [7, 8, 9]
    assert cloud.sh[0, 1].tolist() == [10, 25, 40]  # coefficient 1 of R, G, B
    assert cloud.sh[0, 15].tolist() == [24, 39, 54]
    assert cloud.opacity_logits.tolist() == [55]
    assert cloud.log_scales.tolist() == [[56, 57, 58]]
    assert cloud.rotations.tolist() == [[59, 60, 61, 62]]
    ply.write(tmp_path / "again.ply", cloud)
    assert (tmp_path / "again.ply").read_bytes() == path.read_bytes()


def test_compiled_and_numpy_fills_write_the_same_bytes(tmp_path, monkeypatch):
    """The compiled record fill (where numba loads) and the NumPy one give byte-identical files,
    with normals and extras, and both count non-finite values the same way."""
    from splatwright.core import jit

    cloud = random_cloud(3000, sh_degree=2, seed=41)
    cloud.extras.update(nx=np.linspace(0, 1, 3000, dtype=np.float32), label=np.arange(3000, dtype=np.int32))
    bad = cloud.copy()
    bad.sh[7, 3, 1] = np.nan
    ply.write(tmp_path / "fast.ply", cloud)
    assert jit.status("io.ply_kernels") == "compiled"
    with pytest.raises(SplatFileError, match="sh"):
        ply.write(tmp_path / "bad_fast.ply", bad)
    monkeypatch.setattr(ply.jit, "load", lambda *args, **kwargs: None)
    ply.write(tmp_path / "slow.ply", cloud)
    with pytest.raises(SplatFileError, match="sh"):
        ply.write(tmp_path / "bad_slow.ply", bad)
    assert (tmp_path / "fast.ply").read_bytes() == (tmp_path / "slow.ply").read_bytes()
    assert not (tmp_path / "bad_fast.ply").exists() and not (tmp_path / "bad_slow.ply").exists()
