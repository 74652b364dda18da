"""Sizing for mesh_to_splats from renders: spend splats where the render error says they are needed.

The mesh is rendered once from the views (the user's cameras, or by default four around it at each
of 0.5, 1 and 3 times the distance that frames it) by the reference rasteriser (core.mesh_render,
black background, Cycles' default pixel filter: a box filter's sharper outlines are 34-36 dB from
Cycles' own on the bench's bunny and hand, so refinement chased edges no user sees). A face's pixel
is that of the finest view whose frustum holds it, seen there or not, so that views from other
directions at the same distances are served as well as these; made for antialiased rendering with
the default views, that of the nearest view from anywhere at their nearest distance (antialiased
outlines are as sharp as the finest pixel that sees them).
Target mode then starts coarse (one splat per START_SPACING^2 pixels of each face) and repeats:
build splats, render them with core.render from the same views, compare, attribute every pixel's
squared error to the face seen there (background pixels to the nearest face), and multiply the
density of faces whose local error is above the target by how far above it they are (at most
MAX_GROWTH a round and MAX_PER_PIXEL splats per pixel), until the worst of the views reaches the
target. A face that got denser without its error dropping is left alone until the silhouettes are
calibrated again: more splats cannot fix what the renderer's low-pass filter blurs. After
PATIENCE rounds in a row that rendered no better than the best so far (each with its shift
searched again), refinement stops: the splats stacked edge-on along denser outlines fatten them
more than the extra splats gain. The round that reaches the target is kept as it is: its overshoot is
the margin that views it never rendered need (trimmed back to the target on its own views, Suzanne's
held-out close-ups fell 1.4 dB, below it). When not reached, the result says which view is worst and
why.

Silhouettes: an opaque surface of Gaussians renders about one pixel fatter than the mesh, because
the renderer's 0.3 px^2 low-pass spreads every splat seen edge-on and many such splats stack along
a silhouette. Solid parts are therefore moved inwards along the normal by the shift (in pixels of
each face's finest view) that maximises the worst view's PSNR, found by golden-section search and
searched again whenever the cloud has doubled or a round rendered worse, short of the target
(smaller splats want another shift; without this, refinement stalled with more splats rendering
worse). Splats of one density are built once: a search moves only their positions, and compares
them on the views worst so far (a third of them, at least four, and any its best shows worse),
rendering only the best from the others. A budget (uniform mode) also tries the smaller counts of one
ladder shared by all budgets (2000, 4000, 8000, ...: budget_ladder) and keeps what renders best: the
fattening grows with the splats stacked, so a larger budget could otherwise look worse than a
smaller one (the torus: 38.4 / 38.7 / 37.8 dB at 10k / 30k / 100k on held-out views). Wider, fainter
discs standing for fewer splats were tried first and did worse than fewer splats: a scene needs no
splats that render it worse.
"""

import math
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .memory import human_bytes
from .mesh_render import CYCLES_FILTER_WIDTH, DEFAULT_PIXEL_FILTER, render_mesh
from .mesh_sampling import WALL_BOOST, WALL_INSET, budget_density, thin_wall_density, unplaced_splats
from .mesh_texture import face_detail
from .metrics import psnr_from_mse
from .parallel import map_threads
from .render import Shapes, render

