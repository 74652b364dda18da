"""Splats on a mesh for a density per face: what mesh_to_splats (core/mesh_to_splats.py) and its
refinement (core/mesh_refine.py) both build on. Flat Gaussians lying in the surface:

Counts: every face gets a density (splats per unit area). Its expected count, density * area, is
made an integer by systematic sampling along a Morton curve through the face centroids: counts
are proportional to area to within one splat per face, and faces smaller than a splat share
splats with their spatial neighbours instead of each tossing a coin (no clumps, no holes).
Points: inside a face, the centroids of an equal-area longest-edge bisection into `count`
pieces (measured in the face's own metric, so slivers are cut across and stay covered).
Shape: a disc of standard deviation `overlap / sqrt(density)` in the face plane and `thickness`
times that along the normal, narrowed across nearby outline edges (boundaries, creases) so it
does not reach into the air past them. Colour: the surface colour at the point, as display sRGB
SH; degree 2 for view-dependent (rim) materials, else degree 0. Alpha-cut materials: splats on a
MASK material's cut-outs are left out, a BLEND material's alpha scales their opacity (_alpha_cut).
"""

from dataclasses import dataclass

import numpy as np

from . import geometry, jit
from . import sh as shmod
from .mesh import shade, to_display
from .mesh_texture import colour_seams, local_corners, texture_edges
from .parallel import WORKERS, map_threads
from .spatial import NEIGHBOURS, Grid, morton_order, runs, sort_by_cell
from .splats import SplatCloud, logit

EDGE_SOFTNESS = 2.0  # spread across an outline edge <= distance to it / this
# ... and across a colour edge (a texture's, a material's) <= distance / this. 1.5 against 1: on the
# textured corpus the worst held-out distance rose on the box (+0.4 dB), grid plane (+0.5), cup
# (+0.9) and vertex-coloured sphere (+0.4), with 8-49% fewer splats (the box 306k -> 166k, the
# 9k-triangle checker patch 320k -> 284k), the cylinder and the duck within 0.4 dB.
TEXTURE_SOFTNESS = 1.5
# ... but where an alpha-cut material's alpha steps (one side only covers the edge): the leaves at
# 1.5 took 2.5x the splats (152k -> 377k) for 0.9 dB.
ALPHA_SOFTNESS = 1.0
MIN_ACROSS = 0.05  # ... but at least this fraction of the splat's sigma
WALL_SIGMAS = 8.0  # a splat's in-plane sigma stays below the wall thickness behind it / this,
SAME_WALL_SIGMAS = 4.0  # ... or / this where the far side's display colour is within LEAK_CONTRAST:
LEAK_CONTRAST = 1 / 64  # no leak of it can show (36 dB's RMS error), but wider discs poke out at rims
WALL_BOOST = 16.0  # a budget raises thin walls' density at most this many times
WALL_INSET = 0.1  # silhouette shifts take at most this fraction of the wall behind a face
OPAQUE = 0.99  # the opacity of splats on open surfaces and walls hiding another colour
SOLID_OPACITY = 0.75  # ... and on solid parts, whose outlines it thins (see the design notes)
SEE_THROUGH = 0.5  # a wall's far side differing by more than this (display) keeps OPAQUE: a solid
# layer lets a few per cent through, 36 dB's RMS error at this contrast
MIN_COVERAGE = 1 / 255  # a BLEND material's splat with less alpha than this over its footprint is left out
BUILD_CHUNK = 1 << 16  # splats built per task, on every core
BISECT_CHUNK = 1 << 14  # points placed per task, on every core


def budget_density(density, floor, area, count):
    """`density` scaled to spend `count` splats, with faces raised towards `floor` (thin walls):
    max(k density, min(floor, WALL_BOOST k density)), k found by bisection. A face is raised at
    most WALL_BOOST times, so a small budget still covers the rest of the surface."""
    spend = lambda k: np.maximum(k * density, np.minimum(floor, WALL_BOOST * k * density))
    hi = count / (density * area).sum()
    if not (floor > 0).any():
        return density * hi
    lo = 0.0
    for _ in range(50):
        k = (lo + hi) / 2
        lo, hi = (k, hi) if (spend(k) * area).sum() < count else (lo, k)
    return spend(hi)


