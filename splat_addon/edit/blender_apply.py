"""Blender's own Object > Apply > Rotation / Scale / All Transforms on splat objects, completed.

Blender's Apply moves the vertices (the splat centres) by the part of the object transform it applies
and leaves every other attribute as it was, so after applying a rotation every splat would still face
where it faced before, and after a scale keep its old size: the cloud silently changes. This module
notices an apply and turns orientations, sizes and SH by the same map, as Apply Splat Transform does.

Each splat object carries a record (the custom property data.FRAME_RECORD) of its matrix_basis and
the centres of a few probe splats. After a depsgraph update, an object whose transform changed is
checked: the map an apply would have moved the data by is A = inv(new basis) @ old basis, and when
every probe centre moved by exactly A, Blender applied A to the centres; the rest of the splat data is
then turned by A too. Any other change only refreshes the record. Undo restores the record with the
data (both live in the file), so an undone apply never looks like a new one. Splats bound to an
armature are left alone: their rest pose is the armature's business.
"""

import bpy
import numpy as np
from bpy.app.handlers import persistent

from .. import data
from ..rig.armature import rig_of

TOLERANCE = 1e-5  # relative to the probe centres' size: float32 round-off of the moved centres


def applied_map(obj, record):
    """The 4x4 map Blender's Apply moved `obj`'s centres by since `record`, or None when the centres did
    not move that way (or nothing was applied)."""
    old_basis = np.array(record["basis"], dtype=np.float64).reshape(4, 4)
    new_basis = np.array(obj.matrix_basis, dtype=np.float64)
    if np.array_equal(old_basis, new_basis) or record["count"] != data.splat_count(obj.data):
        return None
    if not np.isfinite(new_basis).all() or abs(np.linalg.det(new_basis[:3, :3])) == 0:
        return None
    moved = np.linalg.inv(new_basis) @ old_basis
    if np.allclose(moved[:3, :3], np.eye(3), rtol=0, atol=1e-12):
        return None  # a translation moves centres only: nothing to complete
    old = np.array(record["centres"], dtype=np.float64).reshape(-1, 3)
    now = data.probe_centres(obj, record["probes"])
    expected = old @ moved[:3, :3].T + moved[:3, 3]
    size = max(1.0, float(np.abs(expected).max(initial=0.0)))
    return moved if np.abs(now - expected).max(initial=0.0) <= TOLERANCE * size else None


def complete_apply(obj, moved):
    """Turn `obj`'s orientations, sizes and SH by the linear part of `moved`, keeping the centres Blender
    already moved."""
    cloud = data.object_cloud(obj)
    turn = np.eye(4)
    turn[:3, :3] = moved[:3, :3]
    turned = data.transform_cloud(cloud, turn)
    data.update_splats(obj, turned.replace(positions=cloud.positions))


def check(obj):
    """Complete an apply found on splat object `obj` and refresh its record; returns whether it did."""
    if obj.mode == "EDIT" or obj.library is not None or not data.is_splat_object(obj):
        return False
    record = obj.get(data.FRAME_RECORD)
    done = False
    if record is not None and not _bound(obj):
        moved = applied_map(obj, record.to_dict())
        if moved is not None:
            complete_apply(obj, moved)
            done = True
    data.remember_frame(obj)
    return done


def _bound(obj):
    return rig_of(obj) is not None


@persistent
def _on_depsgraph_update(scene, depsgraph):
    for update in depsgraph.updates:
        owner = update.id.original
        if isinstance(owner, bpy.types.Object) and (update.is_updated_transform or update.is_updated_geometry):
            check(owner)


@persistent
def _on_load(*_):
    """Objects saved before the extension kept records start one now."""
    for obj in bpy.data.objects:
        if data.FRAME_RECORD not in obj and data.is_splat_object(obj) and obj.library is None:
            data.remember_frame(obj)


HANDLERS = ((bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update), (bpy.app.handlers.load_post, _on_load))


def register():
    data.add_handlers(HANDLERS)


def unregister():
    data.remove_handlers(HANDLERS)
