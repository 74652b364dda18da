"""OpenUSD splats: `ParticleField3DGaussianSplat` prims in .usda, .usdc and .usdz files.

Schema (pxr.UsdVol, usd-core >= 26.3): `positions` point3f[], `orientations` quatf[] (w first in
Gf.Quatf), `scales` float3[] LINEAR, `opacities` float[] LINEAR in [0,1],
`radiance:sphericalHarmonicsDegree` uniform int, `radiance:sphericalHarmonicsCoefficients` float3[]
with (d+1)^2 raw 3DGS coefficients per particle, particle-major (entry 0 = DC); each has a half
twin (`positionsh`, ...). We author `extent` ourselves: the box holding every splat out to the
radius where its alpha falls below 1/255, r = sqrt(2 ln(255 o)) sigma, the renderer's own rule.

Reading (`read`, `read_stage`, `read_frames`)
- Every ParticleField3DGaussianSplat prim (instance proxies included), plus UsdGeomPoints in the
  layout Adobe's USD file-format plugins write for splats, recognised by `primvars:rot`,
  `primvars:widths1` and `primvars:widths2`: `points`; `widths`/`primvars:widths1`/`widths2` are
  2 sigma per axis; `primvars:rot` quatf; `primvars:displayOpacity` linear; `primvars:displayColor`
  the DC colour clamped to [0,1]; `primvars:fRest0..` channel-major like PLY's f_rest; and
  UsdGeomPoints as Blender's USD export writes splat point clouds, recognised by `primvars:rotation`
  and `primvars:scale` (see _blender_cloud). Other prims are skipped with a SplatFileWarning
  listing them.
- Float attributes are preferred to their half twins, as the schema asks. Per the schema, an array
  too long is truncated to the particle count and one too short is ignored (orientation identity,
  scale 1, opacity 1, SH a grey DC); each such repair is reported in a warning.
- Each prim's local-to-world transform is applied, then the stage's upAxis and metersPerUnit, then
  the flip from USD's Y-up (RUB) to the model's 3DGS axes (RDF: y down, z forward), so clouds come
  out in the model's axes and metres. axes="RUB" keeps Y-up, axes=None the stage's own axes;
  meters_per_unit=None keeps its units. USD's fallbacks apply to unauthored metadata: Y up, 0.01 m
  per unit (a warning says so). Our files' prims carry UPRIGHT_OP, so this gives their values back.
- A ParticleField3DGaussianSplat without UPRIGHT_OP (NVIDIA's and OpenUSD's converters copy the PLY's
  coordinates into a Y-up stage unchanged: shown as stored, the capture is upside down) is, with
  unmarked="capture" (the default), taken as capture coordinates: units apply, no axis change, so
  the PLY's values come back. unmarked="stage" reads it in the stage's axes like any geometry.
  A transform that is not a rotation times a uniform scale is exact for positions and covariances
  (re-diagonalised into rotation and scales) but not for SH colours; its anisotropy is reported.
- Our own files also carry `splatwright:opacityLogits`, `splatwright:logScales` and
  `splatwright:rotations` (float32 as the model stores them), used when they still agree with
  `opacities`/`scales`/`orientations`, so PLY -> USD -> PLY is exact; and a cloud read from USD and
  written back unchanged reproduces the file's linear values. `splatwright:antialiased` (true)
  marks splats made for antialiased rendering (SplatCloud.antialiased).

Writing (`write`, `write_stage`, `write_frames`): a Y-up, metersPerUnit 1 stage holding the values
as the reference converters (OpenUSD's hdParticleField example, NVIDIA's usd-convert-gsplat) write
them: the capture's PLY coordinates, normalised quaternions, SH with primvar metadata (elementSize
(d+1)^2, vertex interpolation); the prim's UPRIGHT_OP, a half turn about X, stands the y-down
capture upright in the stage (layout="upright"). layout="y-up" turns the values themselves instead
(no transform), layout="as-is" writes neither (as NVIDIA's converter). One prim per cloud (default
/Splats); a sequence of same-count
clouds (any iterable, consumed one at a time) becomes time samples on one prim, where an attribute
that never changes is authored once as its default value. half=True stores orientations, scales, opacities and SH
as half floats (about half the size; positions stay float32 unless half_positions=True). Extras
become `primvars:<name>` with vertex interpolation. Without pxr.UsdVol's schema classes (an older
pxr, e.g. one bundled with Blender) the same prim and attributes are authored by name through the
generic API, giving the same file.
"""

import contextlib
import ctypes
import itertools
import contextlib
import math
import os
import re
import struct
import warnings
import weakref
from dataclasses import dataclass, field

import numpy as np

from ..core import SplatCloud, geometry
from ..core import sh as shmod
from ..core.splats import logit, sigmoid
from .common import (SplatFileError, SplatFileWarning, apply_nonfinite_policy, atomic_path, check_nonfinite_policy,
                     log_scales_from_linear)
from . import usda
from .policy import inside_package, outside_message, within
from .spz import SH_FLIP, flip_yz

try:
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdUtils, Vt
    PXR_ERRORS = (Tf.ErrorException,)
except ImportError:             # text layers only, through usda (Blender 4.2 bundles no pxr)
    Usd = None
    PXR_ERRORS = ()
try:
    from pxr import UsdVol
except ImportError:
    UsdVol = None

TYPE_NAME = "ParticleField3DGaussianSplat"
SH_DEGREE = "radiance:sphericalHarmonicsDegree"
SH_COEFFS = "radiance:sphericalHarmonicsCoefficients"
LOGITS = "splatwright:opacityLogits"
LOG_SCALES = "splatwright:logScales"
RAW_ROTATIONS = "splatwright:rotations"           # w, x, y, z as the model holds them (any norm)
ANTIALIASED = "splatwright:antialiased"           # authored (true) for splats made for antialiased rendering
UPRIGHT_OP = "xformOp:transform:upright"          # capture (y down, z forward) -> the Y-up stage
UPRIGHT = np.diag([1.0, -1.0, -1.0, 1.0])         # a half turn about X, exact in a matrix op
LAYOUTS = ("upright", "y-up", "as-is")
UNMARKED = ("capture", "stage")
PRIM_PATH = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
ANISOTROPY_TOLERANCE = 1e-6        # below this a transform counts as rotation * uniform scale

# schema attribute -> (Sdf type name, uniform?, schema creator method)
SCHEMA = {
    "positions": ("point3f[]", False, "CreatePositionsAttr"),
    "positionsh": ("point3h[]", False, "CreatePositionshAttr"),
    "orientations": ("quatf[]", False, "CreateOrientationsAttr"),
    "orientationsh": ("quath[]", False, "CreateOrientationshAttr"),
    "scales": ("float3[]", False, "CreateScalesAttr"),
    "scalesh": ("half3[]", False, "CreateScaleshAttr"),
    "opacities": ("float[]", False, "CreateOpacitiesAttr"),
    "opacitiesh": ("half[]", False, "CreateOpacitieshAttr"),
    SH_DEGREE: ("int", True, "CreateRadianceSphericalHarmonicsDegreeAttr"),
    SH_COEFFS: ("float3[]", False, "CreateRadianceSphericalHarmonicsCoefficientsAttr"),
    SH_COEFFS + "h": ("half3[]", False, "CreateRadianceSphericalHarmonicsCoefficientshAttr"),
    "extent": ("float3[]", False, "CreateExtentAttr"),
}
CUSTOM = {LOGITS: "float[]", LOG_SCALES: "float3[]", RAW_ROTATIONS: "float4[]", ANTIALIASED: "bool"}

# NumPy dtype of an extra -> Sdf scalar type of its primvar (narrow ints widen to int, restored on read)
EXTRA_TYPES = {"float32": "float", "float64": "double", "float16": "half", "int32": "int",
               "uint32": "uint", "int64": "int64", "uint64": "uint64", "uint8": "uchar", "bool": "bool",
               "int8": "int", "int16": "int", "uint16": "int"}
DTYPE_KEY = "splatwright:dtype"
NARROW_INTS = {name for name, sdf in EXTRA_TYPES.items() if sdf == "int" and name != "int32"}
ADOBE_PRIMVARS = {"rot", "widths1", "widths2", "displayColor", "displayOpacity", "clipping"}
BLENDER_BASE = "radiance:base"                    # Blender's point-cloud splats: DC rgb + opacity
REST_COUNTS = tuple(k - 1 for k in shmod.VALID_COUNTS)      # higher coefficients per channel: 0, 3, 8, 15, 24
BLENDER_PRIMVARS = {"rotation", "scale", BLENDER_BASE, "displayColor", "displayOpacity"} | \
    {f"radiance:sh_{i}" for i in range(REST_COUNTS[-1])}

# Linear values read from a file, kept per cloud object so that writing an unchanged cloud back
# reproduces them bit for bit (the model stores logs and logits, which float32 cannot invert exactly).
_READ_LINEAR = weakref.WeakKeyDictionary()


@dataclass
class SplatPrim:
    """One splat prim of a stage: its path, the cloud (world space, target axes and units) and what
    reading it had to report."""
    path: str
    cloud: SplatCloud
    source: str                        # "ParticleField3DGaussianSplat" or "Points (Adobe 3DGS primvars)"
    to_world: np.ndarray               # 4x4 (column vectors) applied to the prim's local values
    anisotropy: float = 0.0            # how far to_world is from rotation * uniform scale
    notes: list = field(default_factory=list)


# opening ------------------------------------------------------------------------------------------

MAGIC = {".usdc": (b"PXR-USDC",), ".usdz": (b"PK\x03\x04",), ".usda": (b"#usda",),
         ".usd": (b"PXR-USDC", b"#usda")}


def _require_pxr_for(path):
    """A SplatFileError for a binary layer when pxr is missing: only text layers are ours to write."""
    if Usd is None and os.fspath(path).lower().endswith(".usdc"):
        raise SplatFileError(path, "binary OpenUSD (.usdc) needs OpenUSD's Python module (pxr), which this "
                                   "Python lacks (Blender 4.4 and later bundle it); write .usda, .usd or .usdz")


