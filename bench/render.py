"""Renderer speed against error: the compiled kernels against the NumPy path, and both against the
seed prototype's algorithm.

Baselines, each timed in the same run:
- the NumPy path (`render(..., backend="numpy")`, the readable reference and the fallback where
  numba cannot load), for the targets: 1M SH-3 splats at 1080p in CPU seconds (all threads), deep
  pixel stacks and cost per pixel from 256x144 to 4K (splats per pixel held fixed), and peak memory
  for 10M splats at 1080p (a child process reads the PLY and renders; peak RSS against the file);
- the seed scene's prototype renderer, reimplemented here: isotropic splats, one Python iteration
  per splat, each vectorised over the pixels of its 3-sigma box, full-frame accumulators.
Errors are max abs differences (in 1/255 steps of display sRGB) against the float64 brute-force
reference of tests/reference_render.py at a random sample of pixels. A pair is a splat-pixel pair
with alpha >= 1/255 (the footprint: blended pairs when the transmittance stop is off).

    python bench/render.py [--quick]
    ./run bench render --only big-scene     only the 1M-splat 1080p rows, merged into the report
    ./run bench render --only sweep         only the resolution sweep
"""

import math
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from common import Row, Timing, machine, paired, print_rows, timeit  # noqa: E402
from reference_render import _project_all, reference_render  # noqa: E402

from splatwright.core import SplatCloud  # noqa: E402
from splatwright.core.camera import Camera  # noqa: E402
from splatwright.core.render import backend_status, render  # noqa: E402
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
    """(name, cloud, camera) for each small benchmark scene; quick mode shrinks them."""
    cam = seed_camera()
    for label, edge, sigma, opacity in [
        ("seed cube", 10, 0.05, 0.08),
        ("small splats", 60, 0.008, 0.5),
        ("large splats", 40, 0.05, 0.08),
    ]:
        edge = edge // 2 if quick and edge > 10 else edge
        yield f"{label} {edge}^3 (sigma {sigma}, o {opacity}) 512x512", seed_cube(edge, sigma, opacity=opacity), cam


def wide_camera(width, height):
    return Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), fov_deg=60.0, width=width, height=height)


def footprint(cloud, cam):
    """Splat-pixel pairs with alpha >= 1/255 (blended pairs without the transmittance stop)."""
    return int(render(cloud, cam, t_min=0.0, return_counts=True).counts.sum())


def alpha_pairs(cloud, cam):
    """Splat-pixel pairs with alpha >= 1/255, counted splat by splat over every pixel (for deep
    stacks, where the transmittance of a render without its stop underflows to 0)."""
    splats = _project_all(cloud, cam, "classic")
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    px, py = cols.ravel() + 0.5, rows.ravel() + 0.5
    total = 0
    for start in range(0, len(splats["z"]), 4096):
        sl = slice(start, start + 4096)
        dx, dy = px - splats["mean"][sl, 0, None], py - splats["mean"][sl, 1, None]
        con = splats["conic"][sl]
        q = con[:, 0, 0, None] * dx * dx + 2 * con[:, 0, 1, None] * dx * dy + con[:, 1, 1, None] * dy * dy
        total += int((splats["opacity"][sl, None] * np.exp(-0.5 * q) >= 1 / 255).sum())
    return total


CPU = time.process_time


def run(quick=False):
    print(f"  (compiled kernels: {backend_status()})", flush=True)
    rows = small_scenes(quick)
    rows += big_scene(quick)
    rows += deep_stack(quick, rows[-1])
    rows += resolution_sweep(quick)
    rows += memory(quick)
    return rows


def small_scenes(quick):
    """The seed-cube scenes: compiled and NumPy against the seed prototype."""
    rows = []
    for name, cloud, cam in scenes(quick):
        t0 = time.perf_counter()
        image = baseline_render(cloud, cam)
        base = Timing(time.perf_counter() - t0, 0.0, 1)
        pixels = sample_pixels(cam, 4096)
        ref = reference_render(cloud, cam, pixels=pixels)
        pairs = footprint(cloud, cam)
        for backend in ("compiled", "numpy"):
            result = render(cloud, cam, backend=backend)
            timing = timeit(lambda: render(cloud, cam, backend=backend), repeat=2 if quick else 3)
            rows.append(
                Row(
                    TOPIC,
                    f"{name}: {backend}",
                    timing,
                    base,
                    {"max_err_255": max_error(result.color, pixels, ref)},
                    {
                        "splats": len(cloud),
                        "footprint_pairs": pairs,
                        "ns_per_pair": f"{timing.median / pairs * 1e9:.1f}",
                        "baseline": "seed prototype",
                    },
                )
            )
        rows.append(
            Row(
                TOPIC,
                f"{name}: seed prototype",
                base,
                None,
                {"max_err_255": max_error(image, pixels, ref)},
                {"splats": len(cloud), "footprint_pairs": pairs},
            )
        )
    return rows


