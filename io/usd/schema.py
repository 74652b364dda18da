"""The splat schema and its values, beneath everything else in io/usd: prim type names, attribute
names and types, and the conversions between a cloud's arrays and the values a prim holds.

Nothing here knows which stage implementation is in use (see stages.py). Prims are reached only
through the calls both implementations answer (GetAttribute, GetPath, GetStage ...); where a value
must become the implementation's own array type or a time sample, the implementation is passed in
(`stages`: an object with `filled` and `set_value`, see stages.Stages).
"""

import re
import weakref
from dataclasses import dataclass

import numpy as np

from ...core import geometry
from ...core import sh as shmod
from ...core.splats import logit, sigmoid
from ..common import SplatFileError, log_scales_from_linear
from ..spz import SH_FLIP

TYPE_NAME = "ParticleField3DGaussianSplat"
SH_DEGREE = "radiance:sphericalHarmonicsDegree"
SH_COEFFS = "radiance:sphericalHarmonicsCoefficients"
LOGITS = "splatwright:opacityLogits"
LOG_SCALES = "splatwright:logScales"
RAW_ROTATIONS = "splatwright:rotations"  # w, x, y, z as the model holds them (any norm)
ANTIALIASED = "splatwright:antialiased"  # authored (true) for splats made for antialiased rendering
UPRIGHT_OP = "xformOp:transform:upright"  # capture (y down, z forward) -> the Y-up stage
UPRIGHT = np.diag([1.0, -1.0, -1.0, 1.0])  # a half turn about X, exact in a matrix op
LAYOUTS = ("upright", "y-up", "as-is")
UNMARKED = ("capture", "stage")
PRIM_PATH = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
VALID_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
VALID_NAMESPACED = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(:[A-Za-z_][A-Za-z0-9_]*)*")  # a property name
ANISOTROPY_TOLERANCE = 1e-6  # below this a transform counts as rotation * uniform scale

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
EXTRA_TYPES = {
    "float32": "float",
    "float64": "double",
    "float16": "half",
    "int32": "int",
    "uint32": "uint",
    "int64": "int64",
    "uint64": "uint64",
    "uint8": "uchar",
    "bool": "bool",
    "int8": "int",
    "int16": "int",
    "uint16": "int",
}
DTYPE_KEY = "splatwright:dtype"
NARROW_INTS = {name for name, sdf in EXTRA_TYPES.items() if sdf == "int" and name != "int32"}
ADOBE_PRIMVARS = {"rot", "widths1", "widths2", "displayColor", "displayOpacity", "clipping"}
BLENDER_BASE = "radiance:base"  # Blender's point-cloud splats: DC rgb + opacity
REST_COUNTS = tuple(k - 1 for k in shmod.VALID_COUNTS)  # higher coefficients per channel: 0, 3, 8, 15, 24
BLENDER_PRIMVARS = {"rotation", "scale", BLENDER_BASE, "displayColor", "displayOpacity"} | {
    f"radiance:sh_{i}" for i in range(REST_COUNTS[-1])
}

VT_ARRAYS = {
    "float32": "FloatArray",
    "float64": "DoubleArray",
    "float16": "HalfArray",
    "int32": "IntArray",
    "uint32": "UIntArray",
    "int64": "Int64Array",
    "uint64": "UInt64Array",
    "uint8": "UCharArray",
    "bool": "BoolArray",
}

# Linear values read from a file, kept per cloud object so that writing an unchanged cloud back
# reproduces them bit for bit (the model stores logs and logits, which float32 cannot invert exactly).
_READ_LINEAR = weakref.WeakKeyDictionary()


def is_quaternion(type_name):
    """Whether a value type ("quatf[]" ...) holds quaternions: Vt keeps them x, y, z, w in memory."""
    return str(type_name).startswith("quat")


# reading values ---------------------------------------------------------------------------------


def _file(prim):
    return prim.GetStage().GetRootLayer().identifier


