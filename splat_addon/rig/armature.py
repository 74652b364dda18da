"""Splat objects bound to an armature: bone weights as vertex groups, an Armature modifier, and the
posing deformer that export, animated export, collisions and the render engine read splats through.

Binding (`bind_armature`) gives each splat up to k bone weights, stored as vertex groups named by
bone so they can be painted, and adds an Armature modifier first in the stack, so the viewport
display shows the posed centres. The weights come from:

- the skinned mesh the splats were made from (the splat mesh's `splatwright_source` names it): its
  vertex-group weights interpolated with each splat's barycentrics over `source_vertices`, an exact
  transfer, since a surface point deforms with the barycentric blend of its corners' weights;
- otherwise the bones themselves: w_b proportional to (d_min / d_b)^falloff, d_b the distance from the
  splat centre to bone b's rest segment, so each splat follows its nearest bone and splats near a
  joint blend the bones meeting there.

Weights below `min_weight` of a splat's total are dropped, then all but the k largest; the rest is
normalised (Blender divides by the total anyway).

Posing (`poser`, put in data.POSERS by register()): Blender's Armature modifier moves the vertices only,
so the deformer re-reads the splats from the original mesh, reads the weights from the vertex groups
and skins centres, covariances and SH with the core (linear blend, or dual quaternions with the
modifier's Preserve Volume), in armature space as Blender does. The modifier's vertex-group mask
(`vertex_group`, `invert_vertex_group`) is a per-splat binding strength m, read as Blender reads it: a
splat moves to (1 - m) rest + m posed, its covariance and SH turn by the bones' map blended with the
identity (core.skinning), and a splat outside the group stays still. Native splats hold that strength
as the FLOAT attribute named like MASK_GROUP. Bone envelopes, B-Bone curves and multi-modifier mixing
are not used.

Vertex-group weights cannot be read through foreach_get. They are read in one pass per mesh by a
temporary object evaluating a tiny geometry-nodes group (Mesh to Points turns every vertex group into
a float point attribute, which foreach_get can read), and cached per mesh until the mesh, its groups
or the object's geometry is edited. The temporary object lives in a temporary scene: linked into the
user's scene, it would be evaluated into that scene's depsgraph and then freed under anyone still
reading it (an exporter or a background render iterating object_instances, which crashed so). The
read needs the main thread (it adds a scene and an object for a moment):
a render in a background thread uses the cache, which interactive sessions keep filled.
"""

import json
import threading
from dataclasses import dataclass

import bpy
import numpy as np
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty

from ...core.skinning import Binding, BonePose, SkinningError, skin
from .. import data
from ..data.errors import EXPECTED_ERRORS
from ..data.keys import SOURCE

READER_GROUP = ".Splatwright Weight Reader"
READER_TAG = "splatwright_weight_reader"  # node group property: build version
READER_VERSION = 2  # 2: loose vertices, read through to_mesh()
READER_DROPPED = ("splat_sh_*", "splat_extra_*")  # splat data the reader need not copy
READER_SCENE = ".splatwright weights"  # the reader's scene and object, there only while it reads
TEMP_ATTRIBUTE = "splatwright_weight_in"  # holds one bone's weights while it becomes a group
WEIGHT_PREFIX = "splat_weight:"  # native splats: one FLOAT point attribute per bone
ARMATURE_PROPERTY = "splatwright_armature"  # native splats: the armature object binding them
PRESERVE_VOLUME_PROPERTY = "splatwright_preserve_volume"
MASK_GROUP = "splatwright_bind_strength"  # binding strength: the modifier's mask group (mesh),
# a FLOAT attribute of that name (native splats)
DEFAULT_INFLUENCES = 4
DEFAULT_FALLOFF = 4.0
DEFAULT_MIN_WEIGHT = 0.01
REFRESH_DELAY = 0.3  # seconds after an edit before cached weights refill


class RiggingError(ValueError):
    """A binding that cannot be made; the message names the object and the problem."""


# armatures and bones -------------------------------------------------------------------------------


def armature_modifier(obj, depsgraph=None):
    """The first Armature modifier of `obj` that deforms by vertex groups in the depsgraph's mode
    (viewport or render) with an armature object set, or None."""
    render = depsgraph is not None and depsgraph.mode == "RENDER"
    for mod in obj.modifiers:
        if (
            mod.type == "ARMATURE"
            and (mod.show_render if render else mod.show_viewport)
            and mod.object is not None
            and mod.object.type == "ARMATURE"
            and mod.use_vertex_groups
        ):
            return mod
    return None


