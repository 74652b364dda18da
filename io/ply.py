"""PLY in the 3DGS/INRIA layout, read and written without losing anything.

Vertex properties `x y z [nx ny nz] f_dc_0..2 f_rest_0..M opacity scale_0..2 rot_0..3`, looked up
by name. Reading accepts ASCII and binary of either byte order, every PLY scalar type, any property
order and other elements beside `vertex`; properties the layout does not name are kept in
`cloud.extras` under their own name and dtype and written back after the layout's own.
Normals are kept as float32 extras `nx`, `ny`, `nz` unless they are all zero (the placeholder the
3DGS reference writes); the writer puts them in the normal slot, or zeros when absent. 2-D extras
are written as columns name_0, name_1, ... and read back as those columns, except the material's
albedo (core.material), read back as the one (N,3) extra `albedo` it was.

2DGS files (scale_0 and scale_1, no scale_2) get a flat third axis of sigma FLAT_SIGMA and a
SplatFileWarning saying so; they are written back as 3DGS files with that scale_2.

Non-finite values: `read` refuses a file whose splats hold NaN or Inf (also a double too large for
float32) with a SplatFileError counting them per field, unless told `nonfinite="keep"` (keep them,
warn, and let SplatCloud.problems() report) or `nonfinite="drop"` (drop those splats, warn).
`write` applies the same rule, so no NaN reaches a file unless asked for.
"""

import os
import re
import warnings

import numpy as np

from ..core import SplatCloud, jit, material
from ..core import sh as shmod
from ..core.parallel import WORKERS, in_chunks
from ..core.splats import bad_rows
from . import compressed_ply
from .common import SplatFileError, SplatFileWarning, apply_nonfinite_policy, atomic_write, check_nonfinite_policy
from .ply_header import ANTIALIASED_COMMENT, FORMATS, TYPE_NAMES, read_header, sh_order

KERNELS = "io.ply_kernels"  # the compiled record fill, loaded by core.jit

FLAT_SIGMA = 1e-6  # 2DGS third axis: thin next to any real splat, still invertible
FLAT_LOG_SCALE = float(np.log(FLAT_SIGMA))

NORMALS = ("nx", "ny", "nz")
_BLANK_LINE = re.compile(r"(?:^|\n)[ \t\r]*(?=\n|$)")
CORE = "layout columns"  # the record field holding the layout: whitespace, so no PLY property can clash
REQUIRED = (
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
)
PARALLEL_ROWS = 1 << 16  # below this, threads cost more than they save
CHUNK_ROWS = 1 << 13  # rows converted together while they are in cache (~2 MB)
REST_COUNTS = tuple(3 * (k - 1) for k in shmod.VALID_COUNTS)  # f_rest properties: 0, 9, 24, 45, 72