def big_scene(quick):
    """Target: 1M anisotropic SH-3 splats at 1920x1080, compiled >= 4x the NumPy path in CPU seconds."""
    n = 100_000 if quick else 1_000_000
    cam = wide_camera(1920, 1080)
    cloud = trained_like_scene(n, cam)
    name = f"{n // 1000}k aniso SH3 1920x1080"
    pixels = sample_pixels(cam, 1024)
    ref = reference_render(cloud, cam, pixels=pixels)
    pairs = footprint(cloud, cam)
    repeat = 2 if quick else 3
    slow_cpu, fast_cpu = paired(lambda: render(cloud, cam, backend="numpy"), lambda: render(cloud, cam), repeat, CPU)
    slow_wall, fast_wall = paired(lambda: render(cloud, cam, backend="numpy"), lambda: render(cloud, cam), repeat)
    fast, slow = render(cloud, cam, return_counts=True), render(cloud, cam, return_counts=True, backend="numpy")
    extra = {"splats": n, "footprint_pairs": pairs, "baseline": "NumPy path, CPU s"}
    rows = [
        Row(
            TOPIC,
            f"{name}: compiled, CPU s (target >= 4x)",
            fast_cpu,
            slow_cpu,
            {"max_err_255": max_error(fast.color, pixels, ref)},
            {
                **extra,
                "ns_per_pair": f"{fast_cpu.median / pairs * 1e9:.1f}",
                "evaluated_pairs": fast.stats["evaluated"],
                "blended_pairs": int(fast.counts.sum()),
            },
        ),
        Row(
            TOPIC,
            f"{name}: NumPy path, CPU s",
            slow_cpu,
            None,
            {"max_err_255": max_error(slow.color, pixels, ref)},
            {
                **extra,
                "ns_per_pair": f"{slow_cpu.median / pairs * 1e9:.1f}",
                "evaluated_pairs": slow.stats["evaluated"],
                "blended_pairs": int(slow.counts.sum()),
            },
        ),
        Row(TOPIC, f"{name}: compiled, wall s", fast_wall, slow_wall, {}, {"baseline": "NumPy path, wall s"}),
    ]
    options = (
        []
        if quick
        else [
            ("tile 16", {"tile_size": 16}),
            ("float64", {"precision": "float64"}),
            ("max_sigma 3 (reference cut)", {"max_sigma": 3.0}),
            ("1 thread", {"threads": 1}),
            ("with max_weight per splat", {"return_weights": True}),
        ]
    )
    for label, opts in options:
        timing = timeit(lambda: render(cloud, cam, **opts), repeat=2, clock=CPU)
        result = render(cloud, cam, **opts)
        rows.append(
            Row(
                TOPIC,
                f"{name}: compiled, {label}, CPU s",
                timing,
                slow_cpu,
                {"max_err_255": max_error(result.color, pixels, ref)},
                {"baseline": "NumPy path default, CPU s"},
            )
        )
    big_scene.per_pair = fast_cpu.median / pairs
    return rows


def deep_stack(quick, big_row):
    """Target: 1e5 splats on a 16x16 image (each a few pixels wide, so every pixel lies under
    thousands) cost within 1.5x the CPU time per pair of the big scene."""
    n = 20_000 if quick else 100_000
    cam = wide_camera(16, 16)
    cloud = trained_like_scene(n, cam, seed=3, sigma_px=3.0)
    pairs = alpha_pairs(cloud, cam)
    slow, fast = paired(lambda: render(cloud, cam, backend="numpy"), lambda: render(cloud, cam), 5, CPU)
    pixels = sample_pixels(cam, 256)
    ref = reference_render(cloud, cam, pixels=pixels)
    per_pair = fast.median / pairs
    return [
        Row(
            TOPIC,
            f"deep stack {n // 1000}k splats 16x16: compiled, CPU s",
            fast,
            slow,
            {"max_err_255": max_error(render(cloud, cam).color, pixels, ref)},
            {
                "footprint_pairs": pairs,
                "ns_per_pair": f"{per_pair * 1e9:.1f}",
                "per_pair_vs_big_scene": f"{per_pair / big_scene.per_pair:.2f}x (target <= 1.5x)",
                "baseline": "NumPy path, CPU s",
            },
        )
    ]