def build_splats(
    surface,
    density,
    overlap=0.8,
    opacity=OPAQUE,
    thickness=0.01,
    seed=0,
    max_splats=None,
    offset=None,
    texture_aware=True,
):
    """Splats for a per-face density (splats per unit area; 0 for none), each moved by the face's
    `offset` (world units, default 0) along its unit normal. `texture_aware` (default): colours
    averaged over each splat's Gaussian, splats narrowed across colour edges (_outline_frames);
    False: colours averaged over a square mip footprint of the splats' spacing, as before."""
    unplaced = unplaced_splats(surface, density, overlap, opacity, thickness, seed, max_splats, texture_aware)
    return unplaced.placed(np.zeros(len(surface.faces)) if offset is None else offset)


@dataclass
class Unplaced:
    """Splats of one density before their shift along the normal: everything but the positions
    (colours, shapes, sample points) is independent of the shift, so a search over shifts builds
    them once. `points` (N,3) float64 on the surface, `normal` (N,3) their faces' unit normals."""

    cloud: SplatCloud
    points: np.ndarray
    normal: np.ndarray
    tri: np.ndarray

    def placed(self, offset):
        """The splats moved by their face's `offset` (F,) along its normal."""
        shift = np.asarray(offset, np.float64)[self.tri]
        extras = dict(self.cloud.extras, normal_offset=shift.astype(np.float32))
        return self.cloud.replace(positions=self.points + shift[:, None] * self.normal, extras=extras)


def unplaced_splats(
    surface, density, overlap=0.8, opacity=OPAQUE, thickness=0.01, seed=0, max_splats=None, texture_aware=True
):
    """build_splats without the shift: an Unplaced."""
    expected = density * surface.area
    if max_splats is not None and expected.sum() > max_splats:
        expected *= max_splats / expected.sum()
    counts = systematic_counts(expected, morton_order(surface.centroids), np.random.default_rng(seed))
    tri, bary = bisection_samples(surface, counts)
    opacity = np.broadcast_to(np.asarray(opacity, np.float64), density.shape)  # per face, or one for all
    rotations, edges = _face_rotations(surface), _edge_normals(surface)  # per face, once
    points = surface.points(tri, bary)

    def part(rows):
        t = tri[rows]
        return _cloud(
            surface,
            t,
            bary[rows],
            points[rows],
            density[t],
            rotations[t],
            edges,
            overlap,
            opacity[t],
            thickness,
            texture_aware,
        )

    # Chunks on every core (NumPy releases the GIL): the hand's 636k splats build in half the time.
    rows = [slice(a, a + BUILD_CHUNK) for a in range(0, max(len(tri), 1), BUILD_CHUNK)]
    built = map_threads(part, rows)
    cloud = SplatCloud.concatenate([c for c, _ in built])
    keep = np.concatenate([k for _, k in built])
    if not keep.all():  # splats on alpha cut-outs were left out (_alpha_cut)
        points, tri = points[keep], tri[keep]
    return Unplaced(cloud, points, surface.normal[tri], tri)


# counts per face ---------------------------------------------------------------------------------


def systematic_counts(expected, order, rng):
    """Integer counts with sum round(sum(expected)) and |count - expected| < 1 for every face.

    One uniform offset u: count_i = floor(C_i + u) - floor(C_{i-1} + u) with C the running sum of
    `expected` in `order`; neighbours along the order share fractional splats, so small faces are
    covered by spatially stratified picks rather than independent coin flips.
    """
    e = np.asarray(expected, np.float64)[order]
    total = e.sum()
    running = np.cumsum(e)
    running *= np.round(total) / total if total > 0 else 0.0
    marks = np.floor(np.concatenate([[0.0], running]) + rng.uniform())
    counts = np.empty(len(e), np.int64)
    counts[order] = np.diff(marks).astype(np.int64)
    return counts


# points inside faces -----------------------------------------------------------------------------