VIEW_DISTANCES = (0.5, 1.0, 3.0)  # default view distances, multiples of the one that frames the mesh
VIEWS_PER_DISTANCE = 4
VIEW_FOV = 40.0
SUPERSAMPLE = 3
PIXEL_FILTER = (DEFAULT_PIXEL_FILTER, CYCLES_FILTER_WIDTH)  # the reference's (kind, width): Cycles' default
BACKGROUND = (0.0, 0.0, 0.0)
START_SPACING = 8.0  # pixels of the finest view between splats at the start
MAX_PER_PIXEL = 2.0  # density cap, splats per pixel of the finest view
MAX_ROUNDS = 12
MAX_GROWTH = 2.5
INSET_SEARCH = 6  # evaluations of the golden-section search for the silhouette shift
SEARCH_SHARE = 1 / 3  # ... which compares shifts on this share of the views, the worst ones,
SEARCH_VIEWS = 4  # ... and at least this many (all, when there are no more)
RECALIBRATE_GROWTH = 2.0  # search the shift again once the cloud has grown this much (or got worse)
PATIENCE = 1  # stop after this many rounds in a row that rendered no better than the best
# (on the bench's meshes a second never did, and cost the cup 20 s)
MIN_GROWTH = 0.05  # stop once a round would add fewer splats than this fraction (below the cap)
# The knee of a mesh's PSNR-against-splats curve: from it on, a doubling of the splats buys less than
# this at the worst view. A round that buys less (per doubling, over the best so far) stops refinement
# and the best so far is kept: the striped cup's rounds went 254k splats 29.4 dB, 419k 29.6, 573k 30.0,
# so it keeps 254k where it kept 573k. The bench finds the knees of its curves with the same number.
# 0.6, not 0.5: the 30k-triangle checker sphere's rounds went 286k splats 34.4 dB, 539k 34.9 (0.55 dB
# a doubling), and at held-out views the 286k held as well (36.5 dB at 1x both, 42.2 against 39.8 at 3x).
KNEE_GAIN_DB = 0.6
# ... once the best round has this many splats: below, a round can plateau and the next climb out
# again (the alpha-cut leaves' 96-px test stopped at 564 splats and 19 dB, where 42k gave 26), and
# the bench's curves start here.
KNEE_FROM_SPLATS = 8000
FIT_CHECK_EVERY = 4  # the colour fit leaves out every 4th view (3, 7, 11: one per default distance) to check it
STUCK = 0.8  # a face that got denser with its error above this fraction of the last is left alone
# ... above this one where it has colour detail (core.mesh_texture.face_detail): the decal box took 722k
# splats at 0.97, 307k at 0.9, for the same worst held-out distance (28.6 dB; its 3x views 30.5 -> 35.8)
DETAIL_STUCK = 0.9
AIM = 0.7  # faces aim at this fraction of the target MSE (not all of them can)
MIN_BUDGET_SPLATS = 2000  # a budget also tries this many splats, twice as many, ... (budget_ladder)
RUNG_GAP = 1.25  # ... up to a rung this much below the budget
EDGE_BAND = 2  # pixels either side of a silhouette that count as silhouette error
# A conversion's peak memory, modelled from tracemalloc peaks on the bench's textured cylinder
# (bench/mesh2splats.py, memory rows): about 500-650 bytes per splat (the placed and unplaced splats,
# the best cloud so far, a render's projections) and 480 per pixel of the views (the mesh's
# supersampled reference renders); each is doubled here for what tracemalloc cannot see (numba's own
# buffers, the allocator's slack), so a prediction errs on the safe side.
BYTES_PER_SPLAT = 1280
BYTES_PER_VIEW_PIXEL = 1024
BYTES_PER_FACE = 1024
BASE_BYTES = 48 << 20


def default_views(surface, size=256, count=VIEWS_PER_DISTANCE, fov_deg=VIEW_FOV, distances=VIEW_DISTANCES):
    """`count` square cameras at each of `distances` around the mesh's bounding sphere.

    A distance of 1 frames the whole mesh (its bounding sphere fills the field of view with 10%
    to spare); 0.5 is a close-up, 3 a distant view. The directions of all views together follow
    one Fibonacci spiral, dealt out in turn to the distances, so every distance sees the mesh
    from all around and no two views look along the same line."""
    distances = [float(d) for d in distances]
    if not distances or min(distances) <= 0 or not all(math.isfinite(d) for d in distances):
        raise ValueError(f"view distances must be positive numbers, got {distances}")
    if int(count) < 1:
        raise ValueError(f"need at least one view per distance, got {count}")
    center, radius = _bounding_sphere(surface)
    framing = 1.1 * radius / math.sin(math.radians(fov_deg) / 2)
    total = int(count) * len(distances)
    # A Fibonacci spiral, turned so no view looks straight along a coordinate axis.
    k = np.arange(total) + 0.5
    z = 1 - 2 * k / total
    phi = k * math.pi * (3 - math.sqrt(5)) + 0.4
    ring = np.sqrt(1 - z * z)
    dirs = np.column_stack([ring * np.cos(phi), z * 0.9 + 0.1 * np.sin(phi), ring * np.sin(phi)])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    views = []
    for i, d in enumerate(dirs):
        distance = framing * distances[i % len(distances)]
        views.append(
            Camera.look_at(
                center + distance * d,
                center,
                fov_deg=fov_deg,
                width=size,
                height=size,
                near=max(distance - 1.5 * radius, distance * 1e-3),
            )
        )
    return views


def _bounding_sphere(surface):
    """(centre, radius): the centre of the finite vertices' box, which the default views look at,
    and the largest distance of a vertex from it."""
    pts = surface.vertices[np.isfinite(surface.vertices).all(axis=1)]
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    return centre, max(float(np.linalg.norm(pts - centre, axis=1).max()), 1e-30)


def _pixel_all_around(surface, cameras):
    """World size of one pixel at each face in the closest view that views around the mesh stand
    for: a camera at the smallest of their distances from its centre, from any direction."""
    centre, _ = _bounding_sphere(surface)
    nearest = min(float(np.linalg.norm(cam.center - centre)) for cam in cameras)
    depth = nearest - np.linalg.norm(surface.centroids - centre, axis=1)
    return np.array([np.maximum(depth, cam.near) / cam.fx for cam in cameras]).min(axis=0)


