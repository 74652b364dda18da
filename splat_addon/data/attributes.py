"""Point attributes of splat datablocks: typed reads and writes, SH coefficients one attribute each,
the native form's activated values, and the extras a file carried. Everything moves through
foreach_get/foreach_set on float32/int32 buffers: no per-splat Python."""

import json

import bpy
import numpy as np

from ...core import sh as shmod
from ...core.splats import logit, sigmoid
from ...io.gltf import CUSTOM as GLTF_CUSTOM  # glTF's application-specific `_<name>` attributes
from ...io.ply import material_columns
from .errors import SplatObjectError
from .keys import EXTRA_PREFIX, EXTRAS_SPEC, MAX_NAME, NATIVE_REQUIRED, NATIVE_SH_PREFIX, SH_PREFIX

# Blender attribute type -> (foreach property, components, NumPy buffer dtype)
_TYPES = {
    "FLOAT": ("value", 1, np.float32),
    "FLOAT2": ("vector", 2, np.float32),
    "FLOAT_VECTOR": ("vector", 3, np.float32),
    "QUATERNION": ("value", 4, np.float32),
    "FLOAT_COLOR": ("color", 4, np.float32),
    "FLOAT4": ("vector", 4, np.float32),
    "INT": ("value", 1, np.int32),
    "BOOLEAN": ("value", 1, bool),
}
_EXTRA_TYPES = ("FLOAT", "FLOAT2", "FLOAT_VECTOR", "INT", "BOOLEAN")  # the types extras are stored as


def splat_count(geometry):
    """Splats of a mesh or point cloud datablock (original or evaluated)."""
    return len(geometry.vertices) if isinstance(geometry, bpy.types.Mesh) else len(geometry.points)


def sh_attribute(k):
    return f"{SH_PREFIX}{k}"


# attributes -------------------------------------------------------------------------------------------


def _set(geometry, name, kind, values):
    """Write `values` into the point attribute `name`, creating it if needed."""
    prop, width, dtype = _TYPES[kind]
    attr = geometry.attributes.get(name)
    if attr is not None and (attr.data_type != kind or attr.domain != "POINT"):
        geometry.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = geometry.attributes.new(name, kind, "POINT")
    attr.data.foreach_set(prop, np.ascontiguousarray(values, dtype=dtype).reshape(-1))


def set_attribute(geometry, name, kind, values):
    """Write a point attribute of a splat mesh or point cloud and tell Blender it changed."""
    _set(geometry, name, kind, values)
    _changed(geometry)


def _changed(geometry):
    if isinstance(geometry, bpy.types.Mesh):
        geometry.update()
    else:
        geometry.update_tag()


def _get(geometry, name, kinds, owner, out=None):
    """A point attribute as an (N, width) array (into `out` if given), or SplatObjectError naming what
    is missing or wrong. `kinds`: the accepted type, or a tuple of types of the same width."""
    kinds = (kinds,) if isinstance(kinds, str) else kinds
    attr = geometry.attributes.get(name)
    if attr is None:
        raise SplatObjectError(f"'{owner}' has no '{name}' point attribute")
    if attr.data_type not in kinds or attr.domain != "POINT":
        raise SplatObjectError(
            f"'{owner}': attribute '{name}' is {attr.data_type} on {attr.domain}, "
            f"expected {' or '.join(kinds)} on POINT"
        )
    prop, width, dtype = _TYPES[attr.data_type]
    if out is None:
        out = np.empty((splat_count(geometry), width), dtype=dtype)
    attr.data.foreach_get(prop, out.reshape(-1))
    return out


def _coefficient_major(sh, rows=4096):
    """(N, K, 3) -> contiguous (K, N, 3), a block of rows at a time: about twice as fast as one
    whole-array transpose, whose scattered writes miss the cache."""
    out = np.empty((sh.shape[1], sh.shape[0], 3), np.float32)
    for start in range(0, len(sh), rows):
        out[:, start : start + rows] = sh[start : start + rows].transpose(1, 0, 2)
    return out


def _sh_count(geometry, prefix, offset, owner):
    """Coefficients held as attributes prefix<k> (k = 0..) plus `offset` held elsewhere."""
    present = {
        int(a.name[len(prefix) :])
        for a in geometry.attributes
        if a.name.startswith(prefix) and a.name[len(prefix) :].isdigit()
    }
    stored = max(present, default=-1) + 1
    count = stored + offset
    missing = sorted(set(range(stored)) - present)
    if count not in shmod.VALID_COUNTS or missing:
        raise SplatObjectError(
            f"'{owner}': SH attributes {prefix}0..{stored - 1} do not form a full degree "
            f"(found {count} coefficients, missing {missing or 'none'}; need one of "
            f"{', '.join(map(str, shmod.VALID_COUNTS))})"
        )
    return count


def _read_sh(geometry, prefix, first, owner, count):
    """(N, K, 3) SH with coefficients first..K-1 read from prefix<k - first>; the caller fills those
    before `first`. A view of a coefficient-major buffer: no transpose copy."""
    by_coefficient = np.empty((count, splat_count(geometry), 3), np.float32)
    for k in range(first, count):
        _get(geometry, f"{prefix}{k - first}", "FLOAT_VECTOR", owner, out=by_coefficient[k])
    return by_coefficient.transpose(1, 0, 2)


BASE_TYPES = ("FLOAT4", "FLOAT_COLOR", "QUATERNION")  # what radiance:base may be: four floats


def base_type():
    """The type Blender 5.3's importers give radiance:base (FLOAT4), where this Blender has it; else a
    colour, the four-float type of earlier versions."""
    types = bpy.types.Attribute.bl_rna.properties["data_type"].enum_items.keys()
    return "FLOAT4" if "FLOAT4" in types else "FLOAT_COLOR"


