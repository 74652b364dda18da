"""Hostile glTF and SOG files: names that lead out of the file's folder, special files, JSON nested
past Python's recursion limit, counts nothing holds, and images that decode to far more than the
file stores. Each must end in a SplatFileError naming the file, or a correct read, quickly and in
little memory; nothing outside the allowed folder is ever read (its bytes appear nowhere)."""

import base64
import io
import json
import os
import struct
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import random_cloud, skip_platform
from test_io_fuzz import SMALL_PEAK, outcome, peak_bytes

from splatwright.cli import main
from splatwright.io import SplatFileError, gltf, read_splats, sog, write_splats
from splatwright.io.policy import MAX_IMAGE_PIXELS

pytestmark = pytest.mark.filterwarnings("ignore::splatwright.io.SplatFileWarning")

SECRET = b"SECRET:the-key-is-0123456789abc!"  # 32 bytes: the u8 rotations of 8 splats
N = len(SECRET) // 4


def refusal(read, path, **options):
    """The SplatFileError a read ends in; it names the file and does not quote the secret."""
    with pytest.raises(SplatFileError) as info:
        read(path, **options)
    message = str(info.value)
    assert Path(path).name in message and SECRET.decode() not in message
    return message


def on_time(fn, seconds=10):
    """fn() run in a thread that must finish within `seconds` (a FIFO would block it forever)."""
    box = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), "the read hangs"
    return box


# glTF files whose rotations come from a named buffer -------------------------------------------


def gltf_document(rotation_buffer, n=N, nodes=1, extra_accessor=None):
    """(document, bytes of buffer 0) for n splats: positions, scales, opacities and DC colour as
    floats in buffer 0; rotations u8 normalised in buffer 1 = `rotation_buffer` when given (its
    first 4n bytes), else floats in buffer 0."""
    rng = np.random.default_rng(5)
    arrays = {
        "POSITION": (rng.normal(size=(n, 3)), "VEC3"),
        "KHR_gaussian_splatting:SCALE": (rng.uniform(0.1, 1, (n, 3)), "VEC3"),
        "KHR_gaussian_splatting:OPACITY": (rng.uniform(0.1, 0.9, n), "SCALAR"),
        "KHR_gaussian_splatting:SH_DEGREE_0_COEF_0": (rng.normal(size=(n, 3)), "VEC3"),
    }
    if rotation_buffer is None:
        arrays["KHR_gaussian_splatting:ROTATION"] = (rng.normal(size=(n, 4)), "VEC4")
    blob, views, accessors, attributes = b"", [], [], {}
    for name, (values, kind) in arrays.items():
        data = np.ascontiguousarray(values, "<f4").tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        accessors.append({"bufferView": len(views) - 1, "componentType": 5126, "count": n, "type": kind})
        attributes[name] = len(accessors) - 1
        blob += data
    buffers = [{"byteLength": len(blob)}]
    if rotation_buffer is not None:
        buffers.append(rotation_buffer)
        views.append({"buffer": 1, "byteOffset": 0, "byteLength": 4 * n})
        accessors.append(
            {"bufferView": len(views) - 1, "componentType": 5121, "normalized": True, "count": n, "type": "VEC4"}
        )
        attributes["KHR_gaussian_splatting:ROTATION"] = len(accessors) - 1
    if extra_accessor is not None:  # replaces one attribute's accessor
        name, accessor = extra_accessor
        accessors.append(accessor)
        attributes[name] = len(accessors) - 1
    primitive = {"mode": 0, "attributes": attributes, "extensions": {"KHR_gaussian_splatting": {"kernel": "ellipse"}}}
    doc = {
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_gaussian_splatting"],
        "scenes": [{"nodes": list(range(nodes))}],
        "nodes": [{"mesh": 0} for _ in range(nodes)],
        "meshes": [{"primitives": [primitive]}],
        "buffers": buffers,
        "bufferViews": views,
        "accessors": accessors,
    }
    return doc, blob


