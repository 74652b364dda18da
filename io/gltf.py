"""glTF 2.0 with KHR_gaussian_splatting (`.glb`, and `.gltf` with its buffer beside it).

A splat cloud is a POINTS primitive (mode 0) whose extension object names the kernel ("ellipse")
and colour space ("srgb_rec709_display"), with the attributes
    POSITION                                   VEC3 float
    KHR_gaussian_splatting:ROTATION            VEC4 unit quaternion x, y, z, w (float, or
                                               normalised byte/short)
    KHR_gaussian_splatting:SCALE               VEC3 linear standard deviations
    KHR_gaussian_splatting:OPACITY             SCALAR linear opacity in [0, 1]
    KHR_gaussian_splatting:SH_DEGREE_l_COEF_n  VEC3 float, the raw 3DGS coefficients; degree 0 is
                                               required, degree l needs all 2l+1 and every lower degree;
                                               the extension stops at degree 3 (45 coefficients), so a
                                               degree-4 cloud is written at degree 3 with a warning
    COLOR_0                                    optional VEC4 fallback colour for point renderers
    NORMAL                                     VEC3 float unit normals: the extras nx, ny, nz (when
                                               every one is a unit vector; else written as the
                                               other extras are)
    _<name>                                    an application-specific attribute (glTF 2.0's leading
                                               underscore) per float extra of 1 to 4 columns, its
                                               name kept: albedo VEC3, roughness and metallic SCALAR
Axes: glTF is +Y up with +Z to the front and +X to the left (LUF); the model's 3DGS axes (RDF) are a
half turn about Z from it, so x and y change sign (positions, quaternion x and y, SH by parity), as
PlayCanvas does. Node transforms above a splat primitive are applied on reading.

The writer stores float32 values: quaternions normalised, scales and opacities activated (exp and
sigmoid, so reading back is exact to float32 round-off, about 1e-7 relative). Extras are stored as
float32 (a float64 one reads back as float32); integer and boolean extras, and those of more than four
columns, have no glTF attribute that keeps them and are left out with a warning naming them. Reading,
every `_<name>` attribute of a splat primitive becomes the extra <name> (float32).

A buffer in a file is read only under the reading policy (io/policy.py): a regular file in the
glTF's folder or below (the folder of the file a symbolic link names, where the writer puts it),
its URI percent-decoded first, and no more of it than its byteLength. All the accessors of a file
together may decode to at most DECODE_RATIO numbers per byte its buffers hold (past DECODE_FLOOR),
so instancing, views read many times and accessors without data cannot turn a small file into a
large cloud.
"""

import base64
import json
import os
import re
import struct
import warnings
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np

from ..core import SplatCloud
from ..core import sh as shmod
from ..core.splats import NORMAL_EXTRAS, logit, sigmoid
from .common import (
    SplatFileError,
    SplatFileWarning,
    apply_nonfinite_policy,
    atomic_write,
    check_file,
    check_nonfinite_policy,
    log_scales_from_linear,
    publish_together,
    reduced_sh,
    warn_notes,
)
from .policy import referenced_file
from .spz import flip_axes

EXTENSION = "KHR_gaussian_splatting"
MAX_SH_DEGREE = 3  # "up to 45 spherical harmonic coefficients"
ROTATION, SCALE, OPACITY = (f"{EXTENSION}:{name}" for name in ("ROTATION", "SCALE", "OPACITY"))
GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
LUF = [-1, -1, 1]  # the half turn about Z between RDF and glTF's axes
COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
TYPE = {width: kind for kind, width in WIDTH.items()}
CUSTOM = "_"  # glTF 2.0: application-specific attribute semantics start with an underscore
UNIT_NORMAL = 1e-3  # |length - 1| within which normals are written as glTF's NORMAL (unit vectors)
MAX_BYTES = 1 << 34  # a buffer claiming more than this is refused before reading
# Numbers the accessors of a file may decode to: any file this many, a larger one this many per byte
# its buffers hold. A file read once decodes to at most one number per byte (normalised bytes); the
# ratio leaves room for a mesh instanced 32 times.
DECODE_FLOOR = 1 << 24
DECODE_RATIO = 32


