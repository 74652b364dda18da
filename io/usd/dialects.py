"""The dialects of splats on a stage, each read into a SplatCloud in the prim's local space:

- the schema's ParticleField3DGaussianSplat (`_gaussian_cloud`): positions, orientations, scales,
  opacities and SH, each preferred to its half twin; our own exact model values where they still
  agree with the schema's;
- UsdGeomPoints in the layout Adobe's USD file-format plugins write for splats (`_adobe_cloud`),
  recognised by `primvars:rot`, `primvars:widths1` and `primvars:widths2`;
- UsdGeomPoints as Blender's USD export writes splat point clouds (`_blender_cloud`), recognised by
  `primvars:rotation` and `primvars:scale`, with `radiance:base` and `radiance:sh_*`.

`_dialect(prim)` names the one a prim is written in. Per the schema an array too long is truncated
to the particle count and one too short ignored (a fallback value used); each such repair is noted.
"""

import numpy as np

from ...core import SplatCloud
from ...core import sh as shmod
from ..common import SplatFileError
from . import stages
from .schema import (
    ADOBE_PRIMVARS,
    ANTIALIASED,
    BLENDER_BASE,
    BLENDER_PRIMVARS,
    DTYPE_KEY,
    LOG_SCALES,
    LOGITS,
    RAW_ROTATIONS,
    REST_COUNTS,
    SH_COEFFS,
    SH_DEGREE,
    TYPE_NAME,
    _file,
    _fit,
    _log_scales_from,
    _logits_from,
    _narrowed,
    _numbers,
    _rotations_from,
    _sh_from,
    _valid_opacities,
    is_quaternion,
)

ADOBE = "Points (Adobe 3DGS primvars)"
BLENDER = "Points (Blender splat primvars)"


def _dialect(prim):
    """(source, reader) for a splat prim: its dialect's name and the function reading it (prim,
    time, notes) -> (cloud, linear opacities, linear scales); None for any other prim."""
    if prim.GetTypeName() == TYPE_NAME:
        return TYPE_NAME, _gaussian_cloud
    if _is_adobe_splat(prim):
        return ADOBE, _adobe_cloud
    if _is_blender_splat(prim):
        return BLENDER, _blender_cloud
    return None


def _primvars(prim):
    return stages.active.primvars(prim)


def _value(prim, name, time, shape=()):
    """An authored array attribute as NumPy (numbers, `shape` per entry), or None."""
    attr = prim.GetAttribute(name)
    if not attr or not attr.HasAuthoredValue():
        return None
    value = attr.Get(time)
    return None if value is None else _numbers(prim, name, value, shape)


def _float_or_half(prim, name, time, shape):
    """The float attribute if authored, else its half twin widened to float32."""
    for attr_name in (name, name + "h"):
        value = _value(prim, attr_name, time, shape)
        if value is not None:
            return value.astype(np.float32, copy=False)
    return None


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
    stored_logs = (
        _fit(_value(prim, LOG_SCALES, time, (3,)), n, (3,), LOG_SCALES, "-", []) if scales is not None else None
    )
    rotations = np.tile(np.float32([1, 0, 0, 0]), (n, 1)) if quats is None else quats[:, [3, 0, 1, 2]]
    if quats is not None:
        rotations = _rotations_from(
            rotations, _fit(_value(prim, RAW_ROTATIONS, time, (4,)), n, (4,), RAW_ROTATIONS, "-", []), notes
        )
    opacities = np.ones(n, np.float32) if opacities is None else _valid_opacities(opacities, notes)
    scales = np.ones((n, 3), np.float32) if scales is None else scales
    logits = _logits_from(opacities, stored_logits, notes)
    log_scales = _log_scales_from(scales, stored_logs, notes)
    marked = prim.GetAttribute(ANTIALIASED)
    cloud = SplatCloud(
        positions,
        rotations,
        log_scales,
        logits,
        sh,
        _extras(prim, time, n, set(), notes),
        antialiased=bool(marked and marked.HasAuthoredValue() and marked.Get()),
    )
    return cloud, opacities, np.abs(scales)


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
    return stages.active.is_points(prim) and all(pv.HasPrimvar(n) for n in ("rot", "widths1", "widths2"))


def _is_blender_splat(prim):
    pv = _primvars(prim)
    return stages.active.is_points(prim) and pv.HasPrimvar("rotation") and pv.HasPrimvar("scale")


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
    elif is_quaternion(rotation.GetTypeName()):
        rotations = quats[:, [3, 0, 1, 2]].astype(np.float32)  # Vt quaternions are x, y, z, w in memory
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
    cloud = SplatCloud(
        positions,
        rotations,
        _log_scales_from(scales, None, notes),
        _logits_from(_valid_opacities(opacities, notes), None, notes),
        sh,
        _extras(prim, time, n, BLENDER_PRIMVARS, notes),
    )
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
    cloud = SplatCloud(
        positions,
        rotations,
        _log_scales_from(scales, None, notes),
        _logits_from(opacities, None, notes),
        sh,
        _extras(prim, time, n, taken, notes),
    )
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
