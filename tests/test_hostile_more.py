"""Hostile files, second round: URDF mesh names that leave the robot's folder, textures that
trimesh would decode past the size limit, a PLY header of 45,000 properties, EXR headers that lie
about their sizes, and the command line's answers to all of them (one line, exit status 1)."""

import base64
import json
import os
import struct
import time
import tracemalloc
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.io import SplatFileError, SplatFileWarning, compressed_ply, image, ply, read_splats
from splatwright.io.exr_plain import read_plain_exr
from splatwright.io.meshes import read_mesh_file
from splatwright.io.urdf import read_description, read_robot

SMALL_PEAK = 64 << 20


def peak_bytes(fn):
    tracemalloc.start()
    try:
        fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def error_of(fn, *args, **options):
    with pytest.raises(SplatFileError) as caught:
        fn(*args, **options)
    return str(caught.value)


# PLY: a header of 45,000 properties -------------------------------------------------------------


def ply_with_junk(properties, tmp_path):
    """A valid one-splat binary PLY after an empty element of `properties` uchar properties (1 MB)."""
    names = ply.layout_names(0)
    head = (
        "ply\nformat binary_little_endian 1.0\nelement junk 0\n"
        + "".join(f"property uchar p{i}\n" for i in range(properties))
        + "element vertex 1\n"
        + "".join(f"property float {name}\n" for name in names)
        + "end_header\n"
    ).encode()
    values = np.zeros(len(names), "<f4")
    values[names.index("rot_0")] = 1.0
    path = tmp_path / "junk.ply"
    path.write_bytes(head + values.tobytes())
    return path


def test_a_megabyte_ply_header_is_read_in_linear_time(tmp_path):
    path = ply_with_junk(45_000, tmp_path)
    assert 0.9e6 < path.stat().st_size < 1 << 20
    start = time.process_time()
    cloud = read_splats(path)
    assert time.process_time() - start < 10  # "no bomb": quadratic checks took 88 s of CPU
    assert len(cloud) == 1 and np.array_equal(cloud.rotations, [[1, 0, 0, 0]])
    repeated = path.read_bytes().replace(b"property uchar p44999\n", b"property uchar p7\n")
    path.write_bytes(repeated)
    assert "junk element repeats properties ['p7']" in error_of(read_splats, path)


def test_the_ply_header_is_parsed_once(tmp_path, monkeypatch):
    plain, packed = tmp_path / "a.ply", tmp_path / "b.compressed.ply"
    cloud = random_cloud(300, sh_degree=1, seed=2)
    ply.write(plain, cloud)
    compressed_ply.write(packed, cloud)
    calls = []
    original = ply.read_header

    def counted(path, f):
        calls.append(path)
        return original(path, f)

    monkeypatch.setattr(ply, "read_header", counted)
    monkeypatch.setattr(compressed_ply, "read_header", counted)
    for path in (plain, packed):
        calls.clear()
        assert len(read_splats(path)) == 300
        assert len(calls) == 1, path


# EXR without the OpenEXR library ----------------------------------------------------------------


def exr_attribute(name, kind, value):
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def plain_exr(width, height, rows=None, offsets=None, channels=(("R", 2),)):
    """A single-part uncompressed scanline EXR made by hand: FLOAT channels, one row per chunk
    (`rows`: (height, width, channels) float32, default zeros), at `offsets` (default: in order)."""
    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3sii", t, 0, b"\0\0\0", 1, 1) for n, t in channels) + b"\0"
    window = struct.pack("<4i", 0, 0, width - 1, height - 1)
    header = (
        b"\x76\x2f\x31\x01\x02\x00\x00\x00"
        + exr_attribute("channels", "chlist", chlist)
        + exr_attribute("compression", "compression", b"\0")
        + exr_attribute("dataWindow", "box2i", window)
        + exr_attribute("displayWindow", "box2i", window)
        + exr_attribute("lineOrder", "lineOrder", b"\0")
        + b"\0"
    )
    count = max(height, 0)
    if rows is None:
        rows = np.zeros((count, max(width, 0), len(channels)), np.float32)
    chunks = [struct.pack("<ii", y, rows[y].nbytes) + rows[y].transpose(1, 0).tobytes() for y in range(count)]
    first = len(header) + 8 * count
    if offsets is None:
        offsets = first + np.cumsum([0] + [len(c) for c in chunks[:-1]]) if count else []
    return header + np.asarray(offsets, "<u8").tobytes() + b"".join(chunks)