def rig_of(obj, depsgraph=None):
    """(armature object, preserve volume) that bind splat object `obj`, or None: the Armature modifier
    of a splat mesh (in the depsgraph's mode), the armature property of native splats."""
    if obj.type == "MESH":
        mod = armature_modifier(obj, depsgraph)
        return None if mod is None else (mod.object, mod.use_deform_preserve_volume)
    arm = obj.get(ARMATURE_PROPERTY)
    if not isinstance(arm, bpy.types.Object) or arm.type != "ARMATURE":
        return None
    return arm, bool(obj.get(PRESERVE_VOLUME_PROPERTY, False))


def binding_mask(obj, depsgraph=None):
    """(group name, inverted) of the binding-strength mask of a bound splat object, or None when every
    splat binds fully: the Armature modifier's vertex-group mask when that group exists (Blender
    ignores a mask naming no group), the MASK_GROUP attribute of native splats."""
    if obj.type == "MESH":
        mod = armature_modifier(obj, depsgraph)
        if mod is None or not mod.vertex_group or obj.vertex_groups.get(mod.vertex_group) is None:
            return None
        return mod.vertex_group, bool(mod.invert_vertex_group)
    attr = obj.data.attributes.get(MASK_GROUP)
    return (MASK_GROUP, False) if attr is not None and attr.data_type == "FLOAT" else None


def weight_names(obj):
    """Bone names `obj` holds weights for: its vertex groups (mesh) or weight attributes (native)."""
    if obj.type == "MESH":
        return [g.name for g in obj.vertex_groups]
    return [a.name[len(WEIGHT_PREFIX) :] for a in obj.data.attributes if a.name.startswith(WEIGHT_PREFIX)]


def deform_bones(arm):
    """Names of the bones of an armature object that deform, in the armature's order."""
    return [bone.name for bone in arm.data.bones if bone.use_deform]


def bone_pose(arm, names):
    """The core BonePose of the named bones of an (evaluated) armature object, in armature space:
    rest = bone.matrix_local, pose = pose_bone.matrix, as Blender's Armature modifier uses them."""
    rest = np.array([arm.data.bones[n].matrix_local for n in names], dtype=np.float64)
    pose = np.array([arm.pose.bones[n].matrix for n in names], dtype=np.float64)
    return BonePose.from_blender(rest, pose)


def to_armature_space(obj, arm, depsgraph=None):
    """The matrix taking `obj`'s object space to `arm`'s armature space (float64)."""
    return np.linalg.inv(data.world_matrix(arm, depsgraph)) @ data.world_matrix(obj, depsgraph)


# reading vertex groups --------------------------------------------------------------------------------


def _reader_group():
    """The node group that turns a mesh into loose vertices, one per vertex, its vertex groups
    becoming float point attributes (built once per file)."""
    group = data.built_datablock(bpy.data.node_groups, READER_GROUP, READER_TAG, READER_VERSION)
    if group is not None:
        return group
    group = bpy.data.node_groups.new(READER_GROUP, "GeometryNodeTree")
    group[READER_TAG] = READER_VERSION
    group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    socket = nodes.new("NodeGroupInput").outputs[0]
    for pattern in READER_DROPPED:
        drop = nodes.new("GeometryNodeRemoveAttribute")
        if "Pattern Mode" in drop.inputs:  # a menu socket from Blender 5.0, a property before
            drop.inputs["Pattern Mode"].default_value = "Wildcard"
        else:
            drop.pattern_mode = "WILDCARD"
        drop.inputs["Name"].default_value = pattern
        links.new(socket, drop.inputs["Geometry"])
        socket = drop.outputs["Geometry"]
    # Points have no vertex groups, so the groups become plain attributes; back to vertices, they stay
    # so on the evaluated mesh, where foreach_get reads them (every Blender has to_mesh()).
    to_points, to_vertices = nodes.new("GeometryNodeMeshToPoints"), nodes.new("GeometryNodePointsToVertices")
    links.new(socket, to_points.inputs["Mesh"])
    links.new(to_points.outputs["Points"], to_vertices.inputs["Points"])
    links.new(to_vertices.outputs["Mesh"], nodes.new("NodeGroupOutput").inputs[0])
    return group


def can_read_groups():
    """Reading vertex groups adds an object for a moment: only the main thread may do that."""
    return threading.current_thread() is threading.main_thread()


