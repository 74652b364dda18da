"""Modules Blender ships inside itself that the extension uses when Python cannot import them yet.

Blender 4.4 and later bundle OpenUSD's Python bindings (`pxr`) in their own site-packages. The
Blender application has that folder on sys.path; Blender as a Python module (`bpy` from PyPI) keeps it
inside the module and does not. io/usd.py imports `pxr` once, when it is first imported, so this runs
before any io format module: at the top of the splat_addon package.
"""

import importlib.util
import sys
from pathlib import Path

import bpy


def blender_site_packages():
    """Blender's own site-packages folder (bundled Python modules), or None."""
    python = bpy.utils.system_resource("PYTHON")
    if not python:
        return None
    folder = Path(python) / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    return folder if folder.is_dir() else None


def expose(module="pxr"):
    """Make Blender's bundled `module` importable when it is not; returns whether it is importable.
    The folder is appended, so anything installed earlier on the path keeps precedence."""
    if importlib.util.find_spec(module) is not None:
        return True
    folder = blender_site_packages()
    if folder is None or not (folder / module).is_dir():
        return False
    sys.path.append(str(folder))
    importlib.invalidate_caches()
    return importlib.util.find_spec(module) is not None