def sh_name(degree, coefficient):
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{coefficient}"


# reading ------------------------------------------------------------------------------------------


def _load_document(path, allow_outside):
    """(glTF JSON, list of buffers' bytes, distinct bytes they hold) from a .glb or .gltf file."""
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None
    binary = None
    if raw[:4] == b"glTF":
        doc, binary = _split_glb(path, raw)
    else:
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise SplatFileError(path, f"not a glTF file (neither GLB nor JSON: {exc})") from None
    if not isinstance(doc, dict) or str(doc.get("asset", {}).get("version", "")).split(".")[0] != "2":
        raise SplatFileError(path, "not a glTF 2.0 document (asset.version must be 2.x)")
    return doc, *_load_buffers(path, doc, binary, allow_outside)


def _split_glb(path, raw):
    if len(raw) < 20:
        raise SplatFileError(path, f"truncated: {len(raw)} bytes, a GLB header and JSON chunk need 20")
    magic, version, length = struct.unpack_from("<III", raw)
    if version != 2:
        raise SplatFileError(path, f"GLB version {version}; only glTF 2 is read")
    if length != len(raw):
        raise SplatFileError(path, f"GLB header says {length} bytes, the file has {len(raw)} (truncated?)")
    chunks, at = [], 12
    while at + 8 <= len(raw):
        size, kind = struct.unpack_from("<II", raw, at)
        if at + 8 + size > len(raw):
            raise SplatFileError(path, f"truncated: a GLB chunk of {size} bytes runs past the end of the file")
        chunks.append((kind, raw[at + 8 : at + 8 + size]))
        at += 8 + size
    if not chunks or chunks[0][0] != JSON_CHUNK:
        raise SplatFileError(path, "GLB has no JSON chunk first")
    try:
        doc = json.loads(chunks[0][1].decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise SplatFileError(path, f"GLB JSON chunk is not valid JSON: {exc}") from None
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == BIN_CHUNK else None
    return doc, binary


def _list(path, doc, key):
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise SplatFileError(path, f"glTF '{key}' must be a list of objects")
    return value


def _load_buffers(path, doc, binary, allow_outside):
    """(every buffer's bytes, as views, and the distinct bytes they hold). A file that several
    buffers name is read once, as far as the longest of them reaches (a small .gltf could otherwise
    have a large file beside it read any number of times); one shorter than a buffer is refused from
    its size, unread."""
    named = [_buffer(path, i, b, binary, allow_outside) for i, b in enumerate(_list(path, doc, "buffers"))]
    reach = {}
    for source, length in named:
        if isinstance(source, Path):
            reach[source] = max(reach.get(source, 0), length)
    sizes = {target: _file_size(path, target) for target in reach}
    for index, (source, length) in enumerate(named):
        size = sizes[source] if isinstance(source, Path) else len(source)
        if size < length:
            raise SplatFileError(path, f"truncated: buffer {index} holds {size} of its {length} bytes")
    files = {target: _file_start(path, target, need) for target, need in reach.items()}
    held = [files[source] if isinstance(source, Path) else source for source, _ in named]
    stored = sum(len(data) for data in {id(data): data for data in held}.values())
    return [memoryview(data)[:length] for data, (_, length) in zip(held, named)], stored


def _buffer(path, index, buffer, binary, allow_outside):
    """(bytes, or the path of the file holding them, byteLength) of buffer `index`."""
    length = buffer.get("byteLength")
    if not isinstance(length, int) or not 0 <= length <= MAX_BYTES:
        raise SplatFileError(path, f"buffer {index} has byteLength {length!r}")
    uri = buffer.get("uri")
    if uri is None:
        if binary is None:
            raise SplatFileError(path, f"buffer {index} has no uri and the file has no GLB binary chunk")
        return binary, length
    if not isinstance(uri, str):
        raise SplatFileError(path, f"buffer {index} uri must be a string")
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1], validate=True), length
        except (IndexError, ValueError):
            raise SplatFileError(path, f"buffer {index} has a malformed data URI") from None
    return _buffer_file(path, index, uri, allow_outside), length


