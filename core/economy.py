"""Model only what a scene needs: economies that drop splats, and what they cost in the image.

Pruning keeps a boolean mask of the splats worth keeping:
- `opacity_mask`: splats at least as opaque as a threshold (faint splats barely show);
- `visible_mask`: splats that contribute to at least one pixel of a set of views, by the renderer's
  own rules (alpha >= 1/255, the 0.99 clamp, the stop before T < 1e-4), so splats hidden behind
  opaque surfaces, outside every view or too faint to reach 1/255 anywhere are dropped.

Lowering the SH degree (`SplatCloud.with_sh_degree`) and half-precision OpenUSD (`io.usd`,
`half=True`) are the other economies; bone-weight pruning lives with the bindings
(`core.skinning.Binding`, its `tolerance` and `max_influences`).

Cost: `image_error(before, after, views)` renders both clouds transparent from each view and
compares RGBA (colour premultiplied, clipped to [0, 1] as a display shows it), so a removed splat
counts even where its colour matches the background. `orbit_views` makes views all around a cloud.
"""

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from . import render as rendering
from .camera import frame_points
from .metrics import psnr

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
_BLOCK_EVALS = 1 << 20        # splat-pixel evaluations per block of tiles (bounds memory)


# pruning --------------------------------------------------------------------------------------------

def opacity_mask(cloud, threshold):
    """Splats whose opacity is at least `threshold` (in [0, 1])."""
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"opacity threshold must be in [0, 1], got {threshold!r}")
    return cloud.opacities >= threshold


def visible_mask(cloud, views, min_weight=0.0, mode="classic", threads=None):
    """Splats whose blending weight T * alpha exceeds `min_weight` at some pixel of some view."""
    return contributions(cloud, views, mode=mode, threads=threads) > min_weight


def contributions(cloud, views, mode="classic", tile_size=8, threads=None):
    """(N,) float32: each splat's largest blending weight T * alpha over every pixel of every view,
    0 for splats that reach no pixel (culled, off-image, too faint or hidden behind others).

    Views run in parallel threads (NumPy releases the GIL); each view composites its tiles in waves,
    dropping tiles once every pixel has stopped."""
    views = list(views)
    if not views:
        raise ValueError("contributions need at least one view")
    best = np.zeros(len(cloud), np.float32)
    workers = max(1, min(len(views), int(threads or os.cpu_count() or 1)))
    with ThreadPoolExecutor(workers) as pool:
        for index, weight in pool.map(lambda cam: _view_contributions(cloud, cam, mode, tile_size), views):
            np.maximum.at(best, index, weight)
    return best


