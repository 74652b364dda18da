"""Model only what a scene needs: what each economy saves, and what it costs in the image.

On a trained-like cloud (anisotropic, SH degree 3), each economy is applied on its own to the full
cloud: lower SH degrees, pruning faint splats, pruning splats no view sees, half-precision OpenUSD.
Savings are splats and file bytes; the cost is the PSNR and largest absolute difference of RGBA
renders against the full cloud from views between the ones pruning used (core.economy.image_error);
the speed column is the render time of one 512x512 view, as a ratio against the full cloud's (the
baseline, timed in the same run). Weight pruning is measured on a skinned cloud: influences kept
against centre error and skinning time. A splat budget from a target error is mesh2splats' topic.

    python bench/economy.py [--quick]
"""

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from articulation import workload  # noqa: E402
from common import Row, machine, print_rows, timeit  # noqa: E402
from render import seed_camera, trained_like_scene  # noqa: E402

from splatwright.core import economy  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.core.skinning import Binding, skin_centres  # noqa: E402
from splatwright.io import SplatFileWarning, read_splats, write_splats  # noqa: E402

TOPIC = "economy"


def cloud_rows(n, repeat):
    cloud = trained_like_scene(n, seed_camera(), seed=3)
    points = economy.cloud_points(cloud)
    prune_views = economy.orbit_views(points, count=12, width=128)
    check_views = economy.orbit_views(points, count=12, width=128, phase=0.5)
    reference = economy.render_views(cloud, check_views)
    camera = seed_camera()
    full_time = timeit(lambda: render(cloud, camera), repeat=repeat)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:

        def size(c, name, **options):
            path = Path(tmp) / name
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", SplatFileWarning)
                write_splats(path, c, **options)
                return path.stat().st_size, read_splats(path)

        full_bytes, _ = size(cloud, "full.ply")
        variants = [(f"SH degree 3 -> {d}", cloud.with_sh_degree(d), "ply", {}) for d in (2, 1, 0)]
        for threshold in (0.02, 0.05, 0.1):
            variants.append((f"prune opacity < {threshold}", cloud[economy.opacity_mask(cloud, threshold)], "ply", {}))
        for weight in (0.0, 1 / 255):
            keep = economy.visible_mask(cloud, prune_views, min_weight=weight)
            variants.append((f"prune invisible (weight <= {weight:.3g})", cloud[keep], "ply", {}))
        variants.append(("OpenUSD float", cloud, "usdc", {}))
        variants.append(("OpenUSD half floats", cloud, "usdc", {"half": True}))
        for name, variant, ext, options in variants:
            nbytes, back = size(variant, f"v.{ext}", **options)
            err = economy.image_error(reference, back, check_views)
            t = timeit(lambda: render(back, camera), repeat=repeat)
            rows.append(
                Row(
                    TOPIC,
                    name,
                    t,
                    full_time,
                    error={"psnr_db": err.psnr, "max_abs": err.max_abs},
                    extra={
                        "splats": len(back),
                        "splats_saved": f"{1 - len(back) / n:.1%}",
                        "bytes_saved": f"{1 - nbytes / full_bytes:.1%}",
                    },
                )
            )
    return rows


def weight_rows(n, repeat):
    cloud, binding, pose = workload(n)
    exact = skin_centres(cloud.positions, binding, pose)
    full_time = timeit(lambda: skin_centres(cloud.positions, binding, pose), repeat=repeat)
    rows = []
    for k in (3, 2, 1):
        pruned = Binding.from_weights(binding.indices, binding.weights, max_influences=k)
        t = timeit(lambda: skin_centres(cloud.positions, pruned, pose), repeat=repeat)
        moved = np.linalg.norm(skin_centres(cloud.positions, pruned, pose) - exact, axis=1)
        rows.append(
            Row(
                TOPIC,
                f"skinning weights pruned to {k} of 4 influences",
                t,
                full_time,
                error={"centre_err_median": float(np.median(moved)), "centre_err_max": float(moved.max())},
                extra={"pruned_weight_mean": f"{pruned.pruned.mean():.3f}"},
            )
        )
    return rows


def run(quick=False):
    repeat = 3 if quick else 5
    return cloud_rows(50_000 if quick else 300_000, repeat) + weight_rows(100_000 if quick else 1_000_000, repeat)


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