@dataclass
class Measured:
    """One comparison of a cloud with the mesh over all views."""

    psnr: float  # of the worst view
    err: np.ndarray  # per-face squared-error sums
    px: np.ndarray  # per-face pixel counts
    dilation: float  # pixels the silhouettes of solid parts lie outside the mesh's, on average
    overall: float  # PSNR over all views together
    views: list  # PSNR per view
    edge_share: list  # per view, the fraction of its squared error within EDGE_BAND of a silhouette

    @property
    def worst(self):
        return int(np.argmin(self.views))


class _Views:
    """Reference renders of the mesh and the per-face bookkeeping that maps errors back to faces."""

    def __init__(self, surface, cameras, render_mode, solid, pixel_filter=PIXEL_FILTER):
        self.surface, self.cameras, self.mode = surface, cameras, render_mode
        kind, width = pixel_filter

        def reference(cam):
            ref = render_mesh(
                surface, cam, background=BACKGROUND, supersample=SUPERSAMPLE, pixel_filter=kind, filter_width=width
            )
            owner = _dilate_labels(ref.face, 2 * SUPERSAMPLE)
            return ref, owner, _face_shares(owner, len(surface.faces))

        self.refs, self.owners, self.shares = (list(x) for x in zip(*map_threads(reference, cameras)))
        self._shapes = []
        self.face_pixels = sum(
            np.bincount(face, weights=share, minlength=len(surface.faces)) for _, face, share in self.shares
        )
        self.pixel = self._pixel_sizes()
        # Pixels around the silhouettes of solid parts, and the silhouette length there (pixels).
        centre = SUPERSAMPLE // 2
        pixel_owners = [o[centre::SUPERSAMPLE, centre::SUPERSAMPLE] for o in self.owners]
        self.solid = [(o >= 0) & solid[np.maximum(o, 0)] for o in pixel_owners]
        self.outline = sum(_edge_length(ref.alpha, mask) for ref, mask in zip(self.refs, self.solid))
        self.edges = [_edge_band(ref.alpha, EDGE_BAND) for ref in self.refs]

    def _pixel_sizes(self):
        """World size of one pixel at each face in the finest view whose frustum holds it, whether
        that view sees the face or not: a view from elsewhere at the same distance may see it as
        close, so sizes (densities, silhouette shifts) in these pixels carry over to such views."""
        s = self.surface
        center = s.centroids
        size = np.full(len(s.faces), np.inf)
        for cam, ref in zip(self.cameras, self.refs):
            xy, depth = cam.project(center)
            framed = (depth > 0) & (xy >= 0).all(axis=1) & (xy[:, 0] <= cam.width) & (xy[:, 1] <= cam.height)
            framed[ref.face[ref.face >= 0]] = True  # seen, if only in part
            px = np.full(len(center), 1.0 / cam.fx) if cam.is_orthographic else np.maximum(depth, cam.near) / cam.fx
            size = np.where(framed, np.minimum(size, px), size)
        finite = np.isfinite(size)
        # Faces no view frames keep the coarsest density a framed face could have.
        size[~finite] = size[finite].max() if finite.any() else 1.0
        return size

    def _renders(self, cloud, which):
        """{view: (alpha, per-pixel squared error against the mesh's, channels averaged)} of `cloud`
        from the views `which` (indices). Small views: one whole render per core beats sharing each
        render between the cores."""
        shapes = self._shapes_of(cloud)

        def one(i):
            result = render(cloud, self.cameras[i], background=BACKGROUND, mode=self.mode, threads=1, shapes=shapes)
            return result.alpha, ((result.color.astype(np.float64) - self.refs[i].color) ** 2).mean(axis=2)

        return dict(zip(which, map_threads(one, which)))

    def _shapes_of(self, cloud):
        """core.render's Shapes of `cloud`, kept for the next renders: the clouds of one density,
        whatever their shift, share them (a search's, a round's measure and the next search's)."""
        shapes = next((s for s in self._shapes if s.fits(cloud)), None) or Shapes(cloud)
        self._shapes = [shapes] + [s for s in self._shapes if s is not shapes][:1]
        return shapes

    def psnr_of(self, cloud, which, keep=None):
        """{view: PSNR} of the views `which` (indices); their renders go into the dict `keep`, if
        given, for a measure of the same cloud to take."""
        renders = self._renders(cloud, which)
        if keep is not None:
            keep.update(renders)
        return {i: psnr_from_mse(err.mean()) for i, (_, err) in renders.items()}

    def search_views(self, m):
        """The views a shift search compares on: the worst SEARCH_SHARE of them in `m` (at least
        SEARCH_VIEWS)."""
        count = min(len(self.cameras), max(SEARCH_VIEWS, math.ceil(SEARCH_SHARE * len(self.cameras))))
        return [int(i) for i in np.argsort(m.views, kind="stable")[:count]]

    def measure(self, cloud, rendered=None):
        """A Measured of `cloud` from every view; `rendered` ({view: (alpha, error)}, as psnr_of
        keeps them) holds views of this very cloud rendered before."""
        n = len(self.surface.faces)
        err_sum, mses, shares = np.zeros(n), [], []
        excess = 0.0
        renders = dict(rendered or {})
        renders.update(self._renders(cloud, [i for i in range(len(self.cameras)) if i not in renders]))
        for i, (ref, (pixel, face, share), solid, edge) in enumerate(
            zip(self.refs, self.shares, self.solid, self.edges)
        ):
            alpha, err = renders[i]
            excess += float((alpha - ref.alpha)[solid].sum())
            mses.append(err.mean())
            shares.append(float(err[edge].sum() / max(err.sum(), 1e-300)))
            err_sum += np.bincount(face, weights=err.ravel()[pixel] * share, minlength=n)
        dilation = excess / self.outline if self.outline > 0 else 0.0
        return Measured(
            psnr_from_mse(max(mses)),
            err_sum,
            self.face_pixels,
            dilation,
            psnr_from_mse(np.mean(mses)),
            [psnr_from_mse(m) for m in mses],
            shares,
        )