def native_log_scales(scales):
    """Log-scales of linear scales, in float64 (a zero scale is -inf, a flat axis; a negative one NaN)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(scales.astype(np.float64))


def native_opacity_logits(opacities):
    """Logits of float32 opacities; 0 and 1 become the logits of the nearest float32 opacities
    inside (0, 1), so a fully opaque or clear splat stays finite."""
    return logit(opacities.astype(np.float64), eps=2.0**-24)


def _exact_or(pointcloud, name, kind, owner, linear, from_linear):
    """The exact values Splatwright stored under `name` while they still give `linear` (the native
    attribute, as float32 does); otherwise the values computed from `linear`."""
    if name in pointcloud.attributes:
        exact = _get(pointcloud, name, kind, owner)
        activated = np.exp(exact) if kind == "FLOAT_VECTOR" else sigmoid(exact)
        with np.errstate(over="ignore"):
            if np.array_equal(activated.astype(np.float32), linear):
                return exact
    return from_linear(linear)


# extras -----------------------------------------------------------------------------------------------


def _extra_kind(values):
    """How an extra array is stored: (kind, columns) or None when it does not fit an attribute."""
    if values.ndim not in (1, 2) or values.dtype.kind not in "biuf" or (values.ndim == 2 and values.shape[1] == 0):
        return None
    columns = 1 if values.ndim == 1 else values.shape[1]
    if values.dtype.kind == "b":
        return ("BOOLEAN", columns)
    if values.dtype.kind in "iu":
        info = np.iinfo(np.int32)
        fits = values.size == 0 or (values.min() >= info.min and values.max() <= info.max)
        return ("INT", columns) if fits else None
    if values.ndim == 2 and columns in (2, 3):
        return ({2: "FLOAT2", 3: "FLOAT_VECTOR"}[columns], 1)
    return ("FLOAT", columns)


def _extra_names(name, columns):
    base = EXTRA_PREFIX + name
    return [base] if columns == 1 else [f"{base}.{i}" for i in range(columns)]


def _write_extra(geometry, name, values, kind):
    columns = values.reshape(len(values), -1).T if kind[1] > 1 else [values]
    for attr_name, column in zip(_extra_names(name, kind[1]), columns):
        _set(geometry, attr_name, kind[0], column)


def _write_extras(geometry, extras):
    """Store what fits as attributes (vectors whole, other matrices column by column); return the
    names that did not fit. The dtype is kept in a datablock property so export restores it."""
    spec, skipped = {}, []
    for name, values in extras.items():
        kind = _extra_kind(values)
        names = _extra_names(name, kind[1]) if kind else []
        if kind is None or len(names[-1]) > MAX_NAME or any(n in geometry.attributes for n in names):
            skipped.append(name)
            continue
        _write_extra(geometry, name, values, kind)
        spec[name] = [values.dtype.str, kind[1], values.ndim]
    if spec:
        geometry[EXTRAS_SPEC] = json.dumps(spec)
    return skipped


def _read_extras(geometry, owner, spec_owner):
    spec = json.loads(spec_owner.get(EXTRAS_SPEC, "{}"))
    extras = {}
    for name, (dtype, columns, ndim) in spec.items():
        names = _extra_names(name, columns)
        if all(n in geometry.attributes for n in names):
            values = np.concatenate([_get(geometry, n, geometry.attributes[n].data_type, owner) for n in names], axis=1)
            extras[name] = (values[:, 0] if ndim == 1 else values).astype(np.dtype(dtype))
    # Extras joined in from another splat object whose spec was not kept: read them as stored.
    known = {n for name, (_, columns, _) in spec.items() for n in _extra_names(name, columns)}
    for attr in geometry.attributes:
        name = attr.name[len(EXTRA_PREFIX) :]
        if (
            attr.name.startswith(EXTRA_PREFIX)
            and attr.name not in known
            and "." not in name
            and attr.domain == "POINT"
            and attr.data_type in _TYPES
        ):
            values = _get(geometry, attr.name, attr.data_type, owner)
            extras[name] = values[:, 0] if values.shape[1] == 1 else values
    return extras


# Point attributes of a point cloud that are no extra: the splat's own (NATIVE_REQUIRED, SH), Blender's
# point size, and what Splatwright keeps (names starting "splat_" or hidden ones, starting ".").
_NOT_FOREIGN = (*NATIVE_REQUIRED, "radius")
_OURS = ("splat_", ".")


def foreign_extras(geometry, owner, original, taken=()):
    """{name: (N,) or (N, k)}: the point attributes besides the splats' own that an importer left on a
    native cloud, as extras (what Splatwright's own reader would make of the file): Blender's PLY
    importer keeps a PLY's extra properties by name (albedo_0..2 joined into one (N,3) albedo, as
    io.ply reads them), its glTF importer a glTF's `_<name>` attributes (the extra <name>). Only those
    the `original` datablock holds (not what geometry nodes add to an evaluated one), none in `taken`."""
    extras = {}
    for attr in geometry.attributes:
        name = attr.name
        if (
            name in _NOT_FOREIGN
            or name.startswith((*_OURS, NATIVE_SH_PREFIX))
            or attr.domain != "POINT"
            or attr.data_type not in _EXTRA_TYPES
            or name not in original.attributes
        ):
            continue
        values = _get(geometry, name, attr.data_type, owner)
        extras[name[len(GLTF_CUSTOM) :] if name.startswith(GLTF_CUSTOM) else name] = (
            values[:, 0] if values.shape[1] == 1 else values
        )
    return {name: values for name, values in material_columns(extras).items() if name not in taken}