def _open(path, allow_outside=False):
    """The stage (a usda.Layer where pxr is missing) of a file whose header matches its extension;
    its sublayers, references and payloads must lie in its package or folder (see _composed_layers)."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise SplatFileError(path, f"cannot open: {exc.strerror or exc}") from None
    expected = MAGIC.get(os.path.splitext(path)[1].lower(), ())
    if expected and not any(head.startswith(m) for m in expected):
        names = " or ".join(repr(m.decode("latin-1")) for m in expected)
        raise SplatFileError(path, f"not a {os.path.splitext(path)[1]} file (it does not start with {names})")
    if Usd is None:
        return usda.read_layer(path)
    try:
        layers = _composed_layers(path, allow_outside)      # held open until the stage uses them
        stage = Usd.Stage.Open(layers[0], Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise SplatFileError(path, f"OpenUSD cannot open it (truncated or corrupt?): {_tf_message(exc)}") from None
    if stage is None:
        raise SplatFileError(path, "OpenUSD cannot open it")
    return stage


def _layer(path, identifier):
    """The Sdf layer at `identifier` (a file, or "pkg.usdz[inner]"), re-read if an earlier open left it
    cached (it may be stale); crate files are checked before OpenUSD parses them. None if missing."""
    _check_crate(path, identifier)
    layer = Sdf.Layer.Find(identifier)
    if layer is not None:
        layer.Reload(True)
    else:
        layer = Sdf.Layer.FindOrOpen(identifier)
    if layer is not None:
        _check_children(path, layer)
    return layer


def _names(path, spec, key, where=""):
    """The list of names a spec's field `key` holds ([] if unauthored); a damaged crate file can make
    it any other type, which is a SplatFileError."""
    if not spec.HasInfo(key):
        return []
    names = spec.GetInfo(key)
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise SplatFileError(path, f"{where}{spec.path}: its {key} hold a {type(names).__name__}, "
                                   "not a list of names (corrupt?)")
    return names


def _check_children(path, layer):
    """Every prim and property a prim spec lists as its children must exist: OpenUSD composes a
    stage by those lists and aborts the process ("Dereferenced an invalid SdfPrimSpec") on a name
    without a spec, which one damaged token index in a crate file makes."""
    where = "" if layer.identifier == os.path.abspath(path) else f"layer {layer.identifier}: "
    todo = [layer.pseudoRoot]
    while todo:
        prim = todo.pop()
        for name in _names(path, prim, "primChildren", where):
            child = layer.GetPrimAtPath(prim.path.AppendChild(name)) if Sdf.Path.IsValidIdentifier(name) else None
            if child is None:
                raise SplatFileError(path, f"{where}prim {prim.path} lists a child {name!r} that the "
                                           "layer does not hold (corrupt?)")
            todo.append(child)
        for name in _names(path, prim, "properties", where):
            ok = Sdf.Path.IsValidNamespacedIdentifier(name) and \
                layer.GetPropertyAtPath(prim.path.AppendProperty(name)) is not None
            if not ok:
                raise SplatFileError(path, f"{where}prim {prim.path} lists a property {name!r} that "
                                           "the layer does not hold (corrupt?)")


def _composed_layers(path, allow_outside):
    """The root layer and every layer it composes (sublayers, references, payloads, recursively),
    each opened with Sdf before the stage is: OpenUSD would read any path a layer names (/etc/...,
    ../../, a URL) and only warn about missing ones. A layer outside the stage's package (.usdz) or
    folder is refused unless allow_outside, with the same message whether it exists or not; a
    missing one is a SplatFileError either way."""
    root = os.path.abspath(path)
    package = root if root.lower().endswith(".usdz") else None
    where = "the stage's package" if package else "the stage's folder"
    first = _layer(path, root)
    if first is None:
        raise SplatFileError(path, "OpenUSD cannot open it")
    layers, todo, seen = [first], [first], {first.identifier}
    while todo:
        layer = todo.pop()
        named_by = "" if layer is first else f"layer {layer.identifier} "
        for asset in layer.GetCompositionAssetDependencies():
            resolved = layer.ComputeAbsolutePath(asset)
            if not os.path.isabs(resolved.split("[", 1)[0]):          # a search path: anchored as the resolver does first
                resolved = layer.ComputeAbsolutePath("./" + asset)
            ok = inside_package(package, resolved) if package else within(os.path.dirname(root),
                                                                           resolved.split("[", 1)[0])
            if not ok and not allow_outside:
                raise SplatFileError(path, f"{named_by}refers to a layer: {outside_message(asset, where)} "
                                           "(read with allow_outside=True to allow it)")
            if resolved in seen:
                continue
            try:
                found = _layer(path, resolved)
            except Tf.ErrorException:
                found = None
            if found is None:
                raise SplatFileError(path, f"{named_by}refers to the layer '{asset}', which cannot be opened "
                                           "(missing, or not an OpenUSD layer)")
            seen.add(found.identifier)
            seen.add(resolved)
            layers.append(found)
            todo.append(found)
    return layers


CRATE_EXPANSION = 256      # the most an element count may exceed its section's bytes by (LZ4 tops 255:1)
CRATE_INT_EXPANSION = 1024     # compressed integers: 2 code bits per int, then LZ4 (255:1)
# Non-inlined value types that start with a u64 count, and the fewest bytes each element takes:
# Dictionary (string index + value offset), PathVector, TokenVector, VariantSelectionMap,
# DoubleVector, LayerOffsetVector, StringVector (crateDataTypes.h).
CRATE_COUNTED = {31: 12, 40: 4, 41: 4, 45: 8, 48: 8, 49: 16, 50: 4}
# Bytes per element of uncompressed arrays by crate type (bool .. Vec4i, TimeCode); others take >= 1.
CRATE_ELEMENT = {1: 1, 2: 1, 3: 4, 4: 4, 5: 8, 6: 8, 7: 2, 8: 4, 9: 8, 10: 4, 11: 4, 12: 4, 13: 32, 14: 72,
                 15: 128, 16: 32, 17: 16, 18: 8, 19: 16, 20: 8, 21: 4, 22: 8, 23: 24, 24: 12, 25: 6, 26: 12,
                 27: 32, 28: 16, 29: 8, 30: 16, 56: 8}


class _CrateError(Exception):
    pass


def _check_crate(path, identifier=None):
    """Refuse a .usdc whose structure the file cannot hold, before OpenUSD's crate reader sizes
    buffers by it: the table of contents and every section's counts and compressed sizes, and the
    element count of every array, vector and dictionary the FIELDS section points to (a flipped bit
    in one makes OpenUSD allocate gigabytes, read past the file, or abort the process). The layer
    may sit in a .usdz ("pkg.usdz[inner]", or the package itself for its first file)."""
    import mmap
    import zipfile
    identifier = os.path.abspath(path) if identifier is None else identifier
    outer, _, inner = identifier.partition("[")
    if not os.path.isfile(outer):
        return
    try:
        with open(outer, "rb") as f:
            # not closed explicitly: views of it may live on in a traceback; freed with the last one
            data = memoryview(mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)) if os.fstat(f.fileno()).st_size \
                else memoryview(b"")
        if bytes(data[:4]) == b"PK\x03\x04":
            data = _packaged(data, outer, inner.rstrip("]"))
        if data is not None and bytes(data[:8]) == b"PXR-USDC":
            _check_crate_bytes(path, data)
    except (struct.error, zipfile.BadZipFile):
        raise SplatFileError(path, "crate header or table of contents is truncated") from None
    except (_CrateError, ValueError, IndexError) as exc:
        raise SplatFileError(path, f"crate file is corrupt: {exc}") from None


def _packaged(view, outer, inner):
    """The bytes of file `inner` (default: the first) of the zip `outer`, if stored uncompressed
    (OpenUSD reads no other kind), else None."""
    import zipfile
    with zipfile.ZipFile(outer) as z:
        infos = z.infolist()
        match = [i for i in infos if i.filename == inner] if inner else infos[:1]
        if not match or match[0].compress_type != zipfile.ZIP_STORED:
            return None
        info = match[0]
    name_length, extra_length = struct.unpack_from("<HH", view, info.header_offset + 26)
    start = info.header_offset + 30 + name_length + extra_length
    if start + info.file_size > len(view):
        raise _CrateError(f"packaged file {info.filename!r} runs past the package")
    return view[start:start + info.file_size]


def _check_crate_bytes(path, data):
    size = len(data)
    major, minor, patch = data[8], data[9], data[10]
    toc = struct.unpack_from("<q", data, 16)[0]
    sections = struct.unpack_from("<Q", data, toc)[0] if 88 <= toc <= size - 8 else None
    if sections is None or sections > (size - toc - 8) // 32:
        raise SplatFileError(path, "crate table of contents lies outside the file (truncated or corrupt?)")
    found = {}
    for i in range(sections):
        name, start, length = struct.unpack_from("<16sqq", data, toc + 8 + 32 * i)
        name = name.split(b"\0", 1)[0].decode("latin-1")
        if start < 0 or length < 8 or start + length > size:
            raise SplatFileError(path, f"crate section {name!r} lies outside the file (truncated or corrupt?)")
        count = struct.unpack_from("<Q", data, start)[0]
        if count > CRATE_EXPANSION * length:
            raise SplatFileError(path, f"crate section {name!r} claims {count} entries in {length} bytes "
                                       "(corrupt?)")
        found[name] = (start, length, count)
    if (major, minor) < (0, 4):         # before 0.4.0 sections were not compressed: counts checked above
        return
    sizes = {"TOKENS": 2, "FIELDS": 0, "FIELDSETS": 1, "PATHS": 0, "SPECS": 3}
    for name, (start, length, count) in found.items():
        end, at = start + length, start + 8
        if name == "TOKENS":
            raw, packed = struct.unpack_from("<QQ", data, at)
            if at + 16 + packed > end or raw > 255 * packed + 16 or count > raw:
                raise _CrateError(f"TOKENS claims {count} tokens in {raw} bytes packed in {packed}, "
                                  f"in a {length}-byte section")
        elif name == "PATHS":
            encoded = struct.unpack_from("<Q", data, at)[0]
            if encoded > CRATE_INT_EXPANSION * length:
                raise _CrateError(f"PATHS claims {encoded} encoded paths in {length} bytes")
            _skip_packed(data, at + 8, end, 3, name)
        elif name == "FIELDS":
            at = _skip_packed(data, at, end, 1, name)
            packed = struct.unpack_from("<Q", data, at)[0]
            if at + 8 + packed > end:
                raise _CrateError(f"FIELDS value representations ({packed} bytes) run past the section")
            reps = _fast_decompress(data[at + 8:at + 8 + packed], 8 * count)
            if len(reps) != 8 * count:
                raise _CrateError(f"FIELDS holds {len(reps) // 8} value representations, not {count}")
            _check_values(data, reps, toc, (major, minor) >= (0, 7))
        elif name in sizes:
            _skip_packed(data, at, end, sizes[name], name)


def _skip_packed(data, at, end, blocks, name):
    """The offset after `blocks` compressed blocks (u64 size + bytes) that must end by `end`."""
    for _ in range(blocks):
        packed = struct.unpack_from("<Q", data, at)[0]
        at += 8 + packed
        if at > end:
            raise _CrateError(f"a compressed block of {name} ({packed} bytes) runs past the section")
    return at


def _check_values(data, reps, data_end, wide_counts):
    """Every non-inlined array, vector and dictionary must hold its count in the bytes before the TOC."""
    values = np.frombuffer(reps, "<u8")
    outside = (values >> 62) & 1 == 0                       # not inlined: the payload is a file offset
    offsets = values & ((1 << 48) - 1)
    kinds = (values >> 48) & 0xFF
    arrays = (values >> 63) == 1
    counted = outside & (arrays | np.isin(kinds, list(CRATE_COUNTED)))
    for value, offset, kind, is_array in zip(values[counted].tolist(), offsets[counted].tolist(),
                                             kinds[counted].tolist(), arrays[counted].tolist()):
        width = 8 if wide_counts or not is_array else 4
        if offset == 0 and is_array:                         # an empty array
            continue
        if offset < 88 or offset + width > data_end:
            raise _CrateError(f"a value of type {kind} lies outside the data (offset {offset})")
        count = struct.unpack_from("<Q" if width == 8 else "<I", data, offset)[0]
        room = data_end - offset - width
        if is_array and (value >> 61) & 1:                   # compressed: integers, or a lookup table
            fits = count <= CRATE_INT_EXPANSION * room + 16
        else:
            fits = count * (CRATE_ELEMENT.get(kind, 1) if is_array else CRATE_COUNTED[kind]) <= room
        if not fits:
            raise _CrateError(f"{'an array' if is_array else 'a value'} of type {kind} at byte {offset} claims "
                              f"{count} elements, more than the {room} bytes after it can hold")


def _fast_decompress(src, limit):
    """OpenUSD's TfFastCompression: a chunk count byte (0: one LZ4 block), then sized LZ4 blocks."""
    if not len(src):
        raise _CrateError("an empty compressed block")
    chunks = src[0]
    if chunks == 0:
        return _lz4_block(src[1:], limit)
    out, at = bytearray(), 1
    for _ in range(chunks):
        size = struct.unpack_from("<i", src, at)[0]
        if size < 0 or at + 4 + size > len(src):
            raise _CrateError("a compressed chunk runs past its block")
        out += _lz4_block(src[at + 4:at + 4 + size], limit - len(out))
        at += 4 + size
    return bytes(out)