def _buffer_file(path, index, uri, allow_outside):
    """The file a buffer's URI names (relative, or file://), percent-decoded, under the reading policy."""
    parts = urlsplit(uri)
    if parts.scheme.lower() == "file":
        reference = unquote(parts.path)
        if re.match(r"/[A-Za-z]:", reference):  # file:///C:/... names a drive
            reference = reference[1:]
        elif parts.netloc not in ("", "localhost"):  # a share on another machine
            reference = f"//{parts.netloc}{reference}"
    elif len(parts.scheme) > 1:  # one letter is a Windows drive, refused as a path
        raise SplatFileError(path, f"buffer {index} uri '{uri}': only data: URIs and files are read")
    else:
        reference = unquote(uri)
    folder = Path(os.path.realpath(path)).parent
    return referenced_file(path, reference, folder, folder, allow_outside, what=f"buffer {index} file")


def _file_size(path, target):
    try:
        return os.stat(target).st_size
    except OSError as exc:
        raise SplatFileError(path, f"buffer file '{target.name}' cannot be read: {exc.strerror or exc}") from None


def _file_start(path, target, length):
    """The first `length` bytes of a buffer file."""
    try:
        with open(target, "rb") as f:
            data = f.read(length)
    except OSError as exc:
        raise SplatFileError(path, f"buffer file '{target.name}' cannot be read: {exc.strerror or exc}") from None
    if len(data) < length:  # shortened since its size was taken
        raise SplatFileError(path, f"truncated: buffer file '{target.name}' holds {len(data)} of {length} bytes")
    return data


def _accessor(path, doc, buffers, index, name):
    """Accessor `index` as float64 (count, width), normalised integers mapped to [0,1] / [-1,1]."""
    accessors = _list(path, doc, "accessors")
    if not isinstance(index, int) or not 0 <= index < len(accessors):
        raise SplatFileError(path, f"attribute {name} names accessor {index!r}, which does not exist")
    acc = accessors[index]
    if "sparse" in acc:
        raise SplatFileError(path, f"attribute {name}: sparse accessors are not read")
    kind, width = COMPONENTS.get(acc.get("componentType")), WIDTH.get(acc.get("type"))
    count = acc.get("count")
    if kind is None or width is None or not isinstance(count, int) or count < 0:
        raise SplatFileError(
            path,
            f"attribute {name}: accessor {index} has componentType "
            f"{acc.get('componentType')!r}, type {acc.get('type')!r}, count {count!r}",
        )
    dtype = np.dtype(kind)
    if "bufferView" not in acc:
        return np.zeros((count, width))
    views = _list(path, doc, "bufferViews")
    view_index = acc["bufferView"]
    if not isinstance(view_index, int) or not 0 <= view_index < len(views):
        raise SplatFileError(path, f"attribute {name}: bufferView {view_index!r} does not exist")
    view = views[view_index]
    buffer_index = view.get("buffer")
    if not isinstance(buffer_index, int) or not 0 <= buffer_index < len(buffers):
        raise SplatFileError(path, f"attribute {name}: buffer {buffer_index!r} does not exist")
    data = buffers[buffer_index]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride") or dtype.itemsize * width
    if not isinstance(stride, int) or not dtype.itemsize * width <= stride <= 252:
        raise SplatFileError(
            path, f"attribute {name}: byteStride {stride!r}, elements are {dtype.itemsize * width} bytes (at most 252)"
        )
    need = start + (stride * (count - 1) + dtype.itemsize * width if count else 0)
    view_end = view.get("byteOffset", 0) + view.get("byteLength", 0)
    if need > min(len(data), view_end) or start < 0:
        raise SplatFileError(
            path,
            f"attribute {name}: {count} elements from byte {start} run past the end of "
            f"their buffer view or buffer (truncated or corrupt?)",
        )
    values = np.ndarray((count, width), dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize))
    values = values.astype(np.float64)
    if acc.get("normalized") and dtype.kind in "iu":
        top = float(np.iinfo(dtype).max)
        values = np.maximum(values / top, -1.0) if dtype.kind == "i" else values / top
    return values


