"""PlayCanvas compressed PLY, SOG and glTF KHR_gaussian_splatting: hand-built files from the format
descriptions, closed-form quantisation bounds, the non-finite policy, and damaged files (in the
style of test_io_fuzz: every case a SplatFileError naming the file, or a finite cloud)."""

import json
import struct
import sys
import warnings

import numpy as np
import pytest
from helpers import random_cloud
from test_io_fuzz import check_splat_read, damaged, outcome, write_case

from splatwright.core import sh as shmod
from splatwright.io import (
    SplatFileError,
    SplatFileWarning,
    compressed_ply,
    format_of,
    gltf,
    read_splats,
    sog,
    write_splats,
)

C0 = 0.28209479177387814


def unit_angle_deg(a, b):
    cos = np.abs((a.unit_rotations * b.unit_rotations).sum(axis=1))
    return np.degrees(2 * np.arccos(np.clip(cos, 0, 1)))


def test_format_table_names_the_new_formats(tmp_path):
    assert format_of("a.compressed.ply") == "compressed_ply" and format_of("A.COMPRESSED.PLY") == "compressed_ply"
    assert format_of("a.ply") == "ply" and format_of("scene.sog") == "sog" and format_of("x/meta.json") == "sog"
    assert format_of("a.glb") == "gltf" and format_of("a.gltf") == "gltf"
    for bad in ("a.json", ".ply", "a.sog.bak"):
        with pytest.raises(SplatFileError, match="unknown splat file extension"):
            format_of(bad)


# compressed PLY --------------------------------------------------------------------------------------


def test_compressed_ply_hand_built_bytes(tmp_path):
    """One chunk, two splats, packed by hand from the layout."""
    chunk = struct.pack("<18f", -1, 0, 2, 3, 1, 4, -5, -4, -3, -1, -2, -1, 0.2, 0.3, 0.4, 0.8, 0.9, 1.0)
    # splat 0: the chunk's minimum corner; splat 1: x at 1/2047 of 2047 steps = max, y 0, z half way
    pos = [0, (2047 << 21) | (0 << 11) | 1023]
    # rotations: identity (largest rot_0 = w, others at 1/2 -> 511.5 ~ 512 of 1023); a half turn
    # about z (largest rot_3)
    mid = 512
    rot = [(0 << 30) | (mid << 20) | (mid << 10) | mid, (3 << 30) | (mid << 20) | (mid << 10) | mid]
    scl = [(2047 << 21) | (1023 << 11) | 2047, 0]
    col = [(0 << 24) | (255 << 16) | (0 << 8) | 255, (255 << 24) | (0 << 16) | (51 << 8) | 51]
    sh = bytes([0, 255, 128, 64, 192, 1, 2, 3, 4]) + bytes([128] * 9)
    header = ["ply", "format binary_little_endian 1.0", "element chunk 1"]
    header += [f"property float {n}" for n in compressed_ply.BOUNDS + compressed_ply.COLOR_BOUNDS]
    header += ["element vertex 2"] + [f"property uint {n}" for n in compressed_ply.PACKED]
    header += ["element sh 2"] + [f"property uchar f_rest_{i}" for i in range(9)] + ["end_header"]
    vertices = b"".join(struct.pack("<4I", pos[i], rot[i], scl[i], col[i]) for i in range(2))
    path = tmp_path / "hand.compressed.ply"
    path.write_bytes(("\n".join(header) + "\n").encode() + chunk + vertices + sh)
    got = read_splats(path)
    np.testing.assert_allclose(got.positions, [[-1, 0, 2], [3, 0, 2 + 2 * 1023 / 2047]], atol=1e-6)
    np.testing.assert_allclose(got.log_scales, [[-1, -2, -1], [-5, -4, -3]], atol=1e-6)
    np.testing.assert_allclose(shmod.dc_to_rgb(got.sh[:, 0]), [[0.2, 0.9, 0.4], [0.8, 0.3, 0.4 + 0.6 * 0.2]], atol=1e-6)
    np.testing.assert_allclose(got.opacities, [1 - 1e-7, 0.2], atol=1e-6)
    step = (mid / 1023 - 0.5) * np.sqrt(2)  # what 512 of 1023 stands for: nearly zero
    np.testing.assert_allclose(got.rotations[0, 1:], step, atol=1e-9)
    np.testing.assert_allclose(got.rotations[1, 3], np.sqrt(1 - 3 * step**2))
    # sh bytes: 0 and 255 are the ends (-4, 4), others (b + 0.5) / 256 * 8 - 4; channel-major
    rest = np.array(
        [
            -4,
            4,
            (128.5 / 256 - 0.5) * 8,
            (64.5 / 256 - 0.5) * 8,
            (192.5 / 256 - 0.5) * 8,
            (1.5 / 256 - 0.5) * 8,
            (2.5 / 256 - 0.5) * 8,
            (3.5 / 256 - 0.5) * 8,
            (4.5 / 256 - 0.5) * 8,
        ]
    )
    np.testing.assert_allclose(got.sh[0, 1:], rest.reshape(3, 3).T, atol=1e-6)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compressed_ply_round_trip_within_its_steps(tmp_path, degree):
    cloud = random_cloud(1000, sh_degree=degree, seed=degree)
    cloud.sh[:, 1:] = np.clip(cloud.sh[:, 1:], -3.9, 3.9)
    path = tmp_path / "r.compressed.ply"
    write_splats(path, cloud)
    got = read_splats(path)
    want = cloud[compressed_ply.morton_order(cloud.positions)]
    chunks = -(-len(want) // 256)
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], chunks * 256 - len(a), 0)]).reshape(chunks, 256, -1)  # noqa: E731
    for values, got_values, bits in (
        (want.positions, got.positions, (11, 10, 11)),
        (want.log_scales, got.log_scales, (11, 10, 11)),
    ):
        span = np.repeat(np.ptp(pad(values.astype(np.float64)), axis=1), 256, axis=0)[: len(values)]
        steps = span / (2.0 ** np.array(bits) - 1)
        assert (np.abs(got_values - values) <= steps / 2 + 1e-6).all()
    assert np.abs(got.opacities - want.opacities).max() <= 0.5 / 255 + 1e-7
    # 10 bits over [-1/sqrt2, 1/sqrt2]: each stored component within sqrt2 / 2046, the largest
    # (rebuilt from them) about as close again: a turn of at most ~2 |dq| = 0.3 degrees
    assert unit_angle_deg(got, want).max() <= 0.3
    if degree:
        assert np.abs(got.sh[:, 1:] - want.sh[:, 1:]).max() <= 1 / 32 + 1e-6
    write_splats(tmp_path / "kept.compressed.ply", cloud, order=None)
    assert np.abs(read_splats(tmp_path / "kept.compressed.ply").positions - cloud.positions).max() < 0.02