def _lz4_block(src, limit):
    """One LZ4 block, refusing to produce more than `limit` bytes (only small sections are decoded)."""
    out, i, n = bytearray(), 0, len(src)
    while i < n:
        token = src[i]
        i += 1
        literals, i = _lz4_length(src, i, token >> 4)
        if len(out) + literals > limit or i + literals > n:
            raise _CrateError("compressed data expands past its stated size")
        out += src[i:i + literals]
        i += literals
        if i >= n:
            break
        offset = src[i] | src[i + 1] << 8
        match, i = _lz4_length(src, i + 2, token & 15)
        match += 4
        if not 0 < offset <= len(out) or len(out) + match > limit:
            raise _CrateError("compressed data refers outside itself")
        start = len(out) - offset
        while match > 0:                                     # overlapping copies repeat the pattern
            piece = out[start:start + min(match, offset)]
            out += piece
            start += len(piece)
            match -= len(piece)
    return bytes(out)


def _lz4_length(src, i, length):
    if length == 15:
        while True:
            more = src[i]
            i += 1
            length += more
            if more != 255:
                break
    return length, i


@contextlib.contextmanager
def _pxr_errors(path):
    """OpenUSD parses a layer lazily: a damaged one can fail while prims and values are read, not only
    when it is opened. Its errors (and undecodable strings it hands back) become a SplatFileError
    naming the file."""
    try:
        yield
    except PXR_ERRORS as exc:
        raise SplatFileError(path, f"OpenUSD cannot read it (truncated or corrupt?): {_tf_message(exc)}") from None
    except UnicodeDecodeError:
        raise SplatFileError(path, "OpenUSD cannot read it: it holds names or strings that are not UTF-8 "
                                   "(corrupt?)") from None


def _tf_message(exc):
    try:
        text = str(exc)
    except UnicodeDecodeError:          # OpenUSD quoting bytes of the file that are not UTF-8
        return "it holds bytes that are not UTF-8 text"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0].split(" : ", 1)[-1] if lines else "unknown error"


def _time(stage, time):
    if Usd is None:
        return None if time is None else float(time)
    return Usd.TimeCode.EarliestTime() if time is None else Usd.TimeCode(float(time))


def _primvars(prim):
    return usda.PrimvarsAPI(prim) if Usd is None else UsdGeom.PrimvarsAPI(prim)


def _traverse(stage):
    return stage.traverse() if Usd is None else stage.Traverse(Usd.TraverseInstanceProxies())


def _is_points(prim):
    return prim.GetTypeName() == "Points" if Usd is None else prim.IsA(UsdGeom.Points)


def _is_geometry(prim):
    if Usd is None:
        return prim.GetTypeName() not in ("", "Xform", "Scope")
    return prim.IsA(UsdGeom.Gprim)


# stage units and axes ----------------------------------------------------------------------------

Z_UP_TO_Y_UP = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)    # (x, y, z) -> (x, z, -y)
RUB_TO_RDF = np.diag([1.0, -1.0, -1.0])                                 # y and z reversed
AXES = ("RDF", "RUB", None)
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def stage_matrix(stage, axes="RDF", meters_per_unit=1.0, notes=None):
    """4x4 taking stage coordinates to the target axes and units.

    axes: "RDF" (the model's convention, as 3DGS PLY: y down, z forward), "RUB" (Y-up as USD
    itself), or None (keep the stage's axes, Z-up included). meters_per_unit None keeps its units.
    """
    if axes not in AXES:
        raise ValueError(f"axes must be one of {AXES}, got {axes!r}")
    notes = [] if notes is None else notes
    m = np.eye(4)
    if axes is not None:
        if _stage_metadata(stage, "upAxis", "Y") == "Z":
            m[:3, :3] = Z_UP_TO_Y_UP
        if axes == "RDF":
            m[:3, :3] = RUB_TO_RDF @ m[:3, :3]
    if meters_per_unit is not None:
        units = _stage_metadata(stage, "metersPerUnit", None)
        if units is None:
            notes.append("metersPerUnit is not authored; USD's fallback of 0.01 (centimetres) applies")
        m[:3, :3] *= (0.01 if units is None else units) / float(meters_per_unit)
    return m


def _stage_metadata(stage, key, fallback):
    """Layer metadata `key` (upAxis as "Y"/"Z", metersPerUnit as a positive float), or fallback if
    unauthored; any other value is a SplatFileError naming it (read raw: pxr's own accessors take an
    upAxis of "X" for Y)."""
    if Usd is None:
        value = stage.metadata.get(key)
    elif not stage.HasAuthoredMetadata(key):
        value = None
    else:
        value = stage.GetMetadata(key)
    if value is None:
        return fallback
    path = stage.GetRootLayer().identifier
    if key == "upAxis":
        if str(value) not in ("Y", "Z"):
            raise SplatFileError(path, f"upAxis {str(value)!r}: an OpenUSD stage is Y-up or Z-up")
        return str(value)
    try:
        units = float(value)
    except (TypeError, ValueError):
        units = math.nan
    if not (math.isfinite(units) and units > 0):
        raise SplatFileError(path, f"metersPerUnit {value!r}: it must be a positive, finite number of metres")
    return units


def _world_matrix(prim, time):
    """The prim's local-to-world transform as a 4x4 acting on column vectors. Its own ops are read
    with GetLocalTransformation: a pxr without the splat schema (Blender's) does not count the prim
    as Xformable, and ComputeLocalToWorldTransform would skip them."""
    if Usd is None:
        return prim.world_matrix(time)
    xformable = UsdGeom.Xformable(prim)
    local = np.array(xformable.GetLocalTransformation(time), dtype=np.float64).T
    if xformable.GetResetXformStack():
        return local
    return np.array(UsdGeom.XformCache(time).GetParentToWorldTransform(prim), dtype=np.float64).T @ local


# reading values -----------------------------------------------------------------------------------

def _file(prim):
    return prim.GetStage().GetRootLayer().identifier


