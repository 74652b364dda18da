"""Nearest points of a proxy mesh for captured splats (core.proxy.closest_points, used by binding a
capture through a rigged proxy), against the plain chunked brute force over every triangle (the
same per-pair arithmetic, timed in the same run). A capture-like cloud: most splats within a few
centimetres of a body-sized surface, some far away (floor, walls, floaters). The error column is
the largest difference of the distances found (0: the search is exact).

    python bench/proxy.py [--quick]
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import Row, machine, paired, print_rows  # noqa: E402

from splatwright.core import proxy  # noqa: E402

TOPIC = "proxy"


def body(rows, cols):
    """An ellipsoid 0.5 x 0.3 x 1.8 m as a UV sphere (poles make degenerate triangles, as scans do)."""
    u, v = np.meshgrid(np.linspace(0, np.pi, rows), np.linspace(0, 2 * np.pi, cols), indexing="ij")
    verts = np.stack([0.25 * np.sin(u) * np.cos(v), 0.15 * np.sin(u) * np.sin(v), 0.9 * np.cos(u)], -1).reshape(-1, 3)
    a = (np.arange(rows - 1)[:, None] * cols + np.arange(cols - 1)[None]).ravel()
    faces = np.concatenate([np.stack([a, a + cols, a + 1], 1), np.stack([a + 1, a + cols, a + cols + 1], 1)])
    return verts, faces


def capture(verts, n_near, n_far, seed=0):
    rng = np.random.default_rng(seed)
    near = verts[rng.integers(0, len(verts), n_near)] * rng.uniform(0.97, 1.05, (n_near, 1))
    near += rng.normal(0, 0.01, near.shape)
    far = rng.uniform(-3, 3, (n_far, 3))
    return np.concatenate([near, far])


def brute_force(points, verts, faces, chunk=1 << 20):
    step = max(1, chunk // len(faces))
    best = np.empty(len(points))
    for start in range(0, len(points), step):
        p = points[start : start + step]
        pp = np.repeat(np.arange(len(p)), len(faces))
        tri = np.tile(faces, (len(p), 1))
        d2, _ = proxy.closest_on_triangles(p[pp], verts[tri[:, 0]], verts[tri[:, 1]], verts[tri[:, 2]])
        best[start : start + step] = np.sqrt(d2.reshape(len(p), len(faces)).min(axis=1))
    return best


def run(quick=False):
    rows = []
    repeat = 3
    cases = [((24, 40), 4000, 400), ((48, 80), 8000, 800)]
    for grid, n_near, n_far in cases[:1] if quick else cases:
        verts, faces = body(*grid)
        points = capture(verts, n_near, n_far)
        found = proxy.closest_points(points, verts, faces)
        exact = brute_force(points, verts, faces)
        base, ours = paired(
            lambda: brute_force(points, verts, faces), lambda: proxy.closest_points(points, verts, faces), repeat=repeat
        )
        rows.append(
            Row(
                TOPIC,
                f"{len(points)} splats ({n_far} far), {len(faces)} triangles",
                ours,
                base,
                error={"max_distance_diff_m": float(np.abs(found.distance - exact).max())},
                extra={"us_per_splat": f"{1e6 * ours.median / len(points):.0f}"},
            )
        )
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
