"""Splat clouds as Blender data, in two forms, and the one way every operator reads them.

Mesh form (Splatwright's own, every Blender version): a mesh whose vertices are the centres, with
these point attributes, in object space:

    position              the vertex coordinates: splat centres
    splat_rotation        QUATERNION   w, x, y, z as stored in the file (any norm)
    splat_log_scale       FLOAT_VECTOR natural log of the per-axis standard deviations
    splat_opacity_logit   FLOAT        logit of the opacity
    splat_sh_<k>          FLOAT_VECTOR SH coefficient k (0 = DC) for r, g, b; k < (degree+1)^2
    splat_extra_<name>    extras a file carried (PLY normals, ...): FLOAT, FLOAT2, FLOAT_VECTOR, INT
                          or BOOLEAN; other matrix shapes as columns splat_extra_<name>.<i>

The mesh custom property "splatwright" (the layout version) marks the mesh as a splat cloud.

Native form (Blender 5.3's "3D Gaussian Splats" point clouds, as its PLY/SPZ importer makes them):
a point cloud with

    position              FLOAT_VECTOR centres
    scale                 FLOAT_VECTOR per-axis standard deviations, linear
    rotation              QUATERNION   w, x, y, z
    radiance:base         FLOAT4       SH DC (r, g, b) and the opacity after the sigmoid (Blender 5.3
                          writes FLOAT4; FLOAT_COLOR, from hand-built clouds of earlier versions, is read)
    radiance:sh_<j>       FLOAT_VECTOR SH coefficient j + 1, 3DGS order
    .splatwright_log_scale, .splatwright_opacity_logit   the exact log-scales and logits, when
                          Splatwright wrote the values: used only while exp and the sigmoid of them
                          still give `scale` and the opacity bit for bit, so an edit made elsewhere wins
    splat_extra_<name>    extras, as in the mesh form

Reading (`evaluated_cloud`) takes the object's evaluated geometry at the depsgraph's frame, so edit-mode
changes, shape keys and modifiers reach export, animation export, collisions and the render engine as
the viewport shows them. Modifiers move centres and carry the other attributes along; where the
evaluated splats are whole copies of the object's own, each copy moved by one affine map (Array,
Mirror, a geometry-nodes Transform), that map also turns orientations, sizes and SH exactly. Splats
bound to an armature are posed by the POSERS from the object's own splats instead.

Everything moves through foreach_get/foreach_set on float32/int32 buffers: no per-splat Python.
"""

import contextlib
import json
import warnings
from typing import NamedTuple

import bpy
import numpy as np

from ..core import SplatCloud, sh as shmod
from ..core.splats import logit, sigmoid

MARKER = "splatwright"
LAYOUT_VERSION = 1
EXTRAS_SPEC = "splatwright_extras"     # datablock property: JSON {name: [dtype, columns, ndim]}
ANTIALIASED = "splatwright_antialiased"  # datablock property: the splats were made for antialiased rendering
# Extras that tie splats made from a mesh to its triangles (rigging reads them): bookkeeping of this
# Blender file, not scene content, so exports leave them out.
SOURCE_EXTRAS = ("source_triangle", "barycentric", "source_vertices")

MESH_FORM, NATIVE_FORM = "MESH", "NATIVE"

# Where a splat datablock's values stand (datablock property; see landed_raw): "RAW" when they are a
# file's own axes placed as they are, as Blender's PLY importer places captures; "UPRIGHT" otherwise.
LANDING = "splatwright_landing"
SPZ_POSITION_BITS = 24                 # SPZ stores centres as 24-bit signed fixed point

ROTATION = "splat_rotation"
LOG_SCALE = "splat_log_scale"
OPACITY = "splat_opacity_logit"
SH_PREFIX = "splat_sh_"
EXTRA_PREFIX = "splat_extra_"
MAX_NAME = 63                          # Blender attribute names are cut at 64 bytes

NATIVE_SCALE, NATIVE_ROTATION, NATIVE_BASE = "scale", "rotation", "radiance:base"
NATIVE_SH_PREFIX = "radiance:sh_"      # radiance:sh_<j> holds SH coefficient j + 1
EXACT_LOG_SCALE, EXACT_LOGIT = ".splatwright_log_scale", ".splatwright_opacity_logit"
REST_PREFIX = ".splatwright_rest:"     # bound native splats: their rest pose, while Blender draws the posed
NATIVE_REQUIRED = ("position", NATIVE_SCALE, NATIVE_ROTATION, NATIVE_BASE)

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


class SplatModeWarning(UserWarning):
    """Splats made for antialiased rendering shown or written classic beside classic ones."""


