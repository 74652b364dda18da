"""Collision between splat clouds, for planning: soft Gaussian overlap with gradients, exact
ellipsoid contacts, occupancy, signed distance and per-link collision proxies. NumPy only.

Soft overlap between a robot (Gaussians i) and an environment (Gaussians j):

    C = sum_i sum_j w_i w_j exp(-1/2 d^T (Sigma_i + Sigma_j)^-1 d),   d = mu_i - mu_j

with w = opacity (or 1). The environment is indexed once (`EnvironmentIndex`, a sorted grid per
size class); each query visits only pairs whose Mahalanobis distance can be within `cutoff`.
Every skipped pair contributes less than exp(-cutoff^2 / 2), and a pair further apart than R
contributes less than exp(-R^2 / (2 (lmax_i + lmax_j))) because lmax(Sigma_i + Sigma_j) <=
lmax_i + lmax_j; counting the environment around each robot splat ring by ring turns these two
facts into a bound on everything the cutoff dropped, reported with every result.

Near-singular Sigma_i + Sigma_j (flat or needle splats) are factorised with a square-root-free
Cholesky (L D L^T) whose pivots are floored at PIVOT_FLOOR * trace: a direction thinner than
1e-6 of the pair's size is treated as that thin. Float64 rounding of an explicitly formed
covariance already blurs such directions at about 1e-8 of its size, so nothing measurable is lost,
and far pairs underflow to exactly 0 instead of NaN.
"""

import math
import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from . import geometry
from . import jit
from .spatial import Grid, cell_start, sort_by_cell

DEFAULT_CUTOFF = 6.0          # Mahalanobis distance beyond which pairs are skipped
BOUND_MARGIN = 1.0            # with a bound, pairs up to cutoff + this are visited and their skipped terms summed
PIVOT_FLOOR = 1e-12           # relative floor on L D L^T pivots (see module notes)
_TINY = 1e-300                # absolute floor, for all-zero covariances (point splats)
_UNIT_PAIRS = 1 << 18         # candidate pairs per work unit: bounded memory, two units in flight
COARSE = 32                   # cells a side of the blocks that find a size class's dense part
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))   # the 6 entries of a symmetric 3x3


class CollisionInputError(ValueError):
    """Inputs that no collision query can use; the message names the array and the problem."""


class CollisionPrecisionWarning(UserWarning):
    """Inputs whose stored precision moves the results: float32 positions far from the origin."""


QUANTISATION_LIMIT = 0.01     # warn when float32 rounds positions by more than this fraction of a splat


def _check_precision(name, positions, sigma):
    """Warn when float32 positions are rounded by more than QUANTISATION_LIMIT of their splat's size
    (at 1e6, float32 steps are 6 cm: centimetre splats there are moved by more than their size)."""
    if positions.dtype != np.float32 or not len(positions):
        return
    step = np.spacing(np.abs(positions).max(axis=1))
    coarse = (step > QUANTISATION_LIMIT * sigma) & (sigma > 0)
    if coarse.any():
        warnings.warn(f"{name}: {int(coarse.sum())} splats lie so far from the origin (up to "
                      f"{float(np.abs(positions[coarse]).max()):.3g}) that their float32 positions are rounded by "
                      f"up to {float(step[coarse].max()):.3g}, more than {QUANTISATION_LIMIT:.0%} of their size, and "
                      "collision results shift with them; move the scene nearer the origin, or give "
                      "float64 Gaussians", CollisionPrecisionWarning, stacklevel=4)


# Gaussians: the float64 view every query works on ----------------------------------------------

def _require_finite(name, values, allow_neg_inf=False):
    values = np.asarray(values)
    bad = ~np.isfinite(values)
    if allow_neg_inf:
        bad &= ~np.isneginf(values)
    if bad.any():
        rows = bad.reshape(len(values), -1).any(axis=1) if values.ndim else bad
        raise CollisionInputError(f"{name}: {int(np.sum(rows))} entries are NaN or infinite")


@dataclass(eq=False)
class Gaussians:
    """N Gaussians in float64: means (N,3), covariances (N,3,3), weights (N,), optional link index
    per Gaussian (N,) int, and the largest standard deviation of each (computed when not given)."""

    means: np.ndarray
    covs: np.ndarray
    weights: np.ndarray = None
    links: np.ndarray = None
    sigma_max: np.ndarray = None

    def __post_init__(self):
        self.means = np.asarray(self.means, dtype=np.float64).reshape(-1, 3)
        n = len(self.means)
        self.covs = np.asarray(self.covs, dtype=np.float64).reshape(n, 3, 3)
        self.weights = np.ones(n) if self.weights is None else np.asarray(self.weights, np.float64).reshape(n)
        if self.links is not None:
            self.links = np.asarray(self.links).reshape(n)
            if not np.issubdtype(self.links.dtype, np.integer) or (n and self.links.min() < 0):
                raise CollisionInputError("links: expected non-negative integers, one per Gaussian")
        for name in ("means", "covs", "weights"):
            _require_finite(f"Gaussians.{name}", getattr(self, name))
        if (self.weights < 0).any():
            raise CollisionInputError(f"Gaussians.weights: {int((self.weights < 0).sum())} are negative")
        self.covs = 0.5 * (self.covs + np.swapaxes(self.covs, 1, 2))
        if self.sigma_max is None:
            eig = np.linalg.eigvalsh(self.covs) if n else np.zeros((0, 3))
            low = eig[:, 0] < -1e-9 * np.maximum(eig[:, 2], _TINY)
            if low.any():
                raise CollisionInputError(f"Gaussians.covs: {int(low.sum())} are not positive semi-definite")
            self.sigma_max = np.sqrt(np.maximum(eig[:, 2], 0.0))
        self.sigma_max = np.asarray(self.sigma_max, np.float64).reshape(n)

    @classmethod
    def from_cloud(cls, cloud, opacity_weights=True, links=None, name="cloud"):
        """The Gaussians of a SplatCloud; weights are opacities (or 1). Zero scales (log -inf) are
        allowed and make point splats; NaN or +Inf anywhere is an error naming the field."""
        for field_name in ("positions", "rotations", "opacity_logits"):
            _require_finite(f"{name}.{field_name}", getattr(cloud, field_name))
        _require_finite(f"{name}.log_scales", cloud.log_scales, allow_neg_inf=True)
        scales = cloud.scales
        _check_precision(name, cloud.positions, scales.max(axis=1) if len(cloud) else np.zeros(0))
        weights = cloud.opacities if opacity_weights else np.ones(len(cloud))
        return cls(cloud.positions, geometry.covariances(cloud.rotations, scales), weights, links,
                   scales.max(axis=1) if len(cloud) else np.zeros(0))

    def __len__(self):
        return len(self.means)

    def subset(self, index):
        pick = lambda a: None if a is None else a[index]
        return Gaussians(self.means[index], self.covs[index], self.weights[index], pick(self.links),
                         self.sigma_max[index])

    def transformed(self, rotations, translations):
        """A rigid motion: mu' = R mu + t and Sigma' = R Sigma R^T, with one rotation (3,3) and
        translation (3,) for all, or one per Gaussian."""
        r = np.asarray(rotations, np.float64)
        t = np.asarray(translations, np.float64)
        means = (r @ self.means[:, :, None])[..., 0] + t
        covs = r @ self.covs @ np.swapaxes(r, -1, -2)
        return Gaussians(means, covs, self.weights, self.links, self.sigma_max)


def as_gaussians(x, opacity_weights=True, name="cloud"):
    return x if isinstance(x, Gaussians) else Gaussians.from_cloud(x, opacity_weights, name=name)