def bisection_samples(surface, counts):
    """(tri (N,), bary (N,3)) with counts[f] points in face f: centroids of an equal-area bisection.

    Pieces are tracked as their corners' (b1, b2) barycentric coordinates; a piece holding n > 1
    points is cut across its longest edge (measured in the face's own metric) at the fraction
    floor(n/2)/n, so both halves keep one point per equal share of area. The points come face by
    face, each face's level by level (its halves' first pieces before their second ones), the same
    on every machine: compiled (_bisect_loop) where numba loads, else by NumPy.
    """
    counts = np.asarray(counts, np.int64)
    faces = np.flatnonzero(counts > 0)
    gram = np.stack(
        [
            np.einsum("ij,ij->i", surface.edge1, surface.edge1),
            np.einsum("ij,ij->i", surface.edge1, surface.edge2),
            np.einsum("ij,ij->i", surface.edge2, surface.edge2),
        ],
        axis=1,
    )
    # Faces dealt out to the cores in runs of about BISECT_CHUNK points (NumPy releases the GIL).
    ends = np.cumsum(counts[faces])
    total = int(ends[-1]) if len(ends) else 0
    runs = np.split(np.arange(len(faces)), np.searchsorted(ends, np.arange(BISECT_CHUNK, total, BISECT_CHUNK)))
    kernel = _bisect_kernel()
    if kernel is not None:
        uv = np.empty((total, 2))
        first = ends - counts[faces]
        map_threads(lambda run: kernel(faces[run], counts[faces[run]], first[run], gram, uv), runs)
        tri = np.repeat(faces, counts[faces])
    else:
        parts = map_threads(lambda run: _bisection_leaves(faces[run], counts[faces[run]], gram), runs)
        tri = np.concatenate([np.zeros(0, np.int64)] + [t for t, _ in parts])
        uv = np.concatenate([np.zeros((0, 2))] + [uv for _, uv in parts])
        face_by_face = np.argsort(tri, kind="stable")
        tri, uv = tri[face_by_face], uv[face_by_face]
    bary = np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv])
    return tri, np.clip(bary, 0.0, 1.0)


def _bisection_leaves(tri, n, gram):
    """(tri, uv): the leaves of bisecting faces tri into n[i] pieces each, as their centroids'
    (b1, b2) barycentric coordinates, level by level."""
    reference = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    corners = np.broadcast_to(reference, (len(tri), 3, 2)).copy()
    out_tri, out_uv = [np.zeros(0, np.int64)], [np.zeros((0, 2))]
    while len(tri):
        leaf = n == 1
        out_tri.append(tri[leaf])
        out_uv.append(corners[leaf].mean(axis=1))
        tri, n, corners = tri[~leaf], n[~leaf], corners[~leaf]
        if len(tri):
            tri, n, corners = _bisect(tri, n, corners, gram[tri])
    return np.concatenate(out_tri), np.concatenate(out_uv)


def _bisect_kernel():
    """The compiled twin of _bisection_leaves (core.jit), or None: NumPy then does the work."""
    return jit.compiled(__name__, ("_bisect_loop",))


def _bisect_loop(faces, counts, first, gram, uv):
    """_bisection_leaves one face at a time, as scalar loops for numba: the same cuts with the same
    float64 operations in the same order, the leaves of faces[i] written to uv rows first[i].. in
    the order bisection_samples gives them."""
    most = counts.max() if len(counts) else 0
    pieces, held = np.empty((most, 3, 2)), np.empty(most, np.int64)  # this level's
    firsts, first_held = np.empty((most, 3, 2)), np.empty(most, np.int64)  # the next level's
    seconds, second_held = np.empty((most, 3, 2)), np.empty(most, np.int64)
    for i in range(len(faces)):
        g0, g1, g2 = gram[faces[i], 0], gram[faces[i], 1], gram[faces[i], 2]
        pieces[0] = 0.0
        pieces[0, 1, 0] = pieces[0, 2, 1] = 1.0
        held[0], count, row = counts[i], 1, first[i]
        while count:
            cut = 0
            for p in range(count):
                if held[p] == 1:
                    for axis in range(2):
                        uv[row, axis] = (pieces[p, 0, axis] + pieces[p, 1, axis] + pieces[p, 2, axis]) / 3
                    row += 1
                    continue
                # the longest edge k (corners k+1, k+2) in the face's metric; as argmax: the first
                # of equals, or the first NaN
                k, longest = 0, 0.0
                for e in range(3):
                    dx = pieces[p, (e + 2) % 3, 0] - pieces[p, (e + 1) % 3, 0]
                    dy = pieces[p, (e + 2) % 3, 1] - pieces[p, (e + 1) % 3, 1]
                    length2 = g0 * dx**2 + 2 * g1 * dx * dy + g2 * dy**2
                    if e == 0 or (longest == longest and not length2 <= longest):
                        k, longest = e, length2
                a, b, c = (k + 1) % 3, (k + 2) % 3, k
                n1 = held[p] // 2
                fraction = n1 / held[p]
                for axis in range(2):
                    pa, pb = pieces[p, a, axis], pieces[p, b, axis]
                    middle = pa + fraction * (pb - pa)
                    firsts[cut, 0, axis], firsts[cut, 1, axis], firsts[cut, 2, axis] = pa, middle, pieces[p, c, axis]
                    seconds[cut, 0, axis], seconds[cut, 1, axis], seconds[cut, 2, axis] = middle, pb, pieces[p, c, axis]
                first_held[cut], second_held[cut] = n1, held[p] - n1
                cut += 1
            # the next level: every first half, then every second half
            pieces[:cut], held[:cut] = firsts[:cut], first_held[:cut]
            pieces[cut : 2 * cut], held[cut : 2 * cut] = seconds[:cut], second_held[:cut]
            count = 2 * cut


