"""The Blender side of Splatwright: splat objects, import/export operators, viewport display and
the SPLATWRIGHT render engine. The only package that imports bpy.

Floors, each importing only those below it: data/ (splat clouds as Blender data, the one reader;
imports nothing else of the add-on), then the features (files/, edit/, convert/, rig/, render/),
then ui/ and command.py. Features put their hooks into data/ when they register."""

import bpy

from .data import bundled_pxr

bundled_pxr.expose("pxr")  # before any io format module imports it

from ..core.memory import numpy_huge_pages  # noqa: E402,I001
from . import command  # noqa: E402
from .convert import from_mesh  # noqa: E402
from .edit import blender_apply, cleanup, normals, objects  # noqa: E402
from .files import animation, import_export, landing, webp  # noqa: E402
from .render import engine  # noqa: E402
from .rig import armature, collide, proxy  # noqa: E402
from .ui import panel, preferences  # noqa: E402

CLASSES = (
    import_export.CLASSES
    + objects.CLASSES
    + animation.CLASSES
    + from_mesh.CLASSES
    + armature.CLASSES
    + collide.CLASSES
    + engine.CLASSES
    + cleanup.CLASSES
    + normals.CLASSES
    + proxy.CLASSES
    + preferences.CLASSES
    + panel.CLASSES
)
MENUS = import_export.MENUS + objects.MENUS + from_mesh.MENUS + armature.MENUS + collide.MENUS
_HUGE_PAGES: list = []  # NumPy's setting before register, restored by unregister


def register():
    # Fresh large arrays fault without waiting for the system to compact memory (core.memory)
    _HUGE_PAGES[:] = [numpy_huge_pages(False)]
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for menu, draw in MENUS:
        menu.append(draw)
    engine.register()
    armature.register()
    cleanup.register()
    blender_apply.register()
    landing.register()
    webp.register()  # SOG's WebP images, where Pillow is missing
    command.register()


def unregister():
    command.unregister()
    webp.unregister()
    landing.unregister()
    blender_apply.unregister()
    cleanup.unregister()
    armature.unregister()
    engine.unregister()
    for menu, draw in MENUS:
        menu.remove(draw)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
    if _HUGE_PAGES and _HUGE_PAGES[0] is not None:
        numpy_huge_pages(_HUGE_PAGES.pop())