def read_vertex_groups(mesh, names):
    """(len(names), V) float32 weights of the named vertex groups of `mesh`, 0 where a vertex is not
    in a group. One evaluation of a temporary object sharing the mesh, in a scene of its own so the
    depsgraph of the user's scene (which a caller may be reading) is neither changed nor re-evaluated
    while an object comes and goes; main thread only."""
    out = np.zeros((len(names), len(mesh.vertices)), np.float32)
    if not names or not len(mesh.vertices):
        return out
    if not can_read_groups():
        raise data.SplatObjectError(f"'{mesh.name}': vertex-group weights can only be read on Blender's main thread")
    scene = bpy.data.scenes.new(READER_SCENE)
    helper = bpy.data.objects.new(READER_SCENE, mesh)
    try:
        helper.modifiers.new("Read Weights", "NODES").node_group = _reader_group()
        scene.collection.objects.link(helper)
        with bpy.context.temp_override(scene=scene, view_layer=scene.view_layers[0]):
            evaluated = helper.evaluated_get(bpy.context.evaluated_depsgraph_get())
        try:
            vertices = evaluated.to_mesh()
            for row, name in zip(out, names):
                attr = vertices.attributes.get(name)
                if attr is None or attr.data_type != "FLOAT" or len(attr.data) != len(row):
                    raise data.SplatObjectError(f"'{mesh.name}': vertex group '{name}' could not be read")
                attr.data.foreach_get("value", row)
        finally:
            evaluated.to_mesh_clear()
    finally:
        bpy.data.objects.remove(helper)
        bpy.data.scenes.remove(scene)
    return out


def group_weights(obj, bones):
    """(bone names with weights, (G, N) weights) for `obj`'s vertex groups (mesh) or weight attributes
    (native) named like `bones`, in the object's order."""
    wanted = set(bones)
    names = [name for name in weight_names(obj) if name in wanted]
    if obj.type == "MESH":
        return names, read_vertex_groups(obj.data, names)
    columns = np.empty((len(names), data.splat_count(obj.data)), np.float32)
    for row, name in zip(columns, names):
        obj.data.attributes[WEIGHT_PREFIX + name].data.foreach_get("value", row)
    return names, columns


def binding_from_groups(columns, bone_of_column, count):
    """A core Binding from per-group weight columns (G, N). A splat's influences keep the group
    order, as Blender blends a vertex's groups in their order; nothing is pruned."""
    rows, cols = np.nonzero(columns.T > 0)  # sorted by splat, then by group
    per_splat = np.bincount(rows, minlength=count)
    width = max(int(per_splat.max(initial=0)), 1)
    slot = np.arange(len(rows)) - np.repeat(np.cumsum(per_splat) - per_splat, per_splat)
    indices = np.zeros((count, width), np.int32)
    weights = np.zeros((count, width), np.float32)
    indices[rows, slot] = np.asarray(bone_of_column, np.int32)[cols]
    weights[rows, slot] = columns[cols, rows]
    return Binding.from_weights(indices, weights, tolerance=0.0)


# cached bindings: mesh session_uid -> ((groups, vertex count, bones), Binding); strengths likewise
_CACHE = {}
_STRENGTHS = {}


def splat_binding(obj, bones):
    """The Binding of splat object `obj` to the bones named `bones` (indices into that list), from
    its vertex groups; cached until the mesh or its groups change."""
    geometry = obj.data
    count = data.splat_count(geometry)
    state = (tuple(weight_names(obj)), count, tuple(bones))
    cached = _CACHE.get(geometry.session_uid)
    if cached is not None and cached[0] == state:
        return cached[1]
    if obj.type == "MESH" and not can_read_groups():
        raise data.SplatObjectError(
            f"'{obj.name}': its bone weights changed and cannot be re-read during this render; render again"
        )
    names, columns = group_weights(obj, bones)
    index = {name: i for i, name in enumerate(bones)}
    binding = binding_from_groups(columns, [index[n] for n in names], count)
    _CACHE[geometry.session_uid] = (state, binding)
    return binding


def splat_strength(obj, mask):
    """(N,) float64 binding strengths of splat object `obj` under `mask` (a binding_mask), or None
    when there is no mask; cached like the weights."""
    if mask is None:
        return None
    geometry = obj.data
    count = data.splat_count(geometry)
    state = (tuple(weight_names(obj)), count, mask)
    cached = _STRENGTHS.get(geometry.session_uid)
    if cached is not None and cached[0] == state:
        return cached[1]
    if obj.type == "MESH":
        if not can_read_groups():
            raise data.SplatObjectError(
                f"'{obj.name}': its binding strengths changed and cannot be re-read during this render; render again"
            )
        weights = read_vertex_groups(geometry, [mask[0]])[0]
    else:
        weights = np.empty(count, np.float32)
        geometry.attributes[mask[0]].data.foreach_get("value", weights)
    strength = np.clip(weights.astype(np.float64), 0.0, 1.0)  # Blender clamps group weights too
    strength = 1.0 - strength if mask[1] else strength
    _STRENGTHS[geometry.session_uid] = (state, strength)
    return strength