def _longest_edge(corners, gram):
    """Corners (a, b) of each piece's longest edge and the corner c opposite it."""
    rows = np.arange(len(corners))
    # Edge k joins corners k+1 and k+2 (mod 3); its length^2 in the face metric is d^T G d.
    d = corners[:, [2, 0, 1]] - corners[:, [1, 2, 0]]
    length2 = (
        gram[:, None, 0] * d[..., 0] ** 2
        + 2 * gram[:, None, 1] * d[..., 0] * d[..., 1]
        + gram[:, None, 2] * d[..., 1] ** 2
    )
    k = np.argmax(length2, axis=1)
    return corners[rows, (k + 1) % 3], corners[rows, (k + 2) % 3], corners[rows, k]


def _bisect(tri, n, corners, gram):
    a, b, c = _longest_edge(corners, gram)
    n1 = n // 2
    m = a + (n1 / n)[:, None] * (b - a)
    first = np.stack([a, m, c], axis=1)
    second = np.stack([m, b, c], axis=1)
    return (np.concatenate([tri, tri]), np.concatenate([n1, n - n1]), np.concatenate([first, second]))


# splats ------------------------------------------------------------------------------------------


def _cloud(surface, tri, bary, positions, density, rotations, edges, overlap, opacity, thickness, texture_aware=True):
    """(cloud, kept (n,) bool): flat discs at the sample points `positions` (no shift) but those
    on alpha cut-outs (_alpha_cut): in-plane sigma overlap/sqrt(density), normal axis thin, narrowed
    across outline edges and the surface's colour edges; `edges` the faces' _edge_normals.
    Colours: the surface colour averaged over each disc's own Gaussian."""
    n = len(tri)
    sigma = overlap / np.sqrt(density)
    rotations, in_plane, covariance = _outline_frames(surface, tri, bary, sigma, rotations, edges, texture_aware)
    scales = np.column_stack([in_plane, thickness * sigma])
    keep = None
    if surface.cut:
        keep, opacity = _alpha_cut(surface, tri, bary, covariance / (2 * overlap) ** 2, opacity)
    if texture_aware:
        # The Gaussian shrunk to half the splats' spacing (sigma / overlap): the render blurs the
        # colours by the splats' Gaussians again, and a round splat then gets the colour a square
        # mip footprint of its spacing gave (the whole Gaussian, blurred twice, lost the bench's
        # wavy sphere 0.5 to 2 dB in budgets); a narrowed one, its ellipse likewise shrunk.
        linear = surface.linear_colors(tri, bary, covariance=covariance / (2 * overlap) ** 2)
    else:
        linear = surface.linear_colors(tri, bary, footprint=1.0 / np.sqrt(density))
    if surface.view_dependent:
        sh = _rim_sh(surface, tri, linear)
    else:
        sh = shmod.rgb_to_dc(to_display(linear))[:, None, :]
    with np.errstate(divide="ignore"):
        log_scales = np.log(scales)
    cloud = SplatCloud(
        positions,
        rotations,
        log_scales,
        np.broadcast_to(logit(opacity), (n,)).astype(np.float32),
        sh,
        extras={
            "source_triangle": tri.astype(np.int32),
            "barycentric": bary.astype(np.float32),
            "normal_offset": np.zeros(n, np.float32),
        },
    )
    return (cloud, np.ones(n, bool)) if keep is None else (cloud[keep], keep)


def _alpha_cut(surface, tri, bary, footprint, opacity):
    """(keep (n,) bool, opacity (n,)) for splats on alpha-cut materials (core.mesh.Material.cut):
    a MASK material's splat stays where the alpha averaged over its colour `footprint` (n,2,2,
    local frame) reaches the cutoff and its centre is not cut out (the reference shows nothing
    there); a BLEND material's carries that average as a factor on its opacity."""
    coverage = surface.coverage(tri, bary, footprint)
    materials = surface.face_materials[tri]
    mode = np.array([m.alpha_mode if m.cut else "OPAQUE" for m in surface.materials])[materials]
    cutoff = np.array([m.alpha_cutoff for m in surface.materials])[materials]
    centre = surface.hit_alpha(tri, bary)
    masked = mode == "MASK"
    keep = np.where(masked, (coverage >= cutoff) & (centre > 0), coverage > MIN_COVERAGE)
    opacity = np.where(mode == "BLEND", opacity * np.clip(coverage, 0.0, 1.0), opacity)
    return keep, opacity


