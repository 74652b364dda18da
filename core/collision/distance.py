"""Occupancy (the soft overlap of probe points) and the signed distance to the union of the
environment's k-sigma ellipsoids; the distance bounds are compiled where numba loads."""

from dataclasses import dataclass

import numpy as np

from .. import jit
from ..arrays import Floats, Positions
from ..splats import SplatCloud
from .gaussians import (
    DEFAULT_CUTOFF,
    CollisionInputError,
    Gaussians,
    _full,
    _ldl_quadratic,
    _mahalanobis,
    _require_finite,
)
from .index import EnvironmentIndex, as_index
from .overlap import overlap


@dataclass
class Occupancy:
    values: np.ndarray  # (M,) 1 - exp(-density), in [0, 1)
    density: np.ndarray  # (M,) sum_j alpha_j exp(-1/2 d^T Sigma_j^-1 d)
    bound: np.ndarray  # (M,) upper bound on the density the cutoff dropped (and so on values' error)


def occupancy(
    env: "SplatCloud | Gaussians | EnvironmentIndex",
    points: Positions,
    cutoff: float = DEFAULT_CUTOFF,
    opacity_weights: bool = True,
    threads: int | None = None,
) -> "Occupancy":
    """Occupancy 1 - exp(-sum_j alpha_j G_j(x)) at query points, G_j the unnormalised Gaussians,
    alpha_j the opacities; terms beyond Mahalanobis `cutoff` are skipped and bounded per point."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    _require_finite("points", points)
    probes = Gaussians(points, np.zeros((len(points), 3, 3)), sigma_max=np.zeros(len(points)))
    index = as_index(env, opacity_weights)
    r = overlap(probes, index, cutoff, gradient=False, bound=False, threads=threads)
    bound = index.skipped_bound(points, np.zeros(len(points)), np.ones(len(points)), cutoff)
    return Occupancy(-np.expm1(-r.per_gaussian), r.per_gaussian, bound)


def signed_distance(
    env: "SplatCloud | Gaussians | EnvironmentIndex",
    points: Positions,
    k: float = 3.0,
    max_distance: float = 1.0,
    opacity_weights: bool = True,
    min_opacity: float = 0.0,
    threads: int | None = None,
) -> Floats:
    """Approximate signed distance from points to the union of the environment's k-sigma ellipsoids
    (those with opacity >= min_opacity); values above max_distance are returned as max_distance.

    Outside every ellipsoid the value is exact: the Euclidean distance to each ellipsoid (a 1-D
    root per pair, see _outside_distance), minimised over ellipsoids. Inside, it is
    -a_min (1 - r), r the point's k-sigma radius and a_min the shortest semi-axis: a lower bound on
    the depth inside that ellipsoid (exact for spheres); the union's true depth may be larger.

    Each point searches a radius rho that starts near the smallest splat. Every ellipsoid met gives
    two cheap bounds on its distance (see _distance_bounds); the least upper bound caps the search,
    and only ellipsoids whose lower bound is below it get the exact distance. A point with no
    ellipsoid in reach doubles its rho (up to max_distance); one with an upper bound beyond rho
    jumps to it. The work follows the number of splats within reach, not their shapes.
    """
    if not k > 0 or not max_distance > 0:
        raise CollisionInputError(f"k and max_distance must be positive, got {k} and {max_distance}")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    _require_finite("points", points)
    index = as_index(env, opacity_weights)
    best = np.full(len(points), float(max_distance))
    if not index.levels or not len(points):
        return best
    start = min(float(max_distance), max(k * min(lv.sigma for lv in index.levels), 1e-6 * max_distance))
    rho = np.full(len(points), start)
    todo = np.arange(len(points))
    while len(todo):
        upper = _least_upper_bounds(index, points[todo], rho[todo], k, min_opacity, threads)
        # a hair beyond the bound: the ellipsoid that gave it lies exactly at the edge of its reach
        radius = np.minimum(rho[todo], upper + 1e-9 * (np.abs(upper) + start))
        found = _exact_distances(index, points[todo], radius, k, min_opacity, threads)
        best[todo] = np.minimum(best[todo], found)
        # settled once its distance is within the radius searched; otherwise search further
        open_ = (found > radius) & (rho[todo] < max_distance)
        grow = np.where(np.isfinite(upper) & (upper > rho[todo]), upper, 2.0 * rho[todo])
        rho[todo] = np.minimum(grow, max_distance)
        todo = todo[open_]
    return best


def _distance_bounds(index, points, i, j, k):
    """For point/ellipsoid pairs: a lower bound on the distance (the separating plane normal to
    d = point - centre: |d| - k sqrt(d^T Sigma d) / |d|, tight for flat and needle splats too) and an
    upper bound (the ray from the centre leaves the ellipsoid at |d| / r, r = sqrt(d^T Sigma^-1 d) / k;
    0 inside), the offsets d and the 6 covariance entries."""
    d = (points[i, 0] - index.mx[j], points[i, 1] - index.my[j], points[i, 2] - index.mz[j])
    centre = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    c = [x[j] for x in index.cov]
    spread = (
        c[0] * d[0] * d[0]
        + c[3] * d[1] * d[1]
        + c[5] * d[2] * d[2]
        + 2.0 * (c[1] * d[0] * d[1] + c[2] * d[0] * d[2] + c[4] * d[1] * d[2])
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        lower = np.where(centre > 0, centre - k * np.sqrt(np.maximum(spread, 0.0)) / centre, -np.inf)
        r = np.sqrt(_mahalanobis(d, c)[0]) / k
        upper = np.where(r > 1.0, centre * (1.0 - 1.0 / r), 0.0)
    return lower, upper, d, c


def _least_upper_bounds(index, points, rho, k, min_opacity, threads):
    """Per point, the least upper bound on its distance over the ellipsoids whose lower bound is
    within its rho (inf where there are none)."""

    def reach(lv):
        return rho + k * lv.sigma

    kernel = _bounds_kernel()

    def least(i, j):
        out = np.full(len(points), np.inf)
        if kernel is not None:
            kernel(i, j, points, index.mx, index.my, index.mz, index.cov6, index.w, min_opacity, k, rho, out)
            return out
        lower, upper, _, _ = _distance_bounds(index, points, i, j, k)
        keep = (lower <= rho[i]) & (index.w[j] >= min_opacity)
        np.minimum.at(out, i[keep], upper[keep])
        return out

    parts = index.query(points, reach, least, threads)
    return np.minimum.reduce(parts) if parts else np.full(len(points), np.inf)


def _exact_distances(index, points, radius, k, min_opacity, threads):
    """Per point, the least signed distance to the ellipsoids whose lower bound is within its
    radius (inf where there are none)."""

    def reach(lv):
        return radius + k * lv.sigma

    def exact(i, j):
        lower, _, d, c = _distance_bounds(index, points, i, j, k)
        # both bounds are rounded: keep ties
        keep = (lower <= radius[i] + 1e-9 * (np.abs(radius[i]) + np.abs(lower))) & (index.w[j] >= min_opacity)
        cov = _full([x[keep] for x in c])
        return i[keep], _ellipsoid_signed_distance(np.column_stack([x[keep] for x in d]), cov, k)

    out = np.full(len(points), np.inf)
    for i, dist in index.query(points, reach, exact, threads):
        np.minimum.at(out, i, dist)
    return out


def _bounds_pass(i, j, points, mx, my, mz, cov, w, min_opacity, k, rho, out):
    """out[p] = min over pairs of the point p of _distance_bounds' upper bound, for pairs whose
    lower bound is within rho[p] (compiled: no per-pair temporaries)."""
    x = np.empty(3)
    for n in range(len(i)):
        p, e = i[n], j[n]
        if w[e] < min_opacity:
            continue
        d0, d1, d2 = points[p, 0] - mx[e], points[p, 1] - my[e], points[p, 2] - mz[e]
        centre = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        c00, c01, c02, c11, c12, c22 = cov[0, e], cov[1, e], cov[2, e], cov[3, e], cov[4, e], cov[5, e]
        if centre > 0:
            spread = (
                c00 * d0 * d0 + c11 * d1 * d1 + c22 * d2 * d2 + 2.0 * (c01 * d0 * d1 + c02 * d0 * d2 + c12 * d1 * d2)
            )
            if centre - k * np.sqrt(max(spread, 0.0)) / centre > rho[p]:
                continue
        r = np.sqrt(_ldl_quadratic(c00, c01, c02, c11, c12, c22, d0, d1, d2, x)) / k
        upper = centre * (1.0 - 1.0 / r) if r > 1.0 else 0.0
        if upper < out[p]:
            out[p] = upper


def _bounds_kernel():
    """The compiled distance-bound pass (core.jit), or None: the NumPy path then does the work."""
    return jit.compiled(__name__, ("_ldl_quadratic", "_bounds_pass"))


def _ellipsoid_signed_distance(d, cov, k):
    """Signed distance from points d (relative to the centre, (P,3)) to k-sigma ellipsoids of
    covariances cov (P,3,3): exact outside, the lower bound -a_min (1 - r) on the depth inside."""
    vals, vecs = np.linalg.eigh(cov) if len(d) else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
    semi = k * np.sqrt(np.maximum(vals, 0.0))
    semi = np.maximum(semi, np.maximum(1e-6 * semi.max(axis=1, keepdims=True), 1e-150))
    z = np.abs(np.einsum("pji,pj->pi", vecs, d))
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # point splats: r is inf outside
        r = np.sqrt(((z / semi) ** 2).sum(axis=1))
        out = np.empty(len(d))
        inside = r <= 1.0
        out[inside] = -semi[inside].min(axis=1) * (1.0 - r[inside])
        out[~inside] = _outside_distance(z[~inside], semi[~inside])
    return out


def _outside_distance(z, a, iterations=100):
    """Distance from points z >= 0 (outside) to axis-aligned ellipsoids with semi-axes a > 0.

    The closest point is y_k = a_k^2 z_k / (t + a_k^2) with t > 0 the root of
    G(t) = sum (a_k z_k / (t + a_k^2))^2 = 1. Newton runs on H = G^(-1/2), which is linear in t for
    a sphere, inside the bracket [0, a_max |z|] (G <= 1 there), bisecting when a step leaves it.
    """
    a2, az = a * a, a * z
    t = np.zeros(len(z))
    lo, hi = np.zeros(len(z)), a.max(axis=1) * np.sqrt((z * z).sum(axis=1))
    for _ in range(iterations):
        den = t[:, None] + a2
        u2 = (az / den) ** 2
        g = u2.sum(axis=1)
        h = 1.0 / np.sqrt(g)
        dh = h / g * (u2 / den).sum(axis=1)  # -1/2 G^-3/2 G', G' = -2 sum u^2 / den
        lo = np.where(h < 1.0, t, lo)
        hi = np.where(h < 1.0, hi, t)
        step = t - (h - 1.0) / dh
        step = np.where((step > lo) & (step < hi), step, 0.5 * (lo + hi))
        done = np.abs(step - t) <= 1e-15 * step
        t = step
        if done.all():
            break
    return t * np.sqrt(((z / (t[:, None] + a2)) ** 2).sum(axis=1))
