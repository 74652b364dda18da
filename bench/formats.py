"""Every format against PLY: read and write time of a 1M-splat degree-3 cloud (PLY timed alternately
in the same run as the baseline), file size, and the error each lossy format introduces per
attribute (position, scale, rotation angle, opacity, colour, higher SH). SPZ is also timed against
gsply's SPZ writer (PyPI, in its own environment under .cache/interop, run in the same loop), with
the peak memory of our write against the cloud's own size."""

import subprocess
import sys
import tempfile
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from common import Row, Timing, fresh_file, machine, paired, print_rows  # noqa: E402
from helpers import random_cloud  # noqa: E402

from splatwright.core import sh as shmod  # noqa: E402
from splatwright.core.splats import FIELDS  # noqa: E402
from splatwright.io import SplatFileWarning, compressed_ply, gltf, ply, sog, splat, spz, usd  # noqa: E402

morton = lambda cloud: compressed_ply.morton_order(cloud.positions)  # noqa: E731


def without_pxr(function):
    """`function` run as where OpenUSD's Python module is missing (Blender 4.2): text layers."""

    def run(*args):
        saved, usd.stages.active = usd.stages.active, usd.stages.TEXT
        try:
            return function(*args)
        finally:
            usd.stages.active = saved

    return run


# name -> (file suffix, write(path, cloud), read(path), share of the full splat count, the order the
# file holds the splats in, or None for the cloud's own)
FORMATS = {
    "USD float (.usdc)": (".usdc", usd.write, usd.read, 1, None),
    "USD half (.usdc)": (".usdc", lambda p, c: usd.write(p, c, half=True), usd.read, 1, None),
    # text formats every number in Python's shortest round-trip decimals: a tenth of the splats
    "USD text without pxr (.usda)": (".usda", without_pxr(usd.write), without_pxr(usd.read), 10, None),
    # the lossy web formats compress slowly (gzip 6 / zstd 12, as Niantic's writer; SOG's k-means
    # and WebP): a fifth of the splats measures the same per-splat speed ratio and the same errors
    "SPZ v2": (".spz", lambda p, c: spz.write(p, c, version=2), spz.read, 5, None),
    "SPZ v3": (".spz", lambda p, c: spz.write(p, c, version=3), spz.read, 5, None),
    "SPZ v4 (zstd)": (".spz", lambda p, c: spz.write(p, c, version=4), spz.read, 5, None),
    "compressed PLY": (".compressed.ply", compressed_ply.write, compressed_ply.read, 1, morton),
    "SOG (.sog)": (".sog", sog.write, sog.read, 5, morton),
    "glTF (.glb)": (".glb", gltf.write, gltf.read, 1, None),
    ".splat": (".splat", splat.write, splat.read, 1, None),
}


def attribute_errors(got, want):
    """Per-attribute error of a decoded cloud against the original."""
    a, b = got.unit_rotations, want.unit_rotations
    b = b * np.where((a * b).sum(axis=1, keepdims=True) < 0, -1, 1)  # q and -q: one rotation
    angles = np.degrees(4 * np.arcsin(np.minimum(1, np.linalg.norm(a - b, axis=1) / 2)))
    k = min(got.sh.shape[1], want.sh.shape[1])
    rest = np.abs(got.sh[:, 1:k].astype(np.float64) - want.sh[:, 1:k]) if k > 1 else np.zeros(1)
    dropped = np.abs(want.sh[:, k:]) if want.sh.shape[1] > k else np.zeros(1)
    rest = np.concatenate([rest.reshape(-1), dropped.reshape(-1)])
    return {
        "position_max_m": float(np.abs(got.positions.astype(np.float64) - want.positions).max()),
        "scale_rel_max": float((np.abs(got.scales - want.scales) / want.scales).max()),
        "rotation_deg_median": float(np.median(angles)),
        "rotation_deg_max": float(angles.max()),
        "opacity_max": float(np.abs(got.opacities - want.opacities).max()),
        "dc_rgb_max": float(np.abs(shmod.dc_to_rgb(got.sh[:, 0]) - shmod.dc_to_rgb(want.sh[:, 0])).max()),
        "sh_rest_p99": float(np.percentile(rest, 99)),
        "sh_rest_max": float(rest.max()),
    }