def forget_weights(mesh=None):
    """Drop the cached weights and strengths of `mesh` (all meshes when None)."""
    for cache in (_CACHE, _STRENGTHS):
        if mesh is None:
            cache.clear()
        else:
            cache.pop(mesh.session_uid, None)


def is_cached(geometry):
    return geometry.session_uid in _CACHE or geometry.session_uid in _STRENGTHS


# posing -----------------------------------------------------------------------------------------------


def poser(obj, depsgraph):
    """None when nothing binds `obj` at the depsgraph; else a function posing its own splats (object
    space) by its armature there. A data.POSERS hook (see data.evaluated_cloud)."""
    rig = rig_of(obj, depsgraph)
    if rig is None:
        return None
    arm, preserve_volume = rig[0].evaluated_get(depsgraph), rig[1]
    bones = deform_bones(arm)
    if not bones or not set(bones) & set(weight_names(obj)):
        return None

    mask = binding_mask(obj, depsgraph)

    def pose(cloud):
        binding = splat_binding(obj, bones)
        to_arm = to_armature_space(obj, arm, depsgraph)
        posed = skin(
            data.transform_cloud(cloud, to_arm),
            binding,
            bone_pose(arm, bones),
            mode="dqs" if preserve_volume else "lbs",
            strength=splat_strength(obj, mask),
        )
        return data.transform_cloud(posed, np.linalg.inv(to_arm))

    return pose


def deform(obj, depsgraph, cloud):
    """`cloud` (the splats of `obj`, object space) posed at the depsgraph's frame; itself when nothing
    binds the object."""
    pose = poser(obj, depsgraph)
    return cloud if pose is None else pose(cloud)


def main_bones(obj):
    """(bone names, (N,) index of each splat's largest-weight bone, -1 for none) for a splat object
    bound to an armature; None when it is not bound."""
    rig = rig_of(obj)
    if rig is None:
        return None
    bones = deform_bones(rig[0])
    binding = splat_binding(obj, bones)
    largest = np.argmax(binding.weights, axis=1)
    top = np.take_along_axis(binding.indices, largest[:, None], axis=1)[:, 0]
    bound = binding.weights.max(axis=1) > 0
    return bones, np.where(bound, top, -1)


# computing weights ------------------------------------------------------------------------------------


def segment_distances(points, heads, tails):
    """(N, B) distances from points (N,3) to the segments heads[b]-tails[b] (B,3)."""
    axis = tails - heads
    length2 = np.einsum("bi,bi->b", axis, axis)
    rel = points[:, None, :] - heads[None]
    t = np.einsum("nbi,bi->nb", rel, axis) / np.where(length2 > 0, length2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * axis[None], axis=2)


def bone_weights(points, heads, tails, falloff=DEFAULT_FALLOFF, chunk=1 << 15):
    """(N, B) weights from distances to the bones' segments: (d_min / d_b)^falloff, 1 for the nearest
    bone, smooth wherever two bones are about as near (at joints)."""
    scale = max(float(np.linalg.norm(tails - heads, axis=1).max(initial=0.0)), 1e-9)
    out = np.empty((len(points), len(heads)))
    for start in range(0, len(points), chunk):
        d = segment_distances(points[start : start + chunk], heads, tails) + 1e-9 * scale
        out[start : start + chunk] = (d.min(axis=1, keepdims=True) / d) ** falloff
    return out


def source_weights(obj, bones, warn):
    """(N, B) weights interpolated from the skinned mesh `obj` was made from, or None when it was not
    made from a mesh with vertex groups named like `bones` (or its indices no longer fit)."""
    record = json.loads(obj.data.get(SOURCE, "null") or "null")
    if not record:
        return None
    source = bpy.data.objects.get(record.get("object", ""))
    if source is None or source.type != "MESH":
        warn(f"'{obj.name}': its source mesh '{record.get('object')}' is gone; weights come from the bones")
        return None
    extras = data.object_cloud(obj).extras
    corners, bary = extras.get("source_vertices"), extras.get("barycentric")
    if corners is None or bary is None:
        return None
    if record.get("vertices") != record.get("original_vertices"):
        warn(
            f"'{obj.name}' was made from '{source.name}' after modifiers that change its vertices, so its "
            "splats cannot be traced to the mesh's vertices; weights come from the bones"
        )
        return None
    vertex_count = len(source.data.vertices)
    if record.get("vertices") != vertex_count or corners.size and corners.max() >= vertex_count:
        warn(
            f"'{obj.name}': '{source.name}' no longer has the vertices its splats were made from; "
            "weights come from the bones"
        )
        return None
    names, columns = group_weights(source, bones)
    if not names:
        if len(source.vertex_groups):
            warn(
                f"'{obj.name}': no vertex group of its source mesh '{source.name}' is named like a deforming "
                "bone; weights come from the bones"
            )
        return None
    if not record.get("rest_pose", True):
        warn(f"'{obj.name}' was made from the posed mesh; the binding takes its splats as the rest pose")
    corners = corners.astype(np.int64)
    bary = bary.astype(np.float64)
    weights = np.zeros((len(corners), len(bones)))
    for name, column in zip(names, columns):
        weights[:, bones.index(name)] = np.einsum("nk,nk->n", bary, column.astype(np.float64)[corners])
    return np.maximum(weights, 0.0)