def _node_matrices(path, doc):
    """{node index: 4x4 world matrix} for every node reachable from the scene (all roots when none)."""
    nodes = _list(path, doc, "nodes")
    scenes = _list(path, doc, "scenes")
    if scenes:
        index = doc.get("scene", 0)
        if not isinstance(index, int) or not 0 <= index < len(scenes):
            raise SplatFileError(path, f"scene {index!r} does not exist")
        roots = scenes[index].get("nodes", [])
    else:
        children = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out, stack = {}, [(r, np.eye(4)) for r in roots]
    while stack:
        index, parent = stack.pop()
        if not isinstance(index, int) or not 0 <= index < len(nodes) or index in out:
            raise SplatFileError(path, f"node {index!r} does not exist or is reached twice")
        out[index] = parent @ _local_matrix(nodes[index])
        stack += [(c, out[index]) for c in nodes[index].get("children", [])]
    return out


def _local_matrix(node):
    if "matrix" in node:
        return np.array(node["matrix"], float).reshape(4, 4).T  # column-major
    t = np.eye(4)
    t[:3, 3] = node.get("translation", [0, 0, 0])
    r = np.eye(4)
    if "rotation" in node:  # most nodes have none, and a file may have many nodes
        from ..core.geometry import quaternions_to_matrices

        x, y, z, w = node["rotation"]
        r[:3, :3] = quaternions_to_matrices(np.array([[w, x, y, z]], float))[0]
    s = np.diag([*node.get("scale", [1, 1, 1]), 1.0])
    return t @ r @ s


def _primitive_cloud(path, doc, buffers, primitive, notes):
    attributes = primitive.get("attributes", {})
    if primitive.get("mode", 4) != 0:
        raise SplatFileError(
            path, f"a {EXTENSION} primitive has mode {primitive.get('mode', 4)}; it must be POINTS (0)"
        )
    ext = primitive["extensions"][EXTENSION]
    if ext.get("kernel", "ellipse") != "ellipse":
        notes.append(f"kernel '{ext.get('kernel')}' read as the 3DGS ellipse")
    if ext.get("colorSpace", "srgb_rec709_display") != "srgb_rec709_display":
        notes.append(f"colorSpace '{ext.get('colorSpace')}': SH values kept as they are (the model's are display sRGB)")

    def get(name, width):
        values = _accessor(path, doc, buffers, attributes[name], name)
        if width is not None and values.shape[1] != width:
            raise SplatFileError(path, f"attribute {name} has {values.shape[1]} components, expected {width}")
        return values

    if "POSITION" not in attributes:
        raise SplatFileError(path, f"a {EXTENSION} primitive has no POSITION attribute")
    positions = get("POSITION", 3)
    n = len(positions)
    missing = [name for name in (ROTATION, SCALE) if name not in attributes]
    if missing:
        raise SplatFileError(path, f"a {EXTENSION} primitive lacks the required attributes {missing}")
    xyzw = get(ROTATION, 4)
    scales = get(SCALE, 3)
    if OPACITY in attributes:
        opacities = get(OPACITY, 1)[:, 0]
    elif "COLOR_0" in attributes and get("COLOR_0", None).shape[1] == 4:
        notes.append(f"no {OPACITY}: opacity taken from COLOR_0's alpha")
        opacities = get("COLOR_0", 4)[:, 3]
    else:
        raise SplatFileError(path, f"a {EXTENSION} primitive lacks {OPACITY}")
    sh = _sh(path, attributes, get, n, notes)
    for name, values in (("rotations", xyzw), ("scales", scales), ("opacities", opacities[:, None]), ("SH", sh)):
        if len(values) != n:
            raise SplatFileError(path, f"{name} has {len(values)} entries for {n} positions")
    bad = np.isfinite(opacities) & ((opacities < 0) | (opacities > 1))
    if bad.any():
        notes.append(f"{int(bad.sum())} opacities outside [0, 1] clamped")
        opacities = np.clip(opacities, 0, 1)
    with np.errstate(invalid="ignore"):
        logits = np.where(np.isfinite(opacities), logit(opacities), opacities)
    extras = _extras(path, doc, attributes, get, n, notes)
    return SplatCloud(positions, xyzw[:, [3, 0, 1, 2]], log_scales_from_linear(scales, notes), logits, sh, extras)