def _value(prim, name, time, shape=()):
    """An authored array attribute as NumPy (numbers, `shape` per entry), or None."""
    attr = prim.GetAttribute(name)
    if not attr or not attr.HasAuthoredValue():
        return None
    value = attr.Get(time)
    return None if value is None else _numbers(prim, name, value, shape)


def _numbers(prim, name, value, shape):
    """`value` as NumPy, or a SplatFileError when it is not an array of numbers with `shape` per
    entry (strings, a single value, a float[] where the schema has point3f[] ...)."""
    values = np.asarray(value)
    if values.dtype.kind not in "iuf" or values.ndim != 1 + len(shape) or values.shape[1:] != shape:
        entries = f"{shape[0]}-component vectors" if shape else "numbers"
        raise SplatFileError(_file(prim), f"{prim.GetPath()}: {name} holds a {type(value).__name__} "
                                          f"({values.dtype}, shape {values.shape}), expected an array of {entries}")
    return values


def _float_or_half(prim, name, time, shape):
    """The float attribute if authored, else its half twin widened to float32."""
    for attr_name in (name, name + "h"):
        value = _value(prim, attr_name, time, shape)
        if value is not None:
            return value.astype(np.float32, copy=False)
    return None


def _fit(values, n, shape, name, default, notes):
    """Per the schema: too long -> truncated to n, too short or absent -> the default."""
    if values is None:
        if n:
            notes.append(f"{name} not authored; using {default}")
        return None
    values = values.reshape((-1,) + shape)
    if len(values) > n:
        notes.append(f"{name} has {len(values)} entries for {n} particles; truncated")
        return values[:n]
    if len(values) < n:
        notes.append(f"{name} has {len(values)} entries for {n} particles; ignored, using {default}")
        return None
    return values


def _sh_from(prim, coeffs, degree, n, notes):
    """(n, K, 3) SH from a particle-major coefficient array, following the schema's length rules."""
    if coeffs is None:
        if n:
            notes.append(f"{SH_COEFFS} not authored; using grey (SH degree 0, DC 0)")
        return np.zeros((n, 1, 3), np.float32)
    coeffs = coeffs.reshape(-1, 3)
    if degree is None:                  # unauthored: infer from the count, else the schema's fallback 3
        per = len(coeffs) // n if n else 16
        degree = shmod.degree_of(per) if n and len(coeffs) == n * per and per in shmod.VALID_COUNTS else 3
    k = (degree + 1) ** 2
    if len(coeffs) < n * k:
        notes.append(f"{SH_COEFFS} has {len(coeffs)} entries, {n * k} needed for degree {degree}; "
                     "ignored, using grey")
        return np.zeros((n, 1, 3), np.float32)
    if len(coeffs) > n * k:
        notes.append(f"{SH_COEFFS} has {len(coeffs)} entries for {n} particles; truncated")
    sh = coeffs[:n * k].reshape(n, k, 3)
    if degree > shmod.MAX_DEGREE:
        notes.append(f"SH degree {degree} truncated to {shmod.MAX_DEGREE}")
        sh = sh[:, :shmod.num_coeffs(shmod.MAX_DEGREE)]
    return sh


def _valid_opacities(opacities, notes):
    bad = np.isfinite(opacities) & ((opacities < 0) | (opacities > 1))
    if bad.any():
        notes.append(f"{int(bad.sum())} opacities outside [0, 1] clamped")
        return np.clip(opacities, 0, 1)
    return opacities


def _logits_from(opacities, stored, notes):
    """float32 logits: the stored exact ones where they still reproduce `opacities`, else derived."""
    # NaN and Inf stay as they are (logit would clamp Inf to a finite value) for the non-finite policy
    derived = np.where(np.isfinite(opacities), logit(opacities), opacities).astype(np.float32)
    return _prefer_stored(derived, stored, sigmoid(stored).astype(np.float32) if stored is not None else None,
                          opacities, LOGITS, notes)


def _log_scales_from(scales, stored, notes):
    derived = log_scales_from_linear(scales, notes)
    check = np.exp(stored.astype(np.float64)).astype(np.float32) if stored is not None else None
    return _prefer_stored(derived, stored, check, np.abs(scales), LOG_SCALES, notes)


def _prefer_stored(derived, stored, stored_linear, linear, name, notes):
    if stored is None:
        return derived
    if stored.shape != derived.shape:
        notes.append(f"{name} has shape {stored.shape}, expected {derived.shape}; ignored")
        return derived
    # Where the schema value was edited elsewhere, the stored exact value is stale: use the schema's.
    ok = _within_one_ulp(stored_linear, linear)
    if ok.ndim > 1:
        ok = ok.all(axis=1, keepdims=True)
    if not ok.all():
        notes.append(f"{name}: {int((~ok).sum())} entries no longer match the schema values; re-derived")
    return np.where(ok, stored, derived).astype(np.float32)


def _within_one_ulp(a, b):
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    return (np.abs(a.astype(np.float64) - b) <= np.spacing(np.maximum(np.abs(a), np.abs(b)))) | (a == b)


def _gaussian_cloud(prim, time, notes):
    """A ParticleField3DGaussianSplat prim's particles in its local space."""
    positions = _float_or_half(prim, "positions", time, (3,))
    positions = np.zeros((0, 3), np.float32) if positions is None else positions
    n = len(positions)
    quats = _fit(_float_or_half(prim, "orientations", time, (4,)), n, (4,), "orientations", "identity", notes)
    scales = _fit(_float_or_half(prim, "scales", time, (3,)), n, (3,), "scales", "1", notes)
    opacities = _fit(_float_or_half(prim, "opacities", time, ()), n, (), "opacities", "1 (opaque)", notes)
    sh = _sh_from(prim, _float_or_half(prim, SH_COEFFS, time, (3,)), _sh_degree(prim), n, notes)
    stored_logits = _fit(_value(prim, LOGITS, time), n, (), LOGITS, "-", []) if opacities is not None else None
    stored_logs = _fit(_value(prim, LOG_SCALES, time, (3,)), n, (3,), LOG_SCALES, "-", []) \
        if scales is not None else None
    rotations = np.tile(np.float32([1, 0, 0, 0]), (n, 1)) if quats is None else quats[:, [3, 0, 1, 2]]
    if quats is not None:
        rotations = _rotations_from(rotations, _fit(_value(prim, RAW_ROTATIONS, time, (4,)), n, (4,),
                                                    RAW_ROTATIONS, "-", []), notes)
    opacities = np.ones(n, np.float32) if opacities is None else _valid_opacities(opacities, notes)
    scales = np.ones((n, 3), np.float32) if scales is None else scales
    logits = _logits_from(opacities, stored_logits, notes)
    log_scales = _log_scales_from(scales, stored_logs, notes)
    marked = prim.GetAttribute(ANTIALIASED)
    cloud = SplatCloud(positions, rotations, log_scales, logits, sh, _extras(prim, time, n, set(), notes),
                       antialiased=bool(marked and marked.HasAuthoredValue() and marked.Get()))
    return cloud, opacities, np.abs(scales)


def _rotations_from(orientations, stored, notes):
    """The stored raw quaternions where they still normalise to the schema's orientations (up to
    float32 round-off, either sign), else the orientations."""
    if stored is None:
        return orientations
    unit = _unit_quaternions(stored)
    ok = (np.abs(unit - orientations).max(axis=1) <= 1e-6) | (np.abs(unit + orientations).max(axis=1) <= 1e-6)
    if not ok.all():
        notes.append(f"{RAW_ROTATIONS}: {int((~ok).sum())} entries no longer match the orientations; re-derived")
    return np.where(ok[:, None], stored, orientations).astype(np.float32)


def _unit_quaternions(q):
    """float32 unit quaternions; ones already unit to float32 round-off are kept as they are, so a
    file's normalised values come back unchanged."""
    q = np.asarray(q, np.float32)
    norm = np.linalg.norm(q.astype(np.float64), axis=-1, keepdims=True)
    unit = geometry.normalize_quaternions(q).astype(np.float32)
    return np.where(np.abs(norm - 1) <= 2.5e-7, q, unit)


def _sh_degree(prim):
    """The authored SH degree, None if unauthored, or a SplatFileError if it is no int >= 0."""
    attr = prim.GetAttribute(SH_DEGREE)
    if not attr or not attr.HasAuthoredValue():
        return None
    degree = attr.Get()
    if not isinstance(degree, int) or isinstance(degree, bool) or degree < 0:
        raise SplatFileError(_file(prim), f"{prim.GetPath()}: {SH_DEGREE} is {degree!r}, expected an int >= 0")
    return degree


def _is_adobe_splat(prim):
    pv = _primvars(prim)
    return _is_points(prim) and all(pv.HasPrimvar(n) for n in ("rot", "widths1", "widths2"))


def _is_blender_splat(prim):
    pv = _primvars(prim)
    return _is_points(prim) and pv.HasPrimvar("rotation") and pv.HasPrimvar("scale")


