"""Compiled tile passes for core.render_grad (numba; loaded by core.jit).

The same rules as core/render_grad.py's _Tile, which stays the readable reference and the fallback,
in float64. What the loops buy: a tile's splats are walked front to back over the tile's pixel
state, each only over the pixels its alpha >= 1/255 box covers (the dense arrays evaluate every
splat at every pixel of its tiles, and most of those pairs are below the rule), and the backward
walk goes back to front from each pixel's transmittance after its last splat, dividing by
(1 - alpha) to step back (alpha <= 0.99, so each step loses a rounding at most).
"""

import math

import numpy as np

from .jit import njit
from .render_constants import ALPHA_MAX, ALPHA_MIN, T_MIN

LOG_ALPHA_MIN = math.log(ALPHA_MIN)


@njit
def tile_passes(
    jobs, tiles, starts, ends, members, tile, width, height, uv, conic, opacity, box, rgb, target, bg, scale, image, acc
):
    """For each tile number in `jobs`: its image (written to `image`) and its share of the mean
    squared error's gradient, added per splat to acc (n, 9): d/du, d/dv, d/d conic (a, b, c),
    d/d opacity, d/d rgb. Tile j is tiles[j] (row-major, `tile` pixels square) with splats
    members[starts[j]:ends[j]] front to back."""
    floor = LOG_ALPHA_MIN - np.log(opacity) - 1e-9  # powers below this are clearly under the alpha rule
    tiles_x = (width + tile - 1) // tile
    size = tile * tile
    t = np.empty(size)
    color = np.empty((size, 3))
    stop = np.empty(size, np.int64)
    grad = np.empty((size, 3))
    behind = np.empty(size)
    for job in jobs:
        y0 = (tiles[job] // tiles_x) * tile
        x0 = (tiles[job] % tiles_x) * tile
        tw = min(tile, width - x0)
        th = min(tile, height - y0)
        t[:] = 1.0
        color[:] = 0.0
        stop[:] = ends[job]  # a pixel takes entries before stop[p]
        last = _forward(
            starts[job], ends[job], members, x0, y0, tw, th, uv, conic, opacity, floor, box, rgb, t, color, stop
        )
        for p in range(tw * th):
            y, x = y0 + p // tw, x0 + p % tw
            behind[p] = 0.0
            for ch in range(3):
                c = color[p, ch] + t[p] * bg[ch]
                image[y, x, ch] = c
                grad[p, ch] = scale * (c - target[y, x, ch])
                behind[p] += t[p] * grad[p, ch] * bg[ch]
        _backward(
            starts[job], last, members, x0, y0, tw, th, uv, conic, opacity, floor, box, rgb, t, stop, grad, behind, acc
        )


@njit
def _span(box, s, x0, y0, tw, th):
    """The tile's pixel columns and rows (tile coordinates, end exclusive) inside splat s's box."""
    c0 = max(0, int(math.ceil(box[s, 0])) - x0)
    c1 = min(tw, int(math.floor(box[s, 2])) - x0 + 1)
    r0 = max(0, int(math.ceil(box[s, 1])) - y0)
    r1 = min(th, int(math.floor(box[s, 3])) - y0 + 1)
    return c0, c1, r0, r1


@njit
def _alpha(s, x, y, uv, conic, opacity, floor):
    """(raw alpha, gaussian, dx, dy) of splat s at pixel (x, y); raw alpha 0 when below 1/255."""
    dx = x + 0.5 - uv[s, 0]
    dy = y + 0.5 - uv[s, 1]
    power = -0.5 * (conic[s, 0] * dx * dx + conic[s, 2] * dy * dy) - conic[s, 1] * dx * dy
    if power < floor[s]:  # no exp where the answer is clear
        return 0.0, 0.0, dx, dy
    gauss = math.exp(power)
    raw = opacity[s] * gauss
    return (raw if raw >= ALPHA_MIN else 0.0), gauss, dx, dy


@njit
def _forward(start, end, members, x0, y0, tw, th, uv, conic, opacity, floor, box, rgb, t, color, stop):
    """Composite entries start..end-1 into the tile's t and color; a pixel whose transmittance would
    drop below T_MIN stops before that entry (stop[p]). Returns the entry after the last one used."""
    alive = tw * th
    for e in range(start, end):
        s = members[e]
        c0, c1, r0, r1 = _span(box, s, x0, y0, tw, th)
        for r in range(r0, r1):
            for c in range(c0, c1):
                p = r * tw + c
                if stop[p] != end:
                    continue
                raw, _, _, _ = _alpha(s, x0 + c, y0 + r, uv, conic, opacity, floor)
                if raw == 0.0:
                    continue
                alpha = min(raw, ALPHA_MAX)
                after = t[p] * (1.0 - alpha)
                if after < T_MIN:
                    stop[p] = e
                    alive -= 1
                    continue
                for ch in range(3):
                    color[p, ch] += alpha * t[p] * rgb[s, ch]
                t[p] = after
        if alive == 0:
            return e + 1
    return end


@njit
def _backward(start, last, members, x0, y0, tw, th, uv, conic, opacity, floor, box, rgb, t, stop, grad, behind, acc):
    """Entries last-1 down to start: t[p] holds the transmittance after the entry and is stepped
    back before it; behind[p] holds what the entries after it (and the background) add to the
    pixel's gradient through this one's alpha."""
    for e in range(last - 1, start - 1, -1):
        s = members[e]
        c0, c1, r0, r1 = _span(box, s, x0, y0, tw, th)
        a, b, cc = conic[s, 0], conic[s, 1], conic[s, 2]
        g_u = g_v = g_a = g_b = g_c = g_o = g_r = g_g = g_bl = 0.0
        for r in range(r0, r1):
            for c in range(c0, c1):
                p = r * tw + c
                if e >= stop[p]:
                    continue
                raw, gauss, dx, dy = _alpha(s, x0 + c, y0 + r, uv, conic, opacity, floor)
                if raw == 0.0:
                    continue
                alpha = min(raw, ALPHA_MAX)
                before = t[p] / (1.0 - alpha)
                weight = alpha * before
                g_weight = grad[p, 0] * rgb[s, 0] + grad[p, 1] * rgb[s, 1] + grad[p, 2] * rgb[s, 2]
                g_r += weight * grad[p, 0]
                g_g += weight * grad[p, 1]
                g_bl += weight * grad[p, 2]
                if raw < ALPHA_MAX:  # the clamp holds alpha (its gradient is 0) above
                    g_alpha = before * g_weight - behind[p] / (1.0 - alpha)
                    g_o += g_alpha * gauss
                    g_power = g_alpha * alpha
                    g_a -= 0.5 * g_power * dx * dx
                    g_b -= g_power * dx * dy
                    g_c -= 0.5 * g_power * dy * dy
                    g_u += g_power * (a * dx + b * dy)
                    g_v += g_power * (cc * dy + b * dx)
                behind[p] += weight * g_weight
                t[p] = before
        acc[s, 0] += g_u
        acc[s, 1] += g_v
        acc[s, 2] += g_a
        acc[s, 3] += g_b
        acc[s, 4] += g_c
        acc[s, 5] += g_o
        acc[s, 6] += g_r
        acc[s, 7] += g_g
        acc[s, 8] += g_bl