def _extras(path, doc, attributes, get, n, notes):
    """{name: float32 (n,) or (n, k)}: NORMAL as the extras nx, ny, nz, every `_<name>` as <name>
    (another tool's of a matrix type left out, with a note)."""
    extras, accessors = {}, _list(path, doc, "accessors")
    if "NORMAL" in attributes:
        extras.update(zip(NORMAL_EXTRAS, get("NORMAL", 3).T.astype(np.float32), strict=True))
    for name, index in attributes.items():
        if not name.startswith(CUSTOM) or len(name) == len(CUSTOM):
            continue
        kind = accessors[index].get("type") if isinstance(index, int) and 0 <= index < len(accessors) else None
        if kind is not None and kind not in WIDTH:
            notes.append(f"attribute {name} ({kind}) not read")
            continue
        values = get(name, None).astype(np.float32)
        extras[name[len(CUSTOM) :]] = values[:, 0] if values.shape[1] == 1 else values
    for name, values in extras.items():
        if len(values) != n:
            raise SplatFileError(path, f"extra '{name}' has {len(values)} entries for {n} positions")
    return extras


def _sh(path, attributes, get, n, notes):
    """(n, K, 3) SH from the SH_DEGREE_l_COEF_n attributes (DC from COLOR_0 when absent)."""
    if sh_name(0, 0) in attributes:
        coefficients = [get(sh_name(0, 0), 3)]
    elif "COLOR_0" in attributes:
        notes.append(f"no {sh_name(0, 0)}: DC colour taken from COLOR_0")
        coefficients = [shmod.rgb_to_dc(get("COLOR_0", None)[:, :3])]
    else:
        raise SplatFileError(path, f"a {EXTENSION} primitive lacks {sh_name(0, 0)}")
    for degree in range(1, 4):
        present = [sh_name(degree, c) in attributes for c in range(2 * degree + 1)]
        if not any(present):
            break
        if not all(present):
            raise SplatFileError(path, f"SH degree {degree} has {sum(present)} of its {2 * degree + 1} coefficients")
        coefficients += [get(sh_name(degree, c), 3) for c in range(2 * degree + 1)]
    if sh_name(4, 0) in attributes:
        notes.append("SH above degree 3 dropped")
    if any(len(c) != n for c in coefficients):
        raise SplatFileError(path, f"SH attributes do not hold one entry per each of the {n} splats")
    return np.stack(coefficients, axis=1)


def read(path, nonfinite="raise", allow_outside=False):
    """Every KHR_gaussian_splatting primitive of the default scene (node transforms applied),
    concatenated into one SplatCloud in the model's axes. allow_outside: also read buffer files
    outside the glTF's folder (special files never)."""
    check_nonfinite_policy(nonfinite)
    check_file(path)
    try:
        return _read(path, nonfinite, allow_outside)
    except SplatFileError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError, RecursionError) as exc:
        # JSON of the wrong shape somewhere (a string where an object belongs, a short matrix, ...)
        raise SplatFileError(path, f"malformed glTF document ({type(exc).__name__}: {exc})") from None


def _read(path, nonfinite, allow_outside):
    doc, buffers, stored = _load_document(path, allow_outside)
    unknown = [e for e in doc.get("extensionsRequired", []) if e != EXTENSION]
    if unknown:
        raise SplatFileError(path, f"the file requires glTF extensions this reader does not know: {unknown}")
    placed = _splat_primitives(path, doc)
    _check_claims(path, doc, stored, [primitive for _, _, primitive in placed])
    notes, clouds = [], []
    for node, matrix, primitive in placed:
        with np.errstate(invalid="ignore", over="ignore"):
            cloud = flip_axes(_primitive_cloud(path, doc, buffers, primitive, notes), LUF)
            if not np.array_equal(matrix, np.eye(4)):
                try:
                    cloud = cloud.transformed(np.diag(LUF + [1]) @ matrix @ np.diag(LUF + [1]))
                except ValueError as exc:
                    raise SplatFileError(path, f"node {node} transform cannot be applied: {exc}") from None
        clouds.append(cloud)
    if not clouds:
        raise SplatFileError(path, f"no {EXTENSION} primitive in the file's scene")
    if notes:
        warnings.warn(f"{path}: " + "; ".join(dict.fromkeys(notes)), SplatFileWarning, stacklevel=2)
    cloud = clouds[0] if len(clouds) == 1 else SplatCloud.concatenate(clouds)
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