def test_plain_exr_reads_what_it_was_given(tmp_path):
    rows = np.random.default_rng(1).normal(size=(5, 4, 2)).astype(np.float32)
    path = tmp_path / "ok.exr"
    path.write_bytes(plain_exr(4, 5, rows, channels=(("G", 2), ("R", 2))))
    got = read_plain_exr(path)
    assert np.array_equal(got["G"], rows[..., 0]) and np.array_equal(got["R"], rows[..., 1])
    import OpenEXR  # the library agrees on the hand-made file

    with OpenEXR.File(str(path)) as f:
        assert np.array_equal(f.channels()["R"].pixels, rows[..., 1])


def lying_exrs():
    good = plain_exr(3, 4)
    window = struct.pack("<4i", 0, 0, 2, 3)
    size_at = good.index(b"box2i\0") + 6
    yield "four_bytes", good[:4]
    yield "magic_and_flags_only", good[:8]
    yield "height_0", good.replace(window, struct.pack("<4i", 0, 0, 2, -1))
    yield "height_huge", good.replace(window, struct.pack("<4i", 0, 0, 2, 2**31 - 2))
    yield "width_huge", good.replace(window, struct.pack("<4i", 0, 0, 2**31 - 2, 3))
    yield "width_negative", good.replace(window, struct.pack("<4i", 5, 0, 0, 3))
    yield "attribute_size_negative", good[:size_at] + struct.pack("<i", -20) + good[size_at + 4 :]
    yield "attribute_size_huge", good[:size_at] + struct.pack("<i", 2**31 - 1) + good[size_at + 4 :]
    yield "no_channels", good.replace(good[good.index(b"chlist\0") + 7 : good.index(b"compression")], b"\1\0\0\0\0")
    # every chunk's row starts 8 bytes after the one before: 272 KB naming 256 MB of rows
    height, width = 16000, 4000
    head = plain_exr(width, 1)[: -8 - 8 - 4 * width]
    head = head.replace(struct.pack("<4i", 0, 0, width - 1, 0), struct.pack("<4i", 0, 0, width - 1, height - 1))
    first = len(head) + 8 * height
    pairs = b"".join(struct.pack("<ii", y, 4 * width) for y in range(height))
    offsets = np.arange(first, first + 8 * height, 8, dtype="<u8").tobytes()
    yield "overlapping", head + offsets + pairs + bytes(4 * width)


@pytest.mark.parametrize("label, data", list(lying_exrs()), ids=[label for label, _ in lying_exrs()])
def test_plain_exr_sizes_are_checked_against_the_file(tmp_path, label, data):
    path = tmp_path / f"{label}.exr"
    path.write_bytes(data)
    assert len(data) < 1 << 20
    assert peak_bytes(lambda: pytest.raises(SplatFileError, read_plain_exr, path)) < SMALL_PEAK
    assert f"{label}.exr" in error_of(read_plain_exr, path)


# URDF: mesh names stay under the allowed roots --------------------------------------------------


