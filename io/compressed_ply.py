"""PlayCanvas compressed PLY (`.compressed.ply`): 16 bytes per splat plus 1 byte per SH value.

A binary little-endian PLY with three elements:
    chunk   one per 256 splats: float min/max of x, y, z; of the log scales; of the DC colours
            (0.5 + C0 * f_dc; the last six are optional when reading)
    vertex  uint packed_position   x 11 bits, y 10, z 11 (high to low), each a fraction of the
                                   chunk's range: min + (max - min) * q / (2^bits - 1)
            uint packed_rotation   2 bits: which of rot_0..rot_3 (w, x, y, z) is largest, made
                                   positive; then the other three, 10 bits each: q * sqrt(1/2) + 1/2
            uint packed_scale      log scales 11-10-11, in the chunk's range
            uint packed_color      8 bits each: r, g, b in the chunk's colour range, opacity
    sh      optional, uchar f_rest_0..M channel-major like PLY: byte = trunc((v / 8 + 1/2) * 256),
            read as ((byte + 1/2) / 256 - 1/2) * 8 (0 and 255 as the ends, -4 and 4)

Ranges narrower than 1e-5 store 0; log-scale ranges are clamped to [-20, 20]. The writer orders the
splats along a Morton curve (as PlayCanvas does) so each chunk's ranges, and so its steps, stay
small; `order=None` keeps the cloud's order. Lossy: the error per attribute is in bench/formats.py.
"""

import warnings

import numpy as np

from ..core import SplatCloud, spatial
from ..core import sh as shmod
from ..core.splats import logit, sigmoid
from .common import (
    SplatFileError,
    SplatFileWarning,
    apply_nonfinite_policy,
    atomic_write,
    check_nonfinite_policy,
    reduced_sh,
    warn_notes,
)
from .ply_header import read_header, sh_order

CHUNK = 256
MAX_SH_DEGREE = 3  # the sh element holds 9, 24 or 45 f_rest; degree 4 is reduced on writing
BOUNDS = [
    "min_x",
    "min_y",
    "min_z",
    "max_x",
    "max_y",
    "max_z",
    "min_scale_x",
    "min_scale_y",
    "min_scale_z",
    "max_scale_x",
    "max_scale_y",
    "max_scale_z",
]
COLOR_BOUNDS = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
SCALE_LIMIT = 20.0
TINY_RANGE = 1e-5
SQRT1_2 = np.sqrt(0.5)


def is_compressed(elements):
    """Whether parsed PLY header elements are PlayCanvas's compressed layout."""
    names = {e.name: e for e in elements}
    return (
        "chunk" in names
        and "vertex" in names
        and {"packed_position", "packed_rotation"} <= {p for p, _ in names["vertex"].properties}
    )


# reading ------------------------------------------------------------------------------------------