@dataclass
class BindPlan:
    """The weights one splat object gets: (N, B) dense weights over `bones` after pruning, and
    (N,) binding strengths in 0..1 (the mask MASK_GROUP; None: every splat binds fully)."""

    obj: object
    bones: list
    weights: np.ndarray
    source: str  # where the weights came from, for the report
    report: dict
    strength: np.ndarray = None


def plan_binding(
    obj,
    arm,
    max_influences=DEFAULT_INFLUENCES,
    use_source=True,
    falloff=DEFAULT_FALLOFF,
    min_weight=DEFAULT_MIN_WEIGHT,
    warn=print,
):
    """Compute the weights binding splat object `obj` to armature object `arm` (nothing changes)."""
    if not data.is_splat_object(obj):
        raise RiggingError(f"'{obj.name}' is not a splat object")
    bones = deform_bones(arm)
    if not bones:
        raise RiggingError(f"armature '{arm.name}' has no deforming bones")
    if data.splat_count(obj.data) == 0:
        raise RiggingError(f"'{obj.name}' has no splats to bind")
    dense = source_weights(obj, bones, warn) if use_source else None
    if dense is not None:
        # Splats on unweighted vertices stay unbound: they stay put, as those vertices do.
        source, tolerance = f"mesh '{json.loads(obj.data[SOURCE])['object']}'", 1e-6
    else:
        centres = data.object_cloud(obj).positions.astype(np.float64)
        to_arm = to_armature_space(obj, arm)
        centres = centres @ to_arm[:3, :3].T + to_arm[:3, 3]
        bad = ~np.isfinite(centres).all(axis=1)
        if bad.any():  # (its transform or its splats): no bone is nearest to them
            raise RiggingError(
                f"'{obj.name}': {int(bad.sum())} splat centres are NaN or infinite where '{arm.name}' sees them"
            )
        heads = np.array([arm.data.bones[n].head_local for n in bones], np.float64)
        tails = np.array([arm.data.bones[n].tail_local for n in bones], np.float64)
        dense = bone_weights(centres, heads, tails, falloff)
        source, tolerance = "bones", min_weight
    return plan_from_weights(obj, bones, dense, source, max_influences, tolerance)


def plan_from_weights(obj, bones, dense, source, max_influences, tolerance):
    """The BindPlan of (N, B) `dense` weights over `bones`, pruned below `tolerance` of each splat's
    total and to `max_influences`."""
    binding = Binding.from_dense(dense, max_influences=max_influences, tolerance=tolerance)
    pruned = np.zeros_like(dense, dtype=np.float32)
    rows, slots = np.nonzero(binding.weights > 0)  # unused slots pad with bone 0: skip them
    pruned[rows, binding.indices[rows, slots]] = binding.weights[rows, slots]
    return BindPlan(obj, bones, pruned, source, binding.report())


# writing the binding ----------------------------------------------------------------------------------


def write_weights(obj, bones, weights):
    """Store the columns of (N, B) `weights` on `obj` as its weights for `bones`: vertex groups on a
    splat mesh (to paint into), FLOAT attributes splat_weight:<bone> on native splats."""
    if obj.type == "MESH":
        write_vertex_groups(obj, bones, weights)
        return
    for name in bones:
        data.set_attribute(obj.data, WEIGHT_PREFIX + name, "FLOAT", weights[:, bones.index(name)])