class _Inset:
    """The silhouette shift (pixels of the finest view along the inward normal of solid parts)
    that maximises the worst view's PSNR for a density, found by golden-section search.

    An opaque surface of flat Gaussians renders its silhouette fat by a fixed number of pixels
    (the renderer's 0.3 px^2 low-pass, summed over the splats seen edge-on; more splats stack
    more), so the best shift in world units grows with the pixel size and the splat count: views
    at several distances each want their own, and the search finds the best compromise."""

    def __init__(self, views, make):
        self.views, self.make = views, make

    def search(self, density, lo, hi, basis, evaluations=INSET_SEARCH, known=None):
        """(inset, cloud, Measured) of the best shift in [lo, hi], or `known` (an (inset, cloud,
        Measured) measured before for this density) if none renders better.

        Shifts are compared on the views that `basis` (a Measured of this density) found worst
        (search_views), where the worst view's gains and losses show, and only the best is
        measured on all (its compared views' renders kept, not rendered again). Where that shows
        another view worse than the compared ones (a shift that mends the far views' outlines can
        spoil the close-ups'), the views worse than them join and the search runs again on the
        renders it has. Every default conversion on the bench picks the shifts all views pick, the
        hand's searches with a third of the renders; before views could join, the sphere took
        another shift, and the classic 20k budget of Suzanne at 128 px shifted its far views'
        outlines in and its close-ups fell from 28.1 to 24.6 dB."""
        views, every = set(self.views.search_views(basis)), set(range(len(self.views.cameras)))
        tried = {}  # shift -> [cloud, {view: PSNR}, Measured or None]
        if known is not None:
            tried[known[0]] = [known[1], dict(enumerate(known[2].views)), known[2]]
        kept = [None, {}]  # the best shift so far and its renders, which its measure takes

        def measured(x):
            if tried[x][2] is None:
                tried[x][2] = self.views.measure(tried[x][0], kept[1] if kept[0] == x else None)
                tried[x][1].update(enumerate(tried[x][2].views))
            return tried[x][2]

        def so_far(x):
            return min(tried[x][1].get(i, math.inf) for i in views)

        def worst(x):
            if x not in tried:
                tried[x] = [self.make(density, x), {}, None]
            psnrs = tried[x][1]
            if views == every and not psnrs:  # all views from the start: one measure each
                measured(x)
            missing = sorted(views - psnrs.keys())
            if missing:
                renders = {}
                psnrs.update(self.views.psnr_of(tried[x][0], missing, renders))
                if kept[0] == x:
                    kept[1].update(renders)
                elif kept[0] is None or so_far(x) > so_far(kept[0]):
                    kept[:] = [x, renders]
            return min(psnrs[i] for i in views)

        while True:
            self._golden(worst, lo, hi, evaluations)
            best = max(tried, key=worst)
            m = measured(best)
            worse = {i for i, p in enumerate(m.views) if p < worst(best)} - views
            if not worse:
                return best, tried[best][0], m
            views |= worse

    @staticmethod
    def _golden(worst, lo, hi, evaluations):
        """Evaluate worst(x) along a golden-section search for the x in [lo, hi] with the largest
        worst(x), `evaluations` times (worst keeps what it rendered)."""
        ratio = (math.sqrt(5) - 1) / 2
        a, b = lo, hi
        c, d = b - ratio * (b - a), a + ratio * (b - a)
        for _ in range(max(evaluations - 1, 1)):
            if worst(c) >= worst(d):
                b, d = d, c
                c = b - ratio * (b - a)
            else:
                a, c = c, d
                d = a + ratio * (b - a)