def _blender_cloud(prim, time, notes):
    """UsdGeomPoints as Blender's USD export writes splat point clouds: `points`, primvars `rotation`
    (w, x, y, z; a quatf[] is read by its own order), `scale` linear, `radiance:base` (DC rgb and
    the activated opacity) and `radiance:sh_0..14`, or `..23` for degree 4 as Blender 5.3 writes (the
    higher coefficients in 3DGS order)."""
    positions = _value(prim, "points", time, (3,))
    positions = np.zeros((0, 3), np.float32) if positions is None else positions.astype(np.float32)
    n = len(positions)
    rotation = _primvars(prim).GetPrimvar("rotation")
    quats = _fit(_primvar(prim, "rotation", time, (4,)), n, (4,), "primvars:rotation", "identity", notes)
    if quats is None:
        rotations = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
    elif usda.is_quaternion(rotation.GetTypeName()):
        rotations = quats[:, [3, 0, 1, 2]].astype(np.float32)          # Vt quaternions are x, y, z, w in memory
    else:
        rotations = quats.astype(np.float32)
    scales = _fit(_primvar(prim, "scale", time, (3,)), n, (3,), "primvars:scale", "1", notes)
    scales = np.ones((n, 3), np.float32) if scales is None else scales.astype(np.float32)
    base = _fit(_primvar(prim, BLENDER_BASE, time, (4,)), n, (4,), f"primvars:{BLENDER_BASE}", "displayColor", notes)
    if base is not None:
        dc, opacities = base[:, :3].astype(np.float32), base[:, 3].astype(np.float32)
    else:
        colors = _fit(_primvar(prim, "displayColor", time, (3,)), n, (3,), "primvars:displayColor", "grey", [])
        dc = np.zeros((n, 3), np.float32) if colors is None else shmod.rgb_to_dc(colors).astype(np.float32)
        opacities = _fit(_primvar(prim, "displayOpacity", time), n, (), "primvars:displayOpacity", "1", [])
        opacities = np.ones(n, np.float32) if opacities is None else opacities.astype(np.float32)
    rest = []
    while len(rest) < REST_COUNTS[-1] and (value := _primvar(prim, f"radiance:sh_{len(rest)}", time, (3,))) is not None:
        rest.append(value.astype(np.float32))
    if len(rest) not in REST_COUNTS or any(len(v) != n for v in rest):
        notes.append(f"{len(rest)} radiance:sh_* primvars (or wrong lengths); view-dependent colour dropped")
        rest = []
    sh = np.concatenate([dc[:, None, :]] + [v[:, None, :] for v in rest], axis=1)
    cloud = SplatCloud(positions, rotations, _log_scales_from(scales, None, notes),
                       _logits_from(_valid_opacities(opacities, notes), None, notes), sh,
                       _extras(prim, time, n, BLENDER_PRIMVARS, notes))
    return cloud, opacities, np.abs(scales)


def _primvar(prim, name, time, shape=()):
    pv = _primvars(prim).GetPrimvar(name)
    if not pv or not pv.HasAuthoredValue():
        return None
    value = pv.ComputeFlattened(time)
    return None if value is None else _numbers(prim, f"primvars:{name}", value, shape)


def _adobe_cloud(prim, time, notes):
    """UsdGeomPoints with Adobe's 3DGS primvars, in the prim's local space."""
    positions = _value(prim, "points", time, (3,))
    positions = np.zeros((0, 3), np.float32) if positions is None else positions.astype(np.float32)
    n = len(positions)
    widths = [_value(prim, "widths", time), _primvar(prim, "widths1", time), _primvar(prim, "widths2", time)]
    # a single width is constant interpolation: one value for every point
    widths = [None if w is None else (np.full(n, w[0], np.float32) if len(w) == 1 else w) for w in widths]
    per_axis = [_fit(w, n, (), f"widths axis {i}", "2 (sigma 1)", notes) for i, w in enumerate(widths)]
    scales = np.stack([np.ones(n, np.float32) if a is None else a / np.float32(2) for a in per_axis], axis=1)
    quats = _fit(_primvar(prim, "rot", time, (4,)), n, (4,), "primvars:rot", "identity", notes)
    rotations = np.tile(np.float32([1, 0, 0, 0]), (n, 1)) if quats is None else quats[:, [3, 0, 1, 2]]
    opacities = _fit(_primvar(prim, "displayOpacity", time), n, (), "primvars:displayOpacity", "1", notes)
    opacities = np.ones(n, np.float32) if opacities is None else _valid_opacities(opacities.astype(np.float32), notes)
    colors = _fit(_primvar(prim, "displayColor", time, (3,)), n, (3,), "primvars:displayColor", "grey", notes)
    dc = np.zeros((n, 3)) if colors is None else shmod.rgb_to_dc(colors)
    rest = _adobe_rest(prim, time, n, notes)
    sh = np.concatenate([dc[:, None, :], rest], axis=1)
    clip = _primvar(prim, "clipping", time, (3,))
    if clip is not None:
        notes.append(f"primvars:clipping box {clip.reshape(-1, 3).tolist()} not applied")
    taken = ADOBE_PRIMVARS | {f"fRest{i}" for i in range(3 * REST_COUNTS[-1])}
    cloud = SplatCloud(positions, rotations, _log_scales_from(scales, None, notes),
                       _logits_from(opacities, None, notes), sh, _extras(prim, time, n, taken, notes))
    return cloud, opacities, np.abs(scales)


def _adobe_rest(prim, time, n, notes):
    """(n, K-1, 3) higher-order SH from fRest0.., channel-major: fRest[c*(K-1) + j]."""
    found = []
    while (value := _primvar(prim, f"fRest{len(found)}", time)) is not None and len(found) < 3 * REST_COUNTS[-1]:
        found.append(value)
    if len(found) not in [3 * k for k in REST_COUNTS] or any(len(v) != n for v in found):
        notes.append(f"{len(found)} fRest primvars (or wrong lengths); view-dependent colour dropped")
        found = []
    k1 = len(found) // 3
    if not k1:
        return np.zeros((n, 0, 3), np.float32)
    return np.stack(found, axis=1).reshape(n, 3, k1).transpose(0, 2, 1).astype(np.float32)


def _extras(prim, time, n, taken, notes):
    """Per-particle primvars (vertex/varying, length n * elementSize) as extras."""
    extras = {}
    for pv in _primvars(prim).GetPrimvarsWithAuthoredValues():
        name = pv.GetPrimvarName()
        if name in taken or name in ("displayColor", "displayOpacity"):
            continue
        if pv.GetInterpolation() not in ("vertex", "varying"):
            continue
        value = pv.ComputeFlattened(time)
        if value is None:
            continue
        values = np.asarray(value)
        size = max(pv.GetElementSize(), 1)
        if values.dtype == object or values.ndim > 1 or len(values) != n * size:
            notes.append(f"primvar {name} is not one {size}-value entry per particle; not kept")
            continue
        values = _narrowed(values, pv.GetAttr().GetCustomDataByKey(DTYPE_KEY), name, notes)
        extras[str(name)] = values.reshape(n, size) if size > 1 else values
    return extras


def _narrowed(values, dtype, name, notes):
    """An int primvar back in the narrow integer dtype the writer widened it from (its custom
    data), when every value fits that dtype."""
    if dtype is None:
        return values
    if isinstance(dtype, str) and dtype in NARROW_INTS and values.dtype == np.int32:
        narrow = values.astype(dtype)
        if np.array_equal(narrow, values):
            return narrow
    notes.append(f"primvar {name}: {DTYPE_KEY} {dtype!r} does not fit its {values.dtype} values; ignored")
    return values


def _op_order(prim):
    """The prim's xformOpOrder as a list of op names ([] if unauthored), or a SplatFileError when it
    holds anything else (a damaged crate file can point it at any value)."""
    attr = prim.GetAttribute("xformOpOrder")
    order = attr.Get() if attr else None
    if order is None:
        return []
    names = list(order) if not isinstance(order, str) and hasattr(order, "__iter__") else None
    if names is None or not all(isinstance(n, str) for n in names):
        raise SplatFileError(_file(prim), f"{prim.GetPath()}: xformOpOrder holds a {type(order).__name__}, "
                                          "not a list of transform op names")
    return names


def _is_upright(prim):
    """Whether the prim stands a capture upright with our transform op."""
    return UPRIGHT_OP in _op_order(prim)


def _nonfinite_ops(prim, time):
    """Names of the prim's own transform ops whose values hold NaN or Inf."""
    names = [n.removeprefix("!invert!") for n in _op_order(prim)]
    bad = []
    for name in names:
        attr = prim.GetAttribute(name)
        value = attr.Get(time) if attr else None
        if hasattr(value, "GetImaginary"):          # a Gf quaternion
            value = [value.GetReal(), *value.GetImaginary()]
        try:
            numbers = np.asarray(value, np.float64)
        except (TypeError, ValueError):
            continue
        if not np.isfinite(numbers).all():
            bad.append(name)
    return bad


def _read_prim(prim, time, matrices, notes):
    """SplatPrim for a splat prim, or None for any other prim. matrices: (stage, capture) 4x4s taking
    world space to the target axes and units: stage-axes geometry, and the captures of prims that
    carry no upright transform (unmarked="capture")."""
    stage_m, capture_m = matrices
    if prim.GetTypeName() == TYPE_NAME:
        source, reader = TYPE_NAME, _gaussian_cloud
        if not _is_upright(prim):
            stage_m = capture_m
    elif _is_adobe_splat(prim):
        source, reader = "Points (Adobe 3DGS primvars)", _adobe_cloud
    elif _is_blender_splat(prim):
        source, reader = "Points (Blender splat primvars)", _blender_cloud
    else:
        return None
    prim_notes = []
    cloud, opacities, scales = reader(prim, time, prim_notes)
    to_world = stage_m @ _world_matrix(prim, time)
    if not np.isfinite(to_world).all():
        ops = _nonfinite_ops(prim, time)
        where = f"its transform ops {', '.join(ops)} hold" if ops else "a parent prim's transform holds"
        raise SplatFileError(_file(prim), f"{prim.GetPath()}: {where} NaN or Inf")
    anisotropy = 0.0
    if np.array_equal(to_world, np.eye(4)) or np.array_equal(to_world, FLIP):
        cloud = cloud if to_world[1, 1] == 1 else flip_yz(cloud)       # exact: only signs change
        _READ_LINEAR[cloud] = (cloud.opacity_logits.copy(), opacities, cloud.log_scales.copy(), scales)
    else:
        try:
            anisotropy = float(geometry.anisotropy(to_world[:3, :3]))
            cloud = cloud.transformed(to_world)
        except ValueError as exc:
            raise SplatFileError(_file(prim),
                                 f"{prim.GetPath()}: cannot apply its transform: {exc}") from None
        if anisotropy > ANISOTROPY_TOLERANCE:
            angle = np.degrees(np.arctan(anisotropy / (2 * np.sqrt(1 + anisotropy))))
            prim_notes.append(f"its transform stretches unevenly (anisotropy {anisotropy:.3g}): positions "
                              "and covariances are exact, SH colours follow its nearest rotation only "
                              f"(view directions off by up to {angle:.3g} degrees)")
    notes += [f"{prim.GetPath()}: {text}" for text in prim_notes]
    return SplatPrim(str(prim.GetPath()), cloud, source, to_world, anisotropy, prim_notes)