def _splat_primitives(path, doc):
    """[(node, world matrix, primitive)] of every splat primitive the default scene places."""
    meshes, nodes, placed = _list(path, doc, "meshes"), _list(path, doc, "nodes"), []
    for node, matrix in sorted(_node_matrices(path, doc).items()):
        mesh = nodes[node].get("mesh")
        if mesh is None:
            continue
        if not isinstance(mesh, int) or not 0 <= mesh < len(meshes):
            raise SplatFileError(path, f"node {node} names mesh {mesh!r}, which does not exist")
        primitives = meshes[mesh].get("primitives", [])
        placed += [(node, matrix, p) for p in primitives if EXTENSION in p.get("extensions", {})]
    return placed


def _check_claims(path, doc, stored, primitives):
    """Refuse, before anything is decoded, a file whose placed primitives claim more numbers than
    DECODE_RATIO per byte of its buffers (past DECODE_FLOOR)."""
    accessors, views, claims = _list(path, doc, "accessors"), _list(path, doc, "bufferViews"), [0]
    for primitive in primitives:
        attributes = primitive.get("attributes", {})
        for index in attributes.values() if isinstance(attributes, dict) else ():
            if isinstance(index, int) and 0 <= index < len(accessors):
                claims.append(_claim(accessors[index], views))
    limit = max(DECODE_FLOOR, DECODE_RATIO * stored)
    if sum(claims) > limit:
        raise SplatFileError(
            path,
            f"its {len(primitives)} placed splat primitives claim {sum(claims)} numbers (one accessor "
            f"{max(claims)} of them), more than the {limit} a file whose buffers hold {stored} bytes may decode to "
            "(instanced, aliased or accessors without data?)",
        )


def _claim(acc, views):
    """The numbers an accessor decodes to; 0 for one that reading refuses anyway, before allocating
    (a count its buffer view cannot hold, a type that does not exist)."""
    count, width, kind = acc.get("count"), WIDTH.get(acc.get("type")), COMPONENTS.get(acc.get("componentType"))
    if not isinstance(count, int) or count <= 0 or width is None or kind is None:
        return 0
    view = acc.get("bufferView")
    if view is not None:
        holds = views[view].get("byteLength", 0) if isinstance(view, int) and 0 <= view < len(views) else 0
        if count * np.dtype(kind).itemsize * width > holds:
            return 0
    return count * width


# writing ------------------------------------------------------------------------------------------