def _numbers(prim, name, value, shape):
    """`value` as NumPy, or a SplatFileError when it is not an array of numbers with `shape` per
    entry (strings, a single value, a float[] where the schema has point3f[] ...)."""
    values = np.asarray(value)
    if values.dtype.kind not in "iuf" or values.ndim != 1 + len(shape) or values.shape[1:] != shape:
        entries = f"{shape[0]}-component vectors" if shape else "numbers"
        raise SplatFileError(
            _file(prim),
            f"{prim.GetPath()}: {name} holds a {type(value).__name__} "
            f"({values.dtype}, shape {values.shape}), expected an array of {entries}",
        )
    return values


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
    if degree is None:  # unauthored: infer from the count, else the schema's fallback 3
        per = len(coeffs) // n if n else 16
        degree = shmod.degree_of(per) if n and len(coeffs) == n * per and per in shmod.VALID_COUNTS else 3
    k = (degree + 1) ** 2
    if len(coeffs) < n * k:
        notes.append(f"{SH_COEFFS} has {len(coeffs)} entries, {n * k} needed for degree {degree}; ignored, using grey")
        return np.zeros((n, 1, 3), np.float32)
    if len(coeffs) > n * k:
        notes.append(f"{SH_COEFFS} has {len(coeffs)} entries for {n} particles; truncated")
    sh = coeffs[: n * k].reshape(n, k, 3)
    if degree > shmod.MAX_DEGREE:
        notes.append(f"SH degree {degree} truncated to {shmod.MAX_DEGREE}")
        sh = sh[:, : shmod.num_coeffs(shmod.MAX_DEGREE)]
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
    return _prefer_stored(
        derived, stored, sigmoid(stored).astype(np.float32) if stored is not None else None, opacities, LOGITS, notes
    )


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


# writing values ---------------------------------------------------------------------------------

EXTENT_PAD = 1e-12  # relative: covers float64 round-off in the half widths below
EXTENT_CHUNK = 1 << 15  # splats per block: a block's temporaries stay in cache


def _extent_block(positions, rotations, scales, opacities):
    """(lo, hi) float64 corners of one block of splats (+-inf where none is finite)."""
    # Half width along axis i: reach * sqrt(sum_j (R_ij s_j)^2). With the unnormalised rotation
    # matrix M = |q|^2 R (entries quadratic in q) that is sqrt(sum_j (M_ij s_j)^2) / |q|^2, so no
    # normalisation pass; q is first divided by its largest component so no square under- or
    # overflows, and everything runs on contiguous columns, which NumPy streams fastest.
    q = np.ascontiguousarray(rotations.T, dtype=np.float64)
    big = np.abs(q).max(axis=0)
    unit = big > 0  # a zero quaternion means the identity
    w, x, y, z = q / np.where(unit, big, 1)
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    m = [
        (ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy)),
        (2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx)),
        (2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz),
    ]
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
    corners = [
        _extent_block(*(v[a : a + EXTENT_CHUNK] for v in (positions, rotations, scales, opacities)))
        for a in range(0, len(positions), EXTENT_CHUNK)
    ]
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


def _vt(stages, kind, values):
    """An array of Vt type `kind` ("Vec3fArray" ...) holding a copy of `values`, in the array type
    of the stage implementation `stages` (see stages.Stages.filled)."""
    values = np.asarray(values)
    return stages.filled(kind, values.shape, values.dtype, lambda out: np.copyto(out, values))


def _half(path, name, values):
    """`values` as float16, or a SplatFileError when finite values would overflow to infinity."""
    _check_half_range(path, name, values)
    return values.astype(np.float16)


def _check_half_range(path, name, values):
    big = np.isfinite(values) & (np.abs(values) > np.finfo(np.float16).max)
    if big.any():
        raise SplatFileError(
            path, f"{int(big.sum())} {name} values exceed the half-float range (65504); write without half=True"
        )


@dataclass(frozen=True)
class _WriteOptions:
    """How write_stage stores values (its arguments of the same names)."""

    half: bool = False
    half_positions: bool = False
    exact: bool = True
    axes: str = "RDF"
    nonfinite: str = "raise"
    layout: str = "upright"