def save_gltf(path, doc, blob):
    """`doc` as a .gltf (buffer 0 a data URI) or a .glb (buffer 0 its binary chunk)."""
    if path.suffix == ".gltf":
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path.write_text(json.dumps(doc))
        return path
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob += bytes(-len(blob) % 4)
    path.write_bytes(
        struct.pack("<III", gltf.GLB_MAGIC, 2, 28 + len(text) + len(blob))
        + struct.pack("<II", len(text), gltf.JSON_CHUNK)
        + text
        + struct.pack("<II", len(blob), gltf.BIN_CHUNK)
        + blob
    )
    return path


def rotation_bytes(cloud):
    """The u8 rotations a cloud was read from (x, y, z, w; the axis flip changes only signs)."""
    return np.rint(np.abs(cloud.rotations[:, [1, 2, 3, 0]]) * 255).astype(np.uint8).tobytes()


@pytest.fixture
def layout(tmp_path):
    """tmp/model/ (where the glTF goes) and tmp/outside/secret.bin."""
    (tmp_path / "model").mkdir()
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "secret.bin").write_bytes(SECRET)
    return tmp_path


def escapes(root):
    """URIs a hostile glTF names the secret by."""
    secret = root / "outside" / "secret.bin"
    (root / "model" / "link.bin").symlink_to(secret)
    return {
        "dotdot": "../outside/secret.bin",
        "percent": "%2e%2e/outside/secret.bin",
        "percent_slash": "..%2Foutside%2Fsecret.bin",
        "backslash": "..\\outside\\secret.bin",
        "through": "sub/../../outside/secret.bin",
        "absolute": secret.as_posix(),
        "file_uri": secret.as_uri(),
        "file_localhost": "file://localhost" + secret.as_posix(),
        "symlink": "link.bin",
    }


@pytest.mark.parametrize("ext", [".gltf", ".glb"])
def test_gltf_buffers_outside_the_folder_are_refused_alike_whether_they_exist_or_not(layout, ext):
    uris = escapes(layout)
    for label, uri in uris.items():
        path = save_gltf(layout / "model" / f"{label}{ext}", *gltf_document({"uri": uri, "byteLength": 32}))
        message = refusal(read_splats, path)
        assert "buffer 1" in message, message
        (layout / "outside" / "secret.bin").rename(layout / "outside" / "moved")
        try:
            assert refusal(read_splats, path) == message  # nothing says whether the file is there
        finally:
            (layout / "outside" / "moved").rename(layout / "outside" / "secret.bin")
    # the command line converts nothing and says why
    out = layout / "model" / "out.ply"
    assert main(["convert", str(layout / "model" / f"dotdot{ext}"), str(out)]) == 1
    assert not out.exists()


def test_gltf_allow_outside_reads_the_named_buffer(layout):
    """The refusals above are of a file that does get read when allowed: its bytes are the rotations."""
    path = save_gltf(layout / "model" / "a.gltf", *gltf_document({"uri": "../outside/secret.bin", "byteLength": 32}))
    assert rotation_bytes(read_splats(path, allow_outside=True)) == SECRET
    assert rotation_bytes(gltf.read(path, allow_outside=True)) == SECRET


def test_gltf_buffers_inside_the_folder_read(layout):
    model = layout / "model"
    (model / "bins").mkdir()
    (model / "bins" / "my data.bin").write_bytes(SECRET + b"trailing bytes past byteLength")
    for uri in ("bins/my%20data.bin", "./bins/../bins/my data.bin", "bins%2Fmy%20data.bin"):
        for ext in (".gltf", ".glb"):
            path = save_gltf(model / f"in{ext}", *gltf_document({"uri": uri, "byteLength": 32}))
            assert rotation_bytes(read_splats(path)) == SECRET
    (model / "short.bin").write_bytes(SECRET[:20])
    path = save_gltf(model / "short.gltf", *gltf_document({"uri": "short.bin", "byteLength": 32}))
    assert "truncated: buffer 1 holds 20 of its 32 bytes" in refusal(read_splats, path)
    path = save_gltf(model / "claim.gltf", *gltf_document({"uri": "short.bin", "byteLength": 1 << 33}))
    assert f"holds 20 of its {1 << 33} bytes" in refusal(read_splats, path)  # from its size, unread


