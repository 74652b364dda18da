"""Display sRGB <-> scene-linear, the IEC 61966-2-1 curves (the transform Blender's 'sRGB' applies)."""

import numpy as np


def srgb_to_linear(c, dtype=np.float64):
    """In `dtype` (float32 is about 3x faster on whole images, exact to float32 round-off)."""
    c = np.asarray(c, dtype=dtype)
    return np.where(
        c <= 0.04045, c / dtype(12.92), ((np.maximum(c, dtype(0.04045)) + dtype(0.055)) / dtype(1.055)) ** dtype(2.4)
    )


def linear_to_srgb(c, dtype=np.float64):
    c = np.asarray(c, dtype=dtype)
    return np.where(
        c <= 0.0031308,
        c * dtype(12.92),
        dtype(1.055) * np.maximum(c, dtype(0.0031308)) ** dtype(1 / 2.4) - dtype(0.055),
    )
