"""The numbers of the splat image, one place for every path that makes or differentiates it: the
NumPy rasteriser (core/render.py), its compiled kernels (core/render_kernels.py) and the backward
pass (core/render_grad.py, core/render_grad_kernels.py). They follow the 3DGS reference rasteriser
(see the design notes, "Rasterisation conventions")."""

import numpy as np

ALPHA_MIN = 1.0 / 255.0  # skip a splat at a pixel below this alpha
ALPHA_MAX = 0.99  # per-splat alpha clamp
T_MIN = 1e-4  # stop before T would drop below this
LOW_PASS = 0.3  # px^2 added to the projected covariance's diagonal
AA_MIN_RATIO = 0.000025  # floor of det(Sigma2D) / det(Sigma2D + 0.3 I) in antialiased mode
FRUSTUM_MARGIN = 1.3  # the Jacobian is taken at x/z, y/z clamped to 1.3 x the half field of view
MODES = ("classic", "antialiased")
PRECISIONS = {"float32": np.float32, "float64": np.float64}  # of the per-pixel compositing
TILE_SIZE = 8  # pixels a side of the forward pass's square tiles, by default
MAX_TILE_SIZE = 64  # ... and at most (the compiled compositor keeps a tile's pixels in one buffer)