def _outline_frames(surface, tri, bary, sigma, rotations, edges, texture_aware=True):
    """Rotations, in-plane scales (N,2) and in-plane covariances (N,2,2) in the faces' local frames,
    narrowed across nearby outline edges and colour edges.

    A disc near a boundary or a sharp crease would reach past it into the air and fatten the
    silhouette; its spread across that edge is therefore kept below its distance to the edge
    divided by EDGE_SOFTNESS (a rank-one update of the in-plane covariance per edge), so the
    coverage falls to about one half on the edge itself, like an antialiased edge. Across a colour
    edge (a texture's, or a material or vertex-colour boundary between faces: core.mesh_texture)
    a disc would smear the edge over its width: there the spread is kept below the distance over
    TEXTURE_SOFTNESS (ALPHA_SOFTNESS on alpha-cut materials), so discs near the edge grow long along
    it and thin across it, and the discs of both sides still cover the edge between them.
    """
    n = len(tri)
    covariance = np.zeros((n, 2, 2))
    covariance[:, 0, 0] = covariance[:, 1, 1] = sigma**2
    outline = surface.sharp_edges()[tri]
    if texture_aware:
        seam = colour_seams(surface)[tri] & ~outline
        distance, across_texture = texture_edges(surface, tri, bary, sigma)
    else:
        seam, distance, across_texture = np.zeros_like(outline), np.full(n, np.inf), np.zeros((n, 2))
    softness_of = np.array([ALPHA_SOFTNESS if m.cut else TEXTURE_SOFTNESS for m in surface.materials])
    texture_softness = softness_of[surface.face_materials[tri]]
    textured = distance < texture_softness * sigma
    sel = np.flatnonzero(outline.any(axis=1) | seam.any(axis=1) | textured)
    if not len(sel):
        return rotations, np.column_stack([sigma, sigma]), covariance
    f, b, s = tri[sel], bary[sel], sigma[sel]
    across, reach = edges
    xx, xy, yy = s**2, np.zeros(len(f)), s**2

    def narrow(ax, ay, limit, near):
        nonlocal xx, xy, yy
        lx, ly = xx * ax + xy * ay, xy * ax + yy * ay  # the covariance times `across`
        spread = ax * lx + ay * ly
        cut = np.where(
            near & (spread > limit**2), (1 - limit**2 / np.maximum(spread, 1e-300)) / np.maximum(spread, 1e-300), 0.0
        )
        xx, xy, yy = xx - cut * lx * lx, xy - cut * lx * ly, yy - cut * ly * ly

    for k in range(3):
        distance_k = b[:, k] * reach[f, k] * EDGE_SOFTNESS  # to edge k
        softness = np.where(outline[sel, k], EDGE_SOFTNESS, texture_softness[sel])
        near = outline[sel, k] | seam[sel, k]
        narrow(across[f, k, 0], across[f, k, 1], np.maximum(distance_k / softness, MIN_ACROSS * s), near)
    limit = np.maximum(distance[sel] / texture_softness[sel], MIN_ACROSS * s)
    narrow(across_texture[sel, 0], across_texture[sel, 1], limit, textured[sel])
    covariance[sel] = np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], 1)
    mean, radius = (xx + yy) / 2, np.hypot((xx - yy) / 2, xy)
    half = 0.25 * np.arctan2(2 * xy, xx - yy)  # half the major axis' angle from the first edge
    turn = np.column_stack([np.cos(half), np.zeros(len(f)), np.zeros(len(f)), np.sin(half)])
    rotations = rotations.copy()
    rotations[sel] = geometry.multiply_quaternions(rotations[sel], turn)  # turned about the normal
    in_plane = np.column_stack([sigma, sigma])
    in_plane[sel] = np.sqrt(np.column_stack([mean + radius, np.maximum(mean - radius, 0.0)]))
    return rotations, in_plane, covariance