def test_gltf_a_file_many_buffers_name_is_read_once(layout):
    """400 buffers naming one 2 MB file beside a 40 KB .gltf: read once, not 800 MB."""
    (layout / "model" / "shared.bin").write_bytes(SECRET + bytes(2 << 20))
    doc, blob = gltf_document({"uri": "shared.bin", "byteLength": 32})
    doc["buffers"] += [{"uri": "shared.bin", "byteLength": (2 << 20) - i} for i in range(400)]
    path = save_gltf(layout / "model" / "many.gltf", doc, blob)
    assert peak_bytes(lambda: outcome(read_splats, path)) < 16 << 20
    assert rotation_bytes(read_splats(path)) == SECRET


def test_gltf_special_files_are_refused_without_opening_them(layout):
    model = layout / "model"
    uris = {"zero": "/dev/zero", "null": "/dev/null", "folder": "."}
    if hasattr(os, "mkfifo"):
        os.mkfifo(model / "pipe.bin")
        uris["fifo"] = "pipe.bin"
    else:
        skip_platform("no FIFOs")
    for label, uri in uris.items():
        path = save_gltf(model / f"{label}.gltf", *gltf_document({"uri": uri, "byteLength": 32}))
        for allow in (False, True):  # devices and pipes are refused even where files outside are allowed
            box = on_time(lambda path=path, allow=allow: outcome(gltf.read, path, allow_outside=allow))
            assert box == {"value": None}, (label, box)


# malformed JSON and counts nothing holds --------------------------------------------------------


DEEP = "[" * 100_000 + "]" * 100_000


def test_json_nested_past_the_recursion_limit(tmp_path):
    (tmp_path / "deep.gltf").write_text(DEEP)
    assert "JSON" in refusal(read_splats, tmp_path / "deep.gltf")
    text = DEEP.encode() + b" " * (-len(DEEP) % 4)
    glb = struct.pack("<III", gltf.GLB_MAGIC, 2, 20 + len(text)) + struct.pack("<II", len(text), gltf.JSON_CHUNK) + text
    (tmp_path / "deep.glb").write_bytes(glb)
    assert "JSON" in refusal(read_splats, tmp_path / "deep.glb")
    with zipfile.ZipFile(tmp_path / "deep.sog", "w") as bundle:
        bundle.writestr("meta.json", DEEP)
    assert "meta.json" in refusal(read_splats, tmp_path / "deep.sog")
    (tmp_path / "loose").mkdir()
    (tmp_path / "loose" / "meta.json").write_text(DEEP)
    refusal(read_splats, tmp_path / "loose" / "meta.json")


@pytest.mark.parametrize("attribute", ["POSITION", "KHR_gaussian_splatting:ROTATION"])
def test_gltf_accessor_without_data_claiming_two_billion_elements(tmp_path, attribute):
    """An accessor without a bufferView is all zeros: nothing in the file holds its 2e9 elements."""
    width = 4 if "ROT" in attribute else 3
    accessor = {"componentType": 5126, "count": 2_000_000_000, "type": f"VEC{width}"}
    path = save_gltf(tmp_path / "zeros.gltf", *gltf_document(None, extra_accessor=(attribute, accessor)))
    started = time.perf_counter()
    assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
    assert time.perf_counter() - started < 2  # refused from the count: nothing allocated
    assert f"one accessor {2_000_000_000 * width} of them" in refusal(read_splats, path)
    accessor["count"] = N  # the same accessor with the primitive's own count reads, as zeros
    path = save_gltf(tmp_path / "few.gltf", *gltf_document(None, extra_accessor=(attribute, accessor)))
    cloud = read_splats(path, nonfinite="keep")
    assert len(cloud) == N and not getattr(cloud, "positions" if attribute == "POSITION" else "rotations").any()