@contextlib.contextmanager
def reported_warnings(report):
    """Python warnings raised inside (a format's notes, mixed render modes) passed on to `report`, an
    operator's or render engine's, as Blender warnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        report({"WARNING"}, str(w.message))


class SplatObjectError(ValueError):
    """A Blender object that cannot be read as a splat cloud; the message names it and the problem."""


# forms ------------------------------------------------------------------------------------------------

def is_splat_mesh(mesh):
    return mesh is not None and MARKER in mesh.keys()


def is_native_splats(pointcloud):
    """A point cloud with Blender's Gaussian-splat attributes (whoever made it)."""
    return pointcloud is not None and all(name in pointcloud.attributes for name in NATIVE_REQUIRED)


def is_gaussian_type(pointcloud):
    """A point cloud Blender 5.3 marks as Gaussian splats (its `type`), whatever attributes it holds."""
    return getattr(pointcloud, "type", None) == "GAUSSIAN_SPLAT"


def splat_form(obj):
    """MESH_FORM, NATIVE_FORM, or None for an object that holds no splats. A point cloud of Blender's
    Gaussian-splat type is native splats even with an attribute deleted: reading it names what is missing."""
    if obj is None:
        return None
    if obj.type == "MESH" and is_splat_mesh(obj.data):
        return MESH_FORM
    if obj.type == "POINTCLOUD" and (is_native_splats(obj.data) or is_gaussian_type(obj.data)):
        return NATIVE_FORM
    return None


def is_splat_object(obj):
    return splat_form(obj) is not None


def splat_count(geometry):
    """Splats of a mesh or point cloud datablock (original or evaluated)."""
    return len(geometry.vertices) if isinstance(geometry, bpy.types.Mesh) else len(geometry.points)


def sh_degree(obj):
    """The SH degree of a splat object's own splats, from its attribute names (nothing is read);
    SplatObjectError when they do not form a full degree."""
    geometry = obj.data
    if splat_form(obj) == NATIVE_FORM:
        count = _sh_count(geometry, NATIVE_SH_PREFIX, 1, obj.name)
    else:
        count = _sh_count(geometry, SH_PREFIX, 0, obj.name)
    return shmod.degree_of(count)


def native_supported():
    """Whether this Blender can make point clouds holding points from Python: resize() (5.2 and
    later), or converting a mesh (4.5 and later)."""
    return _resizable() or "POINTCLOUD" in _convert_targets()


def _resizable():
    """Whether point clouds have resize() (5.2 and later). An RNA function: the class lists it in
    bl_rna.functions, while hasattr() on the class is False."""
    return "resize" in bpy.types.PointCloud.bl_rna.functions


def native_by_default():
    """Blender 5.3 draws native splats in its viewport, EEVEE and Cycles: new splat objects take
    that form there."""
    return bpy.app.version >= (5, 3, 0)


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
        raise SplatObjectError(f"'{owner}': attribute '{name}' is {attr.data_type} on {attr.domain}, "
                               f"expected {' or '.join(kinds)} on POINT")
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
        out[:, start:start + rows] = sh[start:start + rows].transpose(1, 0, 2)
    return out


def _sh_count(geometry, prefix, offset, owner):
    """Coefficients held as attributes prefix<k> (k = 0..) plus `offset` held elsewhere."""
    present = {int(a.name[len(prefix):]) for a in geometry.attributes
               if a.name.startswith(prefix) and a.name[len(prefix):].isdigit()}
    stored = max(present, default=-1) + 1
    count = stored + offset
    missing = sorted(set(range(stored)) - present)
    if count not in shmod.VALID_COUNTS or missing:
        raise SplatObjectError(f"'{owner}': SH attributes {prefix}0..{stored - 1} do not form a full degree "
                               f"(found {count} coefficients, missing {missing or 'none'}; need one of "
                               f"{', '.join(map(str, shmod.VALID_COUNTS))})")
    return count


def _read_sh(geometry, prefix, first, owner, count):
    """(N, K, 3) SH with coefficients first..K-1 read from prefix<k - first>; the caller fills those
    before `first`. A view of a coefficient-major buffer: no transpose copy."""
    by_coefficient = np.empty((count, splat_count(geometry), 3), np.float32)
    for k in range(first, count):
        _get(geometry, f"{prefix}{k - first}", "FLOAT_VECTOR", owner, out=by_coefficient[k])
    return by_coefficient.transpose(1, 0, 2)


# the mesh form ----------------------------------------------------------------------------------------