VERSIONS_AGAINST_GSPLY = (3, 4)


def gsply_rows(cloud, tmp, repeat):
    """SPZ v3 and v4 writes of `cloud`: ours against gsply's, alternately in one loop; [] (with a
    note) when gsply cannot be installed."""
    try:
        import interop

        python = interop.python_tool("gsply")
    except BaseException as exc:  # pytest's skip is a BaseException
        print(f"[formats] gsply not available, SPZ is not timed against it: {exc}", file=sys.stderr)
        return []
    interop.save_arrays(tmp / "cloud.npz", **interop.ply_arrays(cloud))
    driver = Path(__file__).resolve().parent.parent / "tests" / "interop" / "gsply_tool.py"
    nbytes = sum(getattr(cloud, name).nbytes for name in FIELDS)
    rows = []
    for version in VERSIONS_AGAINST_GSPLY:
        ours, theirs = [], []
        write = fresh_file(tmp / "ours.spz", lambda p: spz.write(p, cloud, version=version))
        write()
        for _ in range(repeat):
            start = time.perf_counter()
            write()
            ours.append(time.perf_counter() - start)
            done = subprocess.run(
                [str(python), str(driver), "time-spz", str(tmp / "cloud.npz"), str(tmp / "g.spz"), "1", str(version)],
                capture_output=True,
                text=True,
                check=True,
            )
            theirs.append(float(done.stdout.split()[-1]))
        tracemalloc.start()
        spz.write(tmp / "ours.spz", cloud, version=version)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        timing = lambda t: Timing(float(np.median(t)), (max(t) - min(t)) / 2, len(t))  # noqa: E731
        size, their_size = (tmp / "ours.spz").stat().st_size, (tmp / "g.spz").stat().st_size
        rows.append(
            Row(
                "formats",
                f"write SPZ v{version} against gsply, {len(cloud):,} splats, SH degree 3",
                timing(ours),
                timing(theirs),
                {},
                {
                    "baseline": f"gsply write_spz(version={version})",
                    "MiB": f"{size / 2**20:.1f}",
                    "gsply_MiB": f"{their_size / 2**20:.1f}",
                    "peak_memory_vs_cloud": f"{peak / nbytes:.2f}",
                    "speed_vs_gsply": f"{np.median(theirs) / np.median(ours):.2f}x",
                },
            )
        )
    return rows


def run(quick=False):
    n = 100_000 if quick else 1_000_000
    repeat = 3 if quick else 5
    full = random_cloud(n, sh_degree=3, seed=0)
    rows = []
    with tempfile.TemporaryDirectory(prefix="splatwright-bench-formats-") as folder, warnings.catch_warnings():
        warnings.simplefilter("ignore", SplatFileWarning)  # clamping and dropped SH: measured below
        tmp = Path(folder)
        for name, (suffix, write, read, share, order) in FORMATS.items():
            cloud = full[: n // share]
            ply_path = tmp / "cloud.ply"
            ply.write(ply_path, cloud)
            ply_size = ply_path.stat().st_size
            case = f"{len(cloud):,} splats, SH degree 3"
            path = tmp / f"out{suffix}"
            write_ply, write_ours = paired(
                fresh_file(tmp / "base.ply", lambda p: ply.write(p, cloud)),
                fresh_file(path, lambda p: write(p, cloud)),
                repeat,
            )
            read_ply, read_ours = paired(lambda: ply.read(ply_path), lambda: read(path), repeat)
            size = path.stat().st_size
            errors = attribute_errors(read(path), cloud if order is None else cloud[order(cloud)])
            extra = {
                "MiB": f"{size / 2**20:.1f}",
                "bytes_per_splat": f"{size / len(cloud):.1f}",
                "size_vs_ply": f"{size / ply_size:.3f}",
            }
            for verb, ours, base in (("write", write_ours, write_ply), ("read", read_ours, read_ply)):
                rows.append(
                    Row(
                        "formats",
                        f"{verb} {name}, {case}",
                        ours,
                        base,
                        errors,
                        {**extra, "baseline": f"PLY {verb}", "slowdown": f"{ours.median / base.median:.2f}x"},
                    )
                )
        rows += gsply_rows(full, tmp, repeat)
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