def test_compressed_ply_policy_errors_and_damage(tmp_path):
    cloud = random_cloud(300, sh_degree=1, seed=4)
    bad = cloud.copy()
    bad.positions[3] = np.nan
    with pytest.raises(SplatFileError, match="non-finite"):
        write_splats(tmp_path / "n.compressed.ply", bad)
    with pytest.warns(SplatFileWarning, match="1 of 300 splats"):
        write_splats(tmp_path / "n.compressed.ply", bad, nonfinite="drop")
    assert len(read_splats(tmp_path / "n.compressed.ply")) == 299
    path = tmp_path / "v.compressed.ply"
    write_splats(path, cloud)
    data = path.read_bytes()
    header_len = data.index(b"end_header\n") + 11
    for label, damaged_bytes in damaged(data, header_len, seed=70):
        check_splat_read(read_splats, write_case(tmp_path, label, ".compressed.ply", damaged_bytes))
        check_splat_read(read_splats, write_case(tmp_path, label, ".ply", damaged_bytes))  # sniffed as well
    cases = {
        "chunks": data.replace(b"element chunk 2", b"element chunk 3"),
        "count": data.replace(b"element vertex 300", b"element vertex 301"),
        "uint": data.replace(b"property uint packed_scale", b"property float packed_scale"),
        "sh_rest": data.replace(b"property uchar f_rest_8\n", b""),
        "ascii": data.replace(b"binary_little_endian", b"ascii"),
    }
    messages = {
        "chunks": "3 chunks for 300 splats",
        "count": "each of the 301 splats; found 9 properties for 300",
        "uint": "uint properties",
        "sh_rest": "f_rest_0..M",
        "ascii": "must be binary_little_endian",
    }
    for label, bad_bytes in cases.items():
        with pytest.raises(SplatFileError, match=messages[label]):
            read_splats(write_case(tmp_path, label, ".compressed.ply", bad_bytes))