def _write_mesh_form(mesh, cloud):
    _set(mesh, "position", "FLOAT_VECTOR", cloud.positions)      # an empty mesh has no position attribute yet
    _set(mesh, ROTATION, "QUATERNION", cloud.rotations)
    _set(mesh, LOG_SCALE, "FLOAT_VECTOR", cloud.log_scales)
    _set(mesh, OPACITY, "FLOAT", cloud.opacity_logits)
    by_coefficient = _coefficient_major(cloud.sh)
    for k in range(cloud.sh.shape[1]):
        _set(mesh, sh_attribute(k), "FLOAT_VECTOR", by_coefficient[k])


def _read_mesh_form(mesh, owner):
    sh = _read_sh(mesh, SH_PREFIX, 0, owner, _sh_count(mesh, SH_PREFIX, 0, owner))
    return dict(positions=_get(mesh, "position", "FLOAT_VECTOR", owner),
                rotations=_get(mesh, ROTATION, "QUATERNION", owner),
                log_scales=_get(mesh, LOG_SCALE, "FLOAT_VECTOR", owner),
                opacity_logits=_get(mesh, OPACITY, "FLOAT", owner)[:, 0], sh=sh)


# the native form --------------------------------------------------------------------------------------

def _write_native_form(pointcloud, cloud, prefix=""):
    """Write `cloud` as native attributes; `prefix` REST_PREFIX keeps it as the rest pose instead."""
    _set(pointcloud, prefix + "position", "FLOAT_VECTOR", cloud.positions)
    _set(pointcloud, prefix + NATIVE_ROTATION, "QUATERNION", cloud.rotations)
    with np.errstate(over="ignore"):
        _set(pointcloud, prefix + NATIVE_SCALE, "FLOAT_VECTOR", np.exp(cloud.log_scales))
    base = np.empty((len(cloud), 4), np.float32)
    base[:, :3] = cloud.sh[:, 0]
    base[:, 3] = sigmoid(cloud.opacity_logits)
    _set(pointcloud, prefix + NATIVE_BASE, base_type(), base)
    sh_prefix = prefix + NATIVE_SH_PREFIX
    by_coefficient = _coefficient_major(cloud.sh)
    for k in range(1, cloud.sh.shape[1]):
        _set(pointcloud, f"{sh_prefix}{k - 1}", "FLOAT_VECTOR", by_coefficient[k])
    for name in [a.name for a in pointcloud.attributes if a.name.startswith(sh_prefix)]:
        suffix = name[len(sh_prefix):]
        if suffix.isdigit() and int(suffix) >= cloud.sh.shape[1] - 1:      # a lower degree than before
            pointcloud.attributes.remove(pointcloud.attributes[name])
    _set(pointcloud, prefix + EXACT_LOG_SCALE, "FLOAT_VECTOR", cloud.log_scales)
    _set(pointcloud, prefix + EXACT_LOGIT, "FLOAT", cloud.opacity_logits)


def _read_native_form(pointcloud, owner):
    """The native splats' own values: the rest pose where one is kept (see show_posed)."""
    prefix = REST_PREFIX if is_posed_native(pointcloud) else ""
    count = _sh_count(pointcloud, prefix + NATIVE_SH_PREFIX, 1, owner)
    sh = _read_sh(pointcloud, prefix + NATIVE_SH_PREFIX, 1, owner, count)
    base = _get(pointcloud, prefix + NATIVE_BASE, BASE_TYPES, owner)
    sh[:, 0] = base[:, :3]
    scales = _get(pointcloud, prefix + NATIVE_SCALE, "FLOAT_VECTOR", owner)
    return dict(positions=_get(pointcloud, prefix + "position", "FLOAT_VECTOR", owner),
                rotations=_get(pointcloud, prefix + NATIVE_ROTATION, "QUATERNION", owner),
                log_scales=_exact_or(pointcloud, prefix + EXACT_LOG_SCALE, "FLOAT_VECTOR", owner, scales,
                                     native_log_scales),
                opacity_logits=_exact_or(pointcloud, prefix + EXACT_LOGIT, "FLOAT", owner, base[:, 3:],
                                         native_opacity_logits)[:, 0],
                sh=sh)


def is_posed_native(pointcloud):
    """Whether native splats keep a rest pose apart from what Blender draws (bound to an armature)."""
    return REST_PREFIX + "position" in pointcloud.attributes


def keep_rest_pose(obj):
    """From now on `obj`'s native attributes show it posed: its own splats move to the rest attributes."""
    if not is_posed_native(obj.data):
        stamp_landing(obj)
        _write_native_form(obj.data, object_cloud(obj), REST_PREFIX)


def show_posed(obj, posed):
    """Write `posed` (object space) into the native attributes Blender draws; the rest pose stays."""
    _write_native_form(obj.data, posed)
    _changed(obj.data)