def _layout(path, elements):
    """(chunk dtype, vertex dtype, sh dtype or None, counts) checked against the layout."""
    by_name = {e.name: e for e in elements}
    extra = [e.name for e in elements if e.name not in ("chunk", "vertex", "sh")]
    if extra or [e.name for e in elements][:2] != ["chunk", "vertex"]:
        raise SplatFileError(
            path,
            f"compressed PLY needs the elements chunk, vertex[, sh] in that order; found {[e.name for e in elements]}",
        )
    chunk, vertex, sh = by_name["chunk"], by_name["vertex"], by_name.get("sh")
    names = [p for p, _ in chunk.properties]
    if names not in (BOUNDS, BOUNDS + COLOR_BOUNDS) or any(t != "f4" for _, t in chunk.properties):
        raise SplatFileError(
            path,
            f"compressed PLY chunk element must hold the float properties {BOUNDS} "
            f"(and optionally {COLOR_BOUNDS}); found {names}",
        )
    if [p for p, _ in vertex.properties] != PACKED or any(t != "u4" for _, t in vertex.properties):
        raise SplatFileError(
            path,
            f"compressed PLY vertex element must hold the uint properties {PACKED}; "
            f"found {[p for p, _ in vertex.properties]}",
        )
    if chunk.count != -(-vertex.count // CHUNK):
        raise SplatFileError(
            path,
            f"{chunk.count} chunks for {vertex.count} splats; compressed PLY has one "
            f"per {CHUNK} ({-(-vertex.count // CHUNK)})",
        )
    sh_dtype = None
    if sh is not None:
        rest = [p for p, _ in sh.properties]
        if (
            rest != [f"f_rest_{i}" for i in range(len(rest))]
            or len(rest) not in (9, 24, 45)
            or any(t != "u1" for _, t in sh.properties)
            or sh.count != vertex.count
        ):
            raise SplatFileError(
                path,
                f"compressed PLY sh element must hold uchar f_rest_0..M (M+1 = 9, 24 or "
                f"45) for each of the {vertex.count} splats; found {len(rest)} properties "
                f"for {sh.count}",
            )
        sh_dtype = sh.dtype("<")
    return chunk.dtype("<"), vertex.dtype("<"), sh_dtype, chunk.count, vertex.count


def _fields(packed, widths):
    """Unsigned fields of `packed`, high bits first, each as a fraction of its largest value."""
    out, shift = [], sum(widths)
    for bits in widths:
        shift -= bits
        out.append(((packed >> shift) & ((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1))
    return out


def _lerp(lo, hi, t):
    return lo * (1 - t) + hi * t


def decode(chunks, vertices, sh_bytes):
    """SplatCloud from the three elements' records (NumPy structured arrays)."""
    n = len(vertices)
    c = {name: np.repeat(chunks[name].astype(np.float64), CHUNK)[:n] for name in chunks.dtype.names}
    px, py, pz = _fields(vertices["packed_position"], (11, 10, 11))
    positions = np.stack(
        [_lerp(c["min_x"], c["max_x"], px), _lerp(c["min_y"], c["max_y"], py), _lerp(c["min_z"], c["max_z"], pz)],
        axis=1,
    )
    sx, sy, sz = _fields(vertices["packed_scale"], (11, 10, 11))
    log_scales = np.stack(
        [
            _lerp(c["min_scale_x"], c["max_scale_x"], sx),
            _lerp(c["min_scale_y"], c["max_scale_y"], sy),
            _lerp(c["min_scale_z"], c["max_scale_z"], sz),
        ],
        axis=1,
    )
    rgba = np.stack(_fields(vertices["packed_color"], (8, 8, 8, 8)), axis=1)
    rgb = rgba[:, :3]
    if "min_r" in c:
        rgb = np.stack([_lerp(c[f"min_{k}"], c[f"max_{k}"], rgb[:, i]) for i, k in enumerate("rgb")], axis=1)
    rotations = _unpack_rotations(vertices["packed_rotation"])
    sh = shmod.rgb_to_dc(rgb)[:, None, :]
    if sh_bytes is not None:
        rest = np.stack([sh_bytes[name] for name in sh_bytes.dtype.names], axis=1)
        values = np.where(rest == 0, 0.0, np.where(rest == 255, 1.0, (rest + 0.5) / 256))
        k = rest.shape[1] // 3 + 1
        flat = np.concatenate([sh.reshape(n, 3), (values - 0.5) * 8], axis=1)
        sh = flat[:, sh_order(k)].reshape(n, k, 3)
    return SplatCloud(positions, rotations, log_scales, logit(rgba[:, 3]), sh)


def _unpack_rotations(packed):
    a, b, c = (np.float64(2) * SQRT1_2 * (v - 0.5) for v in _fields(packed, (10, 10, 10)))
    largest = (packed >> 30).astype(np.int64)
    q = np.empty((len(packed), 4))
    rows = np.arange(len(packed))
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    for i, v in enumerate((a, b, c)):
        q[rows, others[:, i]] = v
    q[rows, largest] = np.sqrt(np.maximum(0, 1 - (a * a + b * b + c * c)))
    return q


def read(path, nonfinite="raise", header=None):
    """Read a compressed PLY into a SplatCloud (also reached through ply.read, which passes the
    header it parsed: read_header's tuple)."""
    check_nonfinite_policy(nonfinite)
    try:
        with open(path, "rb") as f:
            fmt, elements, start, _ = read_header(path, f) if header is None else header
            if fmt != "binary_little_endian":
                raise SplatFileError(path, f"compressed PLY must be binary_little_endian, not {fmt}")
            chunk_dtype, vertex_dtype, sh_dtype, chunks, n = _layout(path, elements)
            need = (
                chunks * chunk_dtype.itemsize + n * vertex_dtype.itemsize + (n * sh_dtype.itemsize if sh_dtype else 0)
            )
            f.seek(0, 2)
            have = f.tell() - start
            if have != need:
                what = "truncated" if have < need else f"{have - need} bytes beyond the data"
                raise SplatFileError(
                    path,
                    f"{what}: the header's {n} splats in {chunks} chunks need {need} data bytes, the file has {have}",
                )
            f.seek(start)
            chunk_records = np.fromfile(f, chunk_dtype, chunks)
            vertices = np.fromfile(f, vertex_dtype, n)
            sh_bytes = np.fromfile(f, sh_dtype, n) if sh_dtype else None
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None
    with np.errstate(invalid="ignore", over="ignore"):
        cloud = decode(chunk_records, vertices, sh_bytes)
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


# writing ------------------------------------------------------------------------------------------


def morton_order(positions):
    """Indices that sort points along a Morton (Z-order) curve over their bounding box, 10 bits per
    axis, x the most significant bit of each triple."""
    return spatial.morton_order(np.asarray(positions)[:, ::-1], bits=10)


def _unit_fraction(values, lo, hi):
    """(v - lo) / (hi - lo) in [0, 1]; 0 for ranges narrower than TINY_RANGE."""
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(hi - lo < TINY_RANGE, 0.0, (values - lo) / (hi - lo))
    return np.where(values <= lo, 0.0, np.where(values >= hi, 1.0, t))


def _unorm(t, bits):
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _pack(fields, widths):
    out = np.zeros(len(fields[0]), np.uint32)
    for t, bits in zip(fields, widths):
        out = (out << np.uint32(bits)) | _unorm(t, bits)
    return out


def _chunk_bounds(values):
    """(chunks, 2, D) min and max of each chunk of CHUNK rows of `values` (N, D)."""
    n, d = values.shape
    padded = np.concatenate([values, np.repeat(values[-1:], -n % CHUNK, axis=0)]).reshape(-1, CHUNK, d)
    return np.stack([padded.min(axis=1), padded.max(axis=1)], axis=1)


def _pack_rotations(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    bad = ~np.isfinite(q).all(axis=1)
    q[bad] = (1, 0, 0, 0)
    largest = np.argmax(np.abs(q), axis=1)
    rows = np.arange(len(q))
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    fields = [q[rows, others[:, i]] * SQRT1_2 + 0.5 for i in range(3)]
    return (largest.astype(np.uint32) << np.uint32(30)) | _pack(fields, (10, 10, 10))


def encode(cloud):
    """(header bytes, chunk records, vertex records, sh bytes or None) of a cloud, in its order."""
    n, k = len(cloud), cloud.sh.shape[1]
    positions = cloud.positions.astype(np.float64)
    logs = cloud.log_scales.astype(np.float64)
    colors = shmod.dc_to_rgb(cloud.sh[:, 0])
    pb, sb, cb = (_chunk_bounds(v) for v in (positions, logs, colors))
    sb = np.clip(sb, -SCALE_LIMIT, SCALE_LIMIT)
    chunks = np.concatenate([pb.reshape(-1, 6), sb.reshape(-1, 6), cb.reshape(-1, 6)], axis=1).astype("<f4")
    per_splat = lambda bounds: np.repeat(bounds, CHUNK, axis=0)[:n]  # noqa: E731
    p, s, c = per_splat(pb), per_splat(sb), per_splat(cb)
    fractions = lambda v, b: [_unit_fraction(v[:, i], b[:, 0, i], b[:, 1, i]) for i in range(v.shape[1])]  # noqa: E731
    vertices = np.empty((n, 4), "<u4")
    vertices[:, 0] = _pack(fractions(positions, p), (11, 10, 11))
    vertices[:, 1] = _pack_rotations(cloud.rotations.astype(np.float64))
    vertices[:, 2] = _pack(fractions(logs, s), (11, 10, 11))
    vertices[:, 3] = _pack(fractions(colors, c) + [sigmoid(cloud.opacity_logits)], (8, 8, 8, 8))
    rest = None
    if k > 1:
        f_rest = cloud.sh[:, 1:].transpose(0, 2, 1).reshape(n, -1).astype(np.float64)  # channel-major
        rest = np.clip(np.trunc((f_rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment Generated by Splatwright",
        f"element chunk {len(chunks)}",
        *(f"property float {name}" for name in BOUNDS + COLOR_BOUNDS),
        f"element vertex {n}",
        *(f"property uint {name}" for name in PACKED),
    ]
    if rest is not None:
        header += [f"element sh {n}", *(f"property uchar f_rest_{i}" for i in range(rest.shape[1]))]
    return ("\n".join(header) + "\nend_header\n").encode("ascii"), chunks, vertices, rest


def write(path, cloud, order="morton", nonfinite="raise"):
    """Write a compressed PLY; order="morton" sorts the splats along a Morton curve (tighter chunk
    ranges, as PlayCanvas writes), None keeps the cloud's order. Extras are not stored."""
    cloud = apply_nonfinite_policy(path, cloud, nonfinite, "write")
    if order == "morton":
        cloud = cloud[morton_order(cloud.positions)]
    elif order is not None:
        raise ValueError(f"order must be 'morton' or None, got {order!r}")
    if cloud.extras:
        warnings.warn(
            f"{path}: compressed PLY has no room for extras; {sorted(cloud.extras)} not written",
            SplatFileWarning,
            stacklevel=2,
        )
    notes = []
    cloud = reduced_sh(cloud, MAX_SH_DEGREE, "compressed PLY", notes)
    warn_notes(path, notes)
    header, chunks, vertices, rest = encode(cloud) if len(cloud) else _empty(cloud)
    with atomic_write(path) as f:
        f.write(header)
        for block in (chunks, vertices, rest):
            if block is not None:
                f.write(np.ascontiguousarray(block).tobytes())


def _empty(cloud):
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "element chunk 0",
        *(f"property float {name}" for name in BOUNDS + COLOR_BOUNDS),
        "element vertex 0",
        *(f"property uint {name}" for name in PACKED),
    ]
    return ("\n".join(header) + "\nend_header\n").encode("ascii"), None, None, None
