"""Splat clouds as Blender data: a mesh whose vertices are the centres, with point attributes.

Layout (all on the POINT domain, in object space):

    position              the vertex coordinates: splat centres
    splat_rotation        QUATERNION   w, x, y, z as stored in the file (any norm)
    splat_log_scale       FLOAT_VECTOR natural log of the per-axis standard deviations
    splat_opacity_logit   FLOAT        logit of the opacity
    splat_sh_<k>          FLOAT_VECTOR SH coefficient k (0 = DC) for r, g, b; k < (degree+1)^2
    splat_extra_<name>    extras a file carried (PLY normals, ...): FLOAT, FLOAT2, FLOAT_VECTOR, INT
                          or BOOLEAN; other matrix shapes as columns splat_extra_<name>.<i>

The mesh custom property "splatwright" (the layout version) marks the mesh as a splat cloud.
Everything moves through foreach_get/foreach_set on float32/int32 buffers: no per-splat Python.
"""

import json

import bpy
import numpy as np

from ..core import SplatCloud, sh as shmod

MARKER = "splatwright"
LAYOUT_VERSION = 1
EXTRAS_SPEC = "splatwright_extras"     # mesh property: JSON {name: [dtype, columns, ndim]}
# Extras that tie splats made from a mesh to its triangles (rigging reads them): bookkeeping of this
# Blender file, not scene content, so exports leave them out.
SOURCE_EXTRAS = ("source_triangle", "barycentric", "source_vertices")

ROTATION = "splat_rotation"
LOG_SCALE = "splat_log_scale"
OPACITY = "splat_opacity_logit"
SH_PREFIX = "splat_sh_"
EXTRA_PREFIX = "splat_extra_"
MAX_NAME = 63                          # Blender attribute names are cut at 64 bytes

# Blender attribute type -> (foreach property, components, NumPy buffer dtype)
_TYPES = {
    "FLOAT": ("value", 1, np.float32),
    "FLOAT2": ("vector", 2, np.float32),
    "FLOAT_VECTOR": ("vector", 3, np.float32),
    "QUATERNION": ("value", 4, np.float32),
    "INT": ("value", 1, np.int32),
    "BOOLEAN": ("value", 1, bool),
}


class SplatObjectError(ValueError):
    """A Blender object that cannot be read as a splat cloud; the message names it and the problem."""


def is_splat_mesh(mesh):
    return mesh is not None and MARKER in mesh.keys()


def is_splat_object(obj):
    return obj is not None and obj.type == "MESH" and is_splat_mesh(obj.data)


def sh_attribute(k):
    return f"{SH_PREFIX}{k}"


# writing ------------------------------------------------------------------------------------------

def _set(mesh, name, kind, values):
    """Write `values` into the point attribute `name`, creating it if needed."""
    prop, width, dtype = _TYPES[kind]
    attr = mesh.attributes.get(name) or mesh.attributes.new(name, kind, "POINT")
    attr.data.foreach_set(prop, np.ascontiguousarray(values, dtype=dtype).reshape(-1))


def _write_core(mesh, cloud):
    _set(mesh, "position", "FLOAT_VECTOR", cloud.positions)      # an empty mesh has no position attribute yet
    _set(mesh, ROTATION, "QUATERNION", cloud.rotations)
    _set(mesh, LOG_SCALE, "FLOAT_VECTOR", cloud.log_scales)
    _set(mesh, OPACITY, "FLOAT", cloud.opacity_logits)
    by_coefficient = _coefficient_major(cloud.sh)
    for k in range(cloud.sh.shape[1]):
        _set(mesh, sh_attribute(k), "FLOAT_VECTOR", by_coefficient[k])


def _coefficient_major(sh, rows=4096):
    """(N, K, 3) -> contiguous (K, N, 3), a block of rows at a time: about twice as fast as one
    whole-array transpose, whose scattered writes miss the cache."""
    out = np.empty((sh.shape[1], sh.shape[0], 3), np.float32)
    for start in range(0, len(sh), rows):
        out[:, start:start + rows] = sh[start:start + rows].transpose(1, 0, 2)
    return out


