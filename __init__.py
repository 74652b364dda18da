"""Splatwright: 3D Gaussian splats for Blender and NumPy.

The package root is also the Blender extension. Nothing here imports bpy: the Blender side
(`splat_addon`) is imported only when Blender calls register(), so `splatwright.core` and
`splatwright.io` work in any Python.
"""

__version__ = "0.1.0"


def register():
    from . import splat_addon

    splat_addon.register()


def unregister():
    from . import splat_addon

    splat_addon.unregister()
