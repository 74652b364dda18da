"""The Blender side of Splatwright: splat objects, import/export operators, viewport display and
the SPLATWRIGHT render engine. The only package that imports bpy."""

import bpy

from . import bundled

bundled.expose("pxr")      # before any io module imports it

from . import animation, apply_guard, cleanup, collide, command, engine, from_mesh, operators, proxy_binding, rigging  # noqa: E402,I001
from . import panel, preferences  # noqa: E402

CLASSES = (operators.CLASSES + animation.CLASSES + from_mesh.CLASSES + rigging.CLASSES + collide.CLASSES
           + engine.CLASSES + cleanup.CLASSES + proxy_binding.CLASSES + preferences.CLASSES + panel.CLASSES)
MENUS = operators.MENUS + from_mesh.MENUS + rigging.MENUS + collide.MENUS


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for menu, draw in MENUS:
        menu.append(draw)
    engine.register()
    rigging.register()
    cleanup.register()
    apply_guard.register()
    command.register()


def unregister():
    command.unregister()
    apply_guard.unregister()
    cleanup.unregister()
    rigging.unregister()
    engine.unregister()
    for menu, draw in MENUS:
        menu.remove(draw)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