def conversion_bytes(splats, faces, view_pixels):
    """Predicted peak bytes of a conversion holding `splats` splats of a mesh of `faces` faces, measured
    in views of `view_pixels` pixels in all (the model above; bench/mesh2splats.py checks it)."""
    return BASE_BYTES + BYTES_PER_FACE * faces + BYTES_PER_VIEW_PIXEL * view_pixels + BYTES_PER_SPLAT * splats


def splats_within(budget, faces, view_pixels):
    """The most splats a conversion can hold within `budget` bytes; ValueError when its mesh and views
    alone would not fit (nothing could be reached)."""
    fixed = conversion_bytes(0, faces, view_pixels)
    room = (budget - fixed) // BYTES_PER_SPLAT
    if room < MIN_BUDGET_SPLATS:
        raise ValueError(
            f"the memory budget ({human_bytes(budget)}) cannot hold this conversion: its mesh ({faces} faces) "
            f"and views ({view_pixels} pixels) alone take {human_bytes(fixed)}; give a larger memory budget, "
            "or fewer or smaller views"
        )
    return int(room)


def refine_rounds(
    surface,
    target,
    max_splats,
    views,
    view_size,
    render_mode,
    info,
    style,
    uniform=False,
    view_distances=VIEW_DISTANCES,
    view_count=VIEWS_PER_DISTANCE,
    pixel_filter=PIXEL_FILTER,
    try_fewer=True,
    memory_budget=None,
    fit_colours=None,
):
    """Splats whose renders reach `target` dB PSNR against the mesh's (or the best reachable), one
    round at a time: a generator yielding (round, MAX_ROUNDS, label) after the calibration and each
    round and returning the cloud, so a caller can stop between rounds (close() it). With
    `uniform`, the density stays spread evenly for `max_splats` and only the silhouettes are
    calibrated for the views (a budget). With `memory_budget` (bytes) the splats are capped at what
    it holds (splats_within), before anything is allocated for them. `fit_colours(cloud, cameras,
    images, render_mode)`, if given (target mode), refits the best cloud's colours to the mesh's
    renders from the views at the end where the surface has colour detail and the target was not
    reached (_checked_fit: kept only where the views it left out render better too).
    Faces with colour detail (core.mesh_texture.face_detail) count as stuck only when a denser
    round left their error above DETAIL_STUCK of what it was: hard texture edges sharpen a little
    with every doubling, and left alone at STUCK they stayed a few large splats across."""
    cameras = (
        list(views) if views is not None else default_views(surface, view_size, view_count, distances=view_distances)
    )
    if not cameras:
        raise ValueError("need at least one view")
    memory_cap = None
    if memory_budget is not None:
        room = splats_within(memory_budget, len(surface.faces), sum(c.width * c.height for c in cameras))
        if max_splats is None or room < max_splats:
            memory_cap = max_splats = room
    outward = surface.outward_signs()
    v = _Views(surface, cameras, render_mode, outward != 0, pixel_filter)
    pixel = v.pixel
    if views is None and render_mode == "antialiased":
        # Antialiased outlines are as sharp as the finest pixel that sees them, and a view from
        # elsewhere at the nearest distance may come closer to a face than any of these: size for it.
        pixel = np.minimum(pixel, _pixel_all_around(surface, cameras))
    area = surface.area
    density = np.where(surface.valid, 1.0 / (START_SPACING * pixel) ** 2, 0.0)
    if uniform:
        density = np.where(surface.valid, max_splats / area.sum(), 0.0)
    walls, wall = thin_wall_density(surface, density, style["overlap"])  # thin walls need smaller splats
    cap = np.where(surface.valid, MAX_PER_PIXEL / pixel**2, 0.0)
    walls = np.minimum(walls, WALL_BOOST * cap)
    cap = np.maximum(cap, walls)
    density = np.maximum(density, walls)
    even = lambda count: budget_density(np.where(surface.valid, 1.0, 0.0), walls, area, count)
    if uniform:
        density = even(max_splats)
    elif max_splats is not None:
        density = _fit_budget(density, area, max_splats)

    built = []  # recent (density, Unplaced): a shift search rebuilds only the positions

    def make(dens, inset):
        shift = np.minimum(inset * pixel, WALL_INSET * wall)
        for d, unplaced in built:
            if np.array_equal(d, dens):
                return unplaced.placed(-shift * outward)
        unplaced = unplaced_splats(surface, dens, max_splats=max_splats, **style)
        built[:] = [(dens.copy(), unplaced)] + built[:1]
        return unplaced.placed(-shift * outward)

    inset_search = _Inset(v, make)
    mse_target = 10 ** (-target / 10)
    best, previous, rounds, stale = None, None, 0, 0
    saturated = np.zeros(len(area), bool)
    # How much a denser face's error must fall to be refined again: colour detail (texture edges,
    # lines, colour seams) sharpens a little with every doubling, an outline soon not at all (the
    # grid plane's faces at its centre stopped at 5 splats each, their lines blurred, at STUCK).
    detail = face_detail(surface) if style.get("texture_aware", True) else np.zeros(len(area), bool)
    stuck = np.where(detail, DETAIL_STUCK, STUCK)
    stop = "no more splats help"
    if uniform:  # a budget: calibrated, no rounds
        fewest = MIN_BUDGET_SPLATS if try_fewer else max_splats
        inset, cloud, m = yield from _calibrate_budget(v, make, even, outward.any(), max_splats, fewest)
        best, rounds = (m.psnr, cloud, inset, m), 1
    else:
        inset, cloud, m = _calibrate_inset(v, make, density, outward.any())
        yield 0, MAX_ROUNDS, f"mesh2splats: silhouettes calibrated, {m.psnr:.1f} dB"
    calibrated_at = len(cloud)
    for round_ in range(0 if uniform else MAX_ROUNDS):
        rounds = round_ + 1
        if round_:
            cloud = make(density, inset)
            m = v.measure(cloud)
            grown = len(cloud) > RECALIBRATE_GROWTH * calibrated_at
            if outward.any() and m.psnr < target and (grown or m.psnr < best[0]):
                # Smaller splats want another shift (and more stack along the silhouettes): search
                # it again, below the last one as well. (With the last shift as the search's first
                # point, a render fewer, the hand kept 460k splats, not 600k, and fell 0.6 dB at 1x.)
                # A round reaching the target is kept as it is (the bunny's search found nothing
                # better there, in a fifth of its conversion time).
                inset, cloud, m = inset_search.search(density, 0.0, 1.5 * inset + 0.5, m, 3, (inset, cloud, m))
                calibrated_at, saturated[:] = len(cloud), False
        knee = bool(round_) and m.psnr < target and _past_knee(m.psnr, len(cloud), best)
        stale = 0 if best is None or m.psnr > best[0] else stale + 1
        if not (stale or knee):
            best = (m.psnr, cloud, inset, m)
        yield round_ + 1, MAX_ROUNDS, f"mesh2splats: {len(cloud)} splats, {m.psnr:.1f} dB"
        if knee:
            stop = "knee"
            break
        if m.psnr >= target:
            stop = "reached"
            break
        at_cap = max_splats is not None and (density * area).sum() >= 0.999 * max_splats
        if stale >= PATIENCE:
            # Denser clouds kept rendering worse, each with its shift searched again: more splats
            # no longer help (their stacked edge-on splats fatten the outlines more).
            stop = "max_splats" if at_cap else "no more splats help"
            break
        local = _smoothed_error_density(surface, m.err, m.px)
        if previous is not None:
            grew, before = previous
            saturated |= grew & (local > stuck * before)
        grow = np.clip(local / (AIM * mse_target), 1.0, MAX_GROWTH)
        grow[saturated] = 1.0
        new = np.maximum(_grade(surface, np.minimum(density * grow, cap)), walls)
        if max_splats is not None:
            new = _fit_budget(new, area, max_splats)
        # A round adding a few per cent more splats changes a few per cent of the surface (bench
        # meshes: at most 0.4 dB at one distance) for the largest renders of the conversion. At
        # the cap, rounds move splats to where the error is instead.
        grew_little = (new * area).sum() < (1 + MIN_GROWTH) * (density * area).sum()
        if np.allclose(new, density, rtol=1e-3) or (grew_little and not at_cap):
            stop = "max_splats" if at_cap else "no more splats help"
            break
        previous = (new > density * 1.01, local)
        density = new
    else:
        if not uniform:
            at_cap = max_splats is not None and (density * area).sum() >= 0.999 * max_splats
            stop = "max_splats" if at_cap else "rounds"
    if stop == "max_splats" and memory_cap is not None:
        stop = "memory"
    psnr, cloud, inset, m = best
    # A reached target is kept as it is (the fit held the bench's duck and hand within 0.5 dB at held-out
    # views, for 2-4x the time); one that is not reached tries the fit.
    if (
        fit_colours is not None
        and not uniform
        and psnr < target
        and detail.any()
        and len(cameras) >= 2 * FIT_CHECK_EVERY
    ):
        fitted = _checked_fit(v, cloud, fit_colours)
        if fitted is not None:
            fitted_m = v.measure(fitted)
            if fitted_m.psnr > psnr:
                psnr, cloud, m = fitted_m.psnr, fitted, fitted_m
    yield MAX_ROUNDS, MAX_ROUNDS, f"mesh2splats: {len(cloud)} splats, {psnr:.1f} dB"
    if isinstance(info, dict):
        worst = m.worst
        distance = view_distances[worst % len(view_distances)] if views is None else None
        info.update(
            psnr=psnr,
            psnr_all_views=m.overall,
            psnr_views=list(m.views),
            worst_view=worst,
            worst_view_distance=distance,
            worst_view_edge_share=m.edge_share[worst],
            inset_pixels=inset,
            views=len(cameras),
            rounds=rounds,
        )
        if memory_budget is not None:  # the cap is reported only where it bound
            info.update(memory_budget=memory_budget, memory_cap=memory_cap if uniform or stop == "memory" else None)
        if uniform:
            info.update(budget=max_splats)
        if not uniform:
            reached = psnr >= target
            cause = _why(m, stop, max_splats, render_mode, memory_budget)
            info.update(target_psnr=target, reached=reached, limit=None if reached else cause)
    return cloud


