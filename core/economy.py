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
from dataclasses import dataclass

import numpy as np

from . import render as rendering
from .camera import frame_points
from .metrics import psnr, psnr_from_mse
from .parallel import map_threads
from .render_constants import ALPHA_MIN

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


# pruning --------------------------------------------------------------------------------------------


def opacity_mask(cloud, threshold):
    """Splats whose opacity is at least `threshold` (in [0, 1])."""
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"opacity threshold must be in [0, 1], got {threshold!r}")
    return cloud.opacities >= threshold


def visible_mask(cloud, views, min_weight=0.0, mode=None, threads=None):
    """Splats whose blending weight T * alpha exceeds `min_weight` at some pixel of some view."""
    return contributions(cloud, views, mode=mode, threads=threads) > min_weight


def contributions(cloud, views, mode=None, tile_size=8, threads=None):
    """(N,) float32: each splat's largest blending weight T * alpha over every pixel of every view,
    0 for splats that reach no pixel (culled, off-image, too faint or hidden behind others).

    Each view is a render that also returns its weights (`render(..., return_weights=True)`, by the
    renderer's float32 arithmetic). Views render in parallel threads, the cores shared out among
    them: for many small views that beats rendering them in turn on every core."""
    views = list(views)
    if not views:
        raise ValueError("contributions need at least one view")
    threads = max(1, int(threads or os.cpu_count() or 1))
    workers = min(len(views), threads)
    best = np.zeros(len(cloud), np.float32)

    def weights(camera):
        return rendering.render(
            cloud,
            camera,
            background=None,
            mode=mode,
            return_weights=True,
            tile_size=tile_size,
            threads=threads // workers,
        ).max_weight

    for weight in map_threads(weights, views, workers):
        np.maximum(best, weight, out=best)
    return best


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
    z = 1.0 - 2.0 * i / count  # even in z: even area on the sphere
    ring = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    angle = GOLDEN_ANGLE * (i + phase)
    directions = np.column_stack([ring * np.cos(angle), z, ring * np.sin(angle)])
    return [frame_points(points, width, height, fov_deg, up=up, direction=d) for d in directions]


def cloud_points(cloud):
    """The centres worth framing: finite, and opaque enough to show (alpha can reach 1/255)."""
    keep = cloud.finite_mask() & (cloud.opacities >= ALPHA_MIN)
    return cloud.positions[keep]


def render_views(cloud, views, mode=None):
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


def image_error(before, after, views, mode=None):
    """The render error of cloud `after` against `before` from `views`. Either may also be the
    images `render_views` made of it from the same views (render the original once, compare many)."""
    views = list(views)
    ref, test = (x if isinstance(x, list) else render_views(x, views, mode) for x in (before, after))
    if len(ref) != len(views) or len(test) != len(views):
        raise ValueError(f"need one image per view: {len(ref)} and {len(test)} images for {len(views)} views")
    diff = [np.abs(np.asarray(t, np.float64) - r) for r, t in zip(ref, test)]
    mse = sum(float((d * d).sum()) for d in diff) / sum(d.size for d in diff)
    return ImageError(
        psnr_from_mse(mse), max(float(d.max(initial=0.0)) for d in diff), [psnr(t, r) for r, t in zip(ref, test)]
    )


# what a change saves and costs ----------------------------------------------------------------------


def ply_bytes(cloud):
    """Bytes of the splats' records in a 3DGS PLY (float32, normals included): 4 (14 + 3K) a splat."""
    return 4 * len(cloud) * (14 + 3 * cloud.sh.shape[1])


def change_report(before, after, views=None, view_count=6, view_size=96):
    """What turning cloud `before` into `after` saves and costs, as `splatwright convert` reports an
    economy: splats and PLY bytes before and after, and the render error of `after` against `before`
    (RGBA, premultiplied, clipped) from `views`, default `view_count` orbit views of `view_size` px
    around `before`. PSNR is inf when nothing changes in any view; None without views (empty cloud)."""
    report = {
        "splats_before": len(before),
        "splats_after": len(after),
        "bytes_before": ply_bytes(before),
        "bytes_after": ply_bytes(after),
        "psnr": None,
        "max_abs": None,
        "views": 0,
    }
    points = cloud_points(before) if views is None else None
    if views is None and len(points):
        views = orbit_views(points, view_count, view_size, phase=0.5)
    if views:
        error = image_error(before, after, views)
        report.update(psnr=error.psnr, max_abs=error.max_abs, views=len(views))
    return report


def describe_change(report):
    """One line for a change_report: '-1,234 splats (-12.0%), -56 KB, PSNR 41.2 dB over 6 views'."""

    def change(key):
        before, after = report[f"{key}_before"], report[f"{key}_after"]
        return after - before, (100.0 * (after - before) / before) if before else 0.0

    splats, share = change("splats")
    size, _ = change("bytes")
    text = f"{splats:+,} splats ({share:+.1f}%), {size / 1024:+,.0f} KB as PLY"
    if report["psnr"] is not None:
        text += f", PSNR {report['psnr']:.2f} dB over {report['views']} views"
    return text