def write_vertex_groups(obj, bones, weights):
    """Replace `obj`'s vertex groups named like `bones` with the columns of (N, B) `weights`, each
    group holding only its splats with a nonzero weight; every bone gets a group, to paint into."""
    for name in bones:
        group = obj.vertex_groups.get(name)
        if group is not None:
            obj.vertex_groups.remove(group)
    mesh = obj.data
    for b, name in enumerate(bones):
        if not weights[:, b].any():
            obj.vertex_groups.new(name=name)
            continue
        # A whole column at once: a float attribute converted to a vertex group (no per-vertex calls).
        attr = mesh.attributes.new(TEMP_ATTRIBUTE, "FLOAT", "POINT")
        attr.data.foreach_set("value", np.ascontiguousarray(weights[:, b], np.float32))
        mesh.attributes.active = mesh.attributes[TEMP_ATTRIBUTE]
        with bpy.context.temp_override(object=obj, active_object=obj):
            done = bpy.ops.geometry.attribute_convert(mode="VERTEX_GROUP")
        group = obj.vertex_groups.get(TEMP_ATTRIBUTE)
        if done != {"FINISHED"} or group is None:
            if TEMP_ATTRIBUTE in mesh.attributes:
                mesh.attributes.remove(mesh.attributes[TEMP_ATTRIBUTE])
            raise RiggingError(f"'{obj.name}': could not store the weights of bone '{name}'")
        group.name = name


def write_strength(obj, strength):
    """Store (N,) binding strengths as `obj`'s MASK_GROUP (a vertex group, or a FLOAT attribute of
    native splats), or remove it when `strength` is None (every splat binds fully)."""
    if strength is not None:
        if obj.type == "MESH":
            write_vertex_groups(obj, [MASK_GROUP], np.asarray(strength)[:, None])
        else:
            data.set_attribute(obj.data, MASK_GROUP, "FLOAT", np.asarray(strength, np.float32))
    elif obj.type == "MESH":
        if obj.vertex_groups.get(MASK_GROUP) is not None:
            obj.vertex_groups.remove(obj.vertex_groups[MASK_GROUP])
    elif MASK_GROUP in obj.data.attributes:
        obj.data.attributes.remove(obj.data.attributes[MASK_GROUP])


def attach(obj, arm, preserve_volume=False, masked=False):
    """Parent `obj` to `arm` (keeping where it is) and let `arm` pose it: an Armature modifier first in
    the stack of a splat mesh, so the viewport display draws the posed splats; the armature
    properties on native splats. `masked`: the modifier's mask is MASK_GROUP (else a mask of ours
    is cleared; one the artist set is kept)."""
    if obj.type == "MESH":
        mod = next((m for m in obj.modifiers if m.type == "ARMATURE"), None) or obj.modifiers.new(
            "Armature", "ARMATURE"
        )
        mod.object = arm
        mod.use_vertex_groups, mod.use_bone_envelopes = True, False
        mod.use_deform_preserve_volume = preserve_volume
        mod.show_in_editmode = False  # Edit Mode edits the rest pose (see data.own_cloud)
        if masked:
            mod.vertex_group, mod.invert_vertex_group = MASK_GROUP, False
        elif mod.vertex_group == MASK_GROUP:
            mod.vertex_group = ""
        obj.modifiers.move(list(obj.modifiers).index(mod), 0)
    else:
        data.keep_rest_pose(obj)
        obj[ARMATURE_PROPERTY] = arm
        obj[PRESERVE_VOLUME_PROPERTY] = bool(preserve_volume)
    world = obj.matrix_world.copy()
    obj.parent, obj.parent_type = arm, "OBJECT"
    obj.matrix_parent_inverse = arm.matrix_world.inverted()
    obj.matrix_world = world


def _snapshot(obj):
    return {
        "groups": [g.name for g in obj.vertex_groups] if obj.type == "MESH" else [],
        "attributes": [a.name for a in obj.data.attributes],
        "properties": {k: obj[k] for k in (ARMATURE_PROPERTY, PRESERVE_VOLUME_PROPERTY) if k in obj},
        "modifiers": [m.name for m in obj.modifiers],
        "parent": obj.parent,
        "matrix_parent_inverse": obj.matrix_parent_inverse.copy(),
        "matrix_world": obj.matrix_world.copy(),
    }


def _restore(obj, snap):
    """Undo what binding did to `obj` (groups, attributes, properties and modifiers it added, its
    parenting); weights it replaced are not brought back, Blender's undo does that."""
    if obj.type == "MESH":
        for group in list(obj.vertex_groups):
            if group.name not in snap["groups"]:
                obj.vertex_groups.remove(group)
    for name in [a.name for a in obj.data.attributes if a.name not in snap["attributes"]]:
        obj.data.attributes.remove(obj.data.attributes[name])
    for key in (ARMATURE_PROPERTY, PRESERVE_VOLUME_PROPERTY):
        if key in snap["properties"]:
            obj[key] = snap["properties"][key]
        elif key in obj:
            del obj[key]
    for mod in list(obj.modifiers):
        if mod.name not in snap["modifiers"]:
            obj.modifiers.remove(mod)
    obj.parent, obj.matrix_parent_inverse = snap["parent"], snap["matrix_parent_inverse"]
    obj.matrix_world = snap["matrix_world"]