def _edge_normals(surface):
    """Per face and edge k (opposite corner k), in the face's (first edge, normal x first edge)
    frame: the unit in-plane normal of the edge pointing into the face (F,3,2), and
    2 area / (edge length * EDGE_SOFTNESS) (F,3): a point's barycentric coordinate k times this is
    its distance to the edge over EDGE_SOFTNESS."""
    corners = local_corners(surface)
    across, reach = np.zeros((len(surface.faces), 3, 2)), np.zeros((len(surface.faces), 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            p, q = corners[:, (k + 1) % 3], corners[:, (k + 2) % 3]
            length = np.linalg.norm(q - p, axis=1)
            normal = np.column_stack([p[:, 1] - q[:, 1], q[:, 0] - p[:, 0]]) / length[:, None]
            across[:, k] = normal * np.sign(np.einsum("ij,ij->i", normal, corners[:, k] - p))[:, None]
            reach[:, k] = 2 * surface.area / length / EDGE_SOFTNESS
    return across, reach


def _face_rotations(surface):
    """w,x,y,z quaternions of the frames (first edge, normal x first edge, normal) of all faces."""
    length = np.linalg.norm(surface.edge1, axis=1, keepdims=True)
    t1 = np.where(surface.valid[:, None], surface.edge1 / np.where(length > 0, length, 1.0), [1.0, 0.0, 0.0])
    normal = surface.normal
    t2 = np.cross(normal, t1)
    return geometry.matrices_to_quaternions(np.stack([t1, t2, normal], axis=2))


# view-dependent materials: the facing blend projected onto SH ------------------------------------


def _legendre_weights(degree=2, nodes=64):
    """lambda_l = 2 pi * integral of g(t) P_l(t) over [-1, 1] as Gauss-Legendre weights per node.

    Split at t = 0 because the facing blend has a kink in |t| there.
    """
    x, w = np.polynomial.legendre.leggauss(nodes)
    t = np.concatenate([(x - 1) / 2, (x + 1) / 2])
    wt = np.concatenate([w, w]) / 2
    p = np.stack([np.polynomial.legendre.legval(t, np.eye(degree + 1)[l]) for l in range(degree + 1)])
    return t, 2 * np.pi * p * wt  # (Q,), (L+1, Q)


def _rim_sh(surface, tri, base_linear, chunk=1 << 15):
    """Degree-2 SH of the display colour g(n.d) = sRGB(mix(base, rim, 1 - |n.d|)) (Funk-Hecke).

    A function of n.d alone projects to sh_lm = lambda_l Y_lm(n); |n.d| is even, so odd bands
    vanish and degree 2 holds everything up to degree 3. Splats without a rim get their DC term.
    """
    sh = np.zeros((len(tri), 9, 3))
    sh[:, 0] = shmod.rgb_to_dc(to_display(base_linear))
    rim, has = surface.rim_colors(tri)
    t, weights = _legendre_weights()
    band = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2])
    for start in range(0, len(tri), chunk):
        sel = np.flatnonzero(has[start : start + chunk]) + start
        if not len(sel):
            continue
        g = to_display(shade(base_linear[sel, None, :], rim[sel, None, :], True, t[None, :]))  # (n,Q,3)
        lam = np.einsum("lq,nqc->nlc", weights, g)  # (n,3,3)
        sh[sel] = lam[:, band, :] * shmod.basis(surface.normal[tri[sel]], 2)[:, :, None]
        sh[sel, 0] -= 0.5 / shmod.C0  # rgb = 0.5 + sum Y sh
    return sh


# thin walls -------------------------------------------------------------------------------------


def thin_wall_density(surface, density, overlap):
    """(density floor, wall thickness) per face: the density below which its splats would be wider
    than 1/WALL_SIGMAS of the wall behind it, 1/SAME_WALL_SIGMAS where the far side's colour is
    within LEAK_CONTRAST of the face's (0 where the wall is thicker than the splats of `density`
    could matter), and that wall's thickness (inf where none is that thin).

    3DGS renderers sort whole splats by the depth of their centres, so where a splat is wide
    next to the wall's thickness, a splat of the far side gets sorted in front of the near side's
    at oblique views and its colour shows through (the inside of a cup through its wall): on a
    5 mm wall, 14% of the outside pixels of a close-up at sigma = 0.65 wall, under 1% at 0.11.
    A far side of the face's own colour cannot show, so such walls only keep discs from poking
    out past their rims (see the design notes for what each floor measured)."""
    finest = density[density > 0].min() if (density > 0).any() else 0.0
    none = (np.zeros_like(density), np.full(len(density), np.inf))
    if not finest:
        return none
    thickness, contrast = wall_thickness(surface, min(WALL_SIGMAS * overlap / np.sqrt(finest), _size(surface) / 4))
    sigmas = np.where(contrast > LEAK_CONTRAST, WALL_SIGMAS, SAME_WALL_SIGMAS)
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(thickness), (sigmas * overlap / thickness) ** 2, 0.0), thickness


