"""Triangle meshes as proxies of captured splats: the nearest surface point of each splat, and the
bone weights a rigged proxy passes on to splats near its surface.

`closest_points` finds, for N points, the nearest point of a triangle mesh (triangle, barycentric
coordinates, distance) without a Python loop per point or triangle: triangles are grouped in small
clusters along a Morton curve, each with a bounding box; a point's distance to a box bounds its
distance to the triangles inside, so each point is compared only with the clusters that could hold
its nearest point (chunks of points at a time, a two-level bounding-volume search).

`surface_weights` interpolates per-vertex weights (a rigged mesh's vertex groups) barycentrically
at those points: exactly how a point glued to the surface deforms under linear blend skinning.

`falloff_strength` fades a binding with the distance to the surface: 1 up to `start`, 0 from `end`
on, a smoothstep between (s = (d - start) / (end - start), strength = 1 - s^2 (3 - 2 s)), so the
strength and its slope are continuous at both ends.
"""

from dataclasses import dataclass

import numpy as np

from .spatial import morton_order

PAIRS_PER_CHUNK = 1 << 20  # (point, triangle) pairs evaluated together: ~150 MB of float64 at most
LEAF = 8  # triangles per cluster


class ProxyError(ValueError):
    """A proxy mesh that cannot be used (no triangles, bad indices, NaN); the message says which."""


@dataclass
class Closest:
    """Nearest surface points of N query points: triangle (N,) int, barycentric (N,3) float64
    coordinates over that triangle's corners, point (N,3) and distance (N,) float64."""

    triangle: np.ndarray
    barycentric: np.ndarray
    point: np.ndarray
    distance: np.ndarray


def check_mesh(vertices, triangles):
    """(V,3) float64 vertices and (F,3) int64 triangles, or ProxyError naming the problem."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles).reshape(-1, 3)
    if len(triangles) == 0:
        raise ProxyError("the proxy mesh has no faces")
    if triangles.dtype.kind not in "iu" or triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ProxyError(f"the proxy's triangles index vertices outside 0..{len(vertices) - 1}")
    if not np.isfinite(vertices).all():
        raise ProxyError("the proxy mesh has vertices holding NaN or Inf")
    return vertices, triangles.astype(np.int64)


def closest_on_triangles(p, a, b, c):
    """Nearest points of triangles (a, b, c) to points p, all (M,3) float64, pair by pair: (squared
    distance (M,), barycentric (M,3)). The interior (projection onto the plane, where it falls inside)
    competes with the three edges; degenerate triangles have edges only."""
    e0, e1, d = b - a, c - a, p - a
    d00, d01, d11 = _dot(e0, e0), _dot(e0, e1), _dot(e1, e1)
    d20, d21 = _dot(d, e0), _dot(d, e1)
    denom = d00 * d11 - d01 * d01
    usable = denom > 1e-12 * np.maximum(d00 * d11, 1e-300)
    safe = np.where(usable, denom, 1.0)
    v, w = (d11 * d20 - d01 * d21) / safe, (d00 * d21 - d01 * d20) / safe
    u = 1.0 - v - w
    bary = np.stack([u, v, w], axis=1)
    inside = usable & (u >= 0) & (v >= 0) & (w >= 0)
    plane = a + v[:, None] * e0 + w[:, None] * e1
    best = np.where(inside, _dot(p - plane, p - plane), np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):  # edge corner i -> corner j
        x, y = (a, b, c)[i], (a, b, c)[j]
        edge = y - x
        t = np.clip(_dot(p - x, edge) / np.maximum(_dot(edge, edge), 1e-300), 0.0, 1.0)
        q = x + t[:, None] * edge
        dist = _dot(p - q, p - q)
        better = dist < best
        best = np.where(better, dist, best)
        edge_bary = np.zeros_like(bary)
        edge_bary[:, i], edge_bary[:, j] = 1.0 - t, t
        bary = np.where(better[:, None], edge_bary, bary)
    return best, bary


def _dot(x, y):
    return np.einsum("ij,ij->i", x, y)


class _Clusters:
    """Triangles in runs of `LEAF` along a Morton curve of their centroids, each run with the bounding
    box of its triangles: compact groups whose boxes bound the distance to every triangle in them."""

    def __init__(self, vertices, triangles):
        corners = vertices[triangles]  # (F,3,3)
        self.order = morton_order(corners.mean(axis=1))
        self.starts = np.arange(0, len(triangles), LEAF)
        self.counts = np.minimum(LEAF, len(triangles) - self.starts)
        sorted_corners = corners[self.order]
        self.lo = np.minimum.reduceat(sorted_corners.min(axis=1), self.starts)
        self.hi = np.maximum.reduceat(sorted_corners.max(axis=1), self.starts)

    def box_distances(self, points):
        """(n, C) squared distances from points to the clusters' boxes: a lower bound for their triangles."""
        gap = np.maximum(self.lo[None] - points[:, None], 0.0) + np.maximum(points[:, None] - self.hi[None], 0.0)
        return np.einsum("nci,nci->nc", gap, gap)

    def pairs(self, point_ids, cluster_ids):
        """(point, triangle) pairs: every triangle of each given (point, cluster)."""
        counts = self.counts[cluster_ids]
        within = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        return np.repeat(point_ids, counts), self.order[np.repeat(self.starts[cluster_ids], counts) + within]