def resolution_sweep(quick):
    """Target: cost linear in pixels from 256x144 to 4K, at 0.5 splats per pixel of SH-3 splats
    sized as in a capture (sigma ~1.5 px) and as sub-pixel splats (sigma ~0.3 px)."""
    sizes = [(256, 144), (640, 360), (1920, 1080)] + ([] if quick else [(3840, 2160)])
    rows = []
    for sigma_px in (1.5, 0.3):
        per_pixel = {}
        for w, h in sizes:
            cam = wide_camera(w, h)
            cloud = trained_like_scene(w * h // 2, cam, seed=5, sigma_px=sigma_px)
            repeat = 9 if w * h < 1e6 else 3  # small renders are short: more runs steady the median
            slow, fast = paired(lambda: render(cloud, cam, backend="numpy"), lambda: render(cloud, cam), repeat, CPU)
            result, blended = render(cloud, cam), footprint(cloud, cam)
            per_pixel[(w, h)] = fast.median / (w * h)
            rows.append(
                Row(
                    TOPIC,
                    f"sweep sigma {sigma_px} px, {w}x{h}, {len(cloud) // 1000}k splats: compiled, CPU s",
                    fast,
                    slow,
                    {},
                    {
                        "ns_per_pixel": f"{per_pixel[(w, h)] * 1e9:.1f}",
                        "evaluated_per_footprint_pair": f"{result.stats['evaluated'] / blended:.2f}",
                        "baseline": "NumPy path, CPU s",
                    },
                )
            )
        spread = max(per_pixel.values()) / min(per_pixel.values())
        rows[-1].extra["per_pixel_max_over_min"] = f"{spread:.2f} (target <= 1.5, linear)"
    return rows


MEMORY_CHILD = """
    import resource, sys, time
    from splatwright.io import read_splats
    from splatwright.core.camera import Camera
    from splatwright.core.render import render

    def peak():  # this process's own (VmHWM); ru_maxrss also counts the parent's memory at the fork
        linux = sys.platform == "linux"
        hwm = [line for line in open("/proc/self/status") if line.startswith("VmHWM")] if linux else []
        return int(hwm[0].split()[1]) * 1024 if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    cloud = read_splats(sys.argv[1])
    read_peak = peak()
    try:                        # Linux: restart the peak (VmHWM) so that the render's own is measured
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    width, height, backend = int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), fov_deg=60.0, width=width, height=height)
    t0 = time.process_time()
    try:
        result = render(cloud, cam, backend=backend)
        outcome = f"rendered {result.stats['visible']} splats"
    except ValueError as exc:
        outcome = f"refused: {exc}"
    print(time.process_time() - t0)
    print(peak())
    print(read_peak)
    print(outcome)
"""


def memory(quick):
    """Target: 10M SH-3 splats at 1080p in under 4x the file size in peak memory (a child process
    reads the file and renders); a 40000x40000 render refused before allocating."""
    n = 500_000 if quick else 10_000_000
    cam = wide_camera(1920, 1080)
    rows = []
    with tempfile.TemporaryDirectory(prefix="splatwright-bench-render-") as tmp:
        path = Path(tmp) / "cloud.ply"
        from splatwright.io import ply

        ply.write(path, trained_like_scene(n, cam, seed=7))
        size = path.stat().st_size
        for backend, (w, h) in [("compiled", (1920, 1080)), ("numpy", (1920, 1080)), ("compiled", (40000, 40000))]:
            done = subprocess.run(
                [sys.executable, "-c", textwrap.dedent(MEMORY_CHILD), str(path), str(w), str(h), backend],
                capture_output=True,
                text=True,
            )
            if done.returncode != 0:
                raise RuntimeError(done.stderr)
            seconds, peak, read_peak, outcome = done.stdout.strip().splitlines()[-4:]
            rows.append(
                Row(
                    TOPIC,
                    f"{n // 1_000_000 or n / 1e6}M splats from a {size / 2**30:.2f} GiB PLY at {w}x{h}: "
                    f"{backend}, peak memory while rendering",
                    Timing(float(seconds), 0.0, 1),
                    None,
                    {"peak_over_file": round(int(peak) / size, 2)},
                    {
                        "peak_GiB": f"{int(peak) / 2**30:.2f}",
                        "target": "peak < 4x the file",
                        "read_peak_GiB": f"{int(read_peak) / 2**30:.2f}",
                        "outcome": outcome[:90],
                    },
                )
            )
    return rows


# rows that `./run bench render --only NAME` runs alone (merged into the report's section)
PARTS = {"big-scene": big_scene, "sweep": resolution_sweep}


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