def test_gltf_instancing_and_aliasing_cannot_multiply_a_small_file(tmp_path):
    """Many nodes naming one mesh, or a view read by a stride shorter than its elements, would
    decode to far more than the file holds."""
    n = 1000
    doc, blob = gltf_document(None, n=n, nodes=3000)  # 3M splats from 56 KB
    path = save_gltf(tmp_path / "nodes.glb", doc, blob)
    started = time.perf_counter()
    assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
    assert time.perf_counter() - started < 2
    assert "decode" in refusal(read_splats, path)
    doc, blob = gltf_document(None, n=n, nodes=3)
    moved = [np.eye(4) for _ in range(3)]
    for i, node in enumerate(doc["nodes"]):
        node["translation"] = [10.0 * i, 0, 0]
        moved[i][0, 3] = 10.0 * i
    three = read_splats(save_gltf(tmp_path / "three.glb", doc, blob))
    one = read_splats(save_gltf(tmp_path / "one.glb", *gltf_document(None, n=n)))
    assert len(three) == 3 * n
    for i in range(3):  # glTF's +X is the model's -X
        np.testing.assert_allclose(three.positions[i * n : (i + 1) * n], one.positions - [10.0 * i, 0, 0], atol=1e-5)
    doc, blob = gltf_document(None, n=n)
    doc["bufferViews"][0]["byteStride"] = 1  # elements of 12 bytes, 1 byte apart
    doc["accessors"][0]["count"] = len(blob) - 12
    assert "byteStride" in refusal(read_splats, save_gltf(tmp_path / "stride.glb", doc, blob))


# SOG: the files meta.json names ------------------------------------------------------------------


def sog_bundle(path, meta_change=None, files=None, compression=zipfile.ZIP_STORED):
    """A valid 50-splat SOG (SH degree 1) rewritten with meta.json updated by `meta_change` and
    entries replaced or added by `files`."""
    write_splats(path, random_cloud(50, sh_degree=1, seed=3))
    with zipfile.ZipFile(path) as bundle:
        entries = {name: bundle.read(name) for name in bundle.namelist()}
    meta = json.loads(entries["meta.json"])
    if meta_change:
        meta_change(meta)
    entries = {**entries, "meta.json": json.dumps(meta).encode(), **(files or {})}
    with zipfile.ZipFile(path, "w", compression) as bundle:
        for name, data in entries.items():
            bundle.writestr(name, data)
    return path


@pytest.mark.parametrize(
    "key, files",
    [
        ("means", ["means_l.webp"]),
        ("means", []),
        ("means", [1, 2]),
        ("means", "means_l.webp"),
        ("quats", []),
        ("quats", [7]),
        ("sh0", [{"name": "sh0.webp"}]),
        ("scales", None),
        ("shN", ["shN_centroids.webp"]),
        ("shN", [None, None]),
    ],
)
def test_sog_files_lists_of_the_wrong_shape(tmp_path, key, files):
    path = sog_bundle(tmp_path / "files.sog", lambda meta: meta[key].update(files=files))
    message = refusal(read_splats, path)
    assert f"{key}.files" in message, message