def _best_pairs(points, vertices, triangles, pair_point, pair_triangle, best):
    """Lower best = (squared distance, triangle, barycentric), arrays over the points, in place with the
    pairs (point index, triangle index; sorted by point) nearer than what they hold."""
    tri = triangles[pair_triangle]
    d2, bary = closest_on_triangles(points[pair_point], vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]])
    if not len(d2):
        return
    # pair_point comes sorted (pairs are made point by point): the nearest of each run of a point
    runs = np.flatnonzero(np.r_[True, pair_point[1:] != pair_point[:-1]])
    nearest = np.minimum.reduceat(d2, runs)
    hits = np.flatnonzero(d2 == np.repeat(nearest, np.diff(np.r_[runs, len(d2)])))
    first = hits[np.r_[True, pair_point[hits][1:] != pair_point[hits][:-1]]]
    ids = pair_point[first]
    better = d2[first] < best[0][ids]
    ids, first = ids[better], first[better]
    best[0][ids], best[1][ids], best[2][ids] = d2[first], pair_triangle[first], bary[first]


def closest_points(points, vertices, triangles):
    """The nearest point of the triangle mesh (vertices (V,3), triangles (F,3)) to each of `points`
    (N,3): a Closest, in float64.

    Each point first takes the nearest point of the cluster whose box is nearest, then visits only
    the clusters whose boxes are nearer than that: exact, and the work follows the triangles within
    reach (a few clusters for points near the surface)."""
    vertices, triangles = check_mesh(vertices, triangles)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if not np.isfinite(points).all():
        raise ProxyError("points holding NaN or Inf have no nearest surface point")
    n = len(points)
    best = (np.full(n, np.inf), np.zeros(n, np.int64), np.zeros((n, 3)))
    clusters = _Clusters(vertices, triangles)
    step = max(1, min(1 << 14, PAIRS_PER_CHUNK // len(clusters.starts)))
    for start in range(0, n, step):
        ids = np.arange(start, min(n, start + step))
        bound = clusters.box_distances(points[ids])
        nearest_box = np.argmin(bound, axis=1)
        _best_pairs(points, vertices, triangles, *clusters.pairs(ids, nearest_box), best)
        bound[np.arange(len(ids)), nearest_box] = np.inf
        rows, cols = np.nonzero(bound < best[0][ids][:, None])
        per_piece = max(1, PAIRS_PER_CHUNK // LEAF)
        for piece in range(0, len(rows), per_piece):
            _best_pairs(
                points,
                vertices,
                triangles,
                *clusters.pairs(ids[rows[piece : piece + per_piece]], cols[piece : piece + per_piece]),
                best,
            )
    d2, triangle, bary = best
    point = np.einsum("nk,nki->ni", bary, vertices[triangles[triangle]])
    return Closest(triangle, bary, point, np.sqrt(d2))


def surface_weights(closest, triangles, vertex_weights):
    """(N, B) weights of the surface points `closest` (a Closest on the mesh of `triangles`): the
    per-vertex weights (V, B) blended with each point's barycentric coordinates."""
    corners = np.asarray(triangles, np.int64).reshape(-1, 3)[closest.triangle]  # (N,3)
    weights = np.asarray(vertex_weights, np.float64)
    return np.einsum("nk,nkb->nb", closest.barycentric, weights[corners])


def falloff_strength(distance, start, end):
    """(N,) float64 binding strengths for distances to the surface: 1 at or below `start`, 0 beyond
    `end`, a smoothstep between; a hard cut at `end` when start == end."""
    if not 0.0 <= start <= end:
        raise ProxyError(f"the falloff must start ({start:g}) at or after 0 and at or before its end ({end:g})")
    distance = np.asarray(distance, np.float64)
    if end == start:
        return (distance <= end).astype(np.float64)
    s = np.clip((distance - start) / (end - start), 0.0, 1.0)
    return 1.0 - s * s * (3.0 - 2.0 * s)