BASE_TYPES = ("FLOAT4", "FLOAT_COLOR", "QUATERNION")     # what radiance:base may be: four floats


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
    return logit(opacities.astype(np.float64), eps=2.0 ** -24)


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


# where the values stand -------------------------------------------------------------------------------

def landed_raw(obj):
    """Whether `obj`'s own splats are a file's axes placed as they are (a capture lying on its side):
    what Blender's PLY importer makes, while Splatwright's importers and Blender's SPZ importer stand
    captures upright. Exports write such splats in those axes, so the file comes back as it was.

    Splatwright records the answer on every datablock it makes or changes (LANDING). Blender's
    importers record nothing: their clouds are told apart by SPZ's fixed-point grid, which the SPZ
    importer's centres lie on and a PLY's float32 centres (past a handful) do not."""
    stamp = obj.data.get(LANDING) if obj is not None and obj.data is not None else None
    if stamp is not None:
        return stamp == "RAW"
    if splat_form(obj) != NATIVE_FORM or EXACT_LOG_SCALE in obj.data.attributes:
        return False
    return not on_spz_grid(_get(obj.data, "position", "FLOAT_VECTOR", obj.name))


def on_spz_grid(positions):
    """Whether every centre is a multiple of one power of two 2^-k with all of them inside SPZ's 24-bit
    signed range at that k, as centres an SPZ file held are (k is the file's fractional bits)."""
    values = np.asarray(positions, dtype=np.float64).ravel()
    values = values[values != 0]
    if values.size == 0:
        return True
    fraction, exponent = np.frexp(values)               # values = fraction 2^exponent, 0.5 <= |fraction| < 1
    mantissa = np.abs(fraction * 2.0 ** 53).astype(np.uint64)
    trailing = np.log2((mantissa & (~mantissa + np.uint64(1))).astype(np.float64))
    bits_needed = np.maximum(53 - exponent - trailing, 0).max()
    return bool(np.abs(values).max() * 2.0 ** bits_needed < 2.0 ** (SPZ_POSITION_BITS - 1))


def stamp_landing(obj, raw=None):
    """Record where `obj`'s splats stand before Splatwright changes them (afterwards they no longer
    look like what an importer made): `raw`, or what landed_raw finds now."""
    obj.data[LANDING] = "RAW" if (landed_raw(obj) if raw is None else raw) else "UPRIGHT"


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
            values = np.concatenate([_get(geometry, n, geometry.attributes[n].data_type, owner) for n in names],
                                    axis=1)
            extras[name] = (values[:, 0] if ndim == 1 else values).astype(np.dtype(dtype))
    # Extras joined in from another splat object whose spec was not kept: read them as stored.
    known = {n for name, (_, columns, _) in spec.items() for n in _extra_names(name, columns)}
    for attr in geometry.attributes:
        name = attr.name[len(EXTRA_PREFIX):]
        if attr.name.startswith(EXTRA_PREFIX) and attr.name not in known and "." not in name \
                and attr.domain == "POINT" and attr.data_type in _TYPES:
            values = _get(geometry, attr.name, attr.data_type, owner)
            extras[name] = values[:, 0] if values.shape[1] == 1 else values
    return extras


# datablocks -------------------------------------------------------------------------------------------

def geometry_cloud(geometry, owner=None, form=None, spec_owner=None):
    """The SplatCloud a splat mesh or point cloud (original or evaluated) holds, in object space.
    `form` defaults to the datablock's own; an evaluated datablock passes its original as
    `spec_owner`, which holds the extras' dtypes."""
    owner = owner or geometry.name
    if form is None:
        form = MESH_FORM if isinstance(geometry, bpy.types.Mesh) else NATIVE_FORM
        if form == MESH_FORM and not is_splat_mesh(geometry):
            raise SplatObjectError(f"'{owner}' is not a splat cloud (mesh without the '{MARKER}' marker)")
    read = _read_mesh_form if form == MESH_FORM else _read_native_form
    spec_owner = spec_owner or geometry
    return SplatCloud(**read(geometry, owner), extras=_read_extras(geometry, owner, spec_owner),
                      antialiased=made_antialiased(spec_owner))


def made_antialiased(geometry):
    """Whether a splat datablock's splats were made for antialiased rendering."""
    return bool(geometry.get(ANTIALIASED, False))


def _keep_mode(geometry, cloud):
    """Record on the datablock the render mode the splats were made for (see SplatCloud.antialiased)."""
    if cloud.antialiased:
        geometry[ANTIALIASED] = True
    elif ANTIALIASED in geometry:
        del geometry[ANTIALIASED]


def mesh_to_cloud(mesh, owner=None):
    """The SplatCloud a splat mesh holds, in object space."""
    return geometry_cloud(mesh, owner, MESH_FORM if is_splat_mesh(mesh) else None)


