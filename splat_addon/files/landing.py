"""Where Blender's own importers put native splat clouds, recorded as the clouds appear.

Blender 5.3's PLY importer leaves a capture in the file's axes at the identity, its SPZ importer turns
it upright, and its USD importer keeps the prim's values with the stage's transforms in the object's
matrix; none records which. Export needs to know (data.landed_raw): the depsgraph update inside the
import operator shows the new object as its importer left it, and data.stamp_unrecorded records it
then, before a script or the user moves it."""

import bpy
from bpy.app.handlers import persistent

from .. import data


@persistent
def _on_depsgraph_update(scene, depsgraph):
    for update in depsgraph.updates:
        owner = update.id.original
        if isinstance(owner, bpy.types.Object) and update.is_updated_geometry:
            data.stamp_unrecorded(owner)


@persistent
def _on_load(*_):
    """Clouds of a file saved before stamps were kept: their splats alone decide (their matrix may be
    the user's since)."""
    for obj in bpy.data.objects:
        data.stamp_unrecorded(obj, at_import=False)


HANDLERS = ((bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update), (bpy.app.handlers.load_post, _on_load))


def register():
    data.add_handlers(HANDLERS)


def unregister():
    data.remove_handlers(HANDLERS)