# glTF ------------------------------------------------------------------------------------------------


def gltf_doc(attributes, count, extension=None, mode=0):
    return {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_gaussian_splatting"],
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [
            {
                "primitives": [
                    {
                        "mode": mode,
                        "attributes": attributes,
                        "extensions": {
                            "KHR_gaussian_splatting": extension
                            or {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}
                        },
                    }
                ]
            }
        ],
    }


def hand_gltf(path, values, extension=None, mode=0, extra=None):
    """A .gltf with an embedded buffer: {attribute: (array, componentType, type, normalized)}."""
    blob, views, accessors, attributes = b"", [], [], {}
    for name, (array, ctype, kind, normalized) in values.items():
        data = np.ascontiguousarray(array).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        accessors.append(
            {
                "bufferView": len(views) - 1,
                "componentType": ctype,
                "count": len(array),
                "type": kind,
                **({"normalized": True} if normalized else {}),
            }
        )
        attributes[name] = len(accessors) - 1
        blob += data + bytes(-len(data) % 4)
    doc = gltf_doc(attributes, len(next(iter(values.values()))[0]), extension, mode)
    import base64

    doc.update(
        buffers=[
            {"byteLength": len(blob), "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}
        ],
        bufferViews=views,
        accessors=accessors,
        **(extra or {}),
    )
    path.write_text(json.dumps(doc))


def test_gltf_hand_built_file_with_quantised_rotations(tmp_path):
    """glTF's axes (LUF) against the model's (RDF): x and y change sign; normalised shorts for the
    rotation, as the extension allows."""
    positions = np.float32([[1, 2, 3], [-4, 5, 0.5]])
    q = np.array([[0, 0, 0, 1], [0.6, 0, 0, 0.8]])  # x, y, z, w
    rotation = np.rint(q * 32767).astype("<i2")
    values = {
        "POSITION": (positions, 5126, "VEC3", False),
        "KHR_gaussian_splatting:ROTATION": (rotation, 5122, "VEC4", True),
        "KHR_gaussian_splatting:SCALE": (np.float32([[0.1, 0.2, 0.3], [1, 1, 1]]), 5126, "VEC3", False),
        "KHR_gaussian_splatting:OPACITY": (np.float32([0.5, 1.0]), 5126, "SCALAR", False),
        "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0": (np.float32([[0.1, 0.2, 0.3], [0, 0, 0]]), 5126, "VEC3", False),
    }
    for c in range(3):
        values[f"KHR_gaussian_splatting:SH_DEGREE_1_COEF_{c}"] = (
            np.full((2, 3), c + 1, np.float32),
            5126,
            "VEC3",
            False,
        )
    hand_gltf(tmp_path / "hand.gltf", values)
    got = read_splats(tmp_path / "hand.gltf")
    np.testing.assert_array_equal(got.positions, positions * [-1, -1, 1])
    np.testing.assert_allclose(got.rotations, [[1, 0, 0, 0], [0.8, -0.6, 0, 0]], atol=1e-4)
    np.testing.assert_allclose(got.scales, [[0.1, 0.2, 0.3], [1, 1, 1]], rtol=1e-6)
    # degree 1 coefficients (y, z, x) change sign with y and x: -1, +2, -3
    np.testing.assert_allclose(got.sh[:, 1:, 0], [[-1, 2, -3], [-1, 2, -3]])
    values.pop("KHR_gaussian_splatting:SH_DEGREE_1_COEF_2")
    hand_gltf(tmp_path / "partial.gltf", values)
    with pytest.raises(SplatFileError, match="SH degree 1 has 2 of its 3 coefficients"):
        read_splats(tmp_path / "partial.gltf")
    hand_gltf(tmp_path / "triangles.gltf", values, mode=4)
    with pytest.raises(SplatFileError, match="must be POINTS"):
        read_splats(tmp_path / "triangles.gltf")
    hand_gltf(tmp_path / "spz.gltf", values, extra={"extensionsRequired": ["KHR_gaussian_splatting_compression_spz_2"]})
    with pytest.raises(SplatFileError, match="requires glTF extensions .*compression_spz_2"):
        read_splats(tmp_path / "spz.gltf")


def test_gltf_extras_another_tool_wrote(tmp_path):
    """Another tool's attributes: a quantised NORMAL (normalised bytes, as KHR_mesh_quantization
    allows) read as the normals in the model's axes, `_TEMPERATURE` as the extra TEMPERATURE, a
    matrix-typed `_FRAME` left out with a warning; a `_` attribute with too few entries refused."""
    values = {
        "POSITION": (np.float32([[1, 2, 3], [-4, 5, 0.5]]), 5126, "VEC3", False),
        "KHR_gaussian_splatting:ROTATION": (np.float32([[0, 0, 0, 1]] * 2), 5126, "VEC4", False),
        "KHR_gaussian_splatting:SCALE": (np.float32([[0.1, 0.2, 0.3]] * 2), 5126, "VEC3", False),
        "KHR_gaussian_splatting:OPACITY": (np.float32([0.5, 1.0]), 5126, "SCALAR", False),
        "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0": (np.float32([[0.1, 0.2, 0.3]] * 2), 5126, "VEC3", False),
        "NORMAL": (np.int8([[127, 0, 0], [0, 0, -127]]), 5120, "VEC3", True),
        "_TEMPERATURE": (np.float32([20.5, -3.0]), 5126, "SCALAR", False),
        "_FRAME": (np.zeros((2, 16), np.float32), 5126, "MAT4", False),
    }
    hand_gltf(tmp_path / "theirs.gltf", values)
    with pytest.warns(SplatFileWarning, match="_FRAME"):
        got = read_splats(tmp_path / "theirs.gltf")
    assert sorted(got.extras) == ["TEMPERATURE", "nx", "ny", "nz"]
    np.testing.assert_array_equal(got.extras["TEMPERATURE"], [20.5, -3.0])
    normals = np.stack([got.extras[k] for k in ("nx", "ny", "nz")], axis=1)
    np.testing.assert_array_equal(normals, [[-1, 0, 0], [0, 0, -1]])  # x and y reversed from glTF's
    values["_TEMPERATURE"] = (np.float32([20.5]), 5126, "SCALAR", False)
    hand_gltf(tmp_path / "short.gltf", values)
    with pytest.raises(SplatFileError, match="'TEMPERATURE' has 1 entries for 2 positions"):
        read_splats(tmp_path / "short.gltf")


def test_gltf_node_transforms_apply(tmp_path):
    cloud = random_cloud(30, sh_degree=1, seed=3)
    write_splats(tmp_path / "a.glb", cloud)
    doc, binary = gltf.encode(cloud)
    doc["nodes"] = [{"children": [1], "translation": [1, 2, 3]}, {"mesh": 0, "scale": [2, 2, 2]}]
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + __import__("base64").b64encode(binary).decode()
    (tmp_path / "moved.gltf").write_text(json.dumps(doc))
    moved = read_splats(tmp_path / "moved.gltf")
    # glTF translation (1, 2, 3) is (-1, -2, 3) in the model's axes; the scale doubles
    np.testing.assert_allclose(moved.positions, cloud.positions * 2 + [-1, -2, 3], atol=1e-5)
    np.testing.assert_allclose(moved.log_scales, cloud.log_scales + np.log(2), atol=1e-5)


@pytest.mark.parametrize("ext", [".glb", ".gltf"])
def test_gltf_round_trip_policy_and_damage(tmp_path, ext):
    cloud = random_cloud(100, sh_degree=3, seed=5)
    path = tmp_path / f"r{ext}"
    write_splats(path, cloud)
    got = read_splats(path)
    np.testing.assert_array_equal(got.positions, cloud.positions)
    np.testing.assert_array_equal(got.sh, cloud.sh)
    np.testing.assert_allclose(got.rotations, cloud.unit_rotations, atol=1e-7)
    np.testing.assert_allclose(got.log_scales, cloud.log_scales, atol=1e-6)
    np.testing.assert_allclose(got.opacities, cloud.opacities, atol=1e-7)
    bad = cloud.copy()
    bad.sh[7, 2, 1] = np.inf
    with pytest.raises(SplatFileError, match="non-finite"):
        write_splats(tmp_path / f"n{ext}", bad)
    data = path.read_bytes()
    for label, damaged_bytes in damaged(data, 400 if ext == ".gltf" else 20, seed=71):
        check_splat_read(read_splats, write_case(tmp_path, label, ext, damaged_bytes))
    if ext == ".gltf":
        (tmp_path / "r.bin").write_bytes((tmp_path / "r.bin").read_bytes()[:100])
        with pytest.raises(SplatFileError, match="truncated: buffer 0"):
            read_splats(path)


# SOG -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sog_round_trip_within_its_quantisation(tmp_path, degree):
    cloud = random_cloud(800, sh_degree=degree, seed=degree)
    for path in (tmp_path / "a.sog", tmp_path / "meta.json"):
        write_splats(path, cloud)
        got = read_splats(path)
        want = cloud[compressed_ply.morton_order(cloud.positions)]
        logs = np.abs(np.log1p(np.abs(want.positions.astype(np.float64))))
        span = np.ptp(np.sign(want.positions) * logs, axis=0)
        # 16 bits of the log-transformed range: d|x| = (|x| + 1) d(log)
        bound = (np.abs(want.positions) + 1) * span / 65535 / 2 * 1.001 + 1e-6
        assert (np.abs(got.positions - want.positions) <= bound).all()
        assert np.abs(got.opacities - want.opacities).max() <= 0.5 / 255 + 1e-7
        # 8 bits for q * sqrt2 over [-1, 1]: each component within 1 / (255 sqrt2), a turn of at most
        # about 4 |dq| = 1.1 degrees with the rebuilt largest component
        assert unit_angle_deg(got, want).max() <= 1.2
        # codebooks: 256 k-means centres; a value is as far as half the widest gap between them, or
        # beyond the outermost centre
        meta = json.loads(_meta_text(path))
        assert np.abs(got.log_scales - want.log_scales).max() <= codebook_bound(
            meta["scales"]["codebook"], want.log_scales
        )
        if degree:  # fewer splats than palette entries: each its own, only the 8-bit codebook rounds
            assert np.abs(got.sh[:, 1:] - want.sh[:, 1:]).max() <= codebook_bound(
                meta["shN"]["codebook"], want.sh[:, 1:]
            )


def codebook_bound(book, values):
    book = np.sort(np.asarray(book, np.float64))
    ends = max(book[0] - values.min(), values.max() - book[-1], 0)
    return max(np.diff(book).max() / 2, ends) + 1e-5


def _meta_text(path):
    if path.name == "meta.json":
        return path.read_text()
    import zipfile

    return zipfile.ZipFile(path).read("meta.json").decode()


def test_sog_palette_for_large_clouds_is_balanced():
    rng = np.random.default_rng(0)
    vectors = rng.normal(size=(5000, 9)).astype(np.float32)
    centroids, labels = sog.palette(vectors, 512)
    assert centroids.shape == (512, 9) and labels.min() == 0 and labels.max() == 511
    sizes = np.bincount(labels)
    assert sizes.min() >= 5000 // 512 - 1 and sizes.max() <= 5000 // 512 + 2
    np.testing.assert_allclose(centroids[3], vectors[labels == 3].mean(axis=0), rtol=1e-5)
    # better than one centroid for all: the split follows the data
    assert ((vectors - centroids[labels]) ** 2).mean() < 0.75 * ((vectors - vectors.mean(0)) ** 2).mean()


def test_sog_without_pillow_says_what_is_missing(tmp_path, monkeypatch):
    write_splats(tmp_path / "a.sog", random_cloud(10, sh_degree=0))
    monkeypatch.setitem(sys.modules, "PIL", None)
    for call in (lambda: read_splats(tmp_path / "a.sog"), lambda: write_splats(tmp_path / "b.sog", random_cloud(5))):
        with pytest.raises(
            SplatFileError, match="no WebP codec \\(the Pillow package; Blender's own Python lacks it\\)"
        ) as info:
            call()
        assert "pip install" not in str(info.value)
    assert not (tmp_path / "b.sog").exists()


def test_sog_policy_errors_and_damage(tmp_path):
    cloud = random_cloud(200, sh_degree=2, seed=8)
    bad = cloud.copy()
    bad.log_scales[1] = np.nan
    with pytest.raises(SplatFileError, match="non-finite"):
        write_splats(tmp_path / "n.sog", bad)
    with pytest.raises(SplatFileError, match="empty cloud"):
        write_splats(tmp_path / "e.sog", cloud[:0])
    path = tmp_path / "v.sog"
    write_splats(path, cloud)
    data = path.read_bytes()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for label, damaged_bytes in damaged(data, 60, seed=72, flips=12):
            check_splat_read(read_splats, write_case(tmp_path, label, ".sog", damaged_bytes))
    (tmp_path / "loose").mkdir()
    meta = tmp_path / "loose" / "meta.json"
    write_splats(meta, cloud)
    text = json.loads(meta.read_text())
    for _label, change, message in [
        ("version", {"version": 1}, "SOG version 1"),
        ("count", {"count": 10**6}, "pixels for 1000000 splats"),
        ("codebook", {"scales": {"codebook": [0, 1], "files": ["scales.webp"]}}, "256-entry"),
        ("escape", {"quats": {"files": ["../v.sog"]}}, "SOG image '../v.sog' is not a readable file under"),
    ]:
        meta.write_text(json.dumps({**text, **change}))
        with pytest.raises(SplatFileError, match=message):
            read_splats(meta)
    meta.write_text(json.dumps(text))
    (tmp_path / "loose" / "quats.webp").write_bytes(b"RIFF\x00\x00\x00\x00WEBPVP8L")
    assert outcome(read_splats, meta) is None
    (tmp_path / "loose" / "quats.webp").unlink()
    with pytest.raises(SplatFileError, match="SOG image 'quats.webp' is not a readable file under"):  # as refused
        read_splats(meta)


def test_gltf_documents_of_the_wrong_shape(tmp_path):
    import base64

    doc, binary = gltf.encode(random_cloud(5, sh_degree=1))
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    cases = {
        "matrix": (lambda d: d["nodes"][0].update(matrix=[1, 2]), "malformed glTF document"),
        "scene": (lambda d: d.update(scene=5), "scene 5 does not exist"),
        "attributes": (lambda d: d["meshes"][0]["primitives"][0].update(attributes="x"), "no POSITION"),
        "extension": (
            lambda d: d["meshes"][0]["primitives"][0]["extensions"].update(KHR_gaussian_splatting=3),
            "malformed glTF document",
        ),
        "accessor": (lambda d: d["accessors"][0].update(count=10**12), "run past the end"),
        "no_splats": (
            lambda d: d["meshes"][0]["primitives"][0].pop("extensions"),
            "no KHR_gaussian_splatting primitive",
        ),
    }
    for label, (mutate, message) in cases.items():
        broken = json.loads(json.dumps(doc))
        mutate(broken)
        path = tmp_path / f"{label}.gltf"
        path.write_text(json.dumps(broken))
        with pytest.raises(SplatFileError, match=message):
            read_splats(path)


# SH degree 4 where a format stops at 3 -----------------------------------------------------------------


@pytest.mark.parametrize(
    "name, words",
    [
        ("r.compressed.ply", "compressed PLY stores SH up to degree 3"),
        ("r.glb", "KHR_gaussian_splatting stores SH up to degree 3"),
        ("r.sog", "SOG stores SH up to degree 3"),
        ("r.splat", "stores the DC colour only; SH degree 4"),
    ],
)
def test_formats_without_a_fourth_band_reduce_degree_4_and_say_so(tmp_path, name, words):
    """The file is the one the degree-3 truncation of the cloud makes, byte for byte; a cloud whose
    fourth band is zero (a degree-3 cloud padded up) loses nothing and gets no warning."""
    if name.endswith(".sog"):
        pytest.importorskip("PIL")
    cloud = random_cloud(300, sh_degree=4, seed=46)
    path, lower = tmp_path / name, tmp_path / f"three-{name}"
    with pytest.warns(SplatFileWarning, match=words):
        write_splats(path, cloud)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # .splat warns for degree 3 too
        write_splats(lower, cloud.with_sh_degree(3))
    assert path.read_bytes() == lower.read_bytes()
    assert read_splats(path).sh_degree == (0 if name.endswith(".splat") else 3)
    padded = cloud.with_sh_degree(3).with_sh_degree(4)
    if not name.endswith(".splat"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            write_splats(tmp_path / f"padded-{name}", padded)
        assert (tmp_path / f"padded-{name}").read_bytes() == lower.read_bytes()