def _splat_prims(stage, time, axes, meters_per_unit, notes, unmarked="capture"):
    if unmarked not in UNMARKED:
        raise ValueError(f"unmarked must be one of {UNMARKED}, got {unmarked!r}")
    stage_m = stage_matrix(stage, axes, meters_per_unit, notes)
    capture_m = stage_m
    if unmarked == "capture":       # values are capture coordinates already: only units (and RUB) apply
        capture_m = stage_matrix(stage, None, meters_per_unit, [])
        if axes == "RUB":
            capture_m = FLIP @ capture_m
    found, skipped = [], {}
    for prim in _traverse(stage):
        got = _read_prim(prim, time, (stage_m, capture_m), notes)
        if got is not None:
            found.append(got)
        elif _is_geometry(prim) or prim.GetTypeName().startswith("ParticleField"):
            skipped.setdefault(str(prim.GetTypeName()), []).append(str(prim.GetPath()))
    if skipped:
        listed = "; ".join(f"{t} x{len(p)} ({', '.join(p[:3])}{', ...' if len(p) > 3 else ''})"
                           for t, p in sorted(skipped.items()))
        notes.append(f"skipped prims that are not splats: {listed}")
    return found


def _warn(path, notes):
    if notes:
        warnings.warn(f"{path}: " + "; ".join(notes), SplatFileWarning, stacklevel=3)


# public reading -----------------------------------------------------------------------------------

def read_stage(path, time=None, axes="RDF", meters_per_unit=1.0, nonfinite="raise", unmarked="capture",
               allow_outside=False):
    """Every splat prim of a stage as a SplatPrim (path, world-space cloud, transform, notes).

    time: a time code (default: the earliest sample, or the default value of unanimated files).
    unmarked: how to take a ParticleField3DGaussianSplat without our upright transform (NVIDIA's
    and OpenUSD's converters copy PLY coordinates into a Y-up stage unchanged): "capture" takes its
    values as capture (3DGS PLY) coordinates, giving back the PLY's values; "stage" takes them in the
    stage's own axes like any geometry (for files authored truly Y-up).
    allow_outside: also compose sublayers, references and payloads from outside the stage's package
    (.usdz) or folder; by default they are refused, and missing ones are an error either way.
    """
    with _pxr_errors(path):
        return _read_stage(_open(path, allow_outside), path, time, axes, meters_per_unit, nonfinite, unmarked)


def _read_stage(stage, path, time, axes, meters_per_unit, nonfinite, unmarked="capture"):
    notes = []
    prims = _splat_prims(stage, _time(stage, time), axes, meters_per_unit, notes, unmarked)
    for p in prims:
        p.cloud = apply_nonfinite_policy(f"{path}:{p.path}", p.cloud, nonfinite, "read")
    _warn(path, notes)
    return prims


def read(path, time=None, axes="RDF", meters_per_unit=1.0, nonfinite="raise", unmarked="capture",
         allow_outside=False):
    """All splat prims of the stage, in world space, concatenated into one SplatCloud (unmarked and
    allow_outside: see read_stage)."""
    prims = read_stage(path, time, axes, meters_per_unit, nonfinite, unmarked, allow_outside)
    if not prims:
        raise SplatFileError(path, f"no {TYPE_NAME} prims (nor UsdGeomPoints with 3DGS primvars) on the stage")
    if len(prims) == 1:
        return prims[0].cloud
    clouds = [p.cloud for p in prims]
    cloud = SplatCloud.concatenate(clouds)
    remembered = [_READ_LINEAR.get(c) for c in clouds]
    if all(r is not None for r in remembered):
        _READ_LINEAR[cloud] = tuple(np.concatenate(parts) for parts in zip(*remembered))
    return cloud


def time_codes(path, prim_path=None, allow_outside=False):
    """Sorted time codes at which the splat prims (or one of them) have samples; [] if unanimated."""
    with _pxr_errors(path):
        return _time_codes(_open(path, allow_outside), path, prim_path)


def _time_codes(stage, path, prim_path):
    if prim_path:
        prims = [stage.GetPrimAtPath(prim_path)]
        if not prims[0]:
            raise SplatFileError(path, f"no prim at {prim_path}")
    else:
        prims = [p for p in _traverse(stage)
                 if p.GetTypeName() == TYPE_NAME or _is_adobe_splat(p) or _is_blender_splat(p)]
    times = set()
    for prim in prims:
        for attr in prim.GetAttributes():        # transform ops included: a moving prim is animated too
            times.update(attr.GetTimeSamples())
    return sorted(times)


def read_frames(path, prim_path=None, axes="RDF", meters_per_unit=1.0, nonfinite="raise", unmarked="capture",
                allow_outside=False):
    """[(time code, cloud)] for every time sample of the stage's splat prims (concatenated per time),
    or of the one at prim_path; one (None, cloud) entry for an unanimated file."""
    with _pxr_errors(path):
        return _read_frames(_open(path, allow_outside), path, prim_path, axes, meters_per_unit, nonfinite, unmarked)


def _read_frames(stage, path, prim_path, axes, meters_per_unit, nonfinite, unmarked):
    frames = []
    for t in _time_codes(stage, path, prim_path) or [None]:
        prims = _read_stage(stage, path, t, axes, meters_per_unit, nonfinite, unmarked)
        if prim_path:
            prims = [p for p in prims if p.path == prim_path]
        if not prims:
            raise SplatFileError(path, f"no splat prim at {prim_path}" if prim_path else "no splat prims")
        frames.append((t, SplatCloud.concatenate([p.cloud for p in prims]) if len(prims) > 1 else prims[0].cloud))
    return frames


# writing ------------------------------------------------------------------------------------------

EXTENT_PAD = 1e-12         # relative: covers float64 round-off in the half widths below
EXTENT_CHUNK = 1 << 15     # splats per block: a block's temporaries stay in cache