def find_armature(context, name):
    """The armature object named `name`, or the active object when `name` is empty."""
    if name:
        arm = bpy.data.objects.get(name)
        if arm is None:
            raise RiggingError(f"no object named '{name}'")
    else:
        arm = context.view_layer.objects.active
        if arm is None:
            raise RiggingError("no armature given and no active object: name one or make it the active object")
    if arm.type != "ARMATURE":
        raise RiggingError(f"'{arm.name}' is {arm.type.lower()}, not an armature")
    return arm


def bind_armature(
    objects,
    armature,
    max_influences=DEFAULT_INFLUENCES,
    use_source=True,
    falloff=DEFAULT_FALLOFF,
    min_weight=DEFAULT_MIN_WEIGHT,
    preserve_volume=False,
    warn=print,
):
    """Bind the splat objects among `objects` to `armature` (an object); returns their BindPlans.
    Every binding is computed before anything changes, so an error leaves the scene as it was."""
    if max_influences < 1:
        raise RiggingError(f"max_influences must be at least 1, got {max_influences}")
    targets = [o for o in objects if o != armature and data.is_splat_object(o)]
    if not targets:
        listed = ", ".join(f"'{o.name}' ({o.type.lower()})" for o in objects if o != armature)
        raise RiggingError("no splat objects to bind" + (f"; {listed} are not splat objects" if listed else ""))
    plans = [plan_binding(o, armature, max_influences, use_source, falloff, min_weight, warn) for o in targets]
    write_plans(plans, armature, preserve_volume)
    return plans


def write_plans(plans, armature, preserve_volume=False):
    """Store each BindPlan's weights on its object and attach it to `armature`; a failure undoes
    what was done to every object."""
    snapshots = [_snapshot(plan.obj) for plan in plans]
    try:
        for plan in plans:
            write_weights(plan.obj, plan.bones, plan.weights)
            write_strength(plan.obj, plan.strength)
            attach(plan.obj, armature, preserve_volume, plan.strength is not None)
    except BaseException:
        for plan, snap in zip(plans, snapshots):
            _restore(plan.obj, snap)
        raise
    finally:
        for plan in plans:
            forget_weights(plan.obj.data)
    show_poses(bpy.context.evaluated_depsgraph_get(), {armature.name})  # native splats drawn posed at once


# the operator ---------------------------------------------------------------------------------------