def _past_knee(psnr, splats, best):
    """Whether a round of `splats` rendering `psnr` buys less than KNEE_GAIN_DB per doubling of the
    splats over `best` (psnr, cloud, ...), the best round so far, of at least KNEE_FROM_SPLATS. A
    round with fewer splats (the shift search may keep a smaller cloud) is never past it."""
    doublings = math.log2(splats / max(len(best[1]), 1))
    return len(best[1]) >= KNEE_FROM_SPLATS and doublings > 0 and psnr - best[0] < KNEE_GAIN_DB * doublings


def _checked_fit(v, cloud, fit_colours):
    """`cloud` with its colours fitted by `fit_colours` to the views of `v` but every
    FIT_CHECK_EVERY-th, or None when those it left out (one at each default distance) render worse
    for it: a fit that does not carry over to views it never saw (the striped cup's close-ups lost
    1.3 to 5 dB held out, their fitted twins gained) is not kept."""
    check = list(range(FIT_CHECK_EVERY - 1, len(v.cameras), FIT_CHECK_EVERY))
    fit = [i for i in range(len(v.cameras)) if i not in check]
    fitted = fit_colours(cloud, [v.cameras[i] for i in fit], [v.refs[i].color for i in fit], v.mode)

    def worst(c):  # the largest mean squared error of the views left out
        return max(err.mean() for _, err in v._renders(c, check).values())

    return fitted if worst(fitted) < worst(cloud) else None