def _view_contributions(cloud, camera, mode, tile_size):
    """(cloud indices, largest weight of each) for the splats one view projects."""
    proj = rendering.project(cloud, camera, mode=mode)
    n = len(proj)
    best = np.zeros(n + 1, np.float32)                    # the last slot takes padding entries
    if n == 0:
        return proj.index, best[:n]
    bins = rendering.bin_tiles(proj, camera, tile_size)
    tiles = _Tiles(bins, camera)
    log_o = proj.records[:, 5:].view(np.float32)[:, 0]    # the records' documented float32 part
    u, v, a, b, c = proj.mean_conic.T
    total = np.diff(bins.offsets)
    cursor = np.zeros(bins.n_tiles, np.int64)
    trans = tiles.initial_transmittance()
    alive = np.flatnonzero(total > 0)
    wave = 32
    while len(alive):
        take = np.minimum(total[alive] - cursor[alive], wave)
        per_block = max(1, _BLOCK_EVALS // (wave * tiles.pixels))
        for start in range(0, len(alive), per_block):
            group, count = alive[start:start + per_block], take[start:start + per_block]
            slot = np.arange(wave)[:, None]
            entry = np.where(slot < count, bins.entry_splat.take(bins.offsets[group] + cursor[group] + slot,
                                                                 mode="clip"), n)      # (wave, g)
            dx = tiles.x[group][None] - u[entry][..., None]                           # (wave, g, p)
            dy = tiles.y[group][None] - v[entry][..., None]
            power = log_o[entry][..., None] - 0.5 * (a[entry][..., None] * dx * dx + c[entry][..., None] * dy * dy
                                                     + 2.0 * b[entry][..., None] * dx * dy)
            alpha = np.minimum(np.exp(power), rendering.ALPHA_MAX)
            alpha *= alpha >= rendering.ALPHA_MIN
            after = trans[group][None] * np.cumprod(1.0 - alpha, axis=0)            # T after each entry
            before = np.concatenate([trans[group][None], after[:-1]])
            # A pixel stops before the splat that would take T below t_min; T only falls, so the
            # splats from there on are exactly those with after < t_min.
            weight = before * alpha * (after >= rendering.T_MIN)
            np.maximum.at(best, entry.ravel(), weight.max(axis=2).ravel().astype(np.float32))
            trans[group] = np.where(after[-1] >= rendering.T_MIN, after[-1], 0.0)
        cursor[alive] += take
        alive = alive[(cursor[alive] < total[alive]) & trans[alive].any(axis=1)]
    return proj.index, best[:n]


class _Tiles:
    """Pixel-centre coordinates of every pixel of every tile; pixels beyond the image edge get a
    transmittance of 0, so nothing counts there."""

    def __init__(self, bins, camera):
        ts = bins.tile_size
        self.pixels = ts * ts
        t = np.arange(bins.n_tiles)
        k = np.arange(self.pixels)
        self.x = (t % bins.tiles_x)[:, None] * ts + (k % ts)[None] + 0.5      # (tiles, pixels)
        self.y = (t // bins.tiles_x)[:, None] * ts + (k // ts)[None] + 0.5
        self.inside = (self.x < camera.width) & (self.y < camera.height)

    def initial_transmittance(self):
        return self.inside.astype(np.float64)


# views and image error ------------------------------------------------------------------------------

def orbit_views(points, count=8, width=128, height=None, fov_deg=50.0, phase=0.0, up=(0.0, -1.0, 0.0)):
    """`count` perspective cameras spread evenly over a sphere of directions around `points`, each
    framing all of them (core.camera.frame_points). `phase` in [0, 1) turns the spiral of
    directions, so phase=0.5 gives views between those of phase=0. The default up is -y, the
    model's (3DGS) up."""
    if count < 1:
        raise ValueError(f"need at least one view, got {count}")
    height = width if height is None else height
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count                              # even in z: even area on the sphere
    ring = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    angle = GOLDEN_ANGLE * (i + phase)
    directions = np.column_stack([ring * np.cos(angle), z, ring * np.sin(angle)])
    return [frame_points(points, width, height, fov_deg, up=up, direction=d) for d in directions]


def cloud_points(cloud):
    """The centres worth framing: finite, and opaque enough to show (alpha can reach 1/255)."""
    keep = cloud.finite_mask() & (cloud.opacities >= rendering.ALPHA_MIN)
    return cloud.positions[keep]


def render_views(cloud, views, mode="classic"):
    """Transparent renders of `cloud`: one (H, W, 4) float32 RGBA image per view, colour
    premultiplied and clipped to [0, 1]."""
    images = []
    for cam in views:
        result = rendering.render(cloud, cam, background=None, mode=mode)
        images.append(np.clip(np.dstack([result.color, result.alpha]), 0.0, 1.0))
    return images


@dataclass
class ImageError:
    """What a change costs in the image, over all views: PSNR (dB, inf when identical) of the RGBA
    pixels together, the largest absolute difference of any channel, and the PSNR of each view."""
    psnr: float
    max_abs: float
    view_psnr: list

    def __str__(self):
        return f"PSNR {self.psnr:.2f} dB, max abs {self.max_abs:.4f}"


def image_error(before, after, views, mode="classic"):
    """The render error of cloud `after` against `before` from `views`. Either may also be the
    images `render_views` made of it from the same views (render the original once, compare many)."""
    views = list(views)
    ref, test = (x if isinstance(x, list) else render_views(x, views, mode) for x in (before, after))
    if len(ref) != len(views) or len(test) != len(views):
        raise ValueError(f"need one image per view: {len(ref)} and {len(test)} images for {len(views)} views")
    diff = [np.abs(np.asarray(t, np.float64) - r) for r, t in zip(ref, test)]
    mse = sum(float((d * d).sum()) for d in diff) / sum(d.size for d in diff)
    return ImageError(float("inf") if mse == 0 else float(-10.0 * np.log10(mse)),
                      max(float(d.max(initial=0.0)) for d in diff),
                      [psnr(t, r) for r, t in zip(ref, test)])
