"""Compiled triangle rasterisation for core.mesh_render (numba; loaded by core.jit).

The same rules as the NumPy path in core/mesh_render.py, which stays the readable reference and
the fallback, with the same float64 operations in the same order, so the buffers come out
bit-identical: per face and pixel row, the row's span of candidate pixels (_row_spans), then per
candidate the three edge functions a x + (b y + c), the inside test, the perspective-correct
barycentrics and depth, the near/far test, the peeling bound (hits beyond an earlier layer's) and
the z-buffer (nearest, of equals the lowest face).
What the loops buy besides speed: no candidate lists (the NumPy path holds up to a few million
candidates and sorts them by pixel), so memory is the buffers. A call draws every `step`-th
pixel row from `first_row`; core.mesh_render spreads the rows over the cores (the kernel
releases the GIL), and each call writes only its own rows.
"""

import math

from .jit import njit


@njit
def rasterize_rows(
    a, b, c, depths, faces, x0, x1, y0, y1, near, far, width, first_row, step, zmin, fmin, zbuf, fbuf, bbuf
):
    """Draw faces[i] (edge functions a, b, c (F,3), corner camera depths (F,3), pixel boxes
    [x0, x1) x [y0, y1)) on the pixel rows y = first_row (mod step) of the flat buffers zbuf, fbuf,
    bbuf (width pixels a row), only hits beyond (zmin, fmin) per pixel: deeper, or as deep and of
    a higher face index (depth peeling; -inf everywhere for the nearest, +inf to skip a pixel)."""
    for i in range(len(faces)):
        face = faces[i]
        d0, d1, d2 = depths[i, 0], depths[i, 1], depths[i, 2]
        a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
        for y in range(y0[i] + (first_row - y0[i]) % step, y1[i], step):
            yf = float(y)
            e0_row = b[i, 0] * yf + c[i, 0]
            e1_row = b[i, 1] * yf + c[i, 1]
            e2_row = b[i, 2] * yf + c[i, 2]
            first, last = _row_span(a0, a1, a2, e0_row, e1_row, e2_row, x0[i], x1[i])
            row = y * width
            for x in range(first, last):
                xf = float(x)
                e0 = a0 * xf + e0_row
                e1 = a1 * xf + e1_row
                e2 = a2 * xf + e2_row
                total = e0 + e1 + e2
                if total == 0:
                    continue
                if not ((e0 >= 0 and e1 >= 0 and e2 >= 0) or (e0 <= 0 and e1 <= 0 and e2 <= 0)):
                    continue
                b0, b1, b2 = e0 / total, e1 / total, e2 / total
                z = b0 * d0 + b1 * d1 + b2 * d2
                if not (z > near and z <= far):
                    continue
                p = row + x
                if z < zmin[p] or (z == zmin[p] and face <= fmin[p]):
                    continue
                if z < zbuf[p] or (z == zbuf[p] and face < fbuf[p]):
                    zbuf[p] = z
                    fbuf[p] = face
                    bbuf[p, 0] = b0
                    bbuf[p, 1] = b1
                    bbuf[p, 2] = b2


@njit
def _row_span(a0, a1, a2, e0, e1, e2, x0, x1):
    """_row_spans (core/mesh_render.py) for one row, margin 1: [first, last) of the pixels of
    [x0, x1) where the edge functions a_k x + e_k can share a sign."""
    margin = 1.0
    inf = math.inf
    lo_pos, hi_pos, lo_neg, hi_neg = -inf, inf, -inf, inf
    flat = False
    for a, e in ((a0, e0), (a1, e1), (a2, e2)):
        root = -e / a
        if not (a > 0 or a < 0) or not math.isfinite(root):
            flat = True  # a constant edge function (or a NaN): keep the box
        elif a > 0:
            lo_pos = max(lo_pos, root)
            hi_neg = min(hi_neg, root)
        else:
            hi_pos = min(hi_pos, root)
            lo_neg = max(lo_neg, root)
    if flat:
        return x0, x1
    # Here every root is finite, so lo and hi are numbers or infinities, never NaN.
    lo, hi = inf, -inf
    if lo_pos <= hi_pos + 2 * margin:
        lo, hi = min(lo, lo_pos), max(hi, hi_pos)
    if lo_neg <= hi_neg + 2 * margin:
        lo, hi = min(lo, lo_neg), max(hi, hi_neg)
    # clip(ceil(lo - margin), x0, x1) and clip(floor(hi + margin) + 1, x0, x1), infinities included
    t = lo - margin
    first = x0 if t <= x0 else (x1 if t >= x1 else int(math.ceil(t)))
    t = hi + margin
    last = x0 if t < x0 else (x1 if t >= x1 else min(int(math.floor(t)) + 1, x1))
    return first, max(last, first)