def _calibrate_inset(v, make, density, solid, evaluations=INSET_SEARCH):
    """(inset, cloud, Measured) with the best silhouette shift for this density (0 without solids)."""
    first = v.measure(make(density, 0.0))
    if not solid:
        return 0.0, make(density, 0.0), first
    inset, cloud, m = _Inset(v, make).search(density, 0.0, max(4.0 * first.dilation, 2.0), first, evaluations)
    if first.psnr > m.psnr:
        return 0.0, make(density, 0.0), first
    return inset, cloud, m


def _calibrate_budget(v, make, even, solid, max_splats, fewest=MIN_BUDGET_SPLATS):
    """A generator yielding (done, total, label) after each count it tries and returning (inset,
    cloud, Measured) for a budget spread evenly (`even(count)`, a density): the best of
    max_splats and the rungs of budget_ladder below it (down to `fewest`), each with its
    silhouette shift calibrated (stacked edge-on splats fatten silhouettes more the more there
    are). Each rung costs half the renders of the one above, so all are tried: the worst view's
    PSNR against the count is not smooth, and a budget then renders at least as well as every
    rung below it, which every larger budget tries too."""
    counts = [max_splats] + [rung for rung in budget_ladder(max_splats) if rung >= fewest]
    best = None
    for done, count in enumerate(counts, 1):
        tried = _calibrate_inset(v, make, even(count), solid)
        if best is None or tried[2].psnr > best[2].psnr:
            best = tried
        # The last step is the conversion's end (refine_rounds' MAX_ROUNDS of MAX_ROUNDS).
        yield done, len(counts) + 1, f"mesh2splats: {round(count)} splats, {tried[2].psnr:.1f} dB"
    return best


def budget_ladder(budget):
    """The counts below `budget` that a budget also tries, largest first: MIN_BUDGET_SPLATS times
    powers of two, the same for every budget, so a larger budget tries every rung a smaller one
    did (halving each budget instead, 100k never tried the 30k that rendered the torus best).
    Rungs within RUNG_GAP of the budget are left to the budget itself."""
    rungs = []
    rung = MIN_BUDGET_SPLATS
    while rung * RUNG_GAP <= budget:
        rungs.append(rung)
        rung *= 2
    return rungs[::-1]