def cloud_to_mesh(cloud, name):
    """A new mesh datablock holding `cloud` (object space). Returns (mesh, skipped extra names)."""
    mesh = bpy.data.meshes.new(name)
    try:
        n = len(cloud)
        mesh.vertices.add(n)
        _write_core(mesh, cloud)
        skipped = _write_extras(mesh, cloud.extras)
        mesh[MARKER] = LAYOUT_VERSION
        mesh.update()
    except BaseException:
        bpy.data.meshes.remove(mesh)
        raise
    return mesh, skipped


def update_mesh(mesh, cloud):
    """Overwrite a splat mesh's values with `cloud` (same splat count, e.g. after a transform)."""
    if len(cloud) != len(mesh.vertices):
        raise SplatObjectError(f"'{mesh.name}' has {len(mesh.vertices)} vertices, cloud has {len(cloud)}")
    _write_core(mesh, cloud)
    spec = json.loads(mesh.get(EXTRAS_SPEC, "{}"))
    for name, values in cloud.extras.items():
        kind = _extra_kind(values)
        if name in spec and kind is not None:
            _write_extra(mesh, name, values, kind)
    mesh.update()


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


def _write_extra(mesh, name, values, kind):
    columns = values.reshape(len(values), -1).T if kind[1] > 1 else [values]
    for attr_name, column in zip(_extra_names(name, kind[1]), columns):
        _set(mesh, attr_name, kind[0], column)


def _write_extras(mesh, extras):
    """Store what fits as attributes (vectors whole, other matrices column by column); return the
    names that did not fit. The dtype is kept in a mesh property so export restores it."""
    spec, skipped = {}, []
    for name, values in extras.items():
        kind = _extra_kind(values)
        names = _extra_names(name, kind[1]) if kind else []
        if kind is None or len(names[-1]) > MAX_NAME or any(n in mesh.attributes for n in names):
            skipped.append(name)
            continue
        _write_extra(mesh, name, values, kind)
        spec[name] = [values.dtype.str, kind[1], values.ndim]
    if spec:
        mesh[EXTRAS_SPEC] = json.dumps(spec)
    return skipped


# reading ------------------------------------------------------------------------------------------

def _get(mesh, name, kind, owner, out=None):
    """An attribute as an (N, width) array (into `out` if given), or SplatObjectError naming what is
    missing or wrong."""
    attr = mesh.attributes.get(name)
    if attr is None:
        raise SplatObjectError(f"'{owner}' has no '{name}' point attribute")
    if attr.data_type != kind or attr.domain != "POINT":
        raise SplatObjectError(f"'{owner}': attribute '{name}' is {attr.data_type} on {attr.domain}, "
                               f"expected {kind} on POINT")
    prop, width, dtype = _TYPES[kind]
    if out is None:
        out = np.empty((len(mesh.vertices), width), dtype=dtype)
    attr.data.foreach_get(prop, out.reshape(-1))
    return out


def mesh_to_cloud(mesh, owner=None):
    """The SplatCloud a splat mesh holds, in object space."""
    owner = owner or mesh.name
    if not is_splat_mesh(mesh):
        raise SplatObjectError(f"'{owner}' is not a splat cloud (mesh without the '{MARKER}' marker)")
    positions = _get(mesh, "position", "FLOAT_VECTOR", owner)
    by_coefficient = np.empty((_sh_count(mesh, owner), len(positions), 3), np.float32)
    for k, rows in enumerate(by_coefficient):
        _get(mesh, sh_attribute(k), "FLOAT_VECTOR", owner, out=rows)
    sh = by_coefficient.transpose(1, 0, 2)     # a view: (N, K, 3) without copying
    return SplatCloud(
        positions=positions,
        rotations=_get(mesh, ROTATION, "QUATERNION", owner),
        log_scales=_get(mesh, LOG_SCALE, "FLOAT_VECTOR", owner),
        opacity_logits=_get(mesh, OPACITY, "FLOAT", owner)[:, 0],
        sh=sh,
        extras=_read_extras(mesh, owner),
    )