def encode(cloud, generator="Splatwright"):
    """(glTF JSON dict, binary buffer) for a cloud (model axes in, glTF's out)."""
    cloud = flip_axes(cloud, LUF)
    n = len(cloud)
    q = cloud.unit_rotations[:, [1, 2, 3, 0]]
    with np.errstate(over="ignore"):
        scales = np.exp(cloud.log_scales.astype(np.float64))
    opacities = sigmoid(cloud.opacity_logits)
    rgba = np.concatenate([shmod.dc_to_rgb(cloud.sh[:, 0]), opacities[:, None]], axis=1)
    arrays = [
        ("POSITION", cloud.positions, "VEC3"),
        (ROTATION, q, "VEC4"),
        (SCALE, scales, "VEC3"),
        (OPACITY, opacities, "SCALAR"),
    ]
    arrays += [
        (sh_name(d, c), cloud.sh[:, d * d + c], "VEC3") for d in range(cloud.sh_degree + 1) for c in range(2 * d + 1)
    ]
    arrays.append(("COLOR_0", np.clip(np.rint(rgba * 255), 0, 255).astype(np.uint8), "VEC4"))
    arrays += extra_attributes(cloud.extras)[0]
    blobs, views, accessors, attributes, at = [], [], [], {}, 0
    for name, values, kind in arrays:
        values = np.ascontiguousarray(values, np.uint8 if values.dtype == np.uint8 else "<f4")
        blob = values.tobytes()
        views.append({"buffer": 0, "byteOffset": at, "byteLength": len(blob), "target": 34962})
        accessor = {
            "bufferView": len(views) - 1,
            "componentType": 5121 if values.dtype == np.uint8 else 5126,
            "count": n,
            "type": kind,
        }
        if name == "COLOR_0":
            accessor["normalized"] = True
        if name == "POSITION" and n:
            accessor["min"] = values.min(axis=0).tolist()
            accessor["max"] = values.max(axis=0).tolist()
        accessors.append(accessor)
        attributes[name] = len(accessors) - 1
        blobs.append(blob + bytes(-len(blob) % 4))
        at += len(blobs[-1])
    doc = {
        "asset": {"version": "2.0", "generator": generator},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "Splats"}],
        "meshes": [
            {
                "primitives": [
                    {
                        "mode": 0,
                        "attributes": attributes,
                        "extensions": {
                            EXTENSION: {
                                "kernel": "ellipse",
                                "colorSpace": "srgb_rec709_display",
                                "projection": "perspective",
                                "sortingMethod": "cameraDistance",
                            }
                        },
                    }
                ]
            }
        ],
        "buffers": [{"byteLength": at}],
        "bufferViews": views,
        "accessors": accessors,
    }
    return doc, b"".join(blobs)


def extra_attributes(extras):
    """([(attribute, (N, k) float32, type)], names left out) for a cloud's extras in glTF's axes:
    unit normals as NORMAL, other float extras of 1 to 4 columns as `_<name>`."""
    extras, attributes = dict(extras), []
    if all(name in extras for name in NORMAL_EXTRAS):
        normals = np.stack([np.asarray(extras[name], np.float32).reshape(-1) for name in NORMAL_EXTRAS], axis=1)
        with np.errstate(invalid="ignore"):
            unit = np.abs(np.linalg.norm(normals.astype(np.float64), axis=1) - 1.0) <= UNIT_NORMAL
        if unit.all():
            attributes.append(("NORMAL", normals, "VEC3"))
            for name in NORMAL_EXTRAS:
                del extras[name]
    left = []
    for name, values in extras.items():
        values = np.asarray(values)
        columns = {1: 1, 2: values.shape[-1]}.get(values.ndim, 0)
        if values.dtype.kind != "f" or not 1 <= columns <= 4:
            left.append(name)
            continue
        attributes.append((CUSTOM + name, values.reshape(len(values), columns).astype(np.float32), TYPE[columns]))
    return attributes, sorted(left)


def write(path, cloud, nonfinite="raise"):
    """Write a .glb (one file) or a .gltf with its buffer in `<name>.bin` beside it (through a
    symbolic link: beside the file it names, as `<that name>.bin`)."""
    cloud = apply_nonfinite_policy(path, cloud, nonfinite, "write")
    left = extra_attributes(cloud.extras)[1]
    if left:
        warnings.warn(
            f"{path}: glTF attributes hold float extras of 1 to 4 columns only; {left} not written",
            SplatFileWarning,
            stacklevel=2,
        )
    notes = []
    cloud = reduced_sh(cloud, MAX_SH_DEGREE, EXTENSION, notes)
    warn_notes(path, notes)
    doc, binary = encode(cloud)
    if str(path).lower().endswith(".gltf"):
        # beside the file a symbolic link names, which names it by a relative URI
        bin_path = Path(os.path.realpath(path)).with_suffix(".bin")
        doc["buffers"][0]["uri"] = bin_path.name
        with publish_together():  # both files, or neither
            with atomic_write(bin_path) as f:
                f.write(binary)
            with atomic_write(path) as f:
                f.write(json.dumps(doc, indent=1).encode("utf-8"))
        return
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    with atomic_write(path) as f:
        f.write(struct.pack("<III", GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(text), JSON_CHUNK) + text)
        f.write(struct.pack("<II", len(binary), BIN_CHUNK) + binary)