def summary(info):
    """One sentence about the quality a conversion reached, from its `info` ("" without views):
    the worst view's PSNR, which view that is and, for a missed target, why; and whether the memory
    budget held the splats back."""
    capped = info.get("memory_cap") is not None and info.get("reached") is not False  # else "limit" says it
    held = (
        f"the memory budget ({human_bytes(info['memory_budget'])}) held it to {info['memory_cap']} splats"
        if capped
        else ""
    )
    if "psnr" not in info:
        return held
    where = f"view {info['worst_view'] + 1} of {info['views']}"
    if info.get("worst_view_distance") is not None:
        where += f", at {info['worst_view_distance']:g}x the framing distance"
    text = f"{info['psnr']:.1f} dB PSNR in the worst view ({where})"
    if info.get("budget") and info.get("splats", info["budget"]) < info["budget"]:
        text += f"; {info['splats']} of the {info['budget']} splats budgeted: more rendered worse"
    if info.get("reached") is False:
        text = f"target {info['target_psnr']:g} dB not reached: {text}; {info['limit']}"
    return f"{text}; {held}" if held else text


def _why(m, stop, max_splats, render_mode="classic", memory_budget=None):
    """Why the worst view missed the target, in words."""
    share = m.edge_share[m.worst]
    if stop == "memory":
        cause = (
            f"the memory budget ({human_bytes(memory_budget)}) holds at most {max_splats} splats, and they were reached"
        )
    elif stop == "max_splats":
        cause = f"the splat cap (max_splats={max_splats}) was reached"
    elif stop == "knee":
        cause = f"more splats bought less than {KNEE_GAIN_DB:g} dB per doubling"
    elif stop == "rounds":
        cause = f"refinement ran out of rounds ({MAX_ROUNDS})"
    else:
        cause = "more splats no longer lowered the error"
    outline = (
        "edge-on splats render outlines about a pixel fat in classic 3DGS rendering; one cloud cannot "
        "match the outline at every distance: antialiased mode can"
        if render_mode == "classic"
        else "a splat's Gaussian edge is softer than the mesh's pixel-filtered one; larger views make it thinner"
    )
    where = (
        f"{share:.0%} of its error lies within {EDGE_BAND} px of the silhouettes ({outline})"
        if share >= 0.5
        else f"{1 - share:.0%} of its error lies inside the surface (texture detail finer than "
        f"the splats, or hard colour edges: splats blend display colours, a mesh's pixels mix linear light)"
    )
    return f"{cause}; {where}"


def _fit_budget(density, area, max_splats):
    total = (density * area).sum()
    return density * (max_splats / total) if total > max_splats else density


def _face_shares(owner, n_faces):
    """(pixel, face, share): each pixel's flat index, a face seen in its SUPERSAMPLE^2 samples of
    `owner` (labels, -1 for none), and the fraction of those samples that face owns; one row per
    pair. A pixel's error goes to its faces in these shares."""
    s = SUPERSAMPLE
    rows, cols = np.indices(owner.shape)
    pixel = (rows // s) * (owner.shape[1] // s) + cols // s
    mine = owner >= 0
    pairs, counts = np.unique(pixel[mine].astype(np.int64) * n_faces + owner[mine], return_counts=True)
    return pairs // n_faces, pairs % n_faces, counts / s**2


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
    """Give background (-1) samples the label of a labelled neighbour, up to `steps` samples away:
    at each step, every background sample next to a labelled one takes the label of the first
    labelled of the samples above, below, left and right of it. Only the samples along the
    labelled region's edge are visited (768 x 768 samples a view, a few thousand of them there)."""
    out = labels.copy()
    h, w = out.shape
    flat = out.ravel()
    empty = out < 0
    edge = np.zeros_like(empty)
    edge[1:] |= ~empty[:-1]
    edge[:-1] |= ~empty[1:]
    edge[:, 1:] |= ~empty[:, :-1]
    edge[:, :-1] |= ~empty[:, 1:]
    frontier = np.flatnonzero(empty & edge)
    for _ in range(steps):
        if not len(frontier):
            break
        row, col = np.divmod(frontier, w)
        around = [
            np.where(inside, frontier + offset, frontier)
            for inside, offset in ((row > 0, -w), (row < h - 1, w), (col > 0, -1), (col < w - 1, 1))
        ]
        label = np.full(len(frontier), -1, out.dtype)
        for neighbour in around:
            source = flat[neighbour]
            take = (label < 0) & (source >= 0)
            label[take] = source[take]
        flat[frontier] = label
        # next: the background samples next to those just labelled
        around = np.concatenate(around)
        frontier = np.unique(around[flat[around] < 0])
    return out


def _edge_band(alpha, width):
    """Pixels within `width` of a coverage edge of `alpha` (where it is neither all 0 nor all 1 nearby)."""
    a = np.asarray(alpha, np.float64)
    lo, hi = a.copy(), a.copy()
    for _ in range(width):
        for axis in (0, 1):
            for shift in (1, -1):
                lo = np.minimum(lo, np.roll(lo, shift, axis=axis))
                hi = np.maximum(hi, np.roll(hi, shift, axis=axis))
    return (hi - lo) > 0.02