def face_opacities(surface, opacity=None, antialiased=True):
    """Per face, the opacity of its splats: `opacity` if given; made for antialiased rendering,
    SOLID_OPACITY on solid parts (it thins their outlines: see the design notes), except walls
    whose far side, within a quarter of the mesh's size, differs in colour by more than
    SEE_THROUGH, and OPAQUE on those, on the faces next to them and on open surfaces, which have
    nothing behind them to cover for them; made for classic rendering, OPAQUE everywhere."""
    if opacity is not None or not antialiased:
        return np.full(len(surface.faces), OPAQUE if opacity is None else float(opacity))
    _, contrast = wall_thickness(surface, _size(surface) / 4)
    opaque = (surface.outward_signs() == 0) | (contrast > SEE_THROUGH)
    # and the faces along them (a cup's rim between its two colours, seen edge-on from above)
    f, g = surface.edge_neighbours()
    opaque[f[opaque[g]]] = True
    return np.where(opaque, OPAQUE, SOLID_OPACITY)


def _size(surface):
    """The largest extent of the mesh's finite vertices."""
    v = surface.vertices[np.isfinite(surface.vertices).all(axis=1)]
    return float(np.max(v.max(axis=0) - v.min(axis=0)))


def wall_thickness(surface, reach, max_points=60_000):
    """Per face, (thickness, contrast) of the solid behind it where that is thinner than `reach`
    (inf and 0 elsewhere): the distance along the face's inward normal to the nearest surface of
    the same solid that faces the other way (the far side of a cup's wall, say), and how far that
    side's display colour is from the face's (the largest channel difference, 0 to 1): what a
    wall would let show through. Non-solid faces get inf and 0.

    Points are spread over the surface (about reach/2 apart, at most `max_points`, and one or more
    in every face) and paired with the points within `reach` through a grid of cells `reach` wide;
    a pair counts when this point's inward ray meets the other point's face, and that face points
    the other way. Only about one point per reach/2 squared asks: faces smaller than that
    share one, as splats do (one each made a finely cut sphere pair 9k points with thousands of
    candidates each), and take the thinnest wall (and the largest contrast) found on the faces
    around them."""
    outward = surface.outward_signs()
    thickness, contrast = np.full(len(surface.faces), np.inf), np.zeros(len(surface.faces))
    solid = (outward != 0) & surface.valid
    if not solid.any() or not reach > 0:
        return thickness, contrast
    spacing = max(reach / 2, float(np.sqrt(surface.area[solid].sum() / max_points)))
    expected = np.where(solid, surface.area / spacing**2, 0.0)
    tri, bary = bisection_samples(surface, np.ceil(expected - 1e-9).astype(np.int64))
    asking = systematic_counts(expected, morton_order(surface.centroids), np.random.default_rng(0))
    ask_tri, ask_bary = bisection_samples(surface, asking)
    points, normals = surface.points(tri, bary), surface.normal[tri] * outward[tri, None]
    queries, query_normals = surface.points(ask_tri, ask_bary), surface.normal[ask_tri] * outward[ask_tri, None]
    grid = Grid(points.min(axis=0), reach, None)
    cell = grid.cells(points)
    grid.dims = cell.max(axis=0) + 3  # a cell of margin on every side
    query_key = grid.keys(np.clip(grid.cells(queries), 0, grid.dims - 3) + 1)
    order, sorted_keys = sort_by_cell(grid.keys(cell + 1))

    def nearest_in(cells):
        best, nearest = np.full(len(queries), np.inf), np.zeros(len(queries), np.int64)
        for dx, dy, dz in cells:
            lo, hi = runs(sorted_keys, query_key + grid.step(dx, dy, dz))
            _nearest_behind(surface, queries, query_normals, points, normals, tri, order, lo, hi, reach, best, nearest)
        return best, nearest

    # The 27 neighbouring cells dealt out to the cores, each with its own minima, merged after.
    cells = NEIGHBOURS
    # Ties go to the lowest candidate, so the result does not depend on how many cores there are.
    found = map_threads(nearest_in, [cells[k::WORKERS] for k in range(min(WORKERS, len(cells)))])
    depths, candidates = np.stack([b for b, _ in found]), np.stack([n for _, n in found])
    pick = np.lexsort((candidates, depths), axis=0)[0]
    best = depths[pick, np.arange(len(queries))]
    far = candidates[pick, np.arange(len(queries))]
    walled = np.flatnonzero(np.isfinite(best))
    colours = lambda t, b: to_display(surface.linear_colors(t, b))  # noqa: E731
    near_side, far_side = colours(ask_tri[walled], ask_bary[walled]), colours(tri[far[walled]], bary[far[walled]])
    differs = np.abs(near_side - far_side).max(axis=1)
    np.minimum.at(thickness, ask_tri, best)
    np.maximum.at(contrast, ask_tri[walled], differs)
    unsampled = solid & (asking == 0)
    return (
        _spread_to_unsampled(surface, thickness, unsampled, outward),
        -_spread_to_unsampled(surface, -contrast, unsampled, outward),
    )


