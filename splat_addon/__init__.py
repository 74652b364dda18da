"""The Blender side of Splatwright: splat objects, import/export operators, viewport display and
the SPLATWRIGHT render engine. The only package that imports bpy."""

import bpy

from . import animation, command, engine, from_mesh, operators

CLASSES = operators.CLASSES + animation.CLASSES + from_mesh.CLASSES + engine.CLASSES
MENUS = operators.MENUS + from_mesh.MENUS


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for menu, draw in MENUS:
        menu.append(draw)
    engine.add_to_panels()
    command.register()


def unregister():
    command.unregister()
    engine.remove_from_panels()
    for menu, draw in MENUS:
        menu.remove(draw)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