def cloud_to_mesh(cloud, name):
    """A new mesh datablock holding `cloud` (object space). Returns (mesh, skipped extra names)."""
    mesh = bpy.data.meshes.new(name)
    try:
        mesh.vertices.add(len(cloud))
        _write_mesh_form(mesh, cloud)
        skipped = _write_extras(mesh, cloud.extras)
        _keep_mode(mesh, cloud)
        mesh[MARKER] = LAYOUT_VERSION
        mesh.update()
    except BaseException:
        bpy.data.meshes.remove(mesh)
        raise
    return mesh, skipped


def cloud_to_pointcloud(cloud, name):
    """A new point cloud datablock holding `cloud` in the native form. Returns (point cloud, skipped
    extra names); SplatObjectError on a Blender that cannot make point clouds from Python."""
    pointcloud = _new_pointcloud(name, len(cloud))
    try:
        _write_native_form(pointcloud, cloud)
        skipped = _write_extras(pointcloud, cloud.extras)
        _keep_mode(pointcloud, cloud)
        _mark_gaussian(pointcloud)
        _changed(pointcloud)
    except BaseException:
        bpy.data.pointclouds.remove(pointcloud)
        raise
    return pointcloud, skipped


def _convert_targets():
    return {e.identifier for e in bpy.ops.object.convert.get_rna_type().properties["target"].enum_items}


def _new_pointcloud(name, count):
    """A point cloud of `count` points: resized (Blender 5.2+), else converted from a mesh (4.5+)."""
    if _resizable():
        pointcloud = bpy.data.pointclouds.new(name)
        pointcloud.resize(count)
        return pointcloud
    if not native_supported():
        raise SplatObjectError(f"Blender {bpy.app.version_string} cannot make point clouds from Python "
                               f"(Blender 4.5 and later can): '{name}' stays a splat mesh")
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(count)
    obj = bpy.data.objects.new(name, mesh)
    scene = bpy.context.scene
    scene.collection.objects.link(obj)
    try:
        with bpy.context.temp_override(active_object=obj, object=obj, selected_objects=[obj],
                                       selected_editable_objects=[obj]):
            bpy.ops.object.convert(target="POINTCLOUD")
        pointcloud = obj.data
        if not isinstance(pointcloud, bpy.types.PointCloud):
            raise SplatObjectError(f"Blender could not make a point cloud for '{name}'")
        pointcloud.name = name
        return pointcloud
    finally:
        mesh_left = obj.data if isinstance(obj.data, bpy.types.Mesh) else None
        bpy.data.objects.remove(obj)
        if mesh_left is not None:               # not converted: that is `mesh`, gone now
            bpy.data.meshes.remove(mesh_left)
        elif mesh.name in bpy.data.meshes and mesh.users == 0:
            bpy.data.meshes.remove(mesh)


def _mark_gaussian(pointcloud):
    """Blender 5.3 tells Gaussian-splat point clouds apart by a type: set it where this Blender has it."""
    for prop in pointcloud.bl_rna.properties:
        if prop.type == "ENUM" and not prop.is_readonly and prop.identifier == "type":
            items = [e.identifier for e in prop.enum_items if "GAUSS" in e.identifier or "SPLAT" in e.identifier]
            if items:
                setattr(pointcloud, prop.identifier, items[0])


def update_splats(obj, cloud):
    """Overwrite a splat object's own values with `cloud` (same splat count, e.g. after a transform)."""
    geometry, form = obj.data, splat_form(obj)
    stamp_landing(obj)
    if len(cloud) != splat_count(geometry):
        raise SplatObjectError(f"'{obj.name}' has {splat_count(geometry)} splats, the cloud has {len(cloud)}")
    if form == MESH_FORM:
        _write_mesh_form(geometry, cloud)
    else:
        if is_posed_native(geometry):
            _write_native_form(geometry, cloud, REST_PREFIX)
        _write_native_form(geometry, cloud)
    spec = json.loads(geometry.get(EXTRAS_SPEC, "{}"))
    for name, values in cloud.extras.items():
        kind = _extra_kind(values)
        if name in spec and kind is not None:
            _write_extra(geometry, name, values, kind)
    _keep_mode(geometry, cloud)
    _changed(geometry)


def built_datablock(collection, name, tag, version):
    """The datablock `name` of `collection` (bpy.data.materials, node_groups, ...) if it carries the
    custom property `tag` == `version`, else None: an outdated one (a file saved by an earlier build)
    is renamed out of the way, so whatever still uses it keeps it and the caller builds afresh."""
    item = collection.get(name)
    if item is None or item.get(tag) == version:
        return item
    item.name = f"{name} (v{item.get(tag, 0)})"
    return None


