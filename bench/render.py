"""Renderer speed against error, as a ratio against the seed prototype's algorithm.

The baseline is the seed scene's prototype renderer, reimplemented here: isotropic splats, one
Python iteration per splat, each iteration vectorised over the pixels of that splat's 3-sigma box
and composited front to back into full-frame accumulators. Errors are max abs differences (in 1/255
steps of display sRGB) against the float64 brute-force reference of tests/reference_render.py at a
random sample of pixels.

    python bench/render.py [--quick]
"""

import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from common import Row, Timing, machine, print_rows, timeit  # noqa: E402
from reference_render import reference_render  # noqa: E402

from splatwright.core import SplatCloud  # noqa: E402
from splatwright.core.camera import Camera  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.core.scenes import seed_cube  # noqa: E402

TOPIC = "render"


def seed_camera(width=512, height=512):
    return Camera.look_at((1.8, 1.2, 4.5), (0.0, 0.0, 3.0), fov_deg=60.0, width=width, height=height)


def trained_like_scene(n, camera, seed=0, sigma_px=1.5):
    """n anisotropic SH-degree-3 splats filling the view of `camera` between 3 and 12 units deep,
    sized like a trained capture: a projected standard deviation of about `sigma_px` pixels on
    average (log-normal), axis ratios up to ~10, opacities from nearly clear to opaque."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(3.0, 12.0, n)
    half_w, half_h = camera.width / (2 * camera.fx), camera.height / (2 * camera.fy)
    cam = np.stack([rng.uniform(-1, 1, n) * half_w * z, rng.uniform(-1, 1, n) * half_h * z, z], axis=1)
    positions = cam @ camera.rotation + camera.center
    size = np.log(z * sigma_px / camera.fx) + rng.normal(0.0, 0.5, n)
    log_scales = size[:, None] + rng.normal(0.0, 0.6, (n, 3))
    sh = rng.normal(0.0, 0.3, (n, 16, 3))
    sh[:, 0] *= 3.0
    return SplatCloud(positions, rng.normal(size=(n, 4)), log_scales, rng.normal(1.0, 2.5, n), sh)


def baseline_render(cloud, camera, background=(0.0, 0.0, 0.0)):
    """The seed prototype's algorithm: isotropic splats (sigma = the largest scale), one Python
    iteration per splat over its 3-sigma pixel box, full-frame accumulators, no early stop."""
    cam = camera.to_camera(cloud.positions)
    z = cam[:, 2]
    order = np.flatnonzero(z > camera.near)
    order = order[np.argsort(z[order], kind="stable")]
    colors = cloud.colors(camera.center)
    opacity = cloud.opacities
    sigma = cloud.scales.max(axis=1)
    h, w = camera.height, camera.width
    color = np.zeros((h, w, 3))
    trans = np.ones((h, w))
    for i in order:
        x, y, d = cam[i]
        u, v = camera.fx * x / d + camera.cx, camera.fy * y / d + camera.cy
        var = (camera.fx * sigma[i] / d) ** 2 + 0.3
        r = 3.0 * math.sqrt(var)
        x0, x1 = max(int(u - r), 0), min(int(u + r) + 1, w)
        y0, y1 = max(int(v - r), 0), min(int(v + r) + 1, h)
        if x0 >= x1 or y0 >= y1:
            continue
        dx = np.arange(x0, x1) + 0.5 - u
        dy = np.arange(y0, y1) + 0.5 - v
        alpha = np.minimum(0.99, opacity[i] * np.exp(-0.5 * (dx[None, :] ** 2 + dy[:, None] ** 2) / var))
        alpha[alpha < 1 / 255] = 0.0
        t = trans[y0:y1, x0:x1]
        color[y0:y1, x0:x1] += (t * alpha)[..., None] * colors[i]
        t *= 1.0 - alpha
    return color + trans[..., None] * np.asarray(background)


def sample_pixels(camera, m, seed=1):
    rng = np.random.default_rng(seed)
    return np.stack([rng.integers(0, camera.width, m), rng.integers(0, camera.height, m)], axis=1)


def max_error(image, pixels, ref):
    """Max abs colour difference at the sampled pixels, in 1/255 steps."""
    return float(np.abs(image[pixels[:, 1], pixels[:, 0]] - ref["color"]).max() * 255)


def scenes(quick):
    """(name, cloud, camera, time the baseline?) for each benchmark scene; quick mode shrinks them."""
    cam = seed_camera()
    big = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), fov_deg=60.0, width=1920, height=1080)
    for label, edge, sigma, opacity in [("seed cube", 10, 0.05, 0.08), ("small splats", 60, 0.008, 0.5),
                                        ("large splats", 40, 0.05, 0.08)]:
        edge = edge // 2 if quick and edge > 10 else edge
        yield f"{label} {edge}^3 (sigma {sigma}, o {opacity}) 512x512", seed_cube(edge, sigma, opacity=opacity), cam
    n = 100_000 if quick else 1_000_000
    yield f"trained-like {n // 1000}k aniso SH3 1920x1080", trained_like_scene(n, big), big


def run(quick=False):
    rows = []
    repeat = 2 if quick else 3
    for name, cloud, cam in scenes(quick):
        t0 = time.perf_counter()
        image = baseline_render(cloud, cam)      # minutes at 1M splats: timed once
        base = Timing(time.perf_counter() - t0, 0.0, 1)
        pixels = sample_pixels(cam, 1024 if len(cloud) > 100_000 else 4096)
        t0 = time.perf_counter()
        ref = reference_render(cloud, cam, pixels=pixels)
        ref_seconds = time.perf_counter() - t0
        footprint = int(render(cloud, cam, t_min=0.0, return_counts=True).counts.sum())
        options = [("default (tile 8, wave 32, float32)", {})]
        if not quick:
            options += [("tile 4", {"tile_size": 4}), ("tile 16", {"tile_size": 16}),
                        ("wave 8", {"wave": 8}), ("wave 128", {"wave": 128}),
                        ("float64", {"precision": "float64"}), ("max_sigma 3 (reference cut)", {"max_sigma": 3.0}),
                        ("1 thread", {"threads": 1}), ("with max_weight per splat", {"return_weights": True})]
        for label, opts in options:
            result = render(cloud, cam, return_counts=True, **opts)
            timing = timeit(lambda: render(cloud, cam, **opts), repeat=repeat)
            error = {"max_err_255": max_error(result.color, pixels, ref)}
            extra = {"splats": len(cloud), "footprint_pairs": footprint,
                     "footprint_pairs_per_s": f"{footprint / timing.median / 1e6:.0f}M",
                     "blended_pairs": int(result.counts.sum()),
                     "evaluated_pairs": result.stats["evaluated"]}
            rows.append(Row(TOPIC, f"{name}: {label}", timing, base, error, extra))
        rows.append(Row(TOPIC, f"{name}: seed prototype baseline", base, None,
                        {"max_err_255": max_error(image, pixels, ref)},
                        {"splats": len(cloud), "footprint_pairs": footprint,
                         "footprint_pairs_per_s": f"{footprint / base.median / 1e6:.1f}M"}))
        print(f"  ({name}: reference at {len(pixels)} pixels took {ref_seconds:.1f} s)", flush=True)
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
