"""The splats the scene shows: one object as the depsgraph evaluates it, and every splat instance.

Reading (`evaluated_cloud`) takes the object's evaluated geometry at the depsgraph's frame, so edit-mode
changes, shape keys and modifiers reach export, animation export, collisions and the render engine as
the viewport shows them. Modifiers move centres and carry the other attributes along; where the
evaluated splats are whole copies of the object's own, each copy moved by one affine map (Array,
Mirror, a geometry-nodes Transform), that map also turns orientations, sizes and SH exactly. Splats
bound to an armature are posed by the POSERS from the object's own splats instead.
"""

import warnings
from typing import NamedTuple

import numpy as np

from ...core import SplatCloud
from .errors import SplatModeWarning
from .forms import (
    NATIVE_FORM,
    _transformed,
    geometry_cloud,
    is_native_splats,
    is_splat_object,
    object_cloud,
    splat_form,
)
from .transforms import transform_cloud, world_matrix

# the evaluated scene ----------------------------------------------------------------------------------

# Posing hooks: callables (obj, depsgraph) -> None when they do not pose `obj`, else a function that
# takes the object's own splats (object space) and returns them posed at the depsgraph's frame (an
# armature, say). Modifiers are not applied to posed objects.
POSERS = []

# Modifiers that belong to the splat data itself, not to the scene's deformation of it.
OWN_MODIFIERS = ("Splatwright Display",)


# Edit hooks: callables (obj, depsgraph, cloud) -> cloud, applied in turn to what the object shows
# (object space) before it is placed: clean-up and grading kept as settings on the object (edit/cleanup.py).
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
    mesh = evaluated.to_mesh()  # apart from the edit data, where the attribute API would look
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
    return any(
        (mod.show_render if render else mod.show_viewport) and mod.name not in OWN_MODIFIERS for mod in obj.modifiers
    )


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
    blocks = [evaluated[i * n : (i + 1) * n] for i in range(copies)]
    if not all(
        np.array_equal(b.rotations, own.rotations) and np.array_equal(b.log_scales, own.log_scales) for b in blocks
    ):
        return evaluated
    source = np.c_[own.positions.astype(np.float64), np.ones(n)]
    if np.linalg.matrix_rank(source - source.mean(axis=0) * [1, 1, 1, 0]) < 4:
        return evaluated  # coplanar centres leave the map's normal part unknown
    size = max(1.0, float(np.abs(evaluated.positions).max(initial=0.0)))
    turned = []
    for block in blocks:
        target = block.positions.astype(np.float64)
        fit = np.linalg.lstsq(source, target, rcond=None)[0]  # (4, 3): x -> [x 1] fit
        if np.abs(source @ fit - target).max(initial=0.0) > tolerance * size:
            return evaluated
        matrix = np.eye(4)
        matrix[:3, :] = fit.T
        if not np.allclose(matrix, np.eye(4), atol=tolerance):  # values a modifier set stay; frames turn
            block = transform_cloud(block.replace(positions=own.positions), matrix).replace(positions=block.positions)
        turned.append(block)
    return turned[0] if copies == 1 else SplatCloud.concatenate(turned)


class SplatInstance(NamedTuple):
    obj: object  # the splat object (original)
    instancer: object  # the object that instances it (original), None when drawn as itself
    matrix: np.ndarray  # (4, 4) float64 world matrix of this instance


def instancer_of(inst):
    """The original object that generated depsgraph instance `inst` (a collection instance's empty, a
    mesh instancing by vertices or faces), or None for an object drawn as itself."""
    return inst.parent.original if inst.is_instance and inst.parent else None


def splat_instances(depsgraph):
    """A SplatInstance for every splat object the depsgraph draws: objects, linked duplicates and
    instances (collection instances, instancing by vertices or faces), each with its own matrix. The
    display's point cloud of a splat mesh is not counted again."""
    found = []
    for inst in depsgraph.object_instances:  # instance data is only valid during iteration
        evaluated = inst.object
        original = evaluated.original
        instancer = instancer_of(inst)
        if evaluated.type == original.type and is_splat_object(original):
            found.append(SplatInstance(original, instancer, np.array(inst.matrix_world, dtype=np.float64)))
        elif _generated(evaluated, original):
            found.append(
                SplatInstance(
                    original,
                    None if instancer == original else instancer,
                    np.array(inst.matrix_world, dtype=np.float64),
                )
            )
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
    geometry = evaluated.evaluated_geometry()  # the point cloud lives as long as this does
    pointcloud = geometry.pointcloud
    if pointcloud is None or not is_native_splats(pointcloud):
        return None
    return geometry_cloud(pointcloud, obj.name, NATIVE_FORM)


def instances_cloud(depsgraph, instances, conversion=None, prepare=None):
    """One cloud of every (object, matrix) of `instances`, `conversion` @ matrix applied to each; each
    object is evaluated once however many instances it has, then given to `prepare(obj, cloud) ->
    cloud` if set (the render engine marks relit splats so). Splats made for antialiased rendering
    beside classic ones join them as classic (one render shows one mode), with a SplatModeWarning
    naming the objects."""
    conversion = np.eye(4) if conversion is None else conversion
    own = {}
    clouds = []
    for obj, matrix in instances:
        if obj.name not in own:
            own[obj.name] = evaluated_cloud(obj, depsgraph, np.eye(4))
            if prepare is not None:
                own[obj.name] = prepare(obj, own[obj.name])
        clouds.append(_transformed(obj, own[obj.name], conversion @ matrix))
    if len(clouds) == 1:
        return clouds[0]
    marked = sorted(name for name, cloud in own.items() if cloud.antialiased)
    if marked and len(marked) < len(own):
        warnings.warn(
            f"{', '.join(marked)}: made for antialiased rendering, shown classic beside "
            "splats made for classic rendering (outlines about a pixel wider)",
            SplatModeWarning,
            stacklevel=2,
        )
        clouds = [c.replace(antialiased=False) for c in clouds]
    return SplatCloud.concatenate(clouds)


def frame_range(start, end, step=1):
    """The frames start, start + step, ..., end; ValueError naming the problem for a bad range."""
    if step < 1:
        raise ValueError(f"frame step must be at least 1, got {step}")
    if end < start:
        raise ValueError(f"frame range {start}-{end} ends before it starts")
    return list(range(start, end + 1, step))