def _sh_count(mesh, owner):
    present = {int(a.name[len(SH_PREFIX):]) for a in mesh.attributes
               if a.name.startswith(SH_PREFIX) and a.name[len(SH_PREFIX):].isdigit()}
    count = max(present, default=-1) + 1
    missing = sorted(set(range(count)) - present)
    if count not in shmod.VALID_COUNTS or missing:
        raise SplatObjectError(f"'{owner}': SH attributes {SH_PREFIX}0..{count - 1} do not form a full "
                               f"degree (found {count} coefficients, missing {missing or 'none'}; "
                               f"need 1, 4, 9 or 16)")
    return count


def _read_extras(mesh, owner):
    spec = json.loads(mesh.get(EXTRAS_SPEC, "{}"))
    extras = {}
    for name, (dtype, columns, ndim) in spec.items():
        names = _extra_names(name, columns)
        if all(n in mesh.attributes for n in names):
            values = np.concatenate([_get(mesh, n, mesh.attributes[n].data_type, owner) for n in names], axis=1)
            extras[name] = (values[:, 0] if ndim == 1 else values).astype(np.dtype(dtype))
    # Extras joined in from another splat object whose spec was not kept: read them as stored.
    known = {n for name, (_, columns, _) in spec.items() for n in _extra_names(name, columns)}
    for attr in mesh.attributes:
        name = attr.name[len(EXTRA_PREFIX):]
        if attr.name.startswith(EXTRA_PREFIX) and attr.name not in known and "." not in name \
                and attr.domain == "POINT" and attr.data_type in _TYPES:
            values = _get(mesh, attr.name, attr.data_type, owner)
            extras[name] = values[:, 0] if values.shape[1] == 1 else values
    return extras


# objects --------------------------------------------------------------------------------------------

def new_splat_object(cloud, name, collection, matrix=None):
    """Link a new splat object holding `cloud` into `collection`; returns (object, skipped extras)."""
    mesh, skipped = cloud_to_mesh(cloud, name)
    try:
        obj = bpy.data.objects.new(name, mesh)
        if matrix is not None:
            obj.matrix_world = matrix
        collection.objects.link(obj)
    except BaseException:
        bpy.data.meshes.remove(mesh)
        raise
    return obj, skipped


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
    """The splat cloud of `obj` with `matrix` (usually conversion @ world matrix) applied."""
    return _transformed(obj, mesh_to_cloud(obj.data, owner=obj.name), matrix)


def _transformed(obj, cloud, matrix):
    """transform_cloud, with a transform it refuses (singular, NaN) reported as the object's."""
    try:
        return transform_cloud(cloud, matrix)
    except ValueError as exc:
        raise SplatObjectError(f"'{obj.name}': {exc}") from None


# Posing hooks: callables (obj, depsgraph, cloud) -> cloud that deform a splat object's cloud in
# object space (an armature pose, say) before its world matrix is applied. Each returns the cloud
# unchanged when it does not apply to the object.
DEFORMERS = []


def evaluated_cloud(obj, depsgraph, matrix=None):
    """The cloud `obj` shows at the depsgraph's frame: its splats, posed by DEFORMERS, then `matrix`
    applied (default: the evaluated world matrix). Export, animation export and the render engine
    all read splat objects through this one function."""
    obj = obj.original
    cloud = mesh_to_cloud(obj.data, owner=obj.name)
    for deform in DEFORMERS:
        cloud = deform(obj, depsgraph, cloud)
    return _transformed(obj, cloud, world_matrix(obj, depsgraph) if matrix is None else matrix)


def _armature_pose(obj, depsgraph, cloud):
    """Splats bound to an armature (see rigging); imported on use, as rigging imports this module."""
    from . import rigging
    return rigging.deform(obj, depsgraph, cloud)


DEFORMERS.append(_armature_pose)