def layout_names(sh_degree):
    """The 3DGS reference property order for an SH degree."""
    rest = 3 * (shmod.num_coeffs(sh_degree) - 1)
    return (
        ["x", "y", "z", *NORMALS, "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _vertex_element(path, elements):
    """The vertex element and its index, checked for what this reader cannot take."""
    index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if index is None:
        raise SplatFileError(path, "PLY file has no 'vertex' element")
    vertex = elements[index]
    lists = [name for name, t in vertex.properties if isinstance(t, tuple)]
    if lists:
        raise SplatFileError(path, f"vertex element has list properties {lists}, which splat files do not use")
    return index, vertex


# data ---------------------------------------------------------------------------------------------


def _binary_layout(path, fmt, elements, index, header_len):
    """(vertex record dtype, byte offset of the vertex data), once the file size matches the header."""
    order = FORMATS[fmt]
    before, vertex, after = elements[:index], elements[index], elements[index + 1 :]
    if any(e.has_lists for e in before):
        names = [e.name for e in before if e.has_lists]
        raise SplatFileError(
            path, f"elements {names} with list properties come before 'vertex'; this reader cannot skip them"
        )
    dtype = vertex.dtype(order)
    start = header_len + sum(e.count * e.dtype(order).itemsize for e in before)
    need = (
        start + vertex.count * dtype.itemsize + sum(e.count * e.dtype(order).itemsize for e in after if not e.has_lists)
    )
    size = os.path.getsize(path)
    if size < need:
        raise SplatFileError(
            path,
            f"truncated: the header promises {vertex.count} vertices of "
            f"{dtype.itemsize} bytes ({need - header_len} data bytes in all) "
            f"but only {size - header_len} bytes follow the header",
        )
    exact = not any(e.has_lists for e in after)  # list elements have no size known in advance
    if exact and size > need:
        raise SplatFileError(
            path,
            f"{size - need} bytes beyond the data the header describes "
            f"(does its vertex count of {vertex.count} understate the file?)",
        )
    return dtype, start


def _read_ascii(path, elements, index, header_len):
    """The vertex records of an ASCII file, parsed by np.loadtxt (one C loop, no Python per row)."""
    with open(path, "rb") as f:
        f.seek(header_len)
        data = f.read()
    try:
        lines = data.decode("ascii").split("\n")
    except UnicodeDecodeError:
        raise SplatFileError(path, "ASCII PLY data holds non-ASCII bytes") from None
    while lines and not lines[-1].strip():
        lines.pop()
    blank = _BLANK_LINE.search("\n".join(lines)) if lines else None
    if blank:  # np.loadtxt would skip it and shift every row after it
        row = blank.string.count("\n", 0, blank.end()) + 1
        raise SplatFileError(
            path, f"data line {row} (counted after the header) is blank; ASCII PLY has one element per line"
        )
    vertex = elements[index]
    start = sum(e.count for e in elements[:index])
    expected = sum(e.count for e in elements)
    if len(lines) < expected:
        raise SplatFileError(
            path,
            f"truncated: the header promises {expected} data lines "
            f"({vertex.count} vertices) but the file has {len(lines)}",
        )
    if len(lines) > expected:
        raise SplatFileError(
            path,
            f"{len(lines) - expected} data lines beyond what the header describes "
            f"(does its vertex count of {vertex.count} understate the file?)",
        )
    dtype = vertex.dtype("=")
    if vertex.count == 0:
        return np.zeros(0, dtype)
    # Integer properties are parsed as float64 (exact far beyond any PLY integer) and checked after:
    # np.loadtxt would wrap out-of-range integers silently.
    parsed = np.dtype([(name, "f8" if dtype[name].kind in "iu" else dtype[name]) for name in dtype.names])
    try:
        records = np.loadtxt(lines[start : start + vertex.count], dtype=parsed, comments=None, ndmin=1)
    except ValueError as exc:
        raise SplatFileError(path, f"vertex data (rows counted from the first vertex): {exc}") from None
    return records if parsed == dtype else _as_integers(path, records, dtype)


def _as_integers(path, records, dtype):
    """ASCII records with their integer properties converted to `dtype`, each value checked."""
    out = np.empty(len(records), dtype)
    for name in dtype.names:
        values = records[name]
        if dtype[name].kind in "iu":
            info = np.iinfo(dtype[name])
            bad = ~((values == np.round(values)) & (values >= info.min) & (values <= info.max))
            if bad.any():
                row = int(np.argmax(bad))
                raise SplatFileError(
                    path,
                    f"vertex {row}: {TYPE_NAMES[dtype[name].str[1:]]} property '{name}' "
                    f"holds {float(values[row])!r}, not an integer in {info.min}..{info.max}",
                )
        out[name] = values
    return out


def _bytes(records):
    return memoryview(records.view(np.uint8))


def _read_into(path, f, offset, records):
    """Fill `records` from byte `offset` of the open file (reads may come back short)."""
    f.seek(offset)
    view = _bytes(records)
    while len(view):
        got = f.readinto(view)
        if not got:
            raise SplatFileError(path, "truncated: the file ended while it was being read")
        view = view[got:]


def _write_at(fd, records, offset):
    view = _bytes(records)
    while len(view):
        done = os.pwrite(fd, view, offset)
        view, offset = view[done:], offset + done


def _reserve(fd, size):
    """Allocate the file's blocks up front (as ndarray.tofile does): the file system then need not
    extend the file page by page while the body is written. Only a hint; ignored where unsupported."""
    try:
        os.posix_fallocate(fd, 0, size)
    except (AttributeError, OSError):
        pass


# row chunks on every core -------------------------------------------------------------------------


def _in_parallel(n, work):
    """Run work(rows) on one contiguous slice of rows per core (NumPy and file I/O release the GIL);
    below PARALLEL_ROWS, threads cost more than they save."""
    in_chunks(n, lambda a, b: work(slice(a, b)), chunk=max(PARALLEL_ROWS, -(-n // WORKERS)))


def _chunks(rows):
    """Slices of at most CHUNK_ROWS, so each chunk is converted while it is still in cache."""
    for a in range(rows.start, rows.stop, CHUNK_ROWS):
        yield slice(a, min(a + CHUNK_ROWS, rows.stop))


def _nonfinite_rows(arrays, rows):
    """{field: splats among `rows` that the non-finite rule refuses in that field (core.splats.bad_rows)},
    only fields that have some."""
    found = {}
    for name, a in arrays.items():
        bad = int(bad_rows(name, a[rows]).sum())
        if bad:
            found[name] = bad
    return found


def _merge(tallies, order):
    total = {}
    for tally in tallies:
        for name, count in tally.items():
            total[name] = total.get(name, 0) + count
    return {name: total[name] for name in order if name in total}


def _block(records, names):
    """(m, len(names)) float32 of these properties: a strided view when they are adjacent native
    floats in the records (the usual layout), else a converted copy."""
    fields, f32 = records.dtype.fields, np.dtype(np.float32)
    offset = fields[names[0]][1]
    if all(fields[n][0] == f32 and fields[n][1] == offset + 4 * i for i, n in enumerate(names)):
        return np.ndarray(
            (len(records), len(names)),
            np.float32,
            buffer=records.view(np.uint8),
            offset=offset,
            strides=(records.itemsize, 4),
        )
    with np.errstate(over="ignore"):  # doubles beyond float32 become inf: reported as non-finite
        return np.stack([records[n].astype(np.float32) for n in names], axis=1)


# reading ------------------------------------------------------------------------------------------


class _Converter:
    """Fills the cloud's (contiguous) arrays from vertex records, one chunk of rows at a time, so
    each chunk is reordered and checked while it is still in cache."""

    def __init__(self, path, dtype, n, antialiased=False):
        self.antialiased = antialiased
        names = set(dtype.names)
        missing = [p for p in REQUIRED if p not in names]
        if missing:
            raise SplatFileError(path, f"vertex element lacks required 3DGS properties: {', '.join(missing)}")
        self.flat = "scale_2" not in names
        k = _sh_count(path, names)
        self.sh_names = ["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
        self.sh_order = sh_order(k)
        self.arrays = {
            "positions": np.empty((n, 3), np.float32),
            "rotations": np.empty((n, 4), np.float32),
            "log_scales": np.empty((n, 3), np.float32),
            "opacity_logits": np.empty(n, np.float32),
            "sh": np.empty((n, k, 3), np.float32),
        }
        layout = set(layout_names(shmod.degree_of(k))) - set(NORMALS)
        # Normals belong to the layout, so they are float32 like its other fields; extras keep their dtype.
        self.extras = {
            p: np.empty(n, np.float32 if p in NORMALS else dtype[p].newbyteorder("="))
            for p in dtype.names
            if p not in layout
        }
        self._float_extras = {f"extra '{p}'": a for p, a in self.extras.items() if a.dtype.kind == "f"}
        self.tallies = []

    def convert(self, records, rows):
        out = self.arrays
        out["positions"][rows] = _block(records, ["x", "y", "z"])
        out["rotations"][rows] = _block(records, ["rot_0", "rot_1", "rot_2", "rot_3"])
        out["opacity_logits"][rows] = _block(records, ["opacity"])[:, 0]
        if self.flat:
            out["log_scales"][rows, :2] = _block(records, ["scale_0", "scale_1"])
            out["log_scales"][rows, 2] = FLAT_LOG_SCALE
        else:
            out["log_scales"][rows] = _block(records, ["scale_0", "scale_1", "scale_2"])
        sh = out["sh"].reshape(len(out["sh"]), -1)
        np.take(_block(records, self.sh_names), self.sh_order, axis=1, out=sh[rows], mode="clip")
        with np.errstate(over="ignore"):
            for name, values in self.extras.items():
                values[rows] = records[name]
        self.tallies.append(_nonfinite_rows({**out, **self._float_extras}, rows))

    def cloud(self):
        extras = dict(self.extras)
        if all(p in extras for p in NORMALS) and not any(extras[p].any() for p in NORMALS):
            for p in NORMALS:  # all zero: the reference writer's placeholder, nothing to keep
                del extras[p]
        return SplatCloud(**self.arrays, extras=material_columns(extras), antialiased=self.antialiased)


def material_columns(extras):
    """The extras with the albedo's columns (written as albedo_0..2, as 2-D extras are) one (N,3)
    extra again, as core.material names it; other 2-D extras stay columns, as they were read (the
    Blender extension reads a PLY's properties that Blender's own importer kept so too)."""
    names = [f"{material.ALBEDO}_{i}" for i in range(3)]
    if material.ALBEDO in extras or not all(n in extras for n in names) or f"{material.ALBEDO}_3" in extras:
        return extras
    albedo = np.stack([extras.pop(n) for n in names], axis=1)
    return {**extras, material.ALBEDO: albedo}


def _sh_count(path, names):
    """K, the SH coefficients per channel, from the f_rest properties present."""
    rest = [p for p in names if p.startswith("f_rest_")]
    if set(rest) != {f"f_rest_{i}" for i in range(len(rest))}:
        raise SplatFileError(
            path,
            "f_rest properties must be numbered f_rest_0 .. f_rest_M without gaps, "
            f"found {sorted(rest, key=lambda p: (len(p), p))}",
        )
    if len(rest) not in REST_COUNTS:
        raise SplatFileError(
            path, f"{len(rest)} f_rest properties; 3DGS files have 0, 9, 24, 45 or 72 (SH degree 0..{shmod.MAX_DEGREE})"
        )
    return len(rest) // 3 + 1


def read(path, nonfinite="raise"):
    """Read a 3DGS PLY (or a PlayCanvas compressed PLY, see compressed_ply) into a SplatCloud.

    Binary data is read a cache-sized chunk at a time on every core and each chunk is reordered
    into the cloud's arrays (and checked for non-finite values) before the next is read.
    """
    check_nonfinite_policy(nonfinite)
    try:
        with open(path, "rb") as f:
            header = read_header(path, f)  # once: a hostile header may take a megabyte of lines
        if compressed_ply.is_compressed(header[1]):
            return compressed_ply.read(path, nonfinite, header=header)
        convert = _load(path, header)
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None
    if convert.flat:
        warnings.warn(
            f"{path}: 2DGS file (scale_0, scale_1 only); third axis set flat "
            f"(sigma {FLAT_SIGMA:g}, log-scale {FLAT_LOG_SCALE:.4f})",
            SplatFileWarning,
            stacklevel=2,
        )
    cloud = convert.cloud()
    return apply_nonfinite_policy(path, cloud, nonfinite, "read", _merge(convert.tallies, cloud.checked_arrays()))


def _load(path, header):
    """A _Converter holding every vertex of the file, whose parsed header is `header` (read_header's)."""
    fmt, elements, header_len, antialiased = header
    index, vertex = _vertex_element(path, elements)
    n = vertex.count
    if fmt == "ascii":
        records = _read_ascii(path, elements, index, header_len)
        convert = _Converter(path, records.dtype, n, antialiased)
        _in_parallel(n, lambda rows: [convert.convert(records[c], c) for c in _chunks(rows)])
        return convert
    dtype, start = _binary_layout(path, fmt, elements, index, header_len)
    convert = _Converter(path, dtype, n, antialiased)  # checks the properties before any data is read

    def load(rows):
        buffer = np.empty(min(CHUNK_ROWS, rows.stop - rows.start), dtype)
        with open(path, "rb", buffering=0) as f:
            for chunk in _chunks(rows):
                part = buffer[: chunk.stop - chunk.start]
                _read_into(path, f, start + chunk.start * dtype.itemsize, part)
                convert.convert(part, chunk)

    _in_parallel(n, load)
    return convert


# writing ------------------------------------------------------------------------------------------


def write(path, cloud, nonfinite="raise"):
    """Write binary little-endian 3DGS PLY: the reference layout, then the extras.

    The body is filled a cache-sized chunk at a time on every core and written in place; the file
    appears whole or not at all (also when non-finite values stop it under nonfinite='raise').
    """
    check_nonfinite_policy(nonfinite)
    if nonfinite != "raise":
        cloud = apply_nonfinite_policy(path, cloud, nonfinite, "write")
    names = layout_names(cloud.sh_degree)
    extras = _extra_columns(path, cloud, set(names))
    dtype, header = _layout(len(cloud), names, [(name, a.dtype) for name, a in extras], cloud.antialiased)
    fill = _Filler(cloud, extras, jit.load(KERNELS, check=_check_kernels))
    tallies = []
    try:
        with atomic_write(path) as f:
            f.write(header)
            f.flush()
            _reserve(f.fileno(), len(header) + len(cloud) * dtype.itemsize)

            def fill_and_write(rows):
                buffer = np.empty(min(CHUNK_ROWS, rows.stop - rows.start), dtype)
                for chunk in _chunks(rows):
                    part = buffer[: chunk.stop - chunk.start]
                    if not fill(part, chunk):  # tally the non-finite values (rarely)
                        tallies.append(_nonfinite_rows(cloud.checked_arrays(), chunk))
                    _write_at(f.fileno(), part, len(header) + chunk.start * dtype.itemsize)

            _in_parallel(len(cloud), fill_and_write)
            if nonfinite == "raise":
                apply_nonfinite_policy(path, cloud, "raise", "write", _merge(tallies, cloud.checked_arrays()))
    except OSError as exc:
        raise SplatFileError(path, f"cannot write: {exc.strerror or exc}") from exc


def _layout(count, names, extras, antialiased=False):
    """(vertex record dtype, header bytes) of a file of `count` splats with the float32 layout
    properties `names` and (name, dtype) extras after them. PLY has no field for the render mode the
    splats were made for: a comment line carries it, which other readers skip."""
    dtype = np.dtype([(CORE, "<f4", (len(names),))] + [(name, dt.newbyteorder("<")) for name, dt in extras])
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {ANTIALIASED_COMMENT} (made for opacity-compensated rendering)"] if antialiased else []
    header += [f"element vertex {count}"]
    header += [f"property float {name}" for name in names]
    header += [f"property {TYPE_NAMES[np.dtype(dt).str[1:]]} {name}" for name, dt in extras]
    return dtype, ("\n".join(header) + "\nend_header\n").encode("ascii")


def file_size(count, sh_degree):
    """Bytes of the file write() makes for `count` splats of `sh_degree` without extras."""
    dtype, header = _layout(count, layout_names(sh_degree), [])
    return len(header) + count * dtype.itemsize


class _Filler:
    """Fills vertex records with a cloud's splats in the reference layout; returns whether every
    layout value is finite. A compiled loop does it in one pass where numba loads (core.jit)."""

    def __init__(self, cloud, extras, kernels=None):
        self.cloud, self.extras, self.kernels = cloud, extras, kernels
        self.normals = [cloud.extras.get(name) for name in NORMALS]
        k = cloud.sh.shape[1]
        self.sh_columns = np.argsort(sh_order(k))  # cloud SH (K*3) -> file f_dc, f_rest order
        self.m = 3 * k  # f_dc + f_rest columns
        if kernels is not None:
            c = cloud
            normals = (
                np.zeros((0, 0), np.float32)
                if all(n is None for n in self.normals)
                else np.stack(
                    [np.zeros(len(c), np.float32) if n is None else n.astype(np.float32) for n in self.normals]
                )
            )
            self.arrays = [
                np.ascontiguousarray(c.positions, dtype=np.float32),
                normals,
                np.ascontiguousarray(c.sh, dtype=np.float32).reshape(len(c), self.m),
                self.sh_columns.astype(np.int64),
            ] + [np.ascontiguousarray(a, dtype=np.float32) for a in (c.opacity_logits, c.log_scales, c.rotations)]

    def __call__(self, part, rows):
        if self.kernels is not None:
            finite = self.kernels.fill_rows(*self.arrays, rows.start, part[CORE])
            for name, values in self.extras:
                part[name] = values[rows]
            return finite
        self._fill(part, rows)
        return np.isfinite(part[CORE]).all()

    def _fill(self, part, rows):
        """The NumPy path: one block of columns at a time."""
        cloud, core, m = self.cloud, part[CORE], self.m
        core[:, 0:3] = cloud.positions[rows]
        for i, normal in enumerate(self.normals):
            core[:, 3 + i] = 0.0 if normal is None else normal[rows]
        sh = cloud.sh[rows].reshape(len(part), m)
        core[:, 6 : 6 + m] = np.take(sh, self.sh_columns, axis=1, mode="clip")
        core[:, 6 + m] = cloud.opacity_logits[rows]
        core[:, 7 + m : 10 + m] = cloud.log_scales[rows]
        core[:, 10 + m : 14 + m] = cloud.rotations[rows]
        for name, values in self.extras:
            part[name] = values[rows]


def _check_kernels(kernels):
    """The compiled fill against the NumPy one on a small cloud (compiling it, or loading the cache)."""
    from ..core.scenes import seed_cube

    cloud = seed_cube(2)
    dtype = np.dtype([(CORE, "<f4", (len(layout_names(cloud.sh_degree)),))])
    fast, slow = _Filler(cloud, [], kernels), _Filler(cloud, [])
    got, want = np.empty(len(cloud), dtype), np.empty(len(cloud), dtype)
    if not (fast(got, slice(0, len(cloud))) and slow(want, slice(0, len(cloud))) and np.array_equal(got, want)):
        raise RuntimeError("the compiled PLY fill disagrees with the NumPy one")


def _extra_columns(path, cloud, taken):
    """(property name, 1-D array of a PLY type) for each extra but the normals; 2-D extras become
    name_0, name_1, ..."""
    columns = []
    for key, values in cloud.extras.items():
        if key in NORMALS:
            if values.ndim != 1:
                raise SplatFileError(path, f"extra '{key}' must hold one value per splat to be a PLY normal")
            continue
        flat = _ply_typed(path, key, values.reshape(len(values), -1))
        names = [key] if values.ndim == 1 else [f"{key}_{i}" for i in range(flat.shape[1])]
        columns += [(name, flat[:, i]) for i, name in enumerate(names)]
    seen = set(taken) | set(NORMALS)
    for name, _ in columns:
        # f_rest_* would be read back as SH coefficients, so those names belong to the layout too.
        if (
            name in seen
            or name.startswith("f_rest_")
            or not name
            or not name.isascii()
            or any(c.isspace() for c in name)
        ):
            raise SplatFileError(
                path,
                f"extra '{name}' cannot be a PLY property: it is empty, not ASCII, "
                "holds whitespace or clashes with a 3DGS or another extra property",
            )
        seen.add(name)
    return columns


def _ply_typed(path, key, a):
    """`a` in a dtype PLY can hold, converting only where no value changes."""
    if a.dtype == bool:
        return a.astype(np.uint8)
    if a.dtype.kind in "iu" and a.dtype.itemsize == 8:
        small = np.int32 if a.dtype.kind == "i" else np.uint32
        info = np.iinfo(small)
        if a.size == 0 or (a.min() >= info.min and a.max() <= info.max):
            return a.astype(small)
    if a.dtype == np.float16:
        return a.astype(np.float32)
    if a.dtype.kind in "iuf" and a.dtype.str[1:] in TYPE_NAMES:
        return a
    raise SplatFileError(
        path, f"extra '{key}' has dtype {a.dtype}, which PLY cannot store (PLY has 8-32 bit integers, float and double)"
    )
