"""Compiled filling of PLY vertex records (numba; loaded by core.jit, io.ply keeps a NumPy path)."""

import numpy as np

from ..core.jit import njit


@njit
def fill_rows(positions, normals, sh, sh_columns, logits, log_scales, rotations, start, out):
    """out[i] = splat start + i in the reference layout x y z nx ny nz f_dc f_rest opacity scale rot
    (sh: (N, 3K) coefficient-major, sh_columns: file column -> sh column; normals (3, N) or empty).
    Returns whether every value written is finite."""
    m = sh_columns.shape[0]
    finite = True
    for i in range(out.shape[0]):
        s = start + i
        for c in range(3):
            out[i, c] = positions[s, c]
            out[i, 3 + c] = normals[c, s] if normals.size else 0.0
        for c in range(m):
            out[i, 6 + c] = sh[s, sh_columns[c]]
        out[i, 6 + m] = logits[s]
        for c in range(3):
            out[i, 7 + m + c] = log_scales[s, c]
        for c in range(4):
            out[i, 10 + m + c] = rotations[s, c]
        for c in range(out.shape[1]):
            finite &= np.isfinite(out[i, c])
    return finite
