"""Normals estimated from splat shapes (core.normals.estimate_normals), against the true normals of
splats made from closed meshes (each splat's source triangle's winding normal), by orientation rule:
away from the cloud's centre, towards bare camera centres (no visibility), and towards core Cameras
seen through a depth test (vote, head-on, nearest). Meshes: a UV sphere, the decal box and the
striped cup of core.mesh_corpus (a thin-walled concave solid), and a torus (concave, genus one).
Cameras: 24 orbit views round each mesh. "noisy" rows disturb every splat's covariance as a
capture's training leaves it: flatness 0.3 and a random symmetric change of 10% of the in-plane
variance, re-diagonalised. The "roundness" rows give the axis error (sign ignored) against how round
the splats are, which sets core.normals.TOO_ROUND. Times: estimate_normals alone (visibility renders
included for Cameras); the baseline is the centre rule.

    python bench/normals.py [--quick]
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import Row, machine, paired, print_rows, timeit  # noqa: E402

from splatwright.core import economy, geometry, mesh_corpus, mesh_to_splats  # noqa: E402
from splatwright.core import normals as nm  # noqa: E402
from splatwright.core.mesh import Surface  # noqa: E402

TOPIC = "normals"
VIEWS = 24


def torus(segments=96, rings=48, major=0.7, minor=0.3):
    """A closed torus about y, wound outward."""
    u, v = np.meshgrid(
        np.linspace(0, 2 * np.pi, segments, endpoint=False), np.linspace(0, 2 * np.pi, rings, endpoint=False)
    )
    u, v = u.ravel(), v.ravel()
    verts = np.column_stack(
        [(major + minor * np.cos(v)) * np.cos(u), minor * np.sin(v), (major + minor * np.cos(v)) * np.sin(u)]
    )
    i, j = np.meshgrid(np.arange(segments), np.arange(rings))
    i, j = i.ravel(), j.ravel()
    a, b = j * segments + i, j * segments + (i + 1) % segments
    c, d = ((j + 1) % rings) * segments + i, ((j + 1) % rings) * segments + (i + 1) % segments
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    return verts, faces


def meshes(quick):
    found = {
        "sphere": mesh_corpus.vertex_coloured_sphere(),
        "decal box": mesh_corpus.decal_box(),
        "striped cup": mesh_corpus.striped_cup(),
    }
    out = {name: (m.vertices, m.faces) for name, m in found.items()}
    out["torus"] = torus()
    return dict(list(out.items())[:2]) if quick else out


def outward(vertices, faces):
    """The faces wound so that the solid's signed volume is positive (normals outward)."""
    v = np.asarray(vertices, np.float64)[faces]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum()
    return faces if volume > 0 else faces[:, ::-1]


def noisy(cloud, rng, flatness=0.3, change=0.1):
    """The cloud with each covariance disturbed as a capture leaves it (see the module notes)."""
    scales = cloud.scales.copy()
    scales[:, 2] = flatness * scales[:, :2].min(axis=1)
    sigma = geometry.covariances(cloud.rotations, scales)
    e = rng.normal(0.0, 1.0, (len(cloud), 3, 3))
    e = 0.5 * (e + np.swapaxes(e, 1, 2)) * (change * scales[:, :2].mean(axis=1) ** 2)[:, None, None]
    q, s = geometry.decompose_covariances(sigma + e)
    return cloud.replace(rotations=q, log_scales=np.log(np.maximum(s, 1e-12)))


def rows_for(name, cloud, true, repeat):
    cams = economy.orbit_views(cloud.positions, count=VIEWS, width=256)
    centres = np.array([c.center for c in cams])
    base = timeit(lambda: nm.estimate_normals(cloud), repeat=repeat)
    cases = [("centre", {}, base)]
    cases.append(("camera centres, nearest", dict(cameras=centres, rule="nearest"), None))
    for rule in nm.RULES:
        cases.append((f"{VIEWS} cameras, {rule}", dict(cameras=cams, rule=rule), None))
    rows = []
    for label, options, timing in cases:
        found = nm.estimate_normals(cloud, **options)
        if timing is None:
            base, timing = paired(
                lambda: nm.estimate_normals(cloud), lambda: nm.estimate_normals(cloud, **options), repeat
            )
        stats = nm.angular_error(found, true)
        rows.append(
            Row(
                TOPIC,
                f"{name}: {label}",
                timing,
                None if label == "centre" else base,
                error={"flips_pct": 100 * stats.flips, "median_deg": stats.median, "p90_deg": stats.p90},
                extra={"splats": len(cloud), "too_round_pct": f"{100 * nm.too_round(cloud).mean():.3g}"},
            )
        )
    return rows


def roundness_rows(cloud, true, rng):
    """Axis error (sign ignored) of noisy splats against their flatness."""
    rows = []
    for flatness in (0.1, 0.3, 0.5, 0.7, 0.8, 0.9):
        disturbed = noisy(cloud, rng, flatness=flatness)
        axes = nm.shortest_axes(disturbed)
        stats = nm.angular_error(axes * np.sign(np.einsum("ij,ij->i", axes, true))[:, None], true)
        r = nm.roundness(disturbed)
        rows.append(
            Row(
                TOPIC,
                f"roundness: noisy sphere, flatness {flatness}",
                timeit(lambda: nm.shortest_axes(disturbed), repeat=3),
                error={"median_deg": stats.median, "p90_deg": stats.p90},
                extra={"splats": len(cloud), "median_roundness": f"{np.median(r):.2f}"},
            )
        )
    return rows


def run(quick=False):
    rng = np.random.default_rng(0)
    count = 5000 if quick else 40000
    repeat = 2 if quick else 3
    rows = []
    sphere = None
    for name, (vertices, faces) in meshes(quick).items():
        faces = outward(vertices, faces)
        cloud = mesh_to_splats.mesh_to_splats(vertices, faces, max_splats=count, calibrate=False)
        true = Surface(vertices, faces).normal[cloud.extras["source_triangle"]]
        rows += rows_for(name, cloud, true, repeat)
        rows += rows_for(f"{name} noisy", noisy(cloud, rng), true, repeat)
        sphere = (cloud, true) if name == "sphere" else sphere
    rows += roundness_rows(*sphere, rng)
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