def _spread_to_unsampled(surface, thickness, unsampled, outward):
    """Give each face in `unsampled` the thickness of the faces it shares an edge with, across
    edges that do not turn by more than 60 degrees (the wall behind a rim is not the rim's), ring
    after ring; of several, the thinnest, the safe guess (smaller splats, smaller shifts).
    (Spreading -contrast spreads the largest contrast.)"""
    f, g = surface.edge_neighbours()
    normal = surface.normal * outward[:, None]
    smooth = np.einsum("ij,ij->i", normal[f], normal[g]) > 0.5
    f, g = f[smooth], g[smooth]
    known = ~unsampled
    while True:
        step = known[g] & ~known[f]
        if not step.any():
            return thickness
        fresh = np.unique(f[step])
        value = np.full(len(thickness), np.inf)
        np.minimum.at(value, f[step], thickness[g[step]])
        thickness[fresh] = value[fresh]
        known[fresh] = True


def _nearest_behind(
    surface, queries, query_normals, points, normals, tri, order, lo, hi, reach, best, nearest, chunk=1 << 20
):
    """For every query i and the candidate points order[lo[i]:hi[i]] (on faces tri), lower best[i]
    to the depth at which i's inward ray meets a candidate's face facing the other way, and set
    nearest[i] to that candidate."""
    counts = hi - lo
    ends = np.cumsum(counts)
    start = 0
    while start < len(queries):
        stop = max(int(np.searchsorted(ends, (ends[start - 1] if start else 0) + chunk, "right")), start + 1)
        n = counts[start:stop]
        total = int(n.sum())
        if total:
            first = np.cumsum(n) - n
            i = np.repeat(np.arange(start, stop), n)
            j = order[np.repeat(lo[start:stop], n) + (np.arange(total) - np.repeat(first, n))]
            # The inward ray from query i meets candidate j's face at depth t: the far side is
            # found however thin the wall is next to the points' spacing (a long sliver's few
            # points stand for all of it). Only pairs facing each other (few) take the ray test.
            facing = -np.einsum("ij,ij->i", query_normals[i], normals[j])
            pair = np.flatnonzero(facing > 0.3)
            qi, pj = i[pair], j[pair]
            t = np.einsum("ij,ij->i", points[pj] - queries[qi], normals[pj]) / facing[pair]
            hit = (t > 0) & (t < reach) & _inside(surface, tri[pj], queries[qi] - t[:, None] * query_normals[qi])
            depth = np.full(total, np.inf)
            depth[pair[hit]] = t[hit]
            # Candidates come grouped by point, so segmented minima replace a scatter: the least
            # depth, then the first candidate that has it.
            has = n > 0
            least = np.minimum.reduceat(depth, first[has])
            at_least = (depth == np.repeat(least, n[has])) & np.isfinite(depth)
            which = np.minimum.reduceat(np.where(at_least, np.arange(total), total), first[has])
            rows = np.arange(start, stop)[has]
            hit_at = np.isfinite(least)
            candidate = np.where(hit_at, j[np.minimum(which, total - 1)], 0)
            # On a tie, the lowest candidate (the cells' order then does not matter).
            closer = hit_at & ((least < best[rows]) | ((least == best[rows]) & (candidate < nearest[rows])))
            best[rows[closer]] = least[closer]
            nearest[rows[closer]] = candidate[closer]
        start = stop


def _inside(surface, tri, x, slack=1e-6):
    """Whether points x (N,3), in the planes of faces tri, lie inside them (barycentric test)."""
    e1, e2, w = surface.edge1[tri], surface.edge2[tri], x - surface.origin[tri]
    d11, d12, d22 = (np.einsum("ij,ij->i", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
    w1, w2 = np.einsum("ij,ij->i", w, e1), np.einsum("ij,ij->i", w, e2)
    den = d11 * d22 - d12**2
    den = np.where(den > 0, den, np.inf)
    u, v = (d22 * w1 - d12 * w2) / den, (d11 * w2 - d12 * w1) / den
    return (u >= -slack) & (v >= -slack) & (u + v <= 1 + slack)
