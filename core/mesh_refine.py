"""Target-PSNR sizing for mesh_to_splats: spend splats where the render error says they are needed.

The mesh is rendered once from eight views around it by the reference rasteriser
(core.mesh_render, black background). The converter then starts coarse (one splat per
START_SPACING^2 pixels of the finest view of each face) and repeats: build splats, render them with
core.render from the same views, compare, attribute every pixel's squared error to the face seen
there (background pixels to the nearest face), and multiply the density of faces whose local error
is above the target by how far above it they are (at most MAX_GROWTH a round and MAX_PER_PIXEL
splats per pixel), until the worst of the views reaches the target (every view, so the result
holds from directions in between too). A face that got denser without its error dropping is left
alone from then on: more splats cannot fix what the renderer's low-pass filter blurs. Flat
single-colour regions therefore stay coarse. Once reached, two bisection steps between the last
two densities look for a smaller cloud that still reaches the target.

Silhouettes: an opaque surface of Gaussians renders about one pixel fatter than the mesh, because
the renderer's 0.3 px^2 low-pass spreads every splat seen edge-on and many such splats stack along
a silhouette. Closed, consistently wound parts are therefore moved inwards along the normal by
about a pixel of the views, calibrated from the coverage excess measured along the silhouettes.
"""

import math

import numpy as np

from .camera import Camera
from .mesh_render import render_mesh
from .mesh_to_splats import build_splats
from .metrics import psnr_from_mse
from .parallel import map_threads
from .render import render

VIEW_COUNT = 8
VIEW_FOV = 40.0
SUPERSAMPLE = 3
BACKGROUND = (0.0, 0.0, 0.0)
START_SPACING = 4.0       # pixels between splats at the start
MAX_PER_PIXEL = 2.0       # density cap, splats per pixel of the finest view
MAX_ROUNDS = 10
MAX_GROWTH = 2.5
INSET_AIM = 0.15          # pixels of silhouette dilation to leave (best on held-out views)
INSET_TOLERANCE = 0.1     # ... give or take this much
INSET_SHIFTS = 4          # at most this many silhouette recalibrations
AIM = 0.7                 # faces aim at this fraction of the target MSE (not all of them can)