class SPLAT_OT_bind_armature(bpy.types.Operator):
    """Bind the selected splat objects to an armature (the active one unless named): bone weights as
    vertex groups, from the skinned mesh the splats were made from or from the bones, and an
    Armature modifier that poses centres, orientations, sizes and SH colours"""

    bl_idname = "splat.bind_armature"
    bl_label = "Bind Splats to Armature"
    bl_options = {"REGISTER", "UNDO"}

    armature: StringProperty(
        name="Armature", default="", description="Armature object to bind to (empty: the active object)"
    )
    max_influences: IntProperty(
        name="Max Influences", default=DEFAULT_INFLUENCES, min=1, max=32, description="Bones per splat, at most"
    )
    use_source_weights: BoolProperty(
        name="Weights From Source Mesh",
        default=True,
        description="Interpolate the vertex-group weights of the skinned mesh the "
        "splats were made from, when there is one",
    )
    falloff: FloatProperty(
        name="Falloff",
        default=DEFAULT_FALLOFF,
        min=1.0,
        max=16.0,
        description="Weights from bones: how fast a bone's weight falls with distance (higher gives sharper joints)",
    )
    min_weight: FloatProperty(
        name="Min Weight",
        default=DEFAULT_MIN_WEIGHT,
        min=0.0,
        max=0.5,
        description="Weights from bones: drop bones below this share of a splat's weight",
    )
    preserve_volume: BoolProperty(
        name="Preserve Volume",
        default=False,
        description="Dual-quaternion skinning (the Armature modifier's Preserve Volume)",
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def execute(self, context):
        warn = lambda message: self.report({"WARNING"}, message)
        try:
            arm = find_armature(context, self.armature)
            plans = bind_armature(
                context.selected_objects,
                arm,
                self.max_influences,
                self.use_source_weights,
                self.falloff,
                self.min_weight,
                self.preserve_volume,
                warn,
            )
        except (RiggingError, SkinningError, *EXPECTED_ERRORS) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for plan in plans:
            r = plan.report
            self.report(
                {"INFO"},
                f"'{plan.obj.name}': {r['splats']} splats bound to '{arm.name}' (weights from "
                f"{plan.source}), up to {r['max_influences']} bones each, "
                f"{r['pruned_splats']} splats pruned (at most {r['max_pruned_weight']:.1%} "
                "of their weight)",
            )
        return {"FINISHED"}


def menu_parent(self, context):
    self.layout.operator(SPLAT_OT_bind_armature.bl_idname, text="Splats to Armature (Bone Weights)")
    self.layout.operator("splat.bind_proxy", text="Splats to Armature (Through Proxy Mesh)")  # rig/proxy.py


CLASSES = (SPLAT_OT_bind_armature,)
MENUS = ((bpy.types.VIEW3D_MT_object_parent, menu_parent),)


# keeping cached weights true -------------------------------------------------------------------------

GEOMETRY_TYPES = (bpy.types.Mesh, bpy.types.PointCloud)


@persistent
def _on_depsgraph_update(scene, depsgraph):
    """Edits that may change weights (painting, groups added, renamed or assigned, vertices deleted)
    tag the mesh or the object's geometry; frame changes do not come through here."""
    dropped = False
    for update in depsgraph.updates:
        owner = update.id.original
        geometry = (
            owner
            if isinstance(owner, GEOMETRY_TYPES)
            else owner.data
            if isinstance(owner, bpy.types.Object) and update.is_updated_geometry
            else None
        )
        if isinstance(geometry, GEOMETRY_TYPES) and is_cached(geometry):
            forget_weights(geometry)
            dropped = True
    if dropped and not bpy.app.background and not bpy.app.timers.is_registered(_refill):
        bpy.app.timers.register(_refill, first_interval=REFRESH_DELAY)


def show_poses(depsgraph, armatures=None):
    """Write the posed splats of every bound native splat object (of `armatures`, when given) into
    the attributes Blender draws, so its viewport, EEVEE and Cycles show the pose our renderer does."""
    for obj in depsgraph.scene.objects:
        if data.splat_form(obj) != data.NATIVE_FORM:
            continue
        rig = rig_of(obj)
        if rig is None or (armatures is not None and rig[0].name not in armatures):
            continue
        pose = poser(obj, depsgraph)
        if pose is not None:
            try:
                data.keep_rest_pose(obj)  # bound by hand (weights and property): keep its rest pose first
                data.show_posed(obj, pose(data.object_cloud(obj)))
            except (SkinningError, *EXPECTED_ERRORS):
                pass  # reported when the splats are next exported or rendered


@persistent
def _on_frame_change(scene, depsgraph=None):
    show_poses(depsgraph or bpy.context.evaluated_depsgraph_get())


@persistent
def _on_pose_edit(scene, depsgraph):
    """Posing bones by hand changes no frame: repose the native splats of the armatures that moved."""
    moved = {
        u.id.original.name
        for u in depsgraph.updates
        if isinstance(u.id, bpy.types.Object)
        and u.id.type == "ARMATURE"
        and (u.is_updated_transform or u.is_updated_geometry)
    }
    if moved:
        show_poses(depsgraph, moved)


@persistent
def _on_load(*_):
    forget_weights()
    if not bpy.app.background and not bpy.app.timers.is_registered(_refill):
        bpy.app.timers.register(_refill, first_interval=REFRESH_DELAY)


def _refill():
    """Re-read the weights of bound splat objects on the main thread, so that a render started from
    the interface (which runs in another thread) finds them."""
    scene = bpy.context.scene
    for obj in scene.objects if scene is not None else ():
        rig = rig_of(obj) if data.is_splat_object(obj) else None
        if rig is not None:
            try:
                splat_binding(obj, deform_bones(rig[0]))
                splat_strength(obj, binding_mask(obj))
            except (SkinningError, *EXPECTED_ERRORS):
                pass  # reported when the splats are next posed
    return None


HANDLERS = (
    (bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update),
    (bpy.app.handlers.depsgraph_update_post, _on_pose_edit),
    (bpy.app.handlers.frame_change_post, _on_frame_change),
    (bpy.app.handlers.load_post, _on_load),
    (bpy.app.handlers.undo_post, _on_load),
    (bpy.app.handlers.redo_post, _on_load),
)


def register():
    if poser not in data.POSERS:
        data.POSERS.append(poser)
    data.add_handlers(HANDLERS)


def unregister():
    data.remove_handlers(HANDLERS)
    if poser in data.POSERS:
        data.POSERS.remove(poser)
    if bpy.app.timers.is_registered(_refill):
        bpy.app.timers.unregister(_refill)
    forget_weights()