def test_sog_bundle_entries_that_inflate_far_past_their_size(tmp_path):
    """WebP and JSON barely deflate; an entry that inflates 1000-fold is refused unread."""
    padded = lambda meta: meta["asset"].update(padding=" " * (64 << 20))  # noqa: E731
    path = sog_bundle(tmp_path / "deflated.sog", padded, compression=zipfile.ZIP_DEFLATED)
    assert path.stat().st_size < 1 << 20
    started = time.perf_counter()
    assert peak_bytes(lambda: outcome(read_splats, path)) < SMALL_PEAK
    assert time.perf_counter() - started < 2
    assert "meta.json" in refusal(read_splats, path)
    ordinary = sog_bundle(tmp_path / "ordinary.sog", compression=zipfile.ZIP_DEFLATED)
    assert len(read_splats(ordinary)) == 50


# SOG: images that decode to far more than the file stores ----------------------------------------


def webp(width, height, rgba=(0, 0, 0, 252)):
    buffer = io.BytesIO()
    from PIL import Image

    Image.new("RGBA", (width, height), rgba).save(buffer, "WEBP", lossless=True, exact=True, method=0)
    return buffer.getvalue()


def bomb(path, count, width, height, degree=0, image=None):
    """A .sog of one-colour lossless images `width` x `height` (or `image`) claiming `count` splats."""
    image = image or webp(width, height)
    meta = {
        "version": 2,
        "count": count,
        "means": {"mins": [0, 0, 0], "maxs": [1, 1, 1], "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": [-3.0] * 256, "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": [0.5] * 256, "files": ["sh0.webp"]},
    }
    files = dict.fromkeys(["means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"], image)
    if degree:
        k = sog.SH_COEFFS[degree]
        meta["shN"] = {"count": 64, "bands": degree, "codebook": [0.0] * 256, "files": ["c.webp", "l.webp"]}
        files |= {"c.webp": webp(64 * k, 1), "l.webp": image}
    with zipfile.ZipFile(path, "w") as bundle:
        bundle.writestr("meta.json", json.dumps(meta))
        for name, data in files.items():
            bundle.writestr(name, data)
    return path


def in_child(path):
    """(seconds, peak resident bytes, outcome) of reading `path` in a fresh process whose address
    space is capped at 3 GiB (so a regression fails here rather than exhausting the machine)."""
    script = """
import re, resource, sys, time
resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
from splatwright.io import SplatFileError, read_splats
started = time.perf_counter()
try:
    result = str(len(read_splats(sys.argv[1])))
except SplatFileError as exc:
    result = "SplatFileError: " + str(exc)
seconds = time.perf_counter() - started
with open("/proc/self/status") as f:  # this process's own high-water mark (ru_maxrss counts the parent's)
    peak = int(re.search(r"VmHWM:\\s*(\\d+) kB", f.read()).group(1)) * 1024
print(seconds, peak, result)
"""
    if sys.platform != "linux":
        skip_platform("the child's memory is measured from Linux's /proc")
    done = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    seconds, peak, result = done.stdout.strip().split(" ", 2)
    return float(seconds), int(peak), result


def test_sog_bomb_claiming_25_million_splats_is_refused_from_its_headers(tmp_path):
    path = bomb(tmp_path / "bomb.sog", 25_000_000, 5000, 5000)
    assert path.stat().st_size < 16 << 10
    seconds, peak, result = in_child(path)
    assert result.startswith("SplatFileError: ") and "bomb.sog" in result and "25000000" in result, result
    assert seconds < 2 and peak < 1 << 30


@pytest.mark.parametrize("degree", [0, 3])
def test_sog_largest_claims_a_small_file_may_make_read_within_bounds(tmp_path, degree):
    """A file under 1 MB reads at most what its stored bytes allow: the limit read whole, one splat
    more refused, in under 1 GiB (and a generous time, on a shared machine)."""
    values = 3 + 4 + 3 + 1 + 3 * (1 + (sog.SH_COEFFS[degree] if degree else 0))
    probe = bomb(tmp_path / "probe.sog", 1, 4, 4, degree)
    most = sog.SOG_RATIO_FLOOR // values  # what these tiny files may claim
    width = int(np.ceil(np.sqrt(most + 1) / 4) * 4)
    path = bomb(tmp_path / "most.sog", most, width, width, degree)
    assert probe.stat().st_size < path.stat().st_size < 1 << 20
    seconds, peak, result = in_child(path)
    assert result == str(most) and peak < 1 << 30 and seconds < 10, (seconds, peak, result)
    cloud = read_splats(path)
    np.testing.assert_allclose(cloud.log_scales, -3.0)
    np.testing.assert_allclose(cloud.sh[:, 0], 0.5)
    over = bomb(tmp_path / "over.sog", most + 1, width, width, degree)
    assert "decode" in refusal(read_splats, over)