# objects ----------------------------------------------------------------------------------------------

def new_splat_object(cloud, name, collection, matrix=None, form=None):
    """Link a new splat object holding `cloud` into `collection`; returns (object, skipped extras).
    `form`: MESH_FORM or NATIVE_FORM (default: native on Blender 5.3 and later, else the mesh)."""
    form = form or (NATIVE_FORM if native_by_default() else MESH_FORM)
    if form == MESH_FORM:
        geometry, skipped = cloud_to_mesh(cloud, name)
        remove = bpy.data.meshes.remove
    else:
        geometry, skipped = cloud_to_pointcloud(cloud, name)
        remove = bpy.data.pointclouds.remove
    try:
        obj = bpy.data.objects.new(name, geometry)
        if matrix is not None:
            obj.matrix_world = matrix
        collection.objects.link(obj)
        remember_frame(obj)
    except BaseException:
        remove(geometry)
        raise
    return obj, skipped


def remove_geometry(geometry):
    """Remove a mesh or point cloud datablock that nothing uses any more."""
    if geometry is not None and geometry.users == 0:
        (bpy.data.meshes if isinstance(geometry, bpy.types.Mesh) else bpy.data.pointclouds).remove(geometry)


def remove_splat_object(obj):
    """Remove a splat object and its data (when nothing else uses it)."""
    geometry = obj.data
    bpy.data.objects.remove(obj)
    remove_geometry(geometry)


def object_cloud(obj):
    """The splats `obj` holds itself (object space, before modifiers); an object in Edit Mode is synced
    first (its edits live in the edit data until then)."""
    if obj.mode == "EDIT":
        obj.update_from_editmode()
    form = splat_form(obj)
    if form is None:
        raise SplatObjectError(f"'{obj.name}' is not a splat object ({obj.type})")
    return geometry_cloud(obj.data, obj.name, form)


FRAME_RECORD = "splatwright_frame"          # object property: matrix_basis and probe centres (apply_guard)