def default_views(surface, size=256, count=VIEW_COUNT, fov_deg=VIEW_FOV):
    """`count` square cameras evenly around the mesh's bounding sphere, framing all of it."""
    pts = surface.vertices[np.isfinite(surface.vertices).all(axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = (lo + hi) / 2
    radius = max(float(np.linalg.norm(pts - center, axis=1).max()), 1e-30)
    distance = 1.1 * radius / math.sin(math.radians(fov_deg) / 2)
    # A Fibonacci spiral, turned so no view looks straight along a coordinate axis.
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = k * math.pi * (3 - math.sqrt(5)) + 0.4
    ring = np.sqrt(1 - z * z)
    dirs = np.column_stack([ring * np.cos(phi), z * 0.9 + 0.1 * np.sin(phi), ring * np.sin(phi)])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return [Camera.look_at(center + distance * d, center, fov_deg=fov_deg, width=size, height=size,
                           near=max(distance - 1.5 * radius, distance * 1e-6)) for d in dirs]


class _Views:
    """Reference renders of the mesh and the per-face bookkeeping that maps errors back to faces."""

    def __init__(self, surface, cameras, render_mode, solid):
        self.surface, self.cameras, self.mode = surface, cameras, render_mode
        self.refs = map_threads(lambda cam: render_mesh(surface, cam, background=BACKGROUND,
                                                        supersample=SUPERSAMPLE), cameras)
        self.owners = [_dilate_labels(ref.face, 2 * SUPERSAMPLE) for ref in self.refs]
        self.pixel = self._pixel_sizes()
        # Pixels around the silhouettes of solid parts, and the silhouette length there (pixels).
        centre = SUPERSAMPLE // 2
        pixel_owners = [o[centre::SUPERSAMPLE, centre::SUPERSAMPLE] for o in self.owners]
        self.solid = [(o >= 0) & solid[np.maximum(o, 0)] for o in pixel_owners]
        self.outline = sum(_edge_length(ref.alpha, mask) for ref, mask in zip(self.refs, self.solid))

    def _pixel_sizes(self):
        """World size of one pixel at each face in the finest view that sees it."""
        s = self.surface
        center = s.origin + (s.edge1 + s.edge2) / 3
        size = np.full(len(s.faces), np.inf)
        for cam, ref in zip(self.cameras, self.refs):
            seen = np.unique(ref.face[ref.face >= 0])
            depth = cam.to_camera(center[seen])[:, 2]
            px = np.full(len(seen), 1.0 / cam.fx) if cam.is_orthographic else depth / cam.fx
            size[seen] = np.minimum(size[seen], px)
        finite = np.isfinite(size)
        # Faces no view sees keep the coarsest density a seen face could have.
        size[~finite] = size[finite].max() if finite.any() else 1.0
        return size

    def measure(self, cloud):
        """(PSNR of the worst view, per-face squared-error sums, per-face pixel counts, how many
        pixels the silhouettes of solid parts lie outside the mesh's on average, PSNR over all
        views together)."""
        n = len(self.surface.faces)
        err_sum, px_sum, mses = np.zeros(n), np.zeros(n), []
        excess = 0.0
        # Small views: one whole render per core beats sharing each render between the cores.
        results = map_threads(lambda cam: render(cloud, cam, background=BACKGROUND, mode=self.mode, threads=1),
                              self.cameras)
        for result, ref, owner, solid in zip(results, self.refs, self.owners, self.solid):
            excess += float((result.alpha - ref.alpha)[solid].sum())
            err = ((result.color.astype(np.float64) - ref.color) ** 2).mean(axis=2)
            mses.append(err.mean())
            sub = np.repeat(np.repeat(err, SUPERSAMPLE, 0), SUPERSAMPLE, 1) / SUPERSAMPLE**2
            mine = owner >= 0
            err_sum += np.bincount(owner[mine], weights=sub[mine], minlength=n)
            px_sum += np.bincount(owner[mine], minlength=n) / SUPERSAMPLE**2
        dilation = excess / self.outline if self.outline > 0 else 0.0
        return psnr_from_mse(max(mses)), err_sum, px_sum, dilation, psnr_from_mse(np.mean(mses))


def refine_to_target(surface, target, max_splats, views, view_size, render_mode, progress, info, style,
                     uniform=False):
    """Splats whose renders reach `target` dB PSNR against the mesh's (or the best reachable).
    With `uniform`, the density stays spread evenly for `max_splats` and only the silhouettes
    are calibrated for the views. progress(done, total, label) after each round."""
    return drain(refine_rounds(surface, target, max_splats, views, view_size, render_mode, info, style, uniform),
                 progress)


def drain(steps, progress=None):
    """Run a generator of (done, total, label) steps to its end, passing each to `progress`;
    returns the generator's return value."""
    while True:
        try:
            step = next(steps)
        except StopIteration as stop:
            return stop.value
        if progress:
            progress(*step)


def refine_rounds(surface, target, max_splats, views, view_size, render_mode, info, style, uniform=False):
    """refine_to_target one round at a time: a generator yielding (round, MAX_ROUNDS, label) after
    each round and returning the cloud, so a caller can stop between rounds (close() it)."""
    cameras = list(views) if views is not None else default_views(surface, view_size)
    if not cameras:
        raise ValueError("need at least one view")
    outward = surface.outward_signs()
    v = _Views(surface, cameras, render_mode, outward != 0)
    area = surface.area
    cap = np.where(surface.valid, MAX_PER_PIXEL / v.pixel**2, 0.0)
    density = np.where(surface.valid, 1.0 / (START_SPACING * v.pixel) ** 2, 0.0)
    if uniform:
        density = np.where(surface.valid, max_splats / area.sum(), 0.0)
    elif max_splats is not None:
        density = _fit_budget(density, area, max_splats)
    make = lambda dens, inset: build_splats(surface, dens, offset=-inset * v.pixel * outward,
                                            max_splats=max_splats, **style)
    mse_target = 10 ** (-target / 10)
    best, previous, inset = None, None, 0.0
    shifts_left, undo = (INSET_SHIFTS if outward.any() else 0), None
    saturated = np.zeros(len(area), bool)
    for round_ in range(MAX_ROUNDS):
        cloud = make(density, inset)
        psnr, err, px, dilation, overall = v.measure(cloud)
        if best is None or psnr > best[0]:
            best = (psnr, cloud, inset, overall)
        yield round_ + 1, MAX_ROUNDS, f"mesh2splats: {len(cloud)} splats, {psnr:.1f} dB"
        if psnr >= target:
            if previous is not None:
                best = _trim(v, make, previous[2], density, inset, target, best)
            break
        # Calibrate the silhouette shift first: while it is off, silhouette errors would be
        # blamed on the faces there, so the density waits for it. (Driving the dilation all the
        # way to zero overshoots: a slightly soft edge outside the mesh's costs less than one
        # inside it; INSET_AIM was the best on views the calibration did not see.)
        if shifts_left:
            if undo is not None and psnr < undo[0]:          # the last shift made things worse
                inset, shifts_left, undo = undo[1], 0, None
                continue
            undo = None
            if abs(dilation - INSET_AIM) > INSET_TOLERANCE:
                undo, inset = (psnr, inset), max(inset + dilation - INSET_AIM, 0.0)
                shifts_left -= 1
                continue
        if uniform:
            break
        local = _smoothed_error_density(surface, err, px)
        if previous is not None:
            grew, before, _ = previous
            saturated |= grew & (local > 0.8 * before)
        grow = np.clip(local / (AIM * mse_target), 1.0, MAX_GROWTH)
        grow[saturated] = 1.0
        new = _grade(surface, np.minimum(density * grow, cap))
        if max_splats is not None:
            new = _fit_budget(new, area, max_splats)
        if np.allclose(new, density, rtol=1e-3):
            break
        previous = (new > density * 1.01, local, density)
        density = new
    psnr, cloud, inset, overall = best
    yield MAX_ROUNDS, MAX_ROUNDS, f"mesh2splats: {len(cloud)} splats, {psnr:.1f} dB"
    if isinstance(info, dict):
        info.update(psnr=psnr, psnr_all_views=overall, inset_pixels=inset, views=len(cameras))
        if not uniform:
            info.update(target_psnr=target, reached=psnr >= target)
    return cloud


def _trim(v, make, low, high, inset, target, best, steps=2):
    """Bisect (geometrically, per face) between a density that missed the target and one that
    reached it, keeping the smallest cloud that still reaches it."""
    for _ in range(steps):
        mid = np.sqrt(low * high)
        cloud = make(mid, inset)
        measured = v.measure(cloud)
        if measured[0] >= target:
            best, high = (measured[0], cloud, inset, measured[4]), mid
        else:
            low = mid
    return best


def _fit_budget(density, area, max_splats):
    total = (density * area).sum()
    return density * (max_splats / total) if total > max_splats else density


def _smoothed_error_density(surface, err, px):
    """Squared error per pixel around each face: sums over the faces sharing its vertices."""
    n_vertices = len(surface.vertices)
    flat = surface.faces.ravel()
    e_v = np.bincount(flat, weights=np.repeat(err, 3), minlength=n_vertices)
    p_v = np.bincount(flat, weights=np.repeat(px, 3), minlength=n_vertices)
    e_f, p_f = e_v[surface.faces].sum(axis=1), p_v[surface.faces].sum(axis=1)
    return np.where(p_f > 0, e_f / np.maximum(p_f, 1e-12), 0.0)


def _grade(surface, density, ratio=4.0):
    """Keep neighbouring densities within `ratio`, so big splats do not spill over fine regions."""
    vmax = np.zeros(len(surface.vertices))
    np.maximum.at(vmax, surface.faces.ravel(), np.repeat(density, 3))
    neighbour = vmax[surface.faces].max(axis=1)
    return np.where(surface.valid, np.maximum(density, neighbour / ratio), 0.0)


def _edge_length(alpha, mask):
    """Length in pixels of the coverage edges of `alpha` inside `mask` (sum of gradient norms)."""
    a = np.asarray(alpha, np.float64)
    gx = np.zeros_like(a)
    gy = np.zeros_like(a)
    gx[:, :-1] = a[:, 1:] - a[:, :-1]
    gy[:-1] = a[1:] - a[:-1]
    return float(np.hypot(gx, gy)[mask].sum())


def _dilate_labels(labels, steps):
    """Give background (-1) samples the label of a labelled neighbour, up to `steps` samples away."""
    out = labels.copy()
    for _ in range(steps):
        empty = out < 0
        if not empty.any():
            break
        grown = out.copy()
        for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
            moved = np.roll(out, shift, axis=axis)
            edge = [slice(None)] * 2
            edge[axis] = 0 if shift == 1 else -1
            moved[tuple(edge)] = -1
            take = (grown < 0) & (moved >= 0)
            grown[take] = moved[take]
        out = grown
    return out
