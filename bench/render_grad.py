"""The renderer's backward pass (core.render_grad.mse_gradients), compiled and by NumPy, against the
forward render it differentiates.

Scene: the built-in thin-walled cup (core.scenes) converted to splats made for antialiased rendering,
given SH 3 with noise so every band has a gradient, seen by four cameras around it; the target
image is the render of the cloud before the noise. Baseline, timed in the same run: the compiled
forward render of the same view (what one step of bake_splats would cost without a backward
pass). Errors, against the NumPy pass in float64 (its image is core.render's float64 NumPy path's
to 4e-5 of a 1/255 step):
- image: the largest pixel difference, in 1/255 steps;
- gradient: the largest difference, as a fraction of each parameter's largest.
The float64 gradients themselves are checked against central differences of the float64
brute-force reference renderer in tests/test_render_grad.py, on a scene where differences are
well posed: on a converted mesh, steps small enough for the splats (0.1 mm) move some of them
across the 1/255 alpha rule at a pixel or two, jumps as large as the change being measured.

    python bench/render_grad.py [--quick]
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import Row, paired, print_rows  # noqa: E402

from splatwright.core.camera import frame_points  # noqa: E402
from splatwright.core.mesh_to_splats import mesh_to_splats  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.core.render_grad import mse_gradients  # noqa: E402
from splatwright.core.scenes import thin_walled_cup  # noqa: E402
from splatwright.core.splats import FIELDS  # noqa: E402

TOPIC = "render_grad"


def scene(size, budget):
    mesh = thin_walled_cup()
    cloud = mesh_to_splats(
        mesh.vertices,
        mesh.faces,
        **mesh.appearance(),
        max_splats=budget,
        view_size=size,
        render_mode="antialiased",
        try_fewer=False,
    )
    cloud = cloud.with_sh_degree(3)
    rng = np.random.default_rng(0)
    noisy = cloud.replace(sh=(cloud.sh + rng.normal(0, 0.05, cloud.sh.shape)).astype(np.float32))
    cameras = [
        frame_points(mesh.vertices, size, size, fov_deg=40.0, direction=d, near=0.01)
        for d in ((1, 0.6, 1), (-1, 0.8, 0.3), (0.2, -0.5, -1), (0.6, 1.5, -0.4))
    ]
    return noisy, cameras, [render(cloud, cam).color for cam in cameras]


def run(quick=False):
    size, budget = (128, 20_000) if quick else (256, 60_000)
    cloud, cameras, targets = scene(size, budget)
    rows = []
    for view, (camera, target) in enumerate(zip(cameras[:2] if quick else cameras, targets), 1):
        exact = mse_gradients(cloud, camera, target, precision="float64", backend="numpy")
        common = {"splats": len(cloud), "pixels": f"{size}x{size}", "view": view}
        for label, options in (
            ("compiled (float64)", {"backend": "compiled"}),
            ("NumPy, float32 pixels", {"backend": "numpy", "precision": "float32"}),
        ):
            base, ours = paired(
                lambda: render(cloud, camera), lambda: mse_gradients(cloud, camera, target, **options), repeat=5
            )
            image, _, grad = mse_gradients(cloud, camera, target, **options)
            error = {
                "image err (1/255)": 255 * np.abs(image - exact[0]).max(),
                "grad err": max(
                    np.abs(getattr(grad, n) - getattr(exact[2], n)).max() / np.abs(getattr(exact[2], n)).max()
                    for n in FIELDS
                ),
            }
            rows.append(
                Row(
                    TOPIC,
                    f"view {view}: image and gradients, {label} (baseline: the compiled forward render)",
                    ours,
                    base,
                    error=error,
                    extra=common,
                )
            )
    return rows


if __name__ == "__main__":
    print_rows(run(quick="--quick" in sys.argv))
