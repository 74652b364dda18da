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
    <name>, _<name>       other point attributes Blender's importers kept of a file (a PLY's extra
                          properties, albedo_0..2 joined into one albedo; a glTF's `_<name>`
                          attributes): read as the extras <name> (attributes.foreign_extras)

What the attributes are called: keys.py; how they are read and written: attributes.py.
"""

import json

import bpy
import numpy as np

from ...core import SplatCloud
from ...core import sh as shmod
from ...core.splats import sigmoid
from .attributes import (
    BASE_TYPES,
    _changed,
    _coefficient_major,
    _exact_or,
    _extra_kind,
    _extra_names,
    _get,
    _read_extras,
    _read_sh,
    _set,
    _sh_count,
    _write_extra,
    _write_extras,
    base_type,
    foreign_extras,
    native_log_scales,
    native_opacity_logits,
    sh_attribute,
    splat_count,
)
from .errors import SplatObjectError
from .keys import (
    ANTIALIASED,
    EXACT_LOG_SCALE,
    EXACT_LOGIT,
    EXTRAS_SPEC,
    LANDING,
    LAYOUT_VERSION,
    LOG_SCALE,
    MARKER,
    MAX_NAME,
    MESH_FORM,
    NATIVE_BASE,
    NATIVE_FORM,
    NATIVE_REQUIRED,
    NATIVE_ROTATION,
    NATIVE_SCALE,
    NATIVE_SH_PREFIX,
    OPACITY,
    REST_PREFIX,
    ROTATION,
    SH_PREFIX,
    SPZ_POSITION_BITS,
)
from .transforms import remember_frame, transform_cloud

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


# the mesh form ----------------------------------------------------------------------------------------


def _write_mesh_form(mesh, cloud):
    _set(mesh, "position", "FLOAT_VECTOR", cloud.positions)  # an empty mesh has no position attribute yet
    _set(mesh, ROTATION, "QUATERNION", cloud.rotations)
    _set(mesh, LOG_SCALE, "FLOAT_VECTOR", cloud.log_scales)
    _set(mesh, OPACITY, "FLOAT", cloud.opacity_logits)
    by_coefficient = _coefficient_major(cloud.sh)
    for k in range(cloud.sh.shape[1]):
        _set(mesh, sh_attribute(k), "FLOAT_VECTOR", by_coefficient[k])


def _read_mesh_form(mesh, owner):
    sh = _read_sh(mesh, SH_PREFIX, 0, owner, _sh_count(mesh, SH_PREFIX, 0, owner))
    return dict(
        positions=_get(mesh, "position", "FLOAT_VECTOR", owner),
        rotations=_get(mesh, ROTATION, "QUATERNION", owner),
        log_scales=_get(mesh, LOG_SCALE, "FLOAT_VECTOR", owner),
        opacity_logits=_get(mesh, OPACITY, "FLOAT", owner)[:, 0],
        sh=sh,
    )


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
        suffix = name[len(sh_prefix) :]
        if suffix.isdigit() and int(suffix) >= cloud.sh.shape[1] - 1:  # a lower degree than before
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
    return dict(
        positions=_get(pointcloud, prefix + "position", "FLOAT_VECTOR", owner),
        rotations=_get(pointcloud, prefix + NATIVE_ROTATION, "QUATERNION", owner),
        log_scales=_exact_or(pointcloud, prefix + EXACT_LOG_SCALE, "FLOAT_VECTOR", owner, scales, native_log_scales),
        opacity_logits=_exact_or(pointcloud, prefix + EXACT_LOGIT, "FLOAT", owner, base[:, 3:], native_opacity_logits)[
            :, 0
        ],
        sh=sh,
    )


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


# where the values stand -------------------------------------------------------------------------------


def landed_raw(obj):
    """Whether `obj`'s own splats are a file's axes placed as they are (a capture lying on its side):
    what Blender's PLY importer makes, while Splatwright's importers and Blender's SPZ importer stand
    captures upright. Exports write such splats in those axes, so the file comes back as it was.

    Splatwright records the answer on every datablock it makes or changes (LANDING), and on clouds
    Blender's importers make as they appear (stamp_unrecorded). Unrecorded, the splats decide: SPZ's
    fixed-point grid, which the SPZ importer's centres lie on and a PLY's float32 centres (past a
    handful) do not."""
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
    values = values[np.isfinite(values) & (values != 0)]  # NaN/Inf say nothing of a grid (export refuses them)
    if values.size == 0:
        return True
    fraction, exponent = np.frexp(values)  # values = fraction 2^exponent, 0.5 <= |fraction| < 1
    mantissa = np.abs(fraction * 2.0**53).astype(np.uint64)
    trailing = np.log2((mantissa & (~mantissa + np.uint64(1))).astype(np.float64))
    bits_needed = np.maximum(53 - exponent - trailing, 0).max()
    return bool(np.abs(values).max() * 2.0**bits_needed < 2.0 ** (SPZ_POSITION_BITS - 1))


def stamp_unrecorded(obj, at_import=True):
    """Record where an unstamped native cloud's splats stand. Blender's importers record nothing, but
    the depsgraph update inside each import operator shows the new object as the importer left it
    (`at_import`): its PLY and SPZ importers at the identity (landed_raw tells them apart), its USD
    importer turned by the stage's up axis and the prim's transform, a turn of the axes for the files
    of Splatwright and OpenUSD's converters (the splats then stand as the stage shows them, upright).
    Any other placement is a script's: left to landed_raw, as are clouds of files saved before stamps
    were kept (`at_import` False)."""
    if obj.type != "POINTCLOUD" or LANDING in obj.data or obj.data.library is not None:
        return
    if splat_form(obj) != NATIVE_FORM:
        return
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    if not at_import or np.array_equal(matrix, np.eye(4)):
        stamp_landing(obj)
    elif _turns_axes(matrix[:3, :3]):
        stamp_landing(obj, raw=False)


def _turns_axes(linear):
    """Whether a linear map is a signed permutation of the axes times a uniform scale (to float32
    round-off of its Euler angles)."""
    size = abs(np.linalg.det(linear)) ** (1 / 3)
    if not np.isfinite(size) or size == 0:
        return False
    unit = linear / size
    rounded = np.round(unit)
    permutes = (np.abs(rounded).sum(axis=0) == 1).all() and (np.abs(rounded).sum(axis=1) == 1).all()
    return bool(permutes and np.abs(unit - rounded).max() <= 1e-6)


def stamp_landing(obj, raw=None):
    """Record where `obj`'s splats stand before Splatwright changes them (afterwards they no longer
    look like what an importer made): `raw`, or what landed_raw finds now."""
    obj.data[LANDING] = "RAW" if (landed_raw(obj) if raw is None else raw) else "UPRIGHT"


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
    extras = _read_extras(geometry, owner, spec_owner)
    if form == NATIVE_FORM:  # what Blender's importers kept of a file besides the splats
        extras = {**foreign_extras(geometry, owner, spec_owner, taken=extras), **extras}
    return SplatCloud(**read(geometry, owner), extras=extras, antialiased=made_antialiased(spec_owner))


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
        raise SplatObjectError(
            f"Blender {bpy.app.version_string} cannot make point clouds from Python "
            f"(Blender 4.5 and later can): '{name}' stays a splat mesh"
        )
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(count)
    obj = bpy.data.objects.new(name, mesh)
    scene = bpy.context.scene
    scene.collection.objects.link(obj)
    try:
        with bpy.context.temp_override(
            active_object=obj, object=obj, selected_objects=[obj], selected_editable_objects=[obj]
        ):
            bpy.ops.object.convert(target="POINTCLOUD")
        pointcloud = obj.data
        if not isinstance(pointcloud, bpy.types.PointCloud):
            raise SplatObjectError(f"Blender could not make a point cloud for '{name}'")
        pointcloud.name = name
        return pointcloud
    finally:
        mesh_left = obj.data if isinstance(obj.data, bpy.types.Mesh) else None
        bpy.data.objects.remove(obj)
        if mesh_left is not None:  # not converted: that is `mesh`, gone now
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


def set_extras(obj, extras):
    """Store `extras` ({name: (N,) or (N, k) array}) on the splat object `obj`'s own splats, adding
    those it lacks and overwriting those it has (the spec that export reads updated to match);
    returns the names that fit no attribute."""
    geometry = obj.data
    count = splat_count(geometry)
    wrong = [f"'{name}' has {len(values)} rows" for name, values in extras.items() if len(values) != count]
    if wrong:
        raise SplatObjectError(f"'{obj.name}' has {count} splats: {', '.join(wrong)}")
    spec, skipped = json.loads(geometry.get(EXTRAS_SPEC, "{}")), []
    for name, values in extras.items():
        values = np.asarray(values)
        kind = _extra_kind(values)
        if kind is None or len(_extra_names(name, kind[1])[-1]) > MAX_NAME:
            skipped.append(name)
            continue
        _write_extra(geometry, name, values, kind)  # replaces an attribute of that name
        spec[name] = [values.dtype.str, kind[1], values.ndim]
    geometry[EXTRAS_SPEC] = json.dumps(spec)
    _changed(geometry)
    return skipped


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


def object_to_cloud(obj, matrix):
    """The splat cloud of `obj` (its own splats) with `matrix` (usually conversion @ world matrix) applied."""
    return _transformed(obj, object_cloud(obj), matrix)


def _transformed(obj, cloud, matrix):
    """transform_cloud, with a transform it refuses (singular, NaN) reported as the object's."""
    try:
        return transform_cloud(cloud, matrix)
    except ValueError as exc:
        raise SplatObjectError(f"'{obj.name}': {exc}") from None
