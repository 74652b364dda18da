"""The environment index, the broad phase of every query: a sorted grid (core.spatial.Grid) per
size class, the candidate pairs within a reach of query points, and a bound on what the pairs
beyond a cutoff add up to."""

import math
import os
from dataclasses import dataclass, field

import numpy as np

from ..spatial import Grid, cell_start, sort_by_cell
from .gaussians import _TINY, Gaussians, _flatten, _full, _map

_UNIT_PAIRS = 1 << 18  # candidate pairs per work unit: bounded memory, two units in flight
COARSE = 32  # cells a side of the blocks that find a size class's dense part


@dataclass
class _Level(Grid):
    """A size class's grid (core.spatial.Grid: origin, cell size h, dims) and its sorted members."""

    cell_start: np.ndarray  # (cells+1,) first sorted index of each cell, x-major then y then z
    sigma: float  # largest sigma_max in the level
    weight: float  # largest weight in the level
    count: int
    svt: np.ndarray = field(repr=False, default=None)  # summed-volume table of counts


class EnvironmentIndex:
    """The environment, built once: Gaussians sorted into one uniform grid per size class (sizes
    within a factor `level_ratio`), cells `cell_factor` times the class's largest sigma (coarsened so
    a class never has more than `cells_per_splat` cells per Gaussian). Queries walk the cells near
    each query point, z-runs of cells at a time, so the cost is the candidates, not the scene.

    Captured scenes have floaters far from everything: a class whose grid at its natural cell size
    would be too large keeps its dense part (the blocks of 32^3 cells that hold more than one
    member and 1% of the fullest block) in one grid and the rest in grids of their own, so a few
    distant splats never coarsen the cells of the many."""

    def __init__(self, env, opacity_weights=True, cell_factor=2.0, level_ratio=2.0, cells_per_splat=4, threads=None):
        flat = _flatten(env, opacity_weights, "environment", threads)
        keep = np.flatnonzero(flat.weights > 0)  # transparent splats can touch nothing
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
            for part in parts + ([sparse] if len(sparse) else []):  # outliers of every class share a grid
                level, order = self._build_level(flat, part, cell_factor, cells_per_splat, sum(map(len, orders)))
                self.levels.append(level)
                orders.append(order)
        self.order = o = np.concatenate(orders) if orders else np.zeros(0, np.int64)
        self.mx, self.my, self.mz = (flat.means[a][o] for a in range(3))
        self.cov6 = np.stack([c[o] for c in flat.cov6]) if len(o) else np.zeros((6, 0))
        self.cov = list(self.cov6)  # row views: one array per entry, no copy
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
        level = _Level(
            grid.origin, grid.h, grid.dims, start + offset, sigma, float(flat.weights[members].max()), len(members), svt
        )
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
        gx = np.maximum(np.abs(rel[:, :1] - cx - 0.5) - 0.5, 0.0)  # distance to the column, in cells
        gy = np.maximum(np.abs(rel[:, 1:2] - cy - 0.5) - 0.5, 0.0)
        gx[cx > hi[:, :1]] = np.inf
        gy[cy > hi[:, 1:]] = np.inf
        chord2 = ((r * r)[:, None, None] - (gx * gx)[:, :, None] - (gy * gy)[:, None, :]).ravel()
        column = ((cx * lv.dims[1])[:, :, None] + cy[:, None, :]).ravel()
        k = np.flatnonzero(chord2 >= 0)  # flat indices: cheaper than 3-D ones
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
        for level, active, reach, _count in entries:
            mine = owner[offset : offset + len(active)]
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
            first = np.cumsum(stop - start) - (stop - start)  # index of each run's first pair
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
            lam_tot = glam + lv.sigma**2
            gcell = np.array(np.unravel_index(groups, tuple(lv.dims + 2))).T - 1
            # enough rings that the rest is negligible next to one pair at the cutoff
            need = math.sqrt(c2 + 2.0 * math.log(lv.count + 1.0) + 80.0) * math.sqrt(lam_tot.max()) / lv.h
            rings = int(min(math.ceil(need) + 2, lv.dims.max() + 1))
            k = np.arange(rings + 1)
            box = self._box_counts(lv, gcell, k)  # (G, rings+1)
            shell = np.diff(box, axis=1, prepend=0)
            dist = np.maximum(np.maximum(k - 1, 0)[None, :] * lv.h, gout[:, None])
            scale = np.maximum(lam_tot, _TINY)  # 0 for point splats
            with np.errstate(over="ignore", under="ignore"):
                expo = np.maximum(c2, dist**2 / scale[:, None])
                tail_expo = np.maximum(c2, np.maximum(rings * lv.h, gout) ** 2 / scale)
                per_group = (shell * np.exp(-0.5 * expo)).sum(axis=1) + (lv.count - box[:, -1]) * np.exp(
                    -0.5 * tail_expo
                )
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
    return (
        s[x1, y1, z1]
        - s[x0, y1, z1]
        - s[x1, y0, z1]
        - s[x1, y1, z0]
        + s[x0, y0, z1]
        + s[x0, y1, z0]
        + s[x1, y0, z0]
        - s[x0, y0, z0]
    )


def as_index(env, opacity_weights=True, threads=None):
    return env if isinstance(env, EnvironmentIndex) else EnvironmentIndex(env, opacity_weights, threads=threads)
