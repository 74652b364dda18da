"""The array types of the public API, named for what they hold, each annotated with its shape
(N splats, K SH coefficients per channel, B bones, J joints). A type checker sees NumPy arrays of
a dtype family; the shapes are for the reader, and the validators hold the arrays to them at run
time (SplatCloud checks its fields on construction)."""

from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ArrayLike",
    "Floats",
    "Positions",
    "Quaternions",
    "LogScales",
    "Logits",
    "SHCoefficients",
    "Covariances",
    "Colors",
    "Mask",
    "Matrix4",
    "Matrices4",
    "Image",
    "Weights",
    "Indices",
]

Floats = NDArray[np.floating]
Positions = Annotated[Floats, "(N, 3)"]
Quaternions = Annotated[Floats, "(N, 4) w, x, y, z, any norm"]
LogScales = Annotated[Floats, "(N, 3) natural log of the standard deviations"]
Logits = Annotated[Floats, "(N,) logit of the opacity"]
SHCoefficients = Annotated[Floats, "(N, K, 3), K = (degree + 1)^2, [:, 0] the DC term"]
Covariances = Annotated[Floats, "(N, 3, 3)"]
Colors = Annotated[Floats, "(N, 3) display sRGB"]
Mask = Annotated[NDArray[np.bool_], "(N,)"]
Matrix4 = Annotated[Floats, "(4, 4) affine"]
Matrices4 = Annotated[Floats, "(B, 4, 4) affine, one per bone or link"]
Image = Annotated[Floats, "(H, W, C)"]
Weights = Annotated[Floats, "(N, B) per splat and bone"]
Indices = Annotated[NDArray[np.integer], "(M,)"]