def forged(width, height):
    """A lossless WebP of 8 x 8 pixels whose header claims `width` x `height`."""
    image = bytearray(webp(8, 8))
    bits = struct.unpack_from("<I", image, 21)[0] & ~((1 << 28) - 1)  # keep the alpha and version bits
    struct.pack_into("<I", image, 21, bits | (width - 1) | (height - 1) << 14)
    return bytes(image)


def test_sog_images_past_the_pixel_limit_are_refused_from_their_headers(tmp_path):
    side = 16384
    assert side * side > MAX_IMAGE_PIXELS
    path = bomb(tmp_path / "wide.sog", side * side, 0, 0, image=forged(side, side))
    seconds, peak, result = in_child(path)
    assert f"{side} x {side}" in result and "wide.sog" in result, result
    assert seconds < 2 and peak < 1 << 30
    path = sog_bundle(tmp_path / "one.sog", files={"quats.webp": forged(side, side)})
    assert f"quats.webp of {side} x {side} pixels" in refusal(read_splats, path)


# unbundled SOG: meta.json and images beside it --------------------------------------------------


@pytest.fixture
def loose(tmp_path):
    """tmp/model/meta.json with its images, tmp/outside/ with a copy of the quats image."""
    (tmp_path / "model").mkdir()
    (tmp_path / "outside").mkdir()
    write_splats(tmp_path / "model" / "meta.json", random_cloud(50, sh_degree=1, seed=4))
    (tmp_path / "outside" / "q.webp").write_bytes((tmp_path / "model" / "quats.webp").read_bytes())
    return tmp_path


def with_quats(root, name):
    meta = root / "model" / "meta.json"
    text = json.loads(meta.read_text())
    text["quats"]["files"] = [name]
    meta.write_text(json.dumps(text))
    return meta


def test_sog_loose_images_outside_the_folder_are_refused_alike_whether_they_exist_or_not(loose):
    original = read_splats(loose / "model" / "meta.json")
    outside = loose / "outside" / "q.webp"
    (loose / "model" / "link.webp").symlink_to(outside)
    names = ["../outside/q.webp", outside.as_posix(), "..\\outside\\q.webp", "link.webp", "sub/../../outside/q.webp"]
    for name in names:
        meta = with_quats(loose, name)
        message = refusal(read_splats, meta)
        outside.rename(loose / "outside" / "moved")
        try:
            assert refusal(read_splats, meta) == message
        finally:
            (loose / "outside" / "moved").rename(outside)
    # allowed, the image outside is read: the same rotations as the original
    meta = with_quats(loose, "../outside/q.webp")
    np.testing.assert_array_equal(sog.read(meta, allow_outside=True).rotations, original.rotations)
    np.testing.assert_array_equal(read_splats(meta, allow_outside=True).rotations, original.rotations)


def test_sog_loose_special_files_are_refused_without_opening_them(loose):
    if not hasattr(os, "mkfifo"):
        skip_platform("no FIFOs")
    os.mkfifo(loose / "model" / "pipe.webp")
    for name in ("pipe.webp", "/dev/zero", "."):
        meta = with_quats(loose, name)
        for allow in (False, True):
            box = on_time(lambda meta=meta, allow=allow: outcome(sog.read, meta, allow_outside=allow))
            assert box == {"value": None}, (name, box)