def write_stl(path, scale=1.0):
    """A binary STL tetrahedron (80-byte header, count, normal + corners + 2 bytes per facet)."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * scale
    tri = corners[[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]]
    record = np.zeros(4, dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    record["v"] = tri
    path.write_bytes(b"tetra".ljust(80, b" ") + np.uint32(4).tobytes() + record.tobytes())


def robot(folder, filename):
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "r.urdf"
    path.write_text(
        f'<robot name="r"><link name="a"><visual><geometry><mesh filename="{filename}"/></geometry></visual>'
        "</link></robot>"
    )
    return path


@pytest.fixture
def world(tmp_path):
    """tmp/secret.stl and tmp/pkg/meshes/m.stl outside tmp/robot; tmp/robot/inside.stl in it."""
    write_stl(tmp_path / "secret.stl")
    (tmp_path / "pkg" / "meshes").mkdir(parents=True)
    write_stl(tmp_path / "pkg" / "meshes" / "m.stl", 2.0)
    (tmp_path / "robot").mkdir()
    write_stl(tmp_path / "robot" / "inside.stl")
    return tmp_path


ESCAPES = {
    "parent": "../{name}",
    "absolute": "{folder}/{name}",
    "file_uri": "file://{folder}/{name}",
    "file_uri_escaped": "file://{folder}/%2e%2e/{folder_name}/{name}",
    "package_parent": "package://robot/../../{name}",
    "package_dots": "package://../{name}",
}


@pytest.mark.parametrize("kind", sorted(ESCAPES))
def test_urdf_meshes_outside_the_robot_folder_are_refused_alike(world, kind, monkeypatch):
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    messages = []
    for name in ("secret.stl", "missing.stl"):
        filename = ESCAPES[kind].format(folder=world, folder_name=world.name, name=name)
        urdf = robot(world / "robot", filename)
        message = error_of(read_description, urdf)
        assert "r.urdf" in message and f"mesh '{filename}'" in message
        messages.append(message.replace(filename, "NAME"))
    assert messages[0] == messages[1]  # the error does not say whether the file exists
    filename = ESCAPES[kind].format(folder=world, folder_name=world.name, name="secret.stl")
    if kind != "package_dots":  # package://../x is nobody's package, even when allowed
        description = read_description(robot(world / "robot", filename), allow_outside=True)
        assert description.visuals[0].path == world / "secret.stl"


@pytest.mark.parametrize("target", ["/etc/passwd", "/proc/self/environ", "/dev/zero", "fifo"])
def test_urdf_special_and_system_files_read_like_missing_ones(world, target, monkeypatch):
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    if target == "fifo":
        if not hasattr(os, "mkfifo"):
            from helpers import skip_platform

            skip_platform("no FIFOs on this platform")
        os.mkfifo(world / "robot" / "fifo")  # inside the folder: refused as not a regular file
    missing = error_of(read_description, robot(world / "robot", "nothing.stl")).replace("nothing.stl", "NAME")
    message = error_of(read_description, robot(world / "robot", target)).replace(target, "NAME")
    assert message == missing
    if target != "/etc/passwd":  # special files stay refused even when outside files are allowed
        assert error_of(read_robot, robot(world / "robot", target), allow_outside=True)


def test_urdf_packages_are_looked_up_only_in_the_given_roots(world, monkeypatch):
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    urdf = robot(world / "robot", "package://pkg/meshes/m.stl")
    # the package sits beside the robot's folder: found only once its folder is given
    assert "package://pkg/meshes/m.stl' not found" in error_of(read_description, urdf)
    assert read_description(urdf, package_paths=[world]).visuals[0].path == world / "pkg" / "meshes" / "m.stl"
    monkeypatch.setenv("HOME", str(world))
    assert read_description(urdf, package_paths=["~"]).visuals[0].path == world / "pkg" / "meshes" / "m.stl"
    monkeypatch.setenv("ROS_PACKAGE_PATH", f"/nonexistent{os.pathsep}{world}")
    assert read_description(urdf).visuals[0].path == world / "pkg" / "meshes" / "m.stl"
    # a package path names a root, not a way out of it
    monkeypatch.delenv("ROS_PACKAGE_PATH")
    escape = robot(world / "robot", "package://pkg/../secret.stl")
    assert "not found" in error_of(read_description, escape, package_paths=[world / "pkg"])
    # inside the robot's folder, plain and package names still resolve
    assert read_description(robot(world / "robot", "inside.stl")).visuals[0].path == world / "robot" / "inside.stl"
    inside = robot(world / "robot", "package://robot/inside.stl")
    assert read_description(inside).visuals[0].path == world / "robot" / "inside.stl"


def test_urdf_robot_reads_its_own_meshes_and_nothing_outside(world, monkeypatch):
    monkeypatch.delenv("ROS_PACKAGE_PATH", raising=False)
    opened = []
    real_open = open

    def watched(file, *args, **kwargs):
        opened.append(Path(file).resolve() if isinstance(file, str | os.PathLike) else file)
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", watched)
    with pytest.raises(SplatFileError):
        read_robot(robot(world / "robot", "../secret.stl"), max_splats=50)
    assert (world / "secret.stl").resolve() not in opened
    tetra = read_robot(robot(world / "robot", "inside.stl"), max_splats=50)
    assert len(tetra.cloud) > 0 and (world / "robot" / "inside.stl").resolve() in opened


# meshes through trimesh: textures within the limit and the folder -------------------------------


def png_of_zeros(width, height):
    """A grey 8-bit PNG of zeros, its rows compressed one at a time (no whole image in memory)."""
    chunk = lambda kind, data: struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    stream = zlib.compressobj(9)
    row = bytes(1 + width)
    idat = b"".join(stream.compress(row) for _ in range(height)) + stream.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def gltf_triangle(image=None, image_uri=None, buffer_uri=None):
    """(json document, binary buffer) of one textured triangle; the image embedded in the buffer,
    or named by `image_uri`; the buffer named by `buffer_uri` (a .gltf) or left for a GLB."""
    blobs = [
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes(),
        np.array([[0, 0], [1, 0], [0, 1]], np.float32).tobytes(),
        np.array([0, 1, 2, 0], np.uint16).tobytes(),
    ]
    if image is not None:
        blobs.append(image + bytes(-len(image) % 4))
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob)
    views[2]["byteLength"] = 6
    if image is not None:
        views[3]["byteLength"] = len(image)
    source = {"bufferView": 3, "mimeType": "image/png"} if image is not None else {"uri": image_uri}
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}],
        "images": [source],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 3, "type": "SCALAR"},
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": offset, **({"uri": buffer_uri} if buffer_uri else {})}],
    }
    return doc, b"".join(blobs)


def glb_bytes(doc, binary):
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body


def test_an_embedded_texture_past_the_limit_is_refused_before_it_is_decoded(tmp_path, monkeypatch):
    from PIL.PngImagePlugin import PngImageFile

    path = tmp_path / "box.glb"
    path.write_bytes(glb_bytes(*gltf_triangle(image=png_of_zeros(8193, 8192))))
    assert path.stat().st_size < 1 << 20  # decoded: 67 million pixels, 200 MB as RGB
    decoded = []
    monkeypatch.setattr(PngImageFile, "load", lambda self: decoded.append(self.size))
    message = error_of(read_mesh_file, path)
    assert "box.glb: embedded texture of 8193 x 8192 pixels, more than the 67108864 (8192 x 8192)" in message
    assert decoded == []  # refused from its header: no pixel decoded
    monkeypatch.undo()
    assert image.header_size(png_of_zeros(8193, 1)) == (8193, 1)
    # a texture within the limit reads, pixel for pixel; a damaged one is a named error
    pixels = (np.arange(4 * 3 * 3).reshape(4, 3, 3) * 7 % 256).astype(np.uint8)
    path.write_bytes(glb_bytes(*gltf_triangle(image=image.png_bytes(pixels))))
    assert np.array_equal(read_mesh_file(path).materials[0].texture, pixels)
    path.write_bytes(glb_bytes(*gltf_triangle(image=image.png_bytes(pixels)[:-30])))  # its pixels cut short
    assert "box.glb: cannot decode a texture" in error_of(read_mesh_file, path)


def test_gltf_textures_and_buffers_follow_the_reading_policy(tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    small = image.png_bytes(np.full((2, 2, 3), 200, np.uint8))
    (tmp_path / "outside.png").write_bytes(small)
    (model / "inside.png").write_bytes(small)
    ihdr = struct.pack(">IIBBBBB", 12000, 12000, 8, 2, 0, 0, 0)
    huge_header = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", 0)
    (model / "huge.png").write_bytes(huge_header)
    doc, binary = gltf_triangle(image_uri="inside.png", buffer_uri="tri.bin")
    (model / "tri.bin").write_bytes(binary)

    def write(name, **changes):
        changed = json.loads(json.dumps(doc))
        changed["images"][0].update(changes.get("image", {}))
        changed["buffers"][0].update(changes.get("buffer", {}))
        (model / name).write_text(json.dumps(changed))
        return model / name

    inside = read_mesh_file(write("inside.gltf"))
    assert (inside.materials[0].texture == 200).all()
    # a texture outside the folder is left out with a warning that reads the same as for a missing one
    said = []
    for name in ("../outside.png", "../missing.png", f"{tmp_path}/outside.png"):
        with pytest.warns(SplatFileWarning) as caught:
            mesh = read_mesh_file(write("out.gltf", image={"uri": name}))
        assert mesh.materials[0].texture is None
        said.append(str(caught[0].message).replace(name, "NAME"))
    assert said[0] == said[1] == said[2]
    allowed = read_mesh_file(write("out.gltf", image={"uri": "../outside.png"}), allow_outside=True)
    assert (allowed.materials[0].texture == 200).all()
    # a referenced texture past the limit is refused from its header; a buffer outside is an error
    assert "texture 'huge.png' of 12000 x 12000 pixels" in error_of(
        read_mesh_file, write("huge.gltf", image={"uri": "huge.png"})
    )
    (tmp_path / "tri.bin").write_bytes(binary)
    assert "'../tri.bin' is not a readable file" in error_of(
        read_mesh_file, write("buf.gltf", buffer={"uri": "../tri.bin"})
    )
    data_uri = "data:image/png;base64," + base64.b64encode(png_of_zeros(9000, 9000)).decode()
    assert "9000 x 9000" in error_of(read_mesh_file, write("data.gltf", image={"uri": data_uri}))


def test_obj_textures_outside_the_folder_only_when_allowed(tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    image.write_image(tmp_path / "outside.png", np.full((2, 2, 3), 0.5))
    (model / "m.mtl").write_text("newmtl a\nKd 1 0 0\nmap_Kd ../outside.png\n")
    (model / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nusemtl a\nf 1/1 2/1 3/1\n")
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        assert read_mesh_file(model / "m.obj").materials[0].texture is None
    assert read_mesh_file(model / "m.obj", allow_outside=True).materials[0].texture.shape == (2, 2, 3)