def probe_indices(count):
    """A few splats spread over the cloud whose centres stand for all of them in a frame record."""
    return sorted({0, count // 3, (2 * count) // 3, count - 1}) if count else []


def probe_centres(obj, indices):
    """(k, 3) float64 centres of the splats `indices` of `obj`'s own data (Object Mode)."""
    position = obj.data.attributes["position"].data
    return np.array([position[i].vector for i in indices], dtype=np.float64).reshape(-1, 3)


def remember_frame(obj):
    """Record `obj`'s matrix_basis and probe centres: apply_guard tells from them whether a change to
    both was Blender's Apply. Operators that change a splat object's data and transform together call
    this at once, so their own change is not taken for one."""
    count = splat_count(obj.data)
    indices = probe_indices(count)
    obj[FRAME_RECORD] = {"basis": np.array(obj.matrix_basis, dtype=np.float64).ravel().tolist(), "count": count,
                         "probes": indices, "centres": probe_centres(obj, indices).ravel().tolist()}


def world_matrix(obj, depsgraph=None):
    """The object's evaluated world matrix as float64 (4,4)."""
    source = obj.evaluated_get(depsgraph) if depsgraph is not None else obj
    return np.array(source.matrix_world, dtype=np.float64)


def snap_matrix(matrix, tol=1e-6):
    """Blender keeps object rotations as float32 Euler angles, so a quarter turn comes back with
    ~4e-8 residue (cos(pi/2) in float32). A linear part within `tol` of a signed axis permutation is
    snapped to it exactly, so axis conversions cancel and unedited splats export bit for bit."""
    matrix = np.array(matrix, dtype=np.float64)
    linear = matrix[:3, :3]
    rounded = np.round(linear)
    is_permutation = (np.abs(rounded).sum(axis=0) == 1).all() and (np.abs(rounded).sum(axis=1) == 1).all()
    if is_permutation and np.abs(linear - rounded).max() <= tol:
        matrix[:3, :3] = rounded
    return matrix


def transform_cloud(cloud, matrix):
    """`cloud` under the affine 4x4 `matrix`; the identity returns the cloud itself, untouched, and
    a pure translation moves the centres only."""
    matrix = snap_matrix(matrix)
    if not np.isfinite(matrix).all():      # the translation-only path below would spread NaN silently
        raise ValueError("transform holds NaN or Inf")
    if np.array_equal(matrix[:3, :3], np.eye(3)) and np.array_equal(matrix[3], [0, 0, 0, 1]):
        if not matrix[:3, 3].any():
            return cloud
        return cloud.replace(positions=cloud.positions.astype(np.float64) + matrix[:3, 3])
    return cloud.transformed(matrix)


def object_to_cloud(obj, matrix):
    """The splat cloud of `obj` (its own splats) with `matrix` (usually conversion @ world matrix) applied."""
    return _transformed(obj, object_cloud(obj), matrix)


def _transformed(obj, cloud, matrix):
    """transform_cloud, with a transform it refuses (singular, NaN) reported as the object's."""
    try:
        return transform_cloud(cloud, matrix)
    except ValueError as exc:
        raise SplatObjectError(f"'{obj.name}': {exc}") from None


# the evaluated scene ----------------------------------------------------------------------------------

# Posing hooks: callables (obj, depsgraph) -> None when they do not pose `obj`, else a function that
# takes the object's own splats (object space) and returns them posed at the depsgraph's frame (an
# armature, say). Modifiers are not applied to posed objects.
POSERS = []

# Modifiers that belong to the splat data itself, not to the scene's deformation of it.
OWN_MODIFIERS = ("Splatwright Display",)


# Edit hooks: callables (obj, depsgraph, cloud) -> cloud, applied in turn to what the object shows
# (object space) before it is placed: clean-up and grading kept as settings on the object (cleanup.py).
EDITS = []


def evaluated_cloud(obj, depsgraph, matrix=None, edits=True):
    """The cloud `obj` shows at the depsgraph's frame, its edits applied (see EDITS; `edits=False`
    leaves them out), then `matrix` (default: the evaluated world matrix). Export, animation export,
    collisions and the render engine all read splat objects through this one function."""
    obj = obj.original
    cloud = generated_cloud(obj, depsgraph)
    if cloud is not None:
        return _transformed(obj, cloud, world_matrix(obj, depsgraph) if matrix is None else matrix)
    pose = next((p for p in (poser(obj, depsgraph) for poser in POSERS) if p is not None), None)
    cloud = pose(own_cloud(obj, depsgraph)) if pose is not None else modified_cloud(obj, depsgraph)
    for edit in EDITS if edits else ():
        cloud = edit(obj, depsgraph, cloud)
    return _transformed(obj, cloud, world_matrix(obj, depsgraph) if matrix is None else matrix)


def own_cloud(obj, depsgraph):
    """The object's own splats; in Edit Mode from the evaluated data (the original holds none until
    synced, which only the main thread may do)."""
    if obj.mode != "EDIT":
        return object_cloud(obj)
    return _evaluated_geometry_cloud(obj, depsgraph)


def _evaluated_geometry_cloud(obj, depsgraph):
    evaluated, form = obj.evaluated_get(depsgraph), splat_form(obj)
    if obj.mode != "EDIT" or obj.type != "MESH":
        return geometry_cloud(evaluated.data, obj.name, form, spec_owner=obj.data)
    mesh = evaluated.to_mesh()      # apart from the edit data, where the attribute API would look
    try:
        return geometry_cloud(mesh, obj.name, form, spec_owner=obj.data)
    finally:
        evaluated.to_mesh_clear()


def is_modified(obj, depsgraph):
    """Whether the depsgraph shows `obj` other than as its own splats: Edit Mode, shape keys, or a
    modifier enabled for the depsgraph's mode besides Splatwright's own."""
    if obj.mode == "EDIT" or getattr(obj.data, "shape_keys", None) is not None:
        return True
    render = depsgraph.mode == "RENDER"
    return any((mod.show_render if render else mod.show_viewport) and mod.name not in OWN_MODIFIERS
               for mod in obj.modifiers)


def modified_cloud(obj, depsgraph):
    """The splats the depsgraph shows for `obj` (object space): its own where nothing changes them,
    else the evaluated ones, with orientations, sizes and SH carried through copies that moved as a
    whole (see carry_frames)."""
    if not is_modified(obj, depsgraph):
        return object_cloud(obj)
    evaluated = _evaluated_geometry_cloud(obj, depsgraph)
    if obj.mode == "EDIT":
        return evaluated
    return carry_frames(object_cloud(obj), evaluated)


def carry_frames(own, evaluated, tolerance=1e-5):
    """`evaluated` (splats after modifiers) with each copy of `own` that moved by one affine map turned
    by that map as a whole: orientations, sizes and SH, not only centres.

    Modifiers copy attributes and move positions. The evaluated splats are taken as copies of `own`
    when their count is a multiple of it and every block of len(own) carries `own`'s rotations and
    scales unchanged; each block's map is then the least-squares affine fit of its centres to
    `own`'s, accepted when every centre lies within `tolerance` (relative to the cloud's size) of it.
    Anything else (shape keys, merged vertices, non-linear deformers) keeps the evaluated splats
    as they are: centres moved, the rest as stored."""
    n, m = len(own), len(evaluated)
    if n == 0 or m % n or m == 0:
        return evaluated
    copies = m // n
    blocks = [evaluated[i * n:(i + 1) * n] for i in range(copies)]
    if not all(np.array_equal(b.rotations, own.rotations) and np.array_equal(b.log_scales, own.log_scales)
               for b in blocks):
        return evaluated
    source = np.c_[own.positions.astype(np.float64), np.ones(n)]
    if np.linalg.matrix_rank(source - source.mean(axis=0) * [1, 1, 1, 0]) < 4:
        return evaluated          # coplanar centres leave the map's normal part unknown
    size = max(1.0, float(np.abs(evaluated.positions).max(initial=0.0)))
    turned = []
    for block in blocks:
        target = block.positions.astype(np.float64)
        fit = np.linalg.lstsq(source, target, rcond=None)[0]          # (4, 3): x -> [x 1] fit
        if np.abs(source @ fit - target).max(initial=0.0) > tolerance * size:
            return evaluated
        matrix = np.eye(4)
        matrix[:3, :] = fit.T
        if not np.allclose(matrix, np.eye(4), atol=tolerance):   # values a modifier set stay; frames turn
            block = transform_cloud(block.replace(positions=own.positions), matrix).replace(positions=block.positions)
        turned.append(block)
    return turned[0] if copies == 1 else SplatCloud.concatenate(turned)


class SplatInstance(NamedTuple):
    obj: object              # the splat object (original)
    instancer: object        # the object that instances it (original), None when drawn as itself
    matrix: np.ndarray       # (4, 4) float64 world matrix of this instance


def splat_instances(depsgraph):
    """A SplatInstance for every splat object the depsgraph draws: objects, linked duplicates and
    instances (collection instances, instancing by vertices or faces), each with its own matrix. The
    display's point cloud of a splat mesh is not counted again."""
    found = []
    for inst in depsgraph.object_instances:          # instance data is only valid during iteration
        evaluated = inst.object
        original = evaluated.original
        instancer = inst.parent.original if inst.is_instance and inst.parent else None
        if evaluated.type == original.type and is_splat_object(original):
            found.append(SplatInstance(original, instancer, np.array(inst.matrix_world, dtype=np.float64)))
        elif _generated(evaluated, original):
            found.append(SplatInstance(original, None if instancer == original else instancer,
                                       np.array(inst.matrix_world, dtype=np.float64)))
    return found


def _generated(evaluated, original):
    """Whether an evaluated point cloud holds Gaussian splats its object's own data does not: splats
    made by geometry nodes (Blender 5.3's Set Point Cloud Type, say), not a splat mesh's display."""
    return evaluated.type == "POINTCLOUD" and not is_splat_object(original) and is_native_splats(evaluated.data)


def generated_cloud(obj, depsgraph):
    """The splats geometry nodes make on `obj` (object space), or None where they make none."""
    evaluated = obj.evaluated_get(depsgraph)
    if is_splat_object(obj) or not hasattr(evaluated, "evaluated_geometry"):
        return None
    geometry = evaluated.evaluated_geometry()          # the point cloud lives as long as this does
    pointcloud = geometry.pointcloud
    if pointcloud is None or not is_native_splats(pointcloud):
        return None
    return geometry_cloud(pointcloud, obj.name, NATIVE_FORM)


def instances_cloud(depsgraph, instances, conversion=np.eye(4)):
    """One cloud of every (object, matrix) of `instances`, `conversion` @ matrix applied to each; each
    object is evaluated once however many instances it has. Splats made for antialiased rendering
    beside classic ones join them as classic (one render shows one mode), with a SplatModeWarning
    naming the objects."""
    own = {}
    clouds = []
    for obj, matrix in instances:
        if obj.name not in own:
            own[obj.name] = evaluated_cloud(obj, depsgraph, np.eye(4))
        clouds.append(_transformed(obj, own[obj.name], conversion @ matrix))
    if len(clouds) == 1:
        return clouds[0]
    marked = sorted(name for name, cloud in own.items() if cloud.antialiased)
    if marked and len(marked) < len(own):
        warnings.warn(f"{', '.join(marked)}: made for antialiased rendering, shown classic beside "
                      "splats made for classic rendering (outlines about a pixel wider)", SplatModeWarning,
                      stacklevel=2)
        clouds = [c.replace(antialiased=False) for c in clouds]
    return SplatCloud.concatenate(clouds)


def _armature_pose(obj, depsgraph):
    """Splats bound to an armature (see rigging); imported on use, as rigging imports this module."""
    from . import rigging
    return rigging.poser(obj, depsgraph)


POSERS.append(_armature_pose)