def _sym6(covs):
    """The 6 independent entries of symmetric (N,3,3) matrices, as 6 contiguous arrays."""
    return [np.ascontiguousarray(covs[:, a, b]) for a, b in _SYM]


@dataclass
class _Flat:
    """Per-Gaussian arrays as queries use them: coordinates and the 6 covariance entries as
    separate contiguous arrays, the largest variance `lam` and the smallest `nu`."""
    means: list
    cov6: list
    weights: np.ndarray
    lam: np.ndarray
    nu: np.ndarray


def _flatten(x, opacity_weights=True, name="cloud", threads=None):
    if isinstance(x, Gaussians):
        vals = np.linalg.eigvalsh(x.covs) if len(x) else np.zeros((0, 3))
        return _Flat([np.ascontiguousarray(x.means[:, a]) for a in range(3)], _sym6(x.covs), x.weights,
                     np.maximum(vals[:, 2], 0.0), np.maximum(vals[:, 0], 0.0))
    for field_name in ("positions", "rotations", "opacity_logits"):
        _require_finite(f"{name}.{field_name}", getattr(x, field_name))
    _require_finite(f"{name}.log_scales", x.log_scales, allow_neg_inf=True)
    n = len(x)

    def chunk(span):
        a, b = span
        r = geometry.quaternions_to_matrices(x.rotations[a:b])
        s = np.exp(x.log_scales[a:b].astype(np.float64))
        var = s * s
        cov6 = [(r[:, i, :] * r[:, j, :] * var).sum(axis=1) for i, j in _SYM]
        return cov6, var.max(axis=1), var.min(axis=1)

    step = max(1, -(-n // (4 * (threads or os.cpu_count() or 1))))
    parts = _map(chunk, [(a, min(a + step, n)) for a in range(0, n, step)], threads)[0] if n else []
    cat = lambda arrays: np.concatenate(arrays) if arrays else np.zeros(0)
    cov6 = [cat([p[0][k] for p in parts]) for k in range(6)]
    weights = x.opacities if opacity_weights else np.ones(n)
    lam = cat([p[1] for p in parts])
    _check_precision(name, x.positions, np.sqrt(lam))
    return _Flat([x.positions[:, a].astype(np.float64) for a in range(3)], cov6, weights,
                 lam, cat([p[2] for p in parts]))


# the pair kernel ---------------------------------------------------------------------------------

def _mahalanobis(d, s):
    """q = d^T S^-1 d for P pairs at once, and the factors that give S^-1 d (see _solve).

    d: 3 arrays (P,), s: the 6 entries of S, (P,) each. L D L^T with pivots floored at
    PIVOT_FLOOR * trace(S) keeps flat and needle pairs stable; q may be +inf, never NaN.
    """
    s00, s01, s02, s11, s12, s22 = s
    floor = np.maximum(PIVOT_FLOOR * (s00 + s11 + s22), _TINY)
    with np.errstate(over="ignore", invalid="ignore"):
        d0 = np.maximum(s00, floor)
        l10, l20 = s01 / d0, s02 / d0
        d1 = np.maximum(s11 - l10 * s01, floor)
        t12 = s12 - l20 * s01
        l21 = t12 / d1
        d2 = np.maximum(s22 - l20 * s02 - l21 * t12, floor)
        y0 = d[0]
        y1 = d[1] - l10 * y0
        y2 = d[2] - l20 * y0 - l21 * y1
        z0, z1, z2 = y0 / d0, y1 / d1, y2 / d2
        q = y0 * z0 + y1 * z1 + y2 * z2
    return q, (l10, l20, l21, z0, z1, z2)


def _solve(factors):
    """x = S^-1 d by back substitution, from _mahalanobis's factors (of finite-q pairs)."""
    l10, l20, l21, z0, z1, z2 = factors
    x1 = z1 - l21 * z2
    return [z0 - l10 * x1 - l20 * z2, x1, z2]


def _gauss_terms(d, s, w, limit, want_x, want_skipped=False):
    """Pairs with q = d^T S^-1 d <= limit: their indices, w exp(-q/2) and (if asked) S^-1 d, and
    (if asked) the sum of the terms beyond the limit."""
    q, factors = _mahalanobis(d, s)
    inside = q <= limit
    keep = np.flatnonzero(inside)
    with np.errstate(under="ignore"):
        e = w[keep] * np.exp(-0.5 * q[keep])
        skipped = float(np.sum(w[~inside] * np.exp(-0.5 * q[~inside]))) if want_skipped else 0.0
    x = _solve([f[keep] for f in factors]) if want_x else None
    return keep, e, x, skipped


# broad phase: a sorted grid per size class ----------------------------------------------------------

@dataclass
class _Level(Grid):
    """A size class's grid (core.spatial.Grid: origin, cell size h, dims) and its sorted members."""

    cell_start: np.ndarray  # (cells+1,) first sorted index of each cell, x-major then y then z
    sigma: float           # largest sigma_max in the level
    weight: float          # largest weight in the level
    count: int
    svt: np.ndarray = field(repr=False, default=None)   # summed-volume table of counts


class EnvironmentIndex:
    """The environment, built once: Gaussians sorted into one uniform grid per size class (sizes
    within a factor `level_ratio`), cells `cell_factor` times the class's largest sigma (coarsened so
    a class never has more than `cells_per_splat` cells per Gaussian). Queries walk the cells near
    each query point, z-runs of cells at a time, so the cost is the candidates, not the scene.

    Captured scenes have floaters far from everything: a class whose grid at its natural cell size
    would be too large keeps its dense part (the blocks of 32^3 cells that hold more than one
    member and 1% of the fullest block) in one grid and the rest in grids of their own, so a few
    distant splats never coarsen the cells of the many."""

    def __init__(self, env, opacity_weights=True, cell_factor=2.0, level_ratio=2.0, cells_per_splat=4,
                 threads=None):
        flat = _flatten(env, opacity_weights, "environment", threads)
        keep = np.flatnonzero(flat.weights > 0)      # transparent splats can touch nothing
        self.size = len(flat.weights)
        self.levels = []
        orders = []
        if len(keep):
            sig = np.sqrt(flat.lam[keep])
            top = max(float(sig.max()), _TINY)
            cls = np.floor(np.log(top / np.maximum(sig, top * 1e-15)) / math.log(level_ratio)).astype(np.int64)
            by_class = np.argsort(cls, kind="stable")
            edges = np.flatnonzero(np.diff(cls[by_class])) + 1
            parts, sparse = [], []
            for members in np.split(keep[by_class], edges):
                dense, rest = _dense_parts(flat, members, cell_factor, cells_per_splat)
                parts += dense
                sparse.append(rest)
            sparse = np.concatenate(sparse)
            for part in parts + ([sparse] if len(sparse) else []):   # outliers of every class share a grid
                level, order = self._build_level(flat, part, cell_factor, cells_per_splat, sum(map(len, orders)))
                self.levels.append(level)
                orders.append(order)
        self.order = o = np.concatenate(orders) if orders else np.zeros(0, np.int64)
        self.mx, self.my, self.mz = (flat.means[a][o] for a in range(3))
        self.cov6 = np.stack([c[o] for c in flat.cov6]) if len(o) else np.zeros((6, 0))
        self.cov = list(self.cov6)                   # row views: one array per entry, no copy
        self.w = flat.weights[o]
        self.lam = flat.lam[o]
        self.nu = flat.nu[o]

    @staticmethod
    def _build_level(flat, members, cell_factor, cells_per_splat, offset):
        pts = np.column_stack([m[members] for m in flat.means])
        sigma = float(np.sqrt(flat.lam[members].max()))
        lo = pts.min(axis=0)
        extent = pts.max(axis=0) - lo
        h = max(cell_factor * sigma, 1e-9 * float(np.abs(pts).max() + extent.max())) or 1.0
        cap = cells_per_splat * len(members) + 64
        while np.prod(np.floor(extent / h) + 1) > cap:
            h *= 1.25
        grid = Grid(lo, h, (np.floor(extent / h) + 1).astype(np.int64))
        key = grid.keys(np.minimum(grid.cells(pts), grid.dims - 1))
        order, _ = sort_by_cell(key)
        start = cell_start(key, grid.size)
        svt = np.zeros(tuple(grid.dims + 1), np.int64)
        svt[1:, 1:, 1:] = np.diff(start).reshape(tuple(grid.dims)).cumsum(0).cumsum(1).cumsum(2)
        level = _Level(grid.origin, grid.h, grid.dims, start + offset, sigma, float(flat.weights[members].max()),
                       len(members), svt)
        return level, members[order]

    def __len__(self):
        return self.size


    @property
    def typical_sigma(self):
        """The median largest standard deviation of the indexed Gaussians (a reference size, e.g.
        for fit_proxies)."""
        return float(np.sqrt(np.median(self.lam))) if len(self.lam) else 0.0

    def gaussians(self):
        """The indexed Gaussians (those with weight > 0), in the index's order (see `order`)."""
        means = np.column_stack([self.mx, self.my, self.mz])
        return Gaussians(means, _full(self.cov), self.w, sigma_max=np.sqrt(self.lam))

    # candidate generation ----------------------------------------------------------------------

    def _runs(self, level, points, reach):
        """Runs of consecutive sorted Gaussians (cells along z) within `reach` of each point:
        (point index, start, stop) arrays, empty runs dropped. Columns of cells are visited only
        where they meet the ball, and each column's z-range is cut to the ball."""
        lv = self.levels[level]
        rel = (points - lv.origin) / lv.h
        r = np.minimum(reach / lv.h, 1e100)
        lo = _clip(np.floor(rel[:, :2] - r[:, None]), 0, lv.dims[:2] - 1)
        hi = _clip(np.floor(rel[:, :2] + r[:, None]), 0, lv.dims[:2] - 1)
        width = (hi - lo).max(axis=1) + 1
        # points with squares of similar width share one broadcast over their columns
        bucket = np.ceil(np.log2(width)).astype(np.int64) if width.max() > 2 * width.min() + 2 else width * 0
        parts = [self._column_runs(lv, np.flatnonzero(bucket == b), rel, r, lo, hi) for b in np.unique(bucket)]
        return tuple(np.concatenate(x) for x in zip(*parts)) if parts else (np.zeros(0, np.int64),) * 3

    @staticmethod
    def _column_runs(lv, pts, rel, r, lo, hi):
        rel, r, lo, hi = rel[pts], r[pts], lo[pts], hi[pts]
        off = np.arange(int((hi - lo).max()) + 1)
        cx, cy = lo[:, :1] + off, lo[:, 1:] + off
        gx = np.maximum(np.abs(rel[:, :1] - cx - 0.5) - 0.5, 0.0)    # distance to the column, in cells
        gy = np.maximum(np.abs(rel[:, 1:2] - cy - 0.5) - 0.5, 0.0)
        gx[cx > hi[:, :1]] = np.inf
        gy[cy > hi[:, 1:]] = np.inf
        chord2 = ((r * r)[:, None, None] - (gx * gx)[:, :, None] - (gy * gy)[:, None, :]).ravel()
        column = ((cx * lv.dims[1])[:, :, None] + cy[:, None, :]).ravel()
        k = np.flatnonzero(chord2 >= 0)                  # flat indices: cheaper than 3-D ones
        p = k // (len(off) * len(off))
        half = np.sqrt(chord2[k])
        z = rel[p, 2]
        z0 = _clip(np.floor(z - half), 0, lv.dims[2] - 1)
        z1 = _clip(np.floor(z + half), 0, lv.dims[2] - 1)
        base = column[k] * lv.dims[2]
        start = lv.cell_start[(base + z0).astype(np.int64)]
        stop = lv.cell_start[(base + z1).astype(np.int64) + 1]
        ok = (stop > start) & (z + half >= 0) & (z - half < lv.dims[2])
        return pts[p[ok]], start[ok], stop[ok]

    def _tasks(self, points, reach_of_level, parts):
        """Split a query into `parts` tasks of about equal work. Each task is a list of
        (level, point indices, reach); points whose reach holds no Gaussian of a level (counted
        from the summed-volume table) are left out of that level altogether."""
        entries = []
        for level, lv in enumerate(self.levels):
            reach = reach_of_level(lv)
            rel = (points - lv.origin) / lv.h
            lo = np.floor(_clip(rel - (reach / lv.h)[:, None], -1, lv.dims))
            hi = np.floor(_clip(rel + (reach / lv.h)[:, None], -1, lv.dims))
            count = _count_boxes(lv.svt, lo.astype(np.int64), hi.astype(np.int64) + 1)
            active = np.flatnonzero(count > 0)
            if len(active):
                entries.append((level, active, reach[active], count[active]))
        if not entries:
            return []
        load = np.concatenate([e[3] for e in entries]).astype(np.float64)
        owner = np.minimum((np.cumsum(load) - load) * parts // load.sum(), parts - 1).astype(np.int64)
        tasks = [[] for _ in range(parts)]
        offset = 0
        for level, active, reach, count in entries:
            mine = owner[offset:offset + len(active)]
            offset += len(active)
            for t in np.unique(mine):
                sel = mine == t
                tasks[t].append((level, active[sel], reach[sel]))
        return [t for t in tasks if t]

    def _run(self, task, points, pair_fn):
        """pair_fn(point indices, sorted environment indices) over a task, in bounded chunks."""
        out = []
        for level, idx, reach in task:
            p, start, stop = self._runs(level, points[idx], reach)
            if not len(p):
                continue
            first = np.cumsum(stop - start) - (stop - start)      # index of each run's first pair
            cuts = np.flatnonzero(np.diff(first // _UNIT_PAIRS)) + 1
            bounds = [0, *cuts.tolist(), len(p)]
            for a, b in zip(bounds[:-1], bounds[1:]):
                i, j = self._pairs(idx[p[a:b]], start[a:b], stop[a:b])
                out.append(pair_fn(i, j))
        return out

    def query(self, points, reach_of_level, pair_fn, threads=None, meanwhile=None):
        """Run pair_fn over every candidate pair of `points` and the environment, on threads, and
        `meanwhile()` alongside; returns the list of pair_fn results (and meanwhile's result, if
        given)."""
        threads = threads or os.cpu_count() or 1
        points = np.asarray(points, np.float64)
        tasks = self._tasks(points, reach_of_level, threads)
        parts, extra = _map(lambda t: self._run(t, points, pair_fn), tasks, threads, meanwhile)
        results = [r for part in parts for r in part]
        return results if meanwhile is None else (results, extra)

    @staticmethod
    def _pairs(p, start, stop):
        """Expand runs into (point index, sorted environment index) pairs."""
        n = stop - start
        offs = np.cumsum(n) - n
        j = np.arange(int(n.sum())) + np.repeat(start - offs, n)
        return np.repeat(p, n), j

    # error bound ----------------------------------------------------------------------------------

    def skipped_bound(self, points, lam, weights, cutoff):
        """Per query Gaussian i, an upper bound on sum_j w_i w_j exp(-m_ij^2 / 2) over every
        environment Gaussian j at Mahalanobis distance m_ij > cutoff; `points` are the query means,
        `lam` their largest variances.

        Environment Gaussians are counted ring by ring (Chebyshev rings of grid cells around the
        query's cell, from the summed-volume table): a pair in ring k >= 2 is at least (k-1) h apart,
        so it contributes at most exp(-max(c^2, ((k-1) h)^2 / (lam_i + sigma_level^2)) / 2)."""
        c2 = cutoff * cutoff
        total = np.zeros(len(points))
        for lv in self.levels if len(points) else []:
            rel = (points - lv.origin) / lv.h
            cell = np.floor(_clip(rel, -1, lv.dims)).astype(np.int64)
            # a point outside the grid is at least its distance to the grid's box from every member
            outside = lv.h * np.sqrt((np.maximum(np.maximum(-rel, rel - lv.dims), 0.0) ** 2).sum(axis=1))
            key = np.ravel_multi_index((cell + 1).T, tuple(lv.dims + 2))
            groups, inv = np.unique(key, return_inverse=True)
            glam = np.zeros(len(groups))
            np.maximum.at(glam, inv, lam)
            gout = np.full(len(groups), np.inf)
            np.minimum.at(gout, inv, outside)
            lam_tot = glam + lv.sigma ** 2
            gcell = np.array(np.unravel_index(groups, tuple(lv.dims + 2))).T - 1
            # enough rings that the rest is negligible next to one pair at the cutoff
            need = math.sqrt(c2 + 2.0 * math.log(lv.count + 1.0) + 80.0) * math.sqrt(lam_tot.max()) / lv.h
            rings = int(min(math.ceil(need) + 2, lv.dims.max() + 1))
            k = np.arange(rings + 1)
            box = self._box_counts(lv, gcell, k)                       # (G, rings+1)
            shell = np.diff(box, axis=1, prepend=0)
            dist = np.maximum(np.maximum(k - 1, 0)[None, :] * lv.h, gout[:, None])
            scale = np.maximum(lam_tot, _TINY)                          # 0 for point splats
            with np.errstate(over="ignore", under="ignore"):
                expo = np.maximum(c2, dist ** 2 / scale[:, None])
                tail_expo = np.maximum(c2, np.maximum(rings * lv.h, gout) ** 2 / scale)
                per_group = (shell * np.exp(-0.5 * expo)).sum(axis=1) \
                    + (lv.count - box[:, -1]) * np.exp(-0.5 * tail_expo)
            total += lv.weight * weights * per_group[inv]
        return total

    @staticmethod
    def _box_counts(lv, cells, radius):
        """Gaussians in the cell boxes [cell - r, cell + r] (clipped to the grid): (G, R)."""
        lo = cells[:, None, :] - radius[None, :, None]
        return _count_boxes(lv.svt, lo, cells[:, None, :] + radius[None, :, None] + 1)


def _dense_parts(flat, members, cell_factor, cells_per_splat, depth=2):
    """A size class as (groups that get grids of their own, the sparse rest): a class whose grid
    would not fit the cell budget at its natural cell size gives up everything outside its dense
    part (the box of the coarse blocks, COARSE cells a side, holding at least 2 members and 1% of
    the fullest block), recursively; a class without a dense part (or dense everywhere) stays whole,
    with coarser cells."""
    none = members[:0]
    pts = np.column_stack([m[members] for m in flat.means])
    h0 = cell_factor * float(np.sqrt(flat.lam[members].max()))
    cap = cells_per_splat * len(members) + 64
    lo = pts.min(axis=0)
    if h0 <= 0 or np.prod(np.floor((pts.max(axis=0) - lo) / h0) + 1) <= cap:
        return [members], none
    block = np.floor((pts - lo) / (COARSE * h0)).astype(np.int64)
    order = np.lexsort(block.T[::-1])
    first = np.concatenate([[True], (np.diff(block[order], axis=0) != 0).any(axis=1)])
    group = np.empty(len(pts), np.int64)
    group[order] = np.cumsum(first) - 1
    counts = np.bincount(group)
    dense = (counts >= max(2.0, 0.01 * counts.max()))[group]
    if dense.all():
        return [members], none
    if not dense.any():
        return [], members
    inside = ((block >= block[dense].min(axis=0)) & (block <= block[dense].max(axis=0))).all(axis=1)
    if inside.all():
        return [members], none
    if depth == 0:
        return [members[inside]], members[~inside]
    more, rest = _dense_parts(flat, members[~inside], cell_factor, cells_per_splat, depth - 1)
    return [members[inside]] + more, rest


def _clip(x, lo, hi):
    """np.clip without its per-call overhead (it matters at thousands of calls per second)."""
    return np.minimum(np.maximum(x, lo), hi)


def _count_boxes(svt, lo, hi):
    """Counts in the half-open cell boxes [lo, hi) from a summed-volume table; any shape (..., 3),
    boxes clipped to the grid."""
    dims = np.array(svt.shape) - 1
    lo = _clip(lo, 0, dims)
    hi = _clip(hi, 0, dims)
    x0, y0, z0 = lo[..., 0], lo[..., 1], lo[..., 2]
    x1, y1, z1 = hi[..., 0], hi[..., 1], hi[..., 2]
    s = svt
    return (s[x1, y1, z1] - s[x0, y1, z1] - s[x1, y0, z1] - s[x1, y1, z0]
            + s[x0, y0, z1] + s[x0, y1, z0] + s[x1, y0, z0] - s[x0, y0, z0])


def as_index(env, opacity_weights=True, threads=None):
    return env if isinstance(env, EnvironmentIndex) else EnvironmentIndex(env, opacity_weights, threads=threads)


_POOL = {}


def _map(fn, items, threads, meanwhile=None):
    """fn over items on up to `threads` threads (NumPy releases the GIL in the heavy parts), and
    `meanwhile()` on the calling thread as they run; returns (results, meanwhile's result). One pool
    per size is kept, since planners call this thousands of times."""
    threads = min(len(items), threads or os.cpu_count() or 1)
    if threads <= 1:
        return [fn(x) for x in items], meanwhile() if meanwhile else None
    if threads not in _POOL:
        _POOL[threads] = ThreadPoolExecutor(threads)
    futures = [_POOL[threads].submit(fn, x) for x in items]
    extra = meanwhile() if meanwhile else None
    return [f.result() for f in futures], extra


# soft overlap ------------------------------------------------------------------------------------

@dataclass
class Overlap:
    """The soft overlap cost of a query and what it cost to compute."""
    cost: float
    per_gaussian: np.ndarray            # (N,) each robot Gaussian's share of the cost
    grad_means: np.ndarray = None       # (N,3) dC/dmu_i
    grad_covs: np.ndarray = None        # (N,3,3) dC/dSigma_i (symmetric), when asked for
    bound: float = 0.0                  # upper bound on what the cutoff dropped (absolute)
    relative_bound: float = 0.0         # bound / cost (inf when the cost is 0 and the bound is not)
    pairs: int = 0                      # pairs within the cutoff, evaluated exactly
    cutoff: float = math.inf
    grad_q: np.ndarray = None           # (dof,) dC/dq, from overlap_at (robots on kinematic trees)


def _finish(n, parts, want_grad, want_cov):
    per = np.zeros(n)
    grad = np.zeros((n, 3)) if want_grad else None
    gcov = np.zeros((n, 6)) if want_cov else None
    pairs = 0
    for part in parts:
        per += part[0]
        if want_grad:
            grad += part[1]
        if want_cov:
            gcov += part[2]
        pairs += part[3]
    if want_cov:
        full = np.empty((n, 3, 3))
        for k, (a, b) in enumerate(_SYM):
            full[:, a, b] = full[:, b, a] = gcov[:, k]
        gcov = full
    return per, grad, gcov, pairs


def _accumulate(i, n, e, x, want_grad, want_cov):
    per = np.bincount(i, weights=e, minlength=n)
    grad = gcov = None
    if want_grad:
        grad = np.stack([-np.bincount(i, weights=e * xk, minlength=n) for xk in x], axis=1)
    if want_cov:
        gcov = np.stack([0.5 * np.bincount(i, weights=e * x[a] * x[b], minlength=n) for a, b in _SYM], axis=1)
    return per, grad, gcov, len(i)


def overlap(robot, env, cutoff=DEFAULT_CUTOFF, gradient=True, cov_gradient=False, bound=True,
            opacity_weights=True, threads=None):
    """Soft overlap C between `robot` and `env` (SplatCloud, Gaussians or a prebuilt
    EnvironmentIndex), its gradient w.r.t. the robot means (and covariances, if asked), and a
    bound on the error of the cutoff. cutoff=inf sums every pair (use `overlap_all_pairs` then)."""
    robot = as_gaussians(robot, opacity_weights, name="robot")
    if not math.isfinite(cutoff):
        env = env.gaussians() if isinstance(env, EnvironmentIndex) else env
        return overlap_all_pairs(robot, env, gradient, cov_gradient, opacity_weights, threads)
    if cutoff <= 0:
        raise CollisionInputError(f"cutoff must be positive, got {cutoff}")
    index = as_index(env, opacity_weights)
    n = len(robot)
    rm = robot.means
    rx, ry, rz = (np.ascontiguousarray(rm[:, a]) for a in range(3))
    rlam = robot.sigma_max ** 2
    rcov = _sym6(robot.covs)
    c2 = cutoff * cutoff
    visit = cutoff + (BOUND_MARGIN if bound else 0.0)        # pairs the query sees (and accounts for)

    def reach(lv):
        return visit * np.sqrt(rlam + lv.sigma ** 2)

    def work(i, j):
        dx, dy, dz = rx[i] - index.mx[j], ry[i] - index.my[j], rz[i] - index.mz[j]
        # d^T S^-1 d >= |d|^2 / lmax(S) >= |d|^2 / (lmax_i + lmax_j): a cheap test first
        d2, lam = dx * dx + dy * dy + dz * dz, rlam[i] + index.lam[j]
        close = d2 <= visit * visit * lam
        far = 0.0
        if bound:                                            # each far term is below its cheap bound
            with np.errstate(divide="ignore", under="ignore"):
                out = ~close
                far = float(np.sum(robot.weights[i[out]] * index.w[j[out]] * np.exp(-0.5 * d2[out] / lam[out])))
        near = np.flatnonzero(close)
        i, j = i[near], j[near]
        d = (dx[near], dy[near], dz[near])
        s = [rc[i] + ec[j] for rc, ec in zip(rcov, index.cov)]
        keep, e, x, skipped = _gauss_terms(d, s, robot.weights[i] * index.w[j], c2, gradient or cov_gradient, bound)
        return (*_accumulate(i[keep], n, e, x, gradient, cov_gradient), far + skipped)

    def unvisited():
        return float(index.skipped_bound(rm, rlam, robot.weights, visit).sum()) if bound else 0.0

    parts, skip = index.query(rm, reach, work, threads, meanwhile=unvisited) if n else ([], 0.0)
    per, grad, gcov, pairs = _finish(n, parts, gradient, cov_gradient)
    skip += sum(part[4] for part in parts)
    relative = skip / per.sum() if per.sum() > 0 else (0.0 if skip == 0 else math.inf)
    return Overlap(float(per.sum()), per, grad, gcov, skip, relative, pairs, cutoff)


def overlap_all_pairs(robot, env, gradient=True, cov_gradient=False, opacity_weights=True, threads=None,
                      chunk=1 << 18):
    """Every pair, no cutoff, in chunks: the exact reference (and the baseline for speed)."""
    robot = as_gaussians(robot, opacity_weights, name="robot")
    env = as_gaussians(env, opacity_weights, name="environment")
    n, m = len(robot), len(env)
    rcov, ecov = _sym6(robot.covs), _sym6(env.covs)
    per_robot = max(1, chunk // max(m, 1))
    spans = [(a, min(a + per_robot, n)) for a in range(0, n, per_robot)] if m else []

    def work(span):
        a, b = span
        i = np.repeat(np.arange(a, b), m)
        j = np.tile(np.arange(m), b - a)
        d = [robot.means[i, k] - env.means[j, k] for k in range(3)]
        s = [rc[i] + ec[j] for rc, ec in zip(rcov, ecov)]
        # q < 1500 keeps every term that does not underflow to exactly 0
        keep, e, x, _ = _gauss_terms(d, s, robot.weights[i] * env.weights[j], 1500.0, gradient or cov_gradient)
        return _accumulate(i[keep], n, e, x, gradient, cov_gradient)

    per, grad, gcov, pairs = _finish(n, _map(work, spans, threads)[0], gradient, cov_gradient)
    return Overlap(float(per.sum()), per, grad, gcov, 0.0, 0.0, pairs, math.inf)


# robots on kinematic trees: the gradient with respect to joint values ----------------------------

def pose_robot(robot_rest, deform):
    """Robot Gaussians rigidly bound to links (robot_rest.links), given in the world frame at the
    rest configuration, moved by per-link deform matrices world(q) @ world(0)^-1 (L,4,4)."""
    if robot_rest.links is None:
        raise CollisionInputError("robot_rest.links: a link index per Gaussian is needed to pose a robot")
    m = np.asarray(deform, np.float64)
    if len(robot_rest) and robot_rest.links.max() >= len(m):
        raise CollisionInputError(f"links: index {int(robot_rest.links.max())} but only {len(m)} link transforms")
    m = m[robot_rest.links]
    return robot_rest.transformed(m[:, :3, :3], m[:, :3, 3])


def overlap_at(tree, q, robot_rest, env, cutoff=DEFAULT_CUTOFF, base=None, threads=None, **kwargs):
    """Soft overlap of a robot on a kinematic tree at configuration q, with dC/dq.

    robot_rest: Gaussians in the world frame at q = 0 with `links` (rigid binding). Forward
    kinematics is the tree's own; the chain rule goes through each joint's world motion: a joint
    turning by dt about unit axis w through point p moves a Gaussian of its subtree by
    dmu = w x (mu - p) dt and dSigma = (W Sigma - Sigma W) dt (W = [w]x), so
    dC/dt = w . sum_subtree (mu x g + tau - p x g), g = dC/dmu, tau = -2 vex(Sigma G - G Sigma),
    G = dC/dSigma. A prismatic joint gives a . sum g; a ball joint's three values turn about the
    columns of the SO(3) left Jacobian of its rotation vector; planar and floating joints slide
    (a . sum g per direction) and turn about the point they slid to; a mimic joint adds multiplier x
    its own derivative to the column of the joint it follows.
    """
    q = tree._check_configuration(q)
    world = tree.forward_kinematics(q, base=base)
    robot = pose_robot(robot_rest, world @ np.linalg.inv(tree.rest_transforms(base)))
    result = overlap(robot, env, cutoff, gradient=True, cov_gradient=True, threads=threads, **kwargs)
    result.grad_q = _joint_gradient(tree, q, world, base, robot, result.grad_means, result.grad_covs)
    return result


def _joint_gradient(tree, q, world, base, robot, g, gcov):
    n_links = len(tree)
    sg = np.einsum("nij,njk->nik", robot.covs, gcov)
    a = sg - np.swapaxes(sg, 1, 2)                               # Sigma G - G Sigma
    tau = -2.0 * np.stack([a[:, 2, 1], a[:, 0, 2], a[:, 1, 0]], axis=1)
    moment = np.cross(robot.means, g) + tau
    force = np.stack([np.bincount(robot.links, g[:, k], n_links) for k in range(3)], axis=1)
    moment = np.stack([np.bincount(robot.links, moment[:, k], n_links) for k in range(3)], axis=1)
    for i in range(n_links - 1, 0, -1):                          # subtree sums (parents come first)
        if tree.parents[i] >= 0:
            force[tree.parents[i]] += force[i]
            moment[tree.parents[i]] += moment[i]
    # joint frames in the world: F_i = world[parent] @ origins[i] (roots: base @ origins[i])
    parent_world = np.where((tree.parents >= 0)[:, None, None], world[np.maximum(tree.parents, 0)],
                            np.eye(4) if base is None else np.asarray(base, np.float64))
    frames = parent_world @ tree.origins
    grad = np.zeros(tree.dof)
    for i, kind in enumerate(tree.joint_types):
        col, scale = tree.dof_offsets[i], tree._scale[i]           # a mimic joint adds to its source's column
        rot, point = frames[i, :3, :3], frames[i, :3, 3]
        axis = rot @ tree.axes[i]
        if kind in ("revolute", "continuous"):
            grad[col] += scale * axis @ (moment[i] - np.cross(point, force[i]))
        elif kind == "prismatic":
            grad[col] += scale * axis @ force[i]
        elif kind == "ball":
            grad[col:col + 3] += (rot @ _left_jacobian(q[col:col + 3])).T @ (moment[i] - np.cross(point, force[i]))
        elif kind == "planar":                                   # slide along the plane, then turn about the axis
            a, b, _ = q[col:col + 3]
            u, v = rot @ tree.plane_axes[i, 0], rot @ tree.plane_axes[i, 1]
            pivot = point + a * u + b * v
            grad[col:col + 3] += [u @ force[i], v @ force[i], axis @ (moment[i] - np.cross(pivot, force[i]))]
        elif kind == "floating":                                 # translate, then turn about the moved point
            pivot = point + rot @ q[col:col + 3]
            grad[col:col + 3] += rot.T @ force[i]
            torque = moment[i] - np.cross(pivot, force[i])
            grad[col + 3:col + 6] += (rot @ _left_jacobian(q[col + 3:col + 6])).T @ torque
    return grad


def _left_jacobian(v):
    """SO(3) left Jacobian of a rotation vector: exp(v + dv) = exp((J dv)^) exp(v)."""
    theta = float(np.linalg.norm(v))
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    if theta < 1e-6:                                            # series to second order
        return np.eye(3) + 0.5 * k + k @ k / 6.0
    return (np.eye(3) + (1.0 - math.cos(theta)) / theta ** 2 * k
            + (theta - math.sin(theta)) / theta ** 3 * k @ k)


# hard contacts: exact ellipsoid overlap -----------------------------------------------------------

def contact_sigma(mean_a, cov_a, mean_b, cov_b, iterations=100):
    """For P pairs of Gaussians, the sigma multiple mu at which their ellipsoids touch: the k-sigma
    ellipsoids {x: (x-m)^T Sigma^-1 (x-m) <= k^2} overlap exactly when k >= mu.

    mu^2 = max over s in [0,1] of s(1-s) d^T (s A + (1-s) B)^-1 d, the contact function of Perram &
    Wertheim (J. Comput. Phys. 58, 1985), which is the separating test of Gilitschenski & Hanebeck
    (FUSION 2012) that Splat-Nav (Chen, Shorinwa et al., 2024) applies to splat maps. Whitening by
    A + B and diagonalising the whitened A turns the bracket into a sum over 3 eigenvalues a_k in
    [0,1]: f(s) = s(1-s) sum e_k^2 / (a_k s + (1-a_k)(1-s)), concave on [0,1], maximised by a
    bracketed Newton iteration on f'(s) = sum e_k^2 ((1-a_k)(1-s)^2 - a_k s^2) / D_k^2.
    """
    d = np.asarray(mean_a, np.float64) - np.asarray(mean_b, np.float64)
    a = np.asarray(cov_a, np.float64)
    c = a + np.asarray(cov_b, np.float64)
    if not len(d):
        return np.zeros(0)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):   # point splats: mu is inf
        cvals, cvecs = np.linalg.eigh(c)
        floor = np.maximum(PIVOT_FLOOR * cvals.sum(axis=1, keepdims=True), _TINY)
        white = np.swapaxes(cvecs, 1, 2) / np.sqrt(np.maximum(cvals, floor))[:, :, None]   # W C W^T = I
        m = white @ a @ np.swapaxes(white, 1, 2)
        alpha, vecs = np.linalg.eigh(0.5 * (m + np.swapaxes(m, 1, 2)))
        alpha = np.clip(alpha, 0.0, 1.0)
        beta = 1.0 - alpha
        e2 = np.einsum("pji,pj->pi", vecs, np.einsum("pij,pj->pi", white, d)) ** 2
        s = _contact_parameter(alpha, e2, iterations)
        den = alpha * s[:, None] + beta * (1.0 - s[:, None])
        f = s * (1.0 - s) * (e2 / den).sum(axis=1)
    f = np.where((d == 0).all(axis=1), 0.0, np.nan_to_num(f, nan=np.inf, posinf=np.inf))    # coincident: 0
    return np.sqrt(np.maximum(f, 0.0))


def _contact_parameter(alpha, e2, iterations):
    """The s in [0,1] maximising f(s) = s(1-s) sum e_k^2 / (a_k s + (1-a_k)(1-s)): bracketed Newton on
    f'(s), each pair dropped from the work once its step is below 1e-12 (f is flat at its maximum,
    so f is then exact to round-off)."""
    n = len(alpha)
    s, lo, hi = np.full(n, 0.5), np.zeros(n), np.ones(n)
    active = np.arange(n)
    for _ in range(iterations):
        if not len(active):
            break
        a, e, x = alpha[active], e2[active], s[active]
        b, xc = 1.0 - a, x[:, None]
        den = a * xc + b * (1.0 - xc)
        num = b * (1.0 - xc) ** 2 - a * xc ** 2
        g = (e * num / den ** 2).sum(axis=1)
        dnum = -2.0 * (b * (1.0 - xc) + a * xc)
        gp = (e * (dnum * den - 2.0 * num * (a - b)) / den ** 3).sum(axis=1)
        low = np.where(g > 0, x, lo[active])
        high = np.where(g > 0, hi[active], x)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = x - g / gp
        step = np.where((step > low) & (step < high), step, 0.5 * (low + high))
        lo[active], hi[active], s[active] = low, high, step
        active = active[np.abs(step - x) > 1e-12]
    return s


@dataclass
class Contacts:
    """Robot/environment Gaussian pairs whose k-sigma ellipsoids overlap, and a per-link summary."""
    robot: np.ndarray           # (P,) robot Gaussian indices
    env: np.ndarray             # (P,) environment Gaussian indices (the environment's own order)
    sigma: np.ndarray           # (P,) contact_sigma of each pair (<= k)
    k: float
    link_pairs: np.ndarray      # (L,) overlapping pairs per link
    link_gaussians: np.ndarray  # (L,) robot Gaussians of each link that overlap something
    link_min_sigma: np.ndarray  # (L,) the deepest contact per link (inf when none)

    def __len__(self):
        return len(self.robot)


def ellipsoid_contacts(robot, env, k=3.0, links=None, opacity_weights=True, threads=None):
    """Every robot/environment pair whose k-sigma ellipsoids intersect (exact test, batched), with
    counts and the deepest contact per link (links: per robot Gaussian, default robot.links or 0)."""
    if not k > 0:
        raise CollisionInputError(f"k must be positive, got {k}")
    robot = as_gaussians(robot, opacity_weights, name="robot")
    index = as_index(env, opacity_weights)
    links = robot.links if links is None else np.asarray(links)
    links = np.zeros(len(robot), np.int64) if links is None else links.astype(np.int64)
    if links.shape != (len(robot),):
        raise CollisionInputError(f"links: expected {len(robot)} entries, got shape {links.shape}")
    rs = robot.sigma_max
    rx, ry, rz = (robot.means[:, a] for a in range(3))
    rcov = _sym6(robot.covs)
    rcov6 = np.stack(rcov) if len(robot) else np.zeros((6, 0))
    rx, ry, rz = (np.ascontiguousarray(robot.means[:, a]) for a in range(3))

    def reach(lv):
        return k * (rs + lv.sigma)

    kernel = _contact_kernel()

    def work(i, j):
        if kernel is not None:
            mu = np.empty(len(i))
            kernel(i, j, rx, ry, rz, rcov6, rs, index.mx, index.my, index.mz, index.cov6, index.lam, k, mu)
            hit = np.flatnonzero(mu <= k)
            return i[hit], j[hit], mu[hit]
        d = (rx[i] - index.mx[j], ry[i] - index.my[j], rz[i] - index.mz[j])
        near = np.flatnonzero(d[0] ** 2 + d[1] ** 2 + d[2] ** 2 <= (k * (rs[i] + np.sqrt(index.lam[j]))) ** 2)
        i, j = i[near], j[near]
        # mu^2 >= f(1/2) = d^T (A + B)^-1 d / 2: a cheap necessary condition before the exact test
        q = _mahalanobis([x[near] for x in d], [rc[i] + ec[j] for rc, ec in zip(rcov, index.cov)])[0]
        near = np.flatnonzero(q <= 2 * k * k * (1 + 1e-9))
        i, j = i[near], j[near]
        mu = contact_sigma(robot.means[i], _full([c[i] for c in rcov]),
                           np.column_stack([index.mx[j], index.my[j], index.mz[j]]),
                           _full([c[j] for c in index.cov]))
        hit = mu <= k
        return i[hit], j[hit], mu[hit]

    parts = index.query(robot.means, reach, work, threads) if len(robot) else []
    cat = lambda arrays, dtype: np.concatenate(arrays) if arrays else np.zeros(0, dtype)
    i = cat([p[0] for p in parts], np.int64)
    j = cat([p[1] for p in parts], np.int64)
    mu = cat([p[2] for p in parts], np.float64)
    order = np.lexsort((j, i))
    i, j, mu = i[order], j[order], mu[order]
    n_links = int(links.max()) + 1 if len(links) else 0
    min_sigma = np.full(n_links, np.inf)
    np.minimum.at(min_sigma, links[i], mu)
    touched = np.unique(i)
    return Contacts(i, index.order[j], mu, float(k), np.bincount(links[i], minlength=n_links),
                    np.bincount(links[touched], minlength=n_links), min_sigma)


def _ldl_quadratic(s00, s01, s02, s11, s12, s22, d0, d1, d2, x):
    """d^T S^-1 d for one symmetric S by L D L^T with pivots floored as in _mahalanobis; x gets S^-1 d."""
    floor = max(PIVOT_FLOOR * (s00 + s11 + s22), _TINY)
    p0 = max(s00, floor)
    l10, l20 = s01 / p0, s02 / p0
    p1 = max(s11 - l10 * s01, floor)
    t12 = s12 - l20 * s01
    l21 = t12 / p1
    p2 = max(s22 - l20 * s02 - l21 * t12, floor)
    y0 = d0
    y1 = d1 - l10 * y0
    y2 = d2 - l20 * y0 - l21 * y1
    z0, z1, z2 = y0 / p0, y1 / p1, y2 / p2
    x[2] = z2
    x[1] = z1 - l21 * z2
    x[0] = z0 - l10 * x[1] - l20 * z2
    return y0 * z0 + y1 * z1 + y2 * z2


def _contact_pass(i, j, rx, ry, rz, rc, rs, ex, ey, ez, ec, elam, k, out):
    """out[p] = contact_sigma of robot Gaussian i[p] and environment Gaussian j[p], or inf where the
    bounding spheres or mu^2 >= d^T (A+B)^-1 d / 2 already rule out contact at k sigma.

    The same maximum as contact_sigma, found without eigendecompositions: with K(s) = sA + (1-s)B
    and x = K^-1 d, f = s(1-s) d.x, f' = (1-2s) d.x - s(1-s) u and f'' = -2 d.x - 2(1-2s) u +
    2 s(1-s) w, where u = x.(A-B)x and w = y.K^-1 y, y = (A-B)x; bracketed Newton on f'."""
    x = np.empty(3)
    z = np.empty(3)
    limit = 2.0 * k * k * (1.0 + 1e-9)
    for p in range(len(i)):
        a, b = i[p], j[p]
        d0, d1, d2 = rx[a] - ex[b], ry[a] - ey[b], rz[a] - ez[b]
        reach = k * (rs[a] + np.sqrt(elam[b]))
        out[p] = np.inf
        if d0 * d0 + d1 * d1 + d2 * d2 > reach * reach:
            continue
        a00, a01, a02, a11, a12, a22 = rc[0, a], rc[1, a], rc[2, a], rc[3, a], rc[4, a], rc[5, a]
        b00, b01, b02, b11, b12, b22 = ec[0, b], ec[1, b], ec[2, b], ec[3, b], ec[4, b], ec[5, b]
        q = _ldl_quadratic(a00 + b00, a01 + b01, a02 + b02, a11 + b11, a12 + b12, a22 + b22, d0, d1, d2, x)
        if q > limit:
            continue
        s, lo, hi = 0.5, 0.0, 1.0
        for _ in range(100):
            t = 1.0 - s
            dx = _ldl_quadratic(s * a00 + t * b00, s * a01 + t * b01, s * a02 + t * b02, s * a11 + t * b11,
                                s * a12 + t * b12, s * a22 + t * b22, d0, d1, d2, x)
            y0 = (a00 - b00) * x[0] + (a01 - b01) * x[1] + (a02 - b02) * x[2]
            y1 = (a01 - b01) * x[0] + (a11 - b11) * x[1] + (a12 - b12) * x[2]
            y2 = (a02 - b02) * x[0] + (a12 - b12) * x[1] + (a22 - b22) * x[2]
            u = x[0] * y0 + x[1] * y1 + x[2] * y2
            w = _ldl_quadratic(s * a00 + t * b00, s * a01 + t * b01, s * a02 + t * b02, s * a11 + t * b11,
                               s * a12 + t * b12, s * a22 + t * b22, y0, y1, y2, z)
            g = (1.0 - 2.0 * s) * dx - s * t * u
            gp = -2.0 * dx - 2.0 * (1.0 - 2.0 * s) * u + 2.0 * s * t * w
            if g > 0:
                lo = s
            else:
                hi = s
            step = s - g / gp if gp < 0 else 0.5 * (lo + hi)
            if not lo < step < hi:
                step = 0.5 * (lo + hi)
            done = abs(step - s) <= 1e-12
            s = step
            if done:
                break
        t = 1.0 - s
        f = s * t * _ldl_quadratic(s * a00 + t * b00, s * a01 + t * b01, s * a02 + t * b02, s * a11 + t * b11,
                                   s * a12 + t * b12, s * a22 + t * b22, d0, d1, d2, x)
        out[p] = np.sqrt(max(f, 0.0))


def _contact_kernel():
    """The compiled contact pass (core.jit), or None: the NumPy path then does the work."""
    return jit.compiled(__name__, ("_ldl_quadratic", "_contact_pass"))


def _full(c6):
    """(P,3,3) symmetric matrices from their 6 entries."""
    out = np.empty((len(c6[0]), 3, 3))
    for c, (a, b) in zip(c6, _SYM):
        out[:, a, b] = out[:, b, a] = c
    return out


# occupancy and signed distance --------------------------------------------------------------------

@dataclass
class Occupancy:
    values: np.ndarray     # (M,) 1 - exp(-density), in [0, 1)
    density: np.ndarray    # (M,) sum_j alpha_j exp(-1/2 d^T Sigma_j^-1 d)
    bound: np.ndarray      # (M,) upper bound on the density the cutoff dropped (and so on values' error)


def occupancy(env, points, cutoff=DEFAULT_CUTOFF, opacity_weights=True, threads=None):
    """Occupancy 1 - exp(-sum_j alpha_j G_j(x)) at query points, G_j the unnormalised Gaussians,
    alpha_j the opacities; terms beyond Mahalanobis `cutoff` are skipped and bounded per point."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    _require_finite("points", points)
    probes = Gaussians(points, np.zeros((len(points), 3, 3)), sigma_max=np.zeros(len(points)))
    index = as_index(env, opacity_weights)
    r = overlap(probes, index, cutoff, gradient=False, bound=False, threads=threads)
    bound = index.skipped_bound(points, np.zeros(len(points)), np.ones(len(points)), cutoff)
    return Occupancy(-np.expm1(-r.per_gaussian), r.per_gaussian, bound)


def signed_distance(env, points, k=3.0, max_distance=1.0, opacity_weights=True, min_opacity=0.0, threads=None):
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
    spread = (c[0] * d[0] * d[0] + c[3] * d[1] * d[1] + c[5] * d[2] * d[2]
              + 2.0 * (c[1] * d[0] * d[1] + c[2] * d[0] * d[2] + c[4] * d[1] * d[2]))
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
            spread = (c00 * d0 * d0 + c11 * d1 * d1 + c22 * d2 * d2
                      + 2.0 * (c01 * d0 * d1 + c02 * d0 * d2 + c12 * d1 * d2))
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
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):   # point splats: r is inf outside
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
        dh = h / g * (u2 / den).sum(axis=1)          # -1/2 G^-3/2 G', G' = -2 sum u^2 / den
        lo = np.where(h < 1.0, t, lo)
        hi = np.where(h < 1.0, hi, t)
        step = t - (h - 1.0) / dh
        step = np.where((step > lo) & (step < hi), step, 0.5 * (lo + hi))
        done = np.abs(step - t) <= 1e-15 * step
        t = step
        if done.all():
            break
    return t * np.sqrt(((z / (t[:, None] + a2)) ** 2).sum(axis=1))


# collision proxies -------------------------------------------------------------------------------

def fit_proxies(robot, per_link=16, links=None, reference_sigma=None, iterations=10, opacity_weights=True):
    """A few Gaussians per link standing in for the link's splats in the soft overlap.

    Each link's Gaussians are split k-means-like (repeatedly halve the widest cluster along its
    principal axis, then Lloyd iterations), and each cluster becomes one Gaussian by moment
    matching: the overlap of Gaussian i with an environment Gaussian of covariance Sigma_ref, as a
    function of the environment position, is w_i c_i N(mu_i, Sigma_i + Sigma_ref) with
    c_i = (2 pi)^(3/2) sqrt(det(Sigma_i + Sigma_ref)); the proxy matches the mass, mean and
    covariance of that mixture (Sigma_ref cancels from the covariance), so the cost it gives,
    summed over any placement of such environment Gaussians, keeps its total, centre and spread.
    Sigma_ref = reference_sigma^2 I: the environment's typical size (EnvironmentIndex.typical_sigma)
    suits it best; the default is the median robot sigma. Returns Gaussians with
    `links` set; weights carry the matched mass. `proxy_error` measures what they cost.
    """
    robot = as_gaussians(robot, opacity_weights, name="robot")
    links = robot.links if links is None else np.asarray(links)
    links = np.zeros(len(robot), np.int64) if links is None else links.astype(np.int64)
    if per_link < 1:
        raise CollisionInputError(f"per_link must be at least 1, got {per_link}")
    if reference_sigma is None:
        reference_sigma = float(np.median(np.sqrt(np.trace(robot.covs, axis1=1, axis2=2) / 3))) if len(robot) else 0.0
    if reference_sigma <= 0 and len(robot):        # point splats: a size from the robot's extent, or masses vanish
        reference_sigma = 1e-3 * max(float(np.ptp(robot.means, axis=0).max()), 1e-6)
    ref = reference_sigma ** 2 * np.eye(3)
    mass = robot.weights * (2 * np.pi) ** 1.5 * np.sqrt(np.maximum(np.linalg.det(robot.covs + ref), 0.0))
    means, covs, weights, owner = [], [], [], []
    for link in np.unique(links):
        members = np.flatnonzero(links == link)
        labels = _split_clusters(robot.means[members], mass[members], per_link, iterations)
        for c in np.unique(labels):
            pick = members[labels == c]
            m = mass[pick]
            if m.sum() <= 0:
                continue
            p = m / m.sum()
            mean = p @ robot.means[pick]
            off = robot.means[pick] - mean
            cov = np.einsum("n,nij->ij", p, robot.covs[pick]) + np.einsum("n,ni,nj->ij", p, off, off)
            c_proxy = (2 * np.pi) ** 1.5 * np.sqrt(max(np.linalg.det(cov + ref), _TINY))
            means.append(mean)
            covs.append(cov)
            weights.append(m.sum() / c_proxy)
            owner.append(link)
    if not means:
        return Gaussians(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0, np.int64))
    return Gaussians(np.array(means), np.array(covs), np.array(weights), np.array(owner, np.int64))


def _split_clusters(points, mass, count, iterations):
    """Cluster labels for points: split the widest cluster along its principal axis until there
    are `count` (or every point is its own), then mass-weighted Lloyd iterations."""
    labels = np.zeros(len(points), np.int64)
    n = 1
    while n < min(count, len(points)):
        spread = np.array([_weighted_spread(points[labels == c], mass[labels == c]) for c in range(n)])
        worst = int(np.argmax(spread[:, 0]))
        if spread[worst, 0] <= 0:
            break
        pick = np.flatnonzero(labels == worst)
        axis_, centre = spread[worst, 1:4], spread[worst, 4:7]
        labels[pick[(points[pick] - centre) @ axis_ > 0]] = n
        n += 1
    for _ in range(iterations):
        centres = np.array([np.average(points[labels == c], axis=0, weights=mass[labels == c] + 1e-300)
                            for c in range(n)])
        new = np.argmin(((points[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        if np.array_equal(new, labels) or len(np.unique(new)) < n:
            break
        labels = new
    return labels


def _weighted_spread(points, mass):
    """(mass * largest variance, principal axis (3), weighted centre (3)) of a cluster."""
    if len(points) < 2:
        return np.zeros(7)
    w = mass + 1e-300
    centre = np.average(points, axis=0, weights=w)
    off = points - centre
    vals, vecs = np.linalg.eigh((w[:, None, None] * off[:, :, None] * off[:, None, :]).sum(axis=0) / w.sum())
    return np.concatenate([[w.sum() * vals[-1]], vecs[:, -1], centre])


def proxy_error(robot, proxies, env, cutoff=DEFAULT_CUTOFF, opacity_weights=True):
    """What the proxies cost against the full robot in one configuration: |C_proxy - C_full| / C_full
    (0 when both are 0, inf when only the full cost is 0)."""
    index = as_index(env, opacity_weights)
    full = overlap(robot, index, cutoff, gradient=False, bound=False, opacity_weights=opacity_weights).cost
    approx = overlap(proxies, index, cutoff, gradient=False, bound=False).cost
    if full == 0:
        return 0.0 if approx == 0 else math.inf
    return abs(approx - full) / full