def _extent_block(positions, rotations, scales, opacities):
    """(lo, hi) float64 corners of one block of splats (+-inf where none is finite)."""
    # Half width along axis i: reach * sqrt(sum_j (R_ij s_j)^2). With the unnormalised rotation
    # matrix M = |q|^2 R (entries quadratic in q) that is sqrt(sum_j (M_ij s_j)^2) / |q|^2, so no
    # normalisation pass; q is first divided by its largest component so no square under- or
    # overflows, and everything runs on contiguous columns, which NumPy streams fastest.
    q = np.ascontiguousarray(rotations.T, dtype=np.float64)
    big = np.abs(q).max(axis=0)
    unit = big > 0                                            # a zero quaternion means the identity
    w, x, y, z = q / np.where(unit, big, 1)
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    m = [(ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)),
         (2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)),
         (2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz)]
    sx, sy, sz = np.ascontiguousarray(scales.T, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        reach = np.sqrt(2 * np.log(np.maximum(255 * opacities.astype(np.float64), 1)))
        reach *= (1 + EXTENT_PAD) / np.where(unit, ww + xx + yy + zz, 1)
        lo, hi, ok = [], [], np.ones(len(w), bool)
        for i, (a, b, c) in enumerate(m):
            if not unit.all():
                a, b, c = (np.where(unit, v, e) for v, e in zip((a, b, c), np.eye(3)[i]))
            half = reach * np.sqrt((a * sx) ** 2 + (b * sy) ** 2 + (c * sz) ** 2)
            p = positions[:, i].astype(np.float64)
            lo.append(p - half)
            hi.append(p + half)
            ok &= np.isfinite(lo[-1]) & np.isfinite(hi[-1])
    if not ok.all():
        lo, hi = [np.where(ok, v, np.inf) for v in lo], [np.where(ok, v, -np.inf) for v in hi]
    return np.array([v.min() for v in lo]), np.array([v.max() for v in hi])


def alpha_extent(positions, rotations, scales, opacities):
    """(2,3) float32 box holding every splat out to where its alpha falls below 1/255 (rounded
    outwards), or None when no splat is finite. rotations w,x,y,z; scales and opacities linear."""
    corners = [_extent_block(*(v[a:a + EXTENT_CHUNK] for v in (positions, rotations, scales, opacities)))
               for a in range(0, len(positions), EXTENT_CHUNK)]
    if not corners:
        return None
    lo, hi = np.min([c[0] for c in corners], axis=0), np.max([c[1] for c in corners], axis=0)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return None
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return np.stack([lo32, hi32])


def _linear_values(cloud):
    """float32 (opacities, scales) to write: the values read from a file where the cloud still holds
    exactly what was read from them, else sigmoid/exp of the model's values."""
    opacities = sigmoid(cloud.opacity_logits).astype(np.float32)
    with np.errstate(over="ignore"):
        scales = np.exp(cloud.log_scales.astype(np.float64)).astype(np.float32)
    read_back = _READ_LINEAR.get(cloud)
    if read_back is not None:
        logits, read_o, logs, read_s = read_back
        if logits.shape == cloud.opacity_logits.shape:
            opacities = np.where(logits == cloud.opacity_logits, read_o, opacities)
            same = (logs == cloud.log_scales).all(axis=1, keepdims=True)
            scales = np.where(same, read_s, scales)
    return opacities, scales


def _vt_filled(cls, length, shape, dtype, fill):
    """A new Vt array (cls, e.g. Vt.Vec3fArray) of `length` elements, filled by fill(ndarray).

    cls.FromNumpy converts element by element and needs a finished NumPy copy first; for 16M SH
    triples that costs more than the whole file write. A fresh Vt array owns its storage alone, so
    we let NumPy write straight into it. Falls back to FromNumpy if the storage is not laid out
    exactly as expected.
    """
    out = cls(length)
    view = np.asarray(out)
    if view.shape != shape or view.dtype != dtype or not view.flags.c_contiguous or not view.size:
        data = np.empty(shape, dtype)
        fill(data)
        return cls.FromNumpy(data)
    raw = (ctypes.c_char * view.nbytes).from_address(view.ctypes.data)
    fill(np.frombuffer(raw, dtype).reshape(shape))
    return out


def _filled(kind, shape, dtype, fill):
    """An array of Vt type `kind` ("Vec3fArray" ...) filled by fill(ndarray): a Vt array, or a NumPy
    one where pxr is missing (the text layer formats NumPy arrays itself)."""
    if Usd is None:
        out = np.empty(shape, dtype)
        fill(out)
        return out
    return _vt_filled(getattr(Vt, kind), shape[0], shape, dtype, fill)


def _vt(kind, values):
    """An array of Vt type `kind` holding a copy of `values`."""
    values = np.asarray(values)
    return _filled(kind, values.shape, values.dtype, lambda out: np.copyto(out, values))


def _half(path, name, values):
    """`values` as float16, or a SplatFileError when finite values would overflow to infinity."""
    _check_half_range(path, name, values)
    return values.astype(np.float16)


def _check_half_range(path, name, values):
    big = np.isfinite(values) & (np.abs(values) > np.finfo(np.float16).max)
    if big.any():
        raise SplatFileError(path, f"{int(big.sum())} {name} values exceed the half-float range "
                                   "(65504); write without half=True")


@dataclass(frozen=True)
class _WriteOptions:
    """How write_stage stores values (its arguments of the same names)."""
    half: bool = False
    half_positions: bool = False
    exact: bool = True
    axes: str = "RDF"
    nonfinite: str = "raise"
    layout: str = "upright"


def _frame_values(path, cloud, options):
    """{attribute name: Vt array} for one cloud."""
    half, half_positions, exact, axes = options.half, options.half_positions, options.exact, options.axes
    n, k = len(cloud), cloud.sh.shape[1]
    opacities, scales = _linear_values(cloud)
    # The values are the capture's (3DGS PLY) coordinates, as the reference converters write them,
    # unless the layout asks for them flipped into the Y-up stage (folded into the copies Vt needs).
    flip = axes == "RDF" and options.layout == "y-up"
    positions = cloud.positions * np.float32([1, -1, -1]) if flip else np.ascontiguousarray(cloud.positions)
    xyzw = _unit_quaternions(cloud.rotations)[:, [1, 2, 3, 0]]                # Vt's memory order
    xyzw = xyzw * np.float32([1, -1, -1, 1]) if flip else xyzw
    signs = np.repeat(SH_FLIP[:k], 3) if flip else np.ones(3 * k, np.float32)
    flat = cloud.sh.reshape(n, 3 * k)                                       # (N, K*3): fast broadcast
    if half:                   # the extent below is taken from the values as stored
        _check_half_range(path, "SH", flat)
        xyzw, scales, opacities = (_half(path, name, v) for name, v in
                                   (("rotation", xyzw), ("scale", scales), ("opacity", opacities)))
        values = {"orientationsh": _vt("QuathArray", xyzw),
                  "scalesh": _vt("Vec3hArray", scales),
                  "opacitiesh": _vt("HalfArray", opacities),
                  SH_COEFFS + "h": _filled("Vec3hArray", (n * k, 3), np.float16,
                                              lambda out: np.multiply(flat, signs, out=out.reshape(n, 3 * k),
                                                                      casting="same_kind"))}
    else:
        values = {"orientations": _vt("QuatfArray", xyzw),
                  "scales": _vt("Vec3fArray", scales),
                  "opacities": _vt("FloatArray", opacities),
                  SH_COEFFS: _filled("Vec3fArray", (n * k, 3), np.float32,
                                        lambda out: np.multiply(flat, signs, out=out.reshape(n, 3 * k)))}
    if half_positions:
        positions = _half(path, "position", positions)
        values["positionsh"] = _vt("Vec3hArray", positions)
    else:
        values["positions"] = _vt("Vec3fArray", positions)
    if exact and not half:
        values[LOGITS] = _vt("FloatArray", cloud.opacity_logits)
        values[LOG_SCALES] = _vt("Vec3fArray", np.ascontiguousarray(cloud.log_scales))
        raw = cloud.rotations * np.float32([1, 1, -1, -1]) if flip else cloud.rotations
        values[RAW_ROTATIONS] = _vt("Vec4fArray", np.ascontiguousarray(raw))
    box = alpha_extent(positions, xyzw[:, [3, 0, 1, 2]], scales, opacities)
    if box is not None:
        values["extent"] = _vt("Vec3fArray", box)
    return values


def data_size(count, sh_degree, half=False, exact=True):
    """Bytes of the arrays write() authors for `count` splats of `sh_degree` (the attributes of
    _frame_values: positions, orientations, scales, opacities and SH, half floats with `half`, and
    with `exact` the model's own logits, log scales and rotations; the extent). A crate file holds
    them raw plus about a kilobyte of structure (less where OpenUSD compresses constant arrays); a
    text layer takes about 10 bytes per number instead of 4."""
    k = (sh_degree + 1) ** 2
    width = 2 if half else 4
    numbers = 4 + 3 + 1 + 3 * k                       # orientation, scale, opacity, SH
    raw = 1 + 3 + 4 if exact and not half else 0      # logits, log scales, raw rotations (float32)
    return count * (3 * 4 + numbers * width + raw * 4) + 2 * 3 * 4


def _schema_class():
    return getattr(UsdVol, TYPE_NAME, None) if UsdVol is not None else None


def _define_splat_prim(stage, prim_path):
    if Usd is None:
        return stage.define(prim_path, TYPE_NAME)
    schema = _schema_class()
    if schema is not None:
        return schema.Define(stage, prim_path).GetPrim()
    return stage.DefinePrim(prim_path, TYPE_NAME)


def _attribute(prim, name):
    """The attribute `name`, created through the schema class when pxr has it, else by name."""
    if Usd is None:
        type_name, uniform = (CUSTOM[name], False) if name in CUSTOM else SCHEMA[name][:2]
        return prim.attribute(name, type_name, uniform, custom=name in CUSTOM)
    if name in CUSTOM:
        return prim.CreateAttribute(name, Sdf.ValueTypeNames.Find(CUSTOM[name]), True)
    type_name, uniform, creator = SCHEMA[name]
    schema = _schema_class()
    if schema is not None:
        return getattr(schema(prim), creator)()
    variability = Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying
    return prim.CreateAttribute(name, Sdf.ValueTypeNames.Find(type_name), False, variability)


def _extra_primvars(path, prim, cloud):
    """[(attribute, extra name, widen to int32?)] authoring each extra as a vertex primvar."""
    out = []
    for key, values in cloud.extras.items():
        type_name = EXTRA_TYPES.get(values.dtype.name)
        if type_name is None or not usda.VALID_NAMESPACED.fullmatch(key):
            raise SplatFileError(path, f"extra '{key}' ({values.dtype}) cannot be a USD primvar: it needs a "
                                       f"valid identifier and one of the dtypes {sorted(EXTRA_TYPES)}")
        size = int(np.prod(values.shape[1:])) if values.ndim > 1 else -1
        attr = _vertex_primvar(prim, key, type_name + "[]", size)
        widen = type_name == "int" and values.dtype != np.int32
        if widen and Usd is None:
            attr.metadata["customData"] = {"splatwright": {"dtype": values.dtype.name}}   # DTYPE_KEY nested
        elif widen:
            attr.SetCustomDataByKey(DTYPE_KEY, values.dtype.name)
        out.append((attr, key, widen))
    return out


def _vertex_primvar(prim, name, type_name, element_size):
    """The attribute of a new vertex-interpolated primvar (element_size -1: left unauthored)."""
    if Usd is None:
        attr = prim.attribute(f"primvars:{name}", type_name)
        attr.metadata["interpolation"] = "vertex"
        if element_size > 0:
            attr.metadata["elementSize"] = element_size
        return attr
    pv = UsdGeom.PrimvarsAPI(prim).CreatePrimvar(name, Sdf.ValueTypeNames.Find(type_name), UsdGeom.Tokens.vertex,
                                                 element_size)
    return pv.GetAttr()


VT_ARRAYS = {"float32": "FloatArray", "float64": "DoubleArray", "float16": "HalfArray", "int32": "IntArray",
             "uint32": "UIntArray", "int64": "Int64Array", "uint64": "UInt64Array", "uint8": "UCharArray",
             "bool": "BoolArray"}


def _author_prim(path, stage, prim_path, frames, times, options):
    """Author one prim from its frames (a cloud, or clouds one per time code), consumed one at a
    time so only the stage holds them; returns the time codes used ([] for a static prim)."""
    prim, samples, codes, shape = None, {}, [], None
    for cloud, code in _checked_frames(path, prim_path, frames, times, options):
        shape = (len(cloud), cloud.sh.shape[1])
        if prim is None:                     # the first frame sets the prim up
            prim = _define_splat_prim(stage, prim_path)
            _attribute(prim, SH_DEGREE).Set(cloud.sh_degree)
            if cloud.antialiased:
                _attribute(prim, ANTIALIASED).Set(True)
            if options.layout == "upright" and options.axes == "RDF":
                _upright_op(prim)
            extras = _extra_primvars(path, prim, cloud)
        values = {**_frame_values(path, cloud, options), **_extra_values(cloud, extras)}
        for name, value in values.items():
            if name not in samples:
                samples[name] = _Samples(prim.GetAttribute(name) or _attribute(prim, name), name != "positions")
            samples[name].add(value, code)
        codes.append(code)
        del cloud, values                    # let this frame go before the next one is made
    for attr in samples.values():
        attr.finish()
    for name in (SH_COEFFS, SH_COEFFS + "h"):   # one particle's coefficients per element, as primvars say
        if name in samples:
            attr = samples[name].attr
            if Usd is None:
                attr.metadata.update(interpolation="vertex", elementSize=shape[1])
            else:
                UsdGeom.Primvar(attr).SetInterpolation(UsdGeom.Tokens.vertex)
                UsdGeom.Primvar(attr).SetElementSize(shape[1])
    return [c for c in codes if c is not None]


def _upright_op(prim):
    """The transform standing a capture (y down, z forward) upright in the Y-up stage: a half turn
    about X, authored as an exact matrix op named for what it does."""
    if Usd is None:
        prim.attribute(UPRIGHT_OP, "matrix4d").Set(UPRIGHT.T.copy())
        prim.attribute("xformOpOrder", "token[]", uniform=True).Set([UPRIGHT_OP])
        return
    op = prim.CreateAttribute(UPRIGHT_OP, Sdf.ValueTypeNames.Matrix4d, False)
    op.Set(Gf.Matrix4d(*UPRIGHT.T.reshape(-1).tolist()))
    prim.CreateAttribute("xformOpOrder", Sdf.ValueTypeNames.TokenArray, False,
                         Sdf.VariabilityUniform).Set([UPRIGHT_OP])


def _extra_values(cloud, extras):
    """{primvar attribute name: Vt array} of a cloud's extras (see _extra_primvars)."""
    values = {}
    for attr, key, widen in extras:
        flat = np.ascontiguousarray(cloud.extras[key].reshape(-1))
        flat = flat.astype(np.int32) if widen else flat
        values[attr.GetName()] = _vt(VT_ARRAYS[flat.dtype.name], flat)
    return values


class _Samples:
    """One attribute's values over the frames. With `hold`, a value the same in every frame (an
    opacity that is never animated, say) is authored once, not once per frame."""

    def __init__(self, attr, hold):
        self.attr, self.held, self.first, self.waiting = attr, hold, None, []

    def add(self, value, code):
        if self.held:
            if self.first is None:
                self.first = value
            if value is self.first or _same_bytes(value, self.first):
                self.waiting.append(code)
                return
            self.held = False                # the first change: the frames so far get samples
            for earlier in self.waiting:
                self.set(self.first, earlier)
        self.set(value, code)

    def set(self, value, code):
        """Author `value` at time code `code` (None: the default value)."""
        if code is None:
            self.attr.Set(value)
        else:
            self.attr.Set(value, code if Usd is None else Usd.TimeCode(code))

    def finish(self):
        if self.held:
            self.attr.Set(self.first)


def _same_bytes(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.array_equal(a.reshape(-1).view(np.uint8), b.reshape(-1).view(np.uint8))


def _checked_frames(path, prim_path, frames, times, options):
    """(cloud, time code) pairs, each cloud checked as it comes: the same splat count, SH degree and
    extras in every frame, one time code per cloud, the non-finite policy applied."""
    if isinstance(frames, SplatCloud):
        frames, codes = [frames], iter([None])                     # None: the default value
    else:
        codes = (float(t) for t in (itertools.count() if times is None else times))
    shape, count = None, 0
    for cloud in frames:
        code = next(codes, "none left")
        if code == "none left":
            raise SplatFileError(path, f"{prim_path}: more clouds than time codes ({count})")
        cloud = apply_nonfinite_policy(f"{path}:{prim_path}", cloud, options.nonfinite, "write")
        this = (len(cloud), cloud.sh_degree, tuple(sorted(cloud.extras)))
        if shape is not None and this != shape:
            raise SplatFileError(path, f"{prim_path}: time samples need the same splat count, SH degree and "
                                       f"extras in every frame; frame {count} has (count, degree, extras) "
                                       f"{this}, the first {shape}")
        shape, count = this, count + 1
        yield cloud, code
        del cloud
    if count == 0:
        raise SplatFileError(path, f"{prim_path}: no clouds to write")
    if times is not None and next(codes, "none left") != "none left":
        raise SplatFileError(path, f"{prim_path}: more time codes than clouds ({count})")


def write_stage(path, prims, times=None, half=False, half_positions=False, exact=True, axes="RDF",
                nonfinite="raise", fps=None, layout="upright"):
    """Write {prim path: cloud, or clouds one per time code} as a Y-up, metre stage.

    The clouds of an animated prim may come from any iterable (a generator, say): each is authored
    and let go before the next is asked for. An attribute that holds the same values in every frame
    is authored once rather than per frame (positions always get a sample per frame).
    times: time codes for the frames of animated prims (every sequence in `prims` must match it;
    default 0, 1, 2, ...).
    fps: time codes per second for players (OpenUSD assumes 24 when the stage does not say).
    half: orientations, scales, opacities and SH as half floats; half_positions: positions too.
    exact: also store the model's float32 logits and log scales, so reading back is exact.
    axes: "RDF" (the model's convention) or "RUB" (clouds already in Y-up axes: written as they are).
    layout, for RDF clouds: "upright" (the capture's coordinates, as the reference converters write
    them, under a prim transform standing them upright in the Y-up stage), "y-up" (values flipped
    into the Y-up stage, no transform: for viewers that ignore prim transforms) or "as-is" (the
    capture's coordinates and no transform, as NVIDIA's converter writes: upside down in Y-up viewers).
    """
    _require_pxr_for(path)
    if axes not in ("RDF", "RUB"):
        raise ValueError(f"axes must be 'RDF' or 'RUB', got {axes!r}")
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    check_nonfinite_policy(nonfinite)
    options = _WriteOptions(half, half_positions, exact, axes, nonfinite, layout)
    path = os.fspath(path)
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    if not prims:
        raise SplatFileError(path, "no prims to write")
    for prim_path in prims:
        if not PRIM_PATH.fullmatch(prim_path):
            raise SplatFileError(path, f"'{prim_path}' is not an absolute prim path")
    if times is not None:
        times = list(times)
    with atomic_path(path) as tmp:
        if Usd is None:
            _save_text_layer(path, tmp, prims, times, options, fps)
        elif path.lower().endswith(".usdz"):
            layer_path = tmp + ".layer"                 # a partial too: swept with it after a kill
            try:
                _save_stage(path, layer_path, "usdc", prims, times, options, fps)
                usda.write_usdz(tmp, os.path.splitext(os.path.basename(path))[0] + ".usdc", layer_path)
            finally:
                with contextlib.suppress(OSError):
                    os.remove(layer_path)
        else:
            _save_stage(path, tmp, os.path.splitext(path)[1][1:].lower(), prims, times, options, fps)


def _save_stage(path, layer_path, file_format, prims, times, options, fps):
    """Author the prims in a new layer of `file_format` ("usda", "usdc", "usd") saved at layer_path
    (a partial, so the format is named rather than taken from its extension)."""
    try:
        _author_stage(path, layer_path, file_format, prims, times, options, fps)
    except Tf.ErrorException as exc:
        raise SplatFileError(path, f"OpenUSD could not write it: {_tf_message(exc)}") from None


def _author_stage(path, layer_path, file_format, prims, times, options, fps):
    layer = Sdf.Layer.New(Sdf.FileFormat.FindByExtension(file_format), layer_path)
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    all_times = []
    for prim_path, frames in prims.items():
        for ancestor in Sdf.Path(prim_path).GetParentPath().GetPrefixes():
            if not stage.GetPrimAtPath(ancestor):
                stage.DefinePrim(ancestor, "Xform")
        all_times += _author_prim(path, stage, prim_path, frames, times, options)
    root = Sdf.Path(next(iter(prims))).GetPrefixes()[0]
    stage.SetDefaultPrim(stage.GetPrimAtPath(root))
    if all_times:
        stage.SetStartTimeCode(float(min(all_times)))
        stage.SetEndTimeCode(float(max(all_times)))
    if fps is not None:
        stage.SetTimeCodesPerSecond(float(fps))
        stage.SetFramesPerSecond(float(fps))
    if not layer.Save():
        raise SplatFileError(path, "OpenUSD could not save the layer")


def _save_text_layer(path, layer_path, prims, times, options, fps):
    """_save_stage without pxr: the same prims and metadata in a text layer (a .usdz of one)."""
    layer = usda.Layer(layer_path)
    layer.metadata.update(upAxis="Y", metersPerUnit=1.0)
    all_times = []
    for prim_path, frames in prims.items():
        all_times += _author_prim(path, layer, prim_path, frames, times, options)
    layer.metadata["defaultPrim"] = next(iter(prims)).split("/")[1]
    if all_times:
        layer.metadata.update(startTimeCode=float(min(all_times)), endTimeCode=float(max(all_times)))
    if fps is not None:
        layer.metadata.update(timeCodesPerSecond=float(fps), framesPerSecond=float(fps))
    layer.save(layer_path, os.path.splitext(os.path.basename(path))[0] + ".usda", usdz=path.lower().endswith(".usdz"))


def write(path, cloud, prim_path="/Splats", half=False, half_positions=False, exact=True, axes="RDF",
          nonfinite="raise", layout="upright"):
    """Write one cloud as one ParticleField3DGaussianSplat prim (options as write_stage's)."""
    if not isinstance(cloud, SplatCloud):
        raise TypeError(f"write takes one SplatCloud, got {type(cloud).__name__}; write_frames takes a sequence")
    write_stage(path, {prim_path: cloud}, None, half, half_positions, exact, axes, nonfinite, layout=layout)


def write_frames(path, clouds, times=None, prim_path="/Splats", **options):
    """Write same-count clouds (any iterable, consumed one at a time) as time samples of one prim;
    times default to 0, 1, 2, ...; options as write_stage's (fps among them)."""
    write_stage(path, {prim_path: clouds}, times, **options)