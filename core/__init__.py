"""The NumPy splat core: never imports bpy or pxr."""

from .splats import SplatCloud, SplatValidationError

__all__ = ["SplatCloud", "SplatValidationError"]