def _frame_values(path, cloud, options, stages):
    """{attribute name: array} for one cloud, each in the array type of the stage implementation
    `stages` (Vt arrays for pxr, NumPy for text layers)."""
    half, half_positions, exact, axes = options.half, options.half_positions, options.exact, options.axes
    n, k = len(cloud), cloud.sh.shape[1]
    opacities, scales = _linear_values(cloud)
    # The values are the capture's (3DGS PLY) coordinates, as the reference converters write them,
    # unless the layout asks for them flipped into the Y-up stage (folded into the copies Vt needs).
    flip = axes == "RDF" and options.layout == "y-up"
    positions = cloud.positions * np.float32([1, -1, -1]) if flip else np.ascontiguousarray(cloud.positions)
    xyzw = _unit_quaternions(cloud.rotations)[:, [1, 2, 3, 0]]  # Vt's memory order
    xyzw = xyzw * np.float32([1, -1, -1, 1]) if flip else xyzw
    signs = np.repeat(SH_FLIP[:k], 3) if flip else np.ones(3 * k, np.float32)
    flat = cloud.sh.reshape(n, 3 * k)  # (N, K*3): fast broadcast
    if half:  # the extent below is taken from the values as stored
        _check_half_range(path, "SH", flat)
        xyzw, scales, opacities = (
            _half(path, name, v) for name, v in (("rotation", xyzw), ("scale", scales), ("opacity", opacities))
        )
        values = {
            "orientationsh": _vt(stages, "QuathArray", xyzw),
            "scalesh": _vt(stages, "Vec3hArray", scales),
            "opacitiesh": _vt(stages, "HalfArray", opacities),
            SH_COEFFS + "h": stages.filled(
                "Vec3hArray",
                (n * k, 3),
                np.float16,
                lambda out: np.multiply(flat, signs, out=out.reshape(n, 3 * k), casting="same_kind"),
            ),
        }
    else:
        values = {
            "orientations": _vt(stages, "QuatfArray", xyzw),
            "scales": _vt(stages, "Vec3fArray", scales),
            "opacities": _vt(stages, "FloatArray", opacities),
            SH_COEFFS: stages.filled(
                "Vec3fArray", (n * k, 3), np.float32, lambda out: np.multiply(flat, signs, out=out.reshape(n, 3 * k))
            ),
        }
    if half_positions:
        positions = _half(path, "position", positions)
        values["positionsh"] = _vt(stages, "Vec3hArray", positions)
    else:
        values["positions"] = _vt(stages, "Vec3fArray", positions)
    if exact and not half:
        values[LOGITS] = _vt(stages, "FloatArray", cloud.opacity_logits)
        values[LOG_SCALES] = _vt(stages, "Vec3fArray", np.ascontiguousarray(cloud.log_scales))
        raw = cloud.rotations * np.float32([1, 1, -1, -1]) if flip else cloud.rotations
        values[RAW_ROTATIONS] = _vt(stages, "Vec4fArray", np.ascontiguousarray(raw))
    box = alpha_extent(positions, xyzw[:, [3, 0, 1, 2]], scales, opacities)
    if box is not None:
        values["extent"] = _vt(stages, "Vec3fArray", box)
    return values


def data_size(count, sh_degree, half=False, exact=True):
    """Bytes of the arrays write() authors for `count` splats of `sh_degree` (the attributes of
    _frame_values: positions, orientations, scales, opacities and SH, half floats with `half`, and
    with `exact` the model's own logits, log scales and rotations; the extent). A crate file holds
    them raw plus about a kilobyte of structure (less where OpenUSD compresses constant arrays); a
    text layer takes about 10 bytes per number instead of 4."""
    k = (sh_degree + 1) ** 2
    width = 2 if half else 4
    numbers = 4 + 3 + 1 + 3 * k  # orientation, scale, opacity, SH
    raw = 1 + 3 + 4 if exact and not half else 0  # logits, log scales, raw rotations (float32)
    return count * (3 * 4 + numbers * width + raw * 4) + 2 * 3 * 4


class _Samples:
    """One attribute's values over the frames. With `hold`, a value the same in every frame (an
    opacity that is never animated, say) is authored once, not once per frame."""

    def __init__(self, attr, hold, stages):
        self.attr, self.held, self.first, self.waiting, self.stages = attr, hold, None, [], stages

    def add(self, value, code):
        if self.held:
            if self.first is None:
                self.first = value
            if value is self.first or _same_bytes(value, self.first):
                self.waiting.append(code)
                return
            self.held = False  # the first change: the frames so far get samples
            for earlier in self.waiting:
                self.set(self.first, earlier)
        self.set(value, code)

    def set(self, value, code):
        """Author `value` at time code `code` (None: the default value)."""
        self.stages.set_value(self.attr, value, code)

    def finish(self):
        if self.held:
            self.set(self.first, None)


def _same_bytes(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.array_equal(a.reshape(-1).view(np.uint8), b.reshape(-1).view(np.uint8))
