"""Per-splat light visibility from shadow maps: how much of each light reaches each splat.

A shadow map is what the light sees: core.render of the cloud from the light's position (its depth,
the alpha-weighted expected camera z, and its alpha, the coverage), with the depth of occluding
meshes (core.mesh_render.rasterize) folded in, through the light's cameras (core.shadow_cameras:
one for a spot or the sun, a cube's faces for point and area lights; each splat is tested in the
one looking most nearly at it).
The maps draw the splats that may shadow something (the casters section): a floor with nothing
under it is left out. For one picture, only the splats it may show whose seen side faces the light
are tested (`receiving`, `eye`): the others reflect none of the light there.

A splat is tested at its centre: covered by the map's texel where the map is nearer the light than
the splat by more than a bias, partly (by the texel's alpha) where the covering splats are faint.
The bias grows with the splat's own extent along the light ray (its standard deviation there: a
splat's neighbours on the same surface overlap its centre's texel, nearer the light by up to about
that much) and with the depth a map texel spans on a surface tilted to the light.

Soft shadows are percentage-closer filtered, PCSS-like: a blocker search (the mean depth of what
covers the taps of a disc around the splat's texel) sizes the penumbra by similar triangles,
light size x (receiver - blocker) / blocker, and the covered fraction of a disc of taps of that size
is the shadow. The disc has the light's radius for point and spot lights, the angle's tangent for
the sun, and the radius of a disc of the same area for area lights. Where the search finds nothing
in front, the splat is lit.

An area light narrowed by its Spread reaches a point only from within the spread around its axis:
close to the light, where that cone meets less of the panel than its whole, the point is shadowed
as by a sun along the axis whose disc is the spread (the splats ahead of the light casting); far
from it, by the panel's own maps; in between, by a blend of the two (_along_axis).
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from . import jit, material, scratch, shadow_cameras
from . import normals as normal_estimate
from .arrays import Floats
from .camera import Camera
from .lights import Light, spread_terms
from .mesh_render import rasterize
from .normals import TOO_ROUND
from .parallel import WORKERS, Pool, in_chunks, map_threads
from .render import Shapes, render
from .shadow_cameras import unit
from .splats import SplatCloud
from .steps import part_progress

TAPS = 24  # filter taps per splat (a golden-angle spiral over a disc); the blocker search takes half
MAX_SEARCH_TEXELS = 24.0  # the blocker search's radius is capped there
SIGMA_BIAS = 2.5  # standard deviations of a splat along the light ray that count as its own surface
TEXEL_BIAS = 2.5  # texels of depth slope that count as its own surface
# tan of the tilt (about 79 degrees) beyond which the slope bias stops growing. A wall lit at a
# grazing angle from inside an open tube is shadowed by the tube's own wall a few tenths of its radius
# away; at 20 the bias (2.5 texels times the slope) outgrew that gap and the light leaked through
# (the striped cylinder under a point light: 27.2 dB at 0.5x, 28.8 at 5). Against the float64 ray
# reference 5 is the knee: the area light's mean error 0.0096 at 8 to 20, 0.0084 at 5, 0.0117 at 3
# and 0.017 at 2 (acne on faces lit at grazing angles), the other lights unchanged at 3 and above.
MAX_SLOPE = 5.0
CHUNK = 1 << 16  # points per step of the NumPy filter
SOLID_ALPHA = 0.5  # a splat map texel this covered in front of a mesh decides the depth
# An area light's Spread: the reachable disc's radius over the light's, below which its shadows are a
# sun's along its axis and above which its panel's; blended in between (_along_axis)
SPREAD_BLEND = (1.0, 2.0)
# A map's render on T cores ran 0.7 T times as fast as on one (1.4 on two, 512-texel cube faces of
# the relight bench): maps that split evenly enough over the cores are drawn side by side instead
# (_side_by_side; on two cores a point light's three faces 10-14% sooner).
MAP_SPEEDUP = 0.7
MAP_TILE = 16  # the maps' render tiles: a few percent faster than the picture's 8 at 512 texels, the same maps
CASTER_CELL = 8  # texels a side of the cells in which the casters' test looks behind a splat
CASTER_REACH = 24.0  # texels a splat's 3 sigma may span in a map and still be left out of it
# The compiled kernels: each tuple compiles in order, the last one the entry (core.jit.compiled).
SPLAT_AXES = ("_unit_quaternion", "_thinnest")  # the scalar helpers of a splat's axes, compiled first
FILTER_KERNEL = (
    *SPLAT_AXES,
    "_face_one",
    "_texel_one",
    "_plane_one",
    "_pcss_one",
    "_extent_one",
    "_extent_at",
    "_facing_one",
    "_visibility_loop",
)
EXTENT_KERNEL = (*SPLAT_AXES, "_extent_one", "_extent_at", "_extent_loop")
BOXES_KERNEL = ("_face_one", "_texel_one", "_boxes_loop")
CASTERS_KERNEL = (*SPLAT_AXES, "_face_one", "_texel_one", "_shortest_axis", "_casters_loop")


@dataclass
class ShadowView:
    """One camera of a light's shadow map: depth (H,W) float32 camera z of what the light sees
    (inf where nothing), alpha (H,W) float32 its coverage (meshes count as 1)."""

    camera: Camera
    depth: Annotated[np.ndarray, "(H, W)"]
    alpha: Annotated[np.ndarray, "(H, W)"]


def visibility(
    cloud: SplatCloud,
    light,
    *,
    occluders=None,
    resolution: int = 512,
    taps: int = TAPS,
    sigma_bias: float = SIGMA_BIAS,
    texel_bias: float = TEXEL_BIAS,
    soft: bool = True,
    receiver_plane: bool = False,
    blocking: np.ndarray | None = None,
    receiving: np.ndarray | None = None,
    eye: Camera | None = None,
    threads: int | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    shapes: Shapes | None = None,
) -> Annotated[Floats, "(N,)"]:
    """(N,) float32 in [0, 1]: the fraction of `light` reaching each splat's centre (1 lit, 0 in
    shadow), from shadow maps of `resolution` texels a side (per cube face for point and area
    lights) of the cloud and of `occluders` (core.mesh.Surface meshes, or None).

    taps: filter taps per splat; soft=False tests the centre texel only (hard shadows, no search).
    sigma_bias, texel_bias: the self-shadow bias in the splat's standard deviations along the light
    ray and in texels of depth slope. receiver_plane: test each tap of the search and the filter
    against the depth of the splat's own tangent plane there (its material normal; slope capped at
    MAX_SLOPE), so a wide disc of taps on a surface tilted to the light does not find that surface
    in front of the splat (core.ambient's wide suns). blocking: (N,) bool, the splats that may
    shadow (shadow linking; default all: every splat still receives). receiving: (N,) bool, the
    splats whose visibility is wanted (default all; those a picture may show, core.relight): the
    others hold 1, untested, though they still cast. eye: the camera of that picture: of the splats
    with a material normal, those whose seen side (the normal core.shading turns to the eye) faces
    away from the whole light hold 1 too (they reflect none of it). A light with cast_shadow False
    gives all ones. An area light narrowed by its Spread shadows as a sun along its axis close to
    it, as its panel far from it, and as a blend between (_along_axis).
    progress(done, total, "shadows") follows the maps as core.render's progress follows tiles (an
    exception it raises, a cancel, stops the work there). shapes: core.render.Shapes of the cloud,
    when the caller has them (a lit frame makes them once for its maps and its picture)."""
    n = len(cloud)
    if n == 0 or not getattr(light, "cast_shadow", True):
        return np.ones(n, np.float32)
    settings = dict(occluders=occluders, resolution=resolution, taps=taps, sigma_bias=sigma_bias, texel_bias=texel_bias)
    settings.update(soft=soft, receiver_plane=receiver_plane, threads=threads, shapes=shapes)
    settings.update(receiving=None if receiving is None else _mask(receiving, n, "receiving"), eye=eye)
    if light.kind != "area" or spread_terms(light)[0] <= 0.0:
        return _own_maps(cloud, light, blocking=blocking, progress=progress, **settings)
    # an area light's Spread: a sun along its axis, its panel, or a blend of the two (_along_axis)
    height = (cloud.positions - light.position) @ light.direction  # over the light's plane
    along = _along_axis(light, height)
    sun_part, panel_part = bool((along > 0).any()), bool((along < 1).any())
    parts = int(sun_part) + int(panel_part)
    out = np.ones(n, np.float32)
    if sun_part:
        blockers = height > 0.0 if blocking is None else (height > 0.0) & _blocking(blocking, n)  # ahead of it
        sun = Light("sun", direction=light.direction, angle=light.spread)
        step = part_progress(progress, 0, parts)
        out = _own_maps(cloud, sun, blocking=blockers, ahead_of=light.position, progress=step, **settings)
    if panel_part:
        step = part_progress(progress, parts - 1, parts)
        whole = _own_maps(cloud, light, blocking=blocking, progress=step, **settings)
        out = (along * out + (1.0 - along) * whole).astype(np.float32)
    return out


def _blocking(blocking, n):
    """(n,) bool: the splats that may shadow (visibility's `blocking`), checked."""
    return _mask(blocking, n, "blocking")


def _mask(values, n, name):
    """(n,) bool of `values`, one per splat, or ValueError naming `name`."""
    values = np.asarray(values).reshape(-1)
    if values.shape != (n,):
        raise ValueError(f"{name} must be {n} values, one per splat, got {values.shape[0]}")
    return values.astype(bool)


def _along_axis(light, height):
    """(N,) the weight, in [0, 1], of an area light narrowed by its Spread as a sun along its axis
    whose disc is the spread, at points `height` (N,) over the light's plane. A point at height t over
    the light's plane sees the light only within t tan(spread/2) of its foot: where that disc is
    smaller than the light (than R, the radius of the light's area), the light reaches it along the
    axis from within the spread, as a sun's, wherever the panel is (weight 1); where the disc is
    over twice R, the panel sets its shadows from the panel's centre (weight 0); a blend between
    (SPREAD_BLEND). Measured against the float64 ray reference: docs/DESIGN.md."""
    low, high = SPREAD_BLEND
    ratio = np.maximum(height, 0.0) * spread_terms(light)[0] / math.sqrt(light.area / math.pi)
    return np.clip((high - ratio) / (high - low), 0.0, 1.0)


def _own_maps(
    cloud, light, *, occluders, resolution, taps, sigma_bias, texel_bias, soft, receiver_plane, blocking, receiving,
    eye, threads, progress, shapes, ahead_of=None,
):  # fmt: skip
    """visibility() of a light by its own maps (a cube's faces for point and area lights) at the
    splats `receiving` (all where None) that face it from `eye`'s side (_facing); ahead_of as
    shadow_views'."""
    out = scratch.empty(len(cloud), np.float32)
    out.fill(1.0)
    views = shadow_views(
        cloud,
        light,
        occluders=occluders,
        resolution=resolution,
        blocking=blocking,
        threads=threads,
        progress=progress,
        shapes=shapes,
        ahead_of=ahead_of,
    )
    size = _light_size(light)
    kernel = jit.compiled(__name__, FILTER_KERNEL)
    if kernel is not None and len({v.depth.shape for v in views}) == 1:
        settings = (size if soft else 0.0, sigma_bias, texel_bias, float(receiver_plane), *_eye_terms(eye, light))
        discs = (_spiral(_search_taps(taps)), _spiral(taps))
        rows = np.zeros(0, np.int64) if receiving is None else np.flatnonzero(receiving)
        return _visibility_compiled(kernel, cloud, light, views, settings, discs, rows, out)
    sigma, slope = _extent_and_slope(cloud, light)
    points = cloud.positions.astype(np.float64)
    normals = material.normals(cloud) if receiver_plane else None
    face = shadow_cameras.face_of([view.camera for view in views], points)
    if receiving is not None:
        face[~receiving] = -1
    if eye is not None and material.normal_columns(cloud) is not None:
        face[~_facing(cloud, light, eye)] = -1
    for k, view in enumerate(views):
        idx = np.flatnonzero(face == k)
        if len(idx):
            bias = sigma_bias * sigma[idx]
            plane = None if normals is None else normals[idx]
            out[idx] = _filtered(view, points[idx], bias, slope[idx], texel_bias, size, light, taps, soft, plane)
    return out


def shadow_views(
    cloud, light, *, occluders=None, resolution=512, blocking=None, threads=None, progress=None, shapes=None,
    ahead_of=None,
) -> list[ShadowView]:  # fmt: skip
    """The light's shadow-map views (see the module notes); blocking, progress and shapes as
    visibility's. ahead_of: for a sun, a point (3,) of a plane across its direction: the meshes
    shadow only beyond that plane (a Spread's sun part: nothing behind the panel reaches what it
    lights; its splats there are left out by `blocking`)."""
    position = None if light.kind == "sun" else np.asarray(light.position, np.float64)
    if shapes is None or not shapes.fits(cloud):
        shapes = Shapes(cloud, threads)
    reach, gap = shadow_cameras.reach_and_gap(cloud, position, shapes)
    meshes = list(occluders or [])
    cameras = shadow_cameras.light_cameras(light, cloud.positions, reach, gap, meshes, int(resolution))
    masks = shadow_cameras.near_masks(cameras, cloud.positions, reach)
    seen = masks.any(axis=1)
    if len(cameras) > 1 and not seen.all():  # a cube face no splat can reach is left out: no splat is tested there
        seen[np.argmax(seen)] = True  # (one face stays, even for a cloud the light sees none of)
        cameras, masks = [c for c, s in zip(cameras, seen, strict=True) if s], masks[seen]
    casters = _casters(cloud, light, cameras, masks, reach)
    # What the maps need of the splats: their shapes (colour and extras are not drawn, so one black
    # coefficient stands for every splat's: copying out the splats' own would read all their SH).
    # Each map draws its own rows, the casters near it, out of the whole cloud: nothing is copied,
    # and the shapes are made once (or given) for every map and the picture.
    black = scratch.zeros((len(cloud), 1, 3), np.float32)
    bare = SplatCloud(cloud.positions, cloud.rotations, cloud.log_scales, cloud.opacity_logits, black)
    bare.antialiased = cloud.antialiased
    masks &= casters
    if blocking is not None:
        masks &= _blocking(blocking, len(cloud))
    # Maps that split evenly over the cores render side by side, one core each (_side_by_side), and
    # report as each comes in; else one after another on every core, each reporting its tiles. The
    # calling thread reports, and a cancel there stops the maps not yet begun.
    sizes = masks.sum(axis=1)
    side_by_side = _side_by_side(sizes, Pool(threads).threads)
    order = np.argsort(-sizes, kind="stable") if side_by_side else np.arange(len(cameras))

    def draw(k):
        each = None if side_by_side else part_progress(progress, k, len(cameras), "shadows")
        rows, camera = np.flatnonzero(masks[k]), cameras[k]
        beyond = -np.inf if ahead_of is None else float((np.asarray(ahead_of) - camera.center) @ camera.forward)
        return _map_view(bare, camera, rows, meshes, shapes, 1 if side_by_side else threads, each, beyond)

    views: list = [None] * len(cameras)
    if progress is not None:
        progress(0, len(cameras), "shadows")
    with Pool(threads if side_by_side else 1) as maps:
        for done, (k, view) in enumerate(zip(order, maps.imap(draw, order)), 1):
            views[k] = view
            if progress is not None:
                progress(done, len(cameras), "shadows")
    return views


def _side_by_side(sizes, threads):
    """Whether maps drawing `sizes` splats each are drawn sooner side by side, one core each, the
    largest first (each to the first core free), than one after another on all `threads` cores: a
    map's time follows its splats, and split over T cores it runs MAP_SPEEDUP T times as fast."""
    if threads <= 1 or len(sizes) <= 1:
        return False
    loads = np.zeros(threads)
    for size in np.sort(sizes)[::-1]:  # a loop over the maps (at most six)
        loads[np.argmin(loads)] += size
    return bool(loads.max() < sizes.sum() / (MAP_SPEEDUP * threads))


def _map_view(cloud, camera, rows, meshes, shapes, threads, progress, beyond=-np.inf):
    """The ShadowView of `camera`: the splats `rows` of `cloud` (with their `shapes`) and `meshes`
    (their parts at depth `beyond` or farther) drawn as depth (inf where nothing is) and alpha, on
    up to `threads` cores, progress as core.render's."""
    depth = scratch.empty((camera.height, camera.width), np.float32)
    depth.fill(np.inf)
    if len(rows):
        draw = dict(background=None, threads=threads, progress=progress, shapes=shapes, rows=rows)
        result = render(cloud, camera, tile_size=MAP_TILE, **draw)
        alpha = result.alpha
        np.copyto(depth, result.depth, where=alpha > 0)
    else:
        alpha = scratch.zeros((camera.height, camera.width), np.float32)
    for mesh in meshes:
        depth, alpha = _with_mesh(depth, alpha, mesh, camera, beyond)
    return ShadowView(camera, depth, alpha)


# casters --------------------------------------------------------------------------------------------
# A splat shadows only what lies behind it: beyond the plane through its centre across its normal, on
# the side away from the light (a point on the light's side of that plane reaches the whole light
# without crossing it). A floor with nothing under it shadows nothing, yet costs a map as much as any
# splat, and where it is tilted to the light it sits in its own neighbours' blocker search, nearer
# the light than they are. The maps draw the casters only: every splat but those whose neighbourhood
# in the map (the cells within the blocker search's reach) holds nothing behind their plane.


def _casters(cloud, light, cameras, near, reach):
    """(N,) bool: the splats the light's maps (views `cameras`; near, (F, N) near_masks') must
    draw. A splat no map can show is never drawn; kept besides the casters are splats without a
    usable normal, wider than CASTER_REACH texels in the map, or whose plane the light's extent
    straddles. Without material normals (captured splats), a splat's shortest axis stands for its
    normal where it is flat enough to have one (core.normals.too_round)."""
    normals = material.normal_columns(cloud) or (np.zeros(0), np.zeros(0), np.zeros(0))
    grid = (len(cameras), -(-cameras[0].height // CASTER_CELL), -(-cameras[0].width // CASTER_CELL))
    positions = np.ascontiguousarray(cloud.positions, np.float32)
    near = np.ascontiguousarray(near, np.bool_)
    # the cells any tap of a receiver's search can read a splat's texels from, from its centre's cell
    window = math.ceil((MAX_SEARCH_TEXELS + CASTER_REACH) / CASTER_CELL)
    boxes = _dilated(_cell_boxes(positions, near, cameras, grid), window)
    log_scales = np.ascontiguousarray(cloud.log_scales, np.float32)
    light_args = (*_light_source(light), light.kind == "sun")
    kernel = jit.compiled(__name__, CASTERS_KERNEL)
    if kernel is None:
        if not len(normals[0]):
            axes = np.where(normal_estimate.too_round(cloud)[:, None], np.nan, normal_estimate.shortest_axes(cloud))
            normals = tuple(axes.T)
        keep = _casters_numpy(positions, *normals, log_scales, reach, cameras, boxes, *light_args)
    else:
        cams = np.array([_camera_row(camera) for camera in cameras])
        rotations = np.ascontiguousarray(cloud.rotations, np.float32)
        args = (positions, rotations, *normals, log_scales, reach, cams, boxes, *light_args)
        keep = scratch.empty(len(cloud), np.bool_)
        in_chunks(len(cloud), lambda lo, hi: kernel(lo, hi, *args, keep))
    return keep & near.any(axis=0)


def _light_source(light):
    """(source (3,), size): a positional light's centre and the radius of a sphere holding its
    emitting extent (an area light's half diagonal); the sun's direction of travel and the sine of
    its half angle."""
    if light.kind == "sun":
        return unit(light.direction), math.sin(0.5 * float(getattr(light, "angle", 0.0)))
    if light.kind == "area":
        return np.asarray(light.position, np.float64), 0.5 * math.hypot(*light.extent)
    return np.asarray(light.position, np.float64), float(getattr(light, "radius", 0.0))


def _cell_boxes(positions, near, cameras, grid):
    """(F, GY, GX, 6) float64: per view and cell of CASTER_CELL texels, the box (min x, y, z, then
    max x, y, z) of the centres of the splats near it (near (F, N)) that its map shows there; empty
    cells +inf then -inf. One array per thread, merged: the cells are shared."""
    kernel = jit.compiled(__name__, BOXES_KERNEL)
    cams = np.array([_camera_row(camera) for camera in cameras])
    parts = max(1, min(WORKERS, len(positions) // 4096))
    bounds = np.linspace(0, len(positions), parts + 1).astype(np.int64)

    def part(k):
        boxes = _empty_boxes(grid)
        lo, hi = bounds[k], bounds[k + 1]
        if kernel is not None:
            kernel(lo, hi, positions, near, cams, float(CASTER_CELL), boxes)
        else:
            _boxes_numpy(positions[lo:hi], near[:, lo:hi], cameras, boxes)
        return boxes

    boxes = map_threads(part, range(parts))
    lo = np.minimum.reduce([b[..., :3] for b in boxes])
    hi = np.maximum.reduce([b[..., 3:] for b in boxes])
    return np.concatenate([lo, hi], axis=-1)


def _empty_boxes(grid):
    boxes = np.empty((*grid, 6))
    boxes[..., :3], boxes[..., 3:] = np.inf, -np.inf
    return boxes


def _boxes_loop(lo, hi, positions, near, cams, cell, boxes):
    """_cell_boxes for splats lo..hi: each into its cell of every view whose map shows it."""
    views, rows, cols = boxes.shape[0], boxes.shape[1], boxes.shape[2]
    for i in range(lo, hi):
        for f in range(views):
            if not near[f, i]:
                continue
            u, v, _ = _texel_one(positions, i, cams, f)
            if not (u >= 0.0 and v >= 0.0):  # also NaN: behind the camera
                continue
            cx, cy = int(u / cell), int(v / cell)
            if cx >= cols or cy >= rows:
                continue
            for c in range(3):
                boxes[f, cy, cx, c] = min(boxes[f, cy, cx, c], positions[i, c])
                boxes[f, cy, cx, 3 + c] = max(boxes[f, cy, cx, 3 + c], positions[i, c])


def _boxes_numpy(positions, near, cameras, boxes):
    """_boxes_loop's work in NumPy, view by view."""
    points = positions.astype(np.float64)
    for f, camera in enumerate(cameras):  # a loop over views
        uv = camera.project(points)[0]
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            inside = (u >= 0) & (v >= 0) & (u < boxes.shape[2] * CASTER_CELL) & (v < boxes.shape[1] * CASTER_CELL)
        inside &= near[f]
        cell = (v[inside] // CASTER_CELL).astype(np.int64) * boxes.shape[2] + (u[inside] // CASTER_CELL).astype(
            np.int64
        )
        flat = boxes[f].reshape(-1, 6)
        for c in range(3):
            np.minimum.at(flat[:, c], cell, points[inside, c])
            np.maximum.at(flat[:, 3 + c], cell, points[inside, c])


def _dilated(boxes, radius):
    """The boxes of `boxes` (F, GY, GX, 6) grown to the union of their cells within `radius` cells."""
    lo, hi = boxes[..., :3].copy(), boxes[..., 3:].copy()
    for axis in (1, 2):
        lo, hi = _sliding(np.minimum, lo, axis, radius, np.inf), _sliding(np.maximum, hi, axis, radius, -np.inf)
    return np.concatenate([lo, hi], axis=-1)


def _sliding(op, a, axis, radius, empty):
    """op (np.minimum or np.maximum) of `a` over a window of `radius` either way along `axis`."""
    n = a.shape[axis]
    widths = [(0, 0)] * a.ndim
    widths[axis] = (radius, radius)
    padded = np.pad(a, widths, constant_values=empty)
    index = [slice(None)] * a.ndim

    def shifted(step):
        index[axis] = slice(step, step + n)
        return padded[tuple(index)]

    out = shifted(0).copy()
    for step in range(1, 2 * radius + 1):  # a loop over the window's offsets
        op(out, shifted(step), out=out)
    return out


def _casters_loop(lo, hi, positions, rotations, nx, ny, nz, log_scales, reach, cams, boxes, source, size, sun, keep):
    """_casters for splats lo..hi into keep: in its view's cell, whether the dilated box reaches
    behind its plane by more than its own thickness (SIGMA_BIAS of its thinnest sigma) and a texel.
    nx empty: each splat's shortest axis is its normal (_shortest_axis)."""
    rows, cols = boxes.shape[1], boxes.shape[2]
    shaped = nx.shape[0] == 0
    for i in range(lo, hi):
        keep[i] = True
        if shaped:
            n0, n1, n2 = _shortest_axis(
                np.float64(rotations[i, 0]), np.float64(rotations[i, 1]), np.float64(rotations[i, 2]),
                np.float64(rotations[i, 3]),
                np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]), np.float64(log_scales[i, 2]),
            )  # fmt: skip
        else:
            n0, n1, n2 = nx[i], ny[i], nz[i]
        length = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if not (length > 1e-6 and math.isfinite(length)):
            continue
        n0, n1, n2 = n0 / length, n1 / length, n2 / length
        # how far the light is in front of the plane: as a cosine for the sun, else in metres
        if sun:
            side = -(source[0] * n0 + source[1] * n1 + source[2] * n2)
        else:
            p0, p1, p2 = positions[i, 0], positions[i, 1], positions[i, 2]
            side = (source[0] - p0) * n0 + (source[1] - p1) * n1 + (source[2] - p2) * n2
        if not abs(side) > size:
            continue  # the light straddles the plane
        if side > 0.0:  # the normal away from the light
            n0, n1, n2 = -n0, -n1, -n2
        f = _face_one(positions, i, cams)
        if f < 0:
            continue
        u, v, z = _texel_one(positions, i, cams, f)
        if not (u >= 0.0 and v >= 0.0):
            continue
        cx, cy = int(u / CASTER_CELL), int(v / CASTER_CELL)
        texel = (1.0 if cams[f, 16] > 0.5 else z) / cams[f, 12]
        if cx >= cols or cy >= rows or reach[i] > CASTER_REACH * texel:
            continue
        box = boxes[f, cy, cx]  # its far corner is at least as far behind as any centre in it
        behind = max(n0 * box[0], n0 * box[3]) + max(n1 * box[1], n1 * box[4]) + max(n2 * box[2], n2 * box[5])
        behind -= n0 * positions[i, 0] + n1 * positions[i, 1] + n2 * positions[i, 2]
        thinnest = min(min(log_scales[i, 0], log_scales[i, 1]), log_scales[i, 2])
        keep[i] = behind > SIGMA_BIAS * math.exp(np.float64(thinnest)) + texel


def _unit_quaternion(qw, qx, qy, qz):
    """The quaternion (w, x, y, z) normalised; a zero or non-finite one is the identity, as
    geometry.normalize_quaternions."""
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if not (norm > 1e-30 and math.isfinite(norm)):
        return 1.0, 0.0, 0.0, 0.0
    return qw / norm, qx / norm, qy / norm, qz / norm


def _thinnest(ls0, ls1, ls2):
    """The index of a splat's smallest log-scale, the first of equals (as NumPy's argmin)."""
    k = 0
    if ls1 < ls0:
        k = 1
    if ls2 < (ls0 if k == 0 else ls1):
        k = 2
    return k


def _shortest_axis(qw, qx, qy, qz, ls0, ls1, ls2):
    """A splat's shortest axis (its rotation's column of the smallest scale, the first of equals)
    as core.normals.shortest_axes, or NaNs where it is too round to be a normal (the smallest scale
    over the middle one at least TOO_ROUND, or not a number: core.normals.too_round)."""
    qw, qx, qy, qz = _unit_quaternion(qw, qx, qy, qz)
    k = _thinnest(ls0, ls1, ls2)
    middle = min(ls1, ls2) if k == 0 else (min(ls0, ls2) if k == 1 else min(ls0, ls1))
    if not math.exp((ls0 if k == 0 else (ls1 if k == 1 else ls2)) - middle) < TOO_ROUND:
        return math.nan, math.nan, math.nan
    if k == 0:
        return 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy + qw * qz), 2 * (qx * qz - qw * qy)
    if k == 1:
        return 2 * (qx * qy - qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz + qw * qx)
    return 2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx * qx + qy * qy)


def _casters_numpy(positions, nx, ny, nz, log_scales, reach, cameras, boxes, source, size, sun):
    """_casters_loop's test in NumPy, for every splat at once."""
    n = len(positions)
    normals = np.stack([nx, ny, nz], axis=1)
    thin = np.exp(np.min(log_scales, axis=1).astype(np.float64))
    points = positions.astype(np.float64)
    length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = normals / length[:, None]
        side = -(unit @ source) if sun else np.einsum("ij,ij->i", source - points, unit)
        away = np.where((side > 0.0)[:, None], -unit, unit)
    usable = (length > 1e-6) & np.isfinite(length) & (np.abs(side) > size)
    keep = np.ones(n, bool)
    face = shadow_cameras.face_of(cameras, points)
    for f, camera in enumerate(cameras):  # a loop over views
        rows = np.flatnonzero(usable & (face == f))
        uv, z = camera.project(points[rows])
        u, v = uv[:, 0], uv[:, 1]
        texel = (1.0 if camera.is_orthographic else z) / camera.fx
        with np.errstate(invalid="ignore"):
            cx, cy = u // CASTER_CELL, v // CASTER_CELL
            ok = (u >= 0) & (v >= 0) & (cx < boxes.shape[2]) & (cy < boxes.shape[1])
            ok &= ~(reach[rows] > CASTER_REACH * texel)
        rows, cx, cy = rows[ok], cx[ok].astype(np.int64), cy[ok].astype(np.int64)
        box = boxes[f, cy, cx]
        d = away[rows]
        behind = np.maximum(d * box[:, :3], d * box[:, 3:]).sum(axis=1) - np.einsum("ij,ij->i", d, points[rows])
        margin = SIGMA_BIAS * thin[rows] + (texel[ok] if np.ndim(texel) else texel)
        keep[rows] = behind > margin
    return keep


# meshes ---------------------------------------------------------------------------------------------


def _with_mesh(depth, alpha, mesh, camera, beyond=-np.inf):
    """The map with a mesh's depth folded in, of its parts at depth `beyond` or farther: the mesh
    covers fully; where a fairly solid splat surface is in front of it, the splats' depth stays."""
    face, _, mesh_depth = rasterize(mesh, camera, beyond=beyond)
    hit = face >= 0
    splat_first = (alpha >= SOLID_ALPHA) & (depth < mesh_depth)
    depth = np.where(hit & ~splat_first, mesh_depth, depth).astype(np.float32)
    return depth, np.where(hit, np.float32(1.0), alpha)


# the test -------------------------------------------------------------------------------------------


def _light_rays(light, points):
    """(N,3) unit directions from the light towards each point (the sun's own for all), normalised
    as the compiled _extent_loop does (its test holds the two to 1e-12)."""
    if light.kind == "sun":
        return np.broadcast_to(unit(light.direction), points.shape)
    rel = points - np.asarray(light.position, np.float64)
    return rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-300)


def _extent_and_slope(cloud, light):
    """(N,) each splat's standard deviation along its ray from the light, sqrt(l^T Sigma l), and
    (N,) the tan of the angle between its surface normal (the material's, else its thinnest axis)
    and that ray, capped at MAX_SLOPE: how much depth a texel spans across it."""
    kernel = jit.compiled(__name__, EXTENT_KERNEL)
    if kernel is not None:
        return _extent_compiled(kernel, cloud, light)
    points = cloud.positions.astype(np.float64)
    rays = _light_rays(light, points)
    rot = cloud.rotation_matrices()
    local = np.einsum("nji,nj->ni", rot, rays)  # the ray in the splat's axes
    sigma = np.sqrt(np.einsum("ni,ni->n", local * local, cloud.scales**2))
    normal = material.normals(cloud)
    if normal is None:
        cos = np.abs(local[np.arange(len(points)), np.argmin(cloud.log_scales, axis=1)])
    else:
        cos = np.abs(np.einsum("ni,ni->n", normal, rays))
    slope = np.minimum(np.sqrt(np.maximum(1 - cos * cos, 0)) / np.maximum(cos, 1e-9), MAX_SLOPE)
    return sigma, slope


def _extent_compiled(kernel, cloud, light):
    """_extent_and_slope by the compiled kernel, on every core."""
    n = len(cloud)
    sigma, slope = scratch.empty(n), scratch.empty(n)
    args = _extent_args(cloud, light)
    in_chunks(n, lambda lo, hi: kernel(lo, hi, *args, sigma, slope))
    return sigma, slope


def _extent_args(cloud, light):
    """What _extent_one reads of the cloud and the light: positions, rotations and log-scales
    (float32), the normals' columns (empty without), the light's position (the sun's direction)
    and whether it is the sun."""
    normals = material.normal_columns(cloud) or (np.zeros(0), np.zeros(0), np.zeros(0))
    sun = light.kind == "sun"
    source = unit(light.direction) if sun else np.asarray(light.position, np.float64)
    fields = [np.ascontiguousarray(a, np.float32) for a in (cloud.positions, cloud.rotations, cloud.log_scales)]
    return (*fields, *normals, source, sun)


def _extent_loop(lo, hi, positions, rotations, log_scales, nx, ny, nz, source, sun, sigma, slope):
    """_extent_and_slope for splats lo..hi."""
    for i in range(lo, hi):
        sigma[i], slope[i] = _extent_at(positions, rotations, log_scales, nx, ny, nz, source, sun, i)


def _extent_at(positions, rotations, log_scales, nx, ny, nz, source, sun, i):
    """_extent_one of splat i (_extent_args' arrays; nx empty: no normals)."""
    normal = nx.shape[0] > 0
    return _extent_one(
        np.float64(positions[i, 0]), np.float64(positions[i, 1]), np.float64(positions[i, 2]),
        np.float64(rotations[i, 0]), np.float64(rotations[i, 1]), np.float64(rotations[i, 2]),
        np.float64(rotations[i, 3]),
        np.float64(log_scales[i, 0]), np.float64(log_scales[i, 1]), np.float64(log_scales[i, 2]),
        nx[i] if normal else math.nan, ny[i] if normal else 0.0, nz[i] if normal else 0.0,
        source[0], source[1], source[2], sun,
    )  # fmt: skip


def _extent_one(p0, p1, p2, qw, qx, qy, qz, ls0, ls1, ls2, n0, n1, n2, s0, s1, s2, sun):
    """(sigma, slope) of one splat as _extent_and_slope: its centre p, quaternion q (w, x, y, z; a
    zero or non-finite one is the identity, as geometry.normalize_quaternions), log-scales ls and
    normal n (n0 NaN: none, its thinnest axis stands for it), for a light at s (the sun: s its unit
    direction). All scalars: a compiled helper reading the arrays itself cost the shadow test a
    third more."""
    if sun:
        r0, r1, r2 = s0, s1, s2
    else:
        r0, r1, r2 = p0 - s0, p1 - s1, p2 - s2
        length = max(math.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-300)
        r0, r1, r2 = r0 / length, r1 / length, r2 / length
    qw, qx, qy, qz = _unit_quaternion(qw, qx, qy, qz)
    # local = R^T ray, R's columns the splat's axes
    l0 = (1 - 2 * (qy * qy + qz * qz)) * r0 + 2 * (qx * qy + qw * qz) * r1 + 2 * (qx * qz - qw * qy) * r2
    l1 = 2 * (qx * qy - qw * qz) * r0 + (1 - 2 * (qx * qx + qz * qz)) * r1 + 2 * (qy * qz + qw * qx) * r2
    l2 = 2 * (qx * qz + qw * qy) * r0 + 2 * (qy * qz - qw * qx) * r1 + (1 - 2 * (qx * qx + qy * qy)) * r2
    e0, e1, e2 = math.exp(ls0), math.exp(ls1), math.exp(ls2)
    sigma = math.sqrt(l0 * l0 * e0 * e0 + l1 * l1 * e1 * e1 + l2 * l2 * e2 * e2)
    if math.isnan(n0):  # the thinnest axis stands for the normal
        thin = _thinnest(ls0, ls1, ls2)
        cos = abs(l0 if thin == 0 else (l1 if thin == 1 else l2))
    else:
        cos = abs(n0 * r0 + n1 * r1 + n2 * r2)
    return sigma, min(math.sqrt(max(1 - cos * cos, 0.0)) / max(cos, 1e-9), MAX_SLOPE)


def _light_size(light):
    """The radius (m) of the disc standing for the light's emitting area; for the sun the tangent of
    its half angle. 0 is a hard shadow."""
    kind = light.kind
    if kind == "sun":
        return math.tan(0.5 * float(getattr(light, "angle", 0.0)))
    if kind == "area":
        return math.sqrt(light.area / math.pi)
    return float(getattr(light, "radius", 0.0))


def _facing(cloud, light, eye):
    """(N,) bool: the splats whose seen side from the camera `eye` (the material normal turned to
    it, as core.shading's two-sided shading turns it) faces some of the light (its extent,
    _light_source's size: a surface whose plane passes farther behind its centre sees none of it);
    False where a normal is not finite. The cloud must have normals."""
    points = cloud.positions.astype(np.float64)
    normals = material.normals(cloud)
    toward_eye = -eye.forward[None] if eye.is_orthographic else eye.center - points
    seen = np.where(np.einsum("ni,ni->n", normals, toward_eye) < 0.0, -1.0, 1.0)
    toward_light = -unit(light.direction)[None] if light.kind == "sun" else light.position - points
    with np.errstate(invalid="ignore"):
        return seen * np.einsum("ni,ni->n", normals, toward_light) > -_light_source(light)[1]


def _eye_terms(eye, light):
    """_facing's terms as _visibility_loop reads them (for a cloud with normals): 1 (0 without an
    eye: every splat tested), the eye's centre (or the direction to it, orthographic), 1 for
    orthographic, the light's extent (_light_source's size)."""
    if eye is None:
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    ortho = eye.is_orthographic
    return (1.0, *(-eye.forward if ortho else eye.center), float(ortho), _light_source(light)[1])


def _facing_one(positions, nx, ny, nz, source, sun, params, i):
    """_facing of splat i (params[4:10]: _eye_terms; source and sun: _extent_args')."""
    p0, p1, p2 = np.float64(positions[i, 0]), np.float64(positions[i, 1]), np.float64(positions[i, 2])
    if params[8] > 0.5:
        v0, v1, v2 = params[5], params[6], params[7]
    else:
        v0, v1, v2 = params[5] - p0, params[6] - p1, params[7] - p2
    seen = -1.0 if nx[i] * v0 + ny[i] * v1 + nz[i] * v2 < 0.0 else 1.0
    if sun:
        l0, l1, l2 = -source[0], -source[1], -source[2]
    else:
        l0, l1, l2 = source[0] - p0, source[1] - p1, source[2] - p2
    return seen * (nx[i] * l0 + ny[i] * l1 + nz[i] * l2) > -params[9]


def _spiral(taps):
    """(taps, 2) points of a golden-angle spiral filling the unit disc evenly (area per tap equal)."""
    k = np.arange(taps) + 0.5
    r = np.sqrt(k / taps)
    t = k * math.pi * (3 - math.sqrt(5))
    return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)


def _search_taps(taps):
    """The blocker search's taps: half the filter's (a mean depth needs fewer than a coverage)."""
    return max(taps // 2, 1)


def _filtered(view, points, bias, slope, texel_bias, size, light, taps, soft, normals=None):
    """(n,) visibility of points in one view: PCSS search and percentage-closer filtering; with
    `normals` (n,3), each tap against the receiver's tangent plane (_plane_gradient)."""
    cam = view.camera
    uv, z = cam.project(points)
    texel = (z if not cam.is_orthographic else 1.0) / cam.fx  # world size of a texel at the splat
    limit = z - bias - texel_bias * texel * slope
    gradient = None if normals is None else _plane_gradient(cam, normals, z)
    out = np.ones(len(z))
    seen = np.flatnonzero(np.isfinite(uv).all(axis=1))  # not behind a spot light
    uv, z, limit = uv[seen], z[seen], limit[seen]
    gradient = None if gradient is None else gradient[seen]
    if not soft or size <= 0:
        out[seen] = 1.0 - _covered(view, uv, limit, np.zeros((1, 2)), np.zeros(len(z)))[0]
        return out
    disc, search_disc = _spiral(taps), _spiral(_search_taps(taps))
    # Blockers that can shade a receiver lie in the cone from it to the light; its radius in texels,
    # f r (z - zb) / (z zb) (perspective) or f tan (z - zb) (sun), taken at a quarter of the way.
    if cam.is_orthographic:
        search = cam.fx * size * 0.75 * (z - cam.near)
    else:
        search = cam.fx * size * 3.0 / np.maximum(z, 1e-9)
    search = np.clip(search, 1.0, MAX_SEARCH_TEXELS)
    vis = np.empty(len(z))
    for start in range(0, len(z), CHUNK):  # a loop over chunks: (chunk, taps) arrays stay small
        sl = slice(start, start + CHUNK)
        plane = None if gradient is None else gradient[sl]
        blocker = _covered(view, uv[sl], limit[sl], search_disc, search[sl], plane)[1]
        radius = _penumbra(z[sl], blocker, cam.fx * size, cam.is_orthographic)
        covered = _covered(view, uv[sl], limit[sl], disc, radius, plane)[0]
        vis[sl] = np.where(np.isfinite(blocker), 1.0 - covered, 1.0)  # no blocker found: lit
    out[seen] = vis
    return out


def _plane_gradient(camera, normals, z):
    """(n,2) the depth change per texel along u and v of each receiver's tangent plane (normals
    (n,3) in world, z (n,) its camera depth), at most MAX_SLOPE texels' worth; 0 for a plane seen
    edge-on."""
    n = normals @ camera.rotation.T  # in the camera's axes
    facing = np.where(np.abs(n[:, 2]) > 1e-6, n[:, 2], np.inf)
    # the world size of a texel along u and v at the receiver
    texel = (np.ones_like(z) if camera.is_orthographic else z)[:, None] / np.array([camera.fx, camera.fy])
    gradient = -n[:, :2] / facing[:, None] * texel
    size = np.hypot(gradient[:, 0], gradient[:, 1])
    return gradient * np.minimum(1.0, MAX_SLOPE * texel[:, 0] / np.maximum(size, 1e-300))[:, None]


def _penumbra(z, blocker, scale, ortho):
    """The filter's radius in texels for receivers at z and blockers at mean depth `blocker` (inf:
    none, radius 0): scale (z - zb) for the sun, scale (z - zb) / (z zb) in perspective, at least
    half a texel."""
    gap = np.maximum(z - blocker, 0.0)
    radius = scale * gap if ortho else scale * gap / np.maximum(z * blocker, 1e-12)
    return np.where(np.isfinite(blocker), np.maximum(radius, 0.5), 0.0)


def _visibility_compiled(kernel, cloud, light, views, settings, discs, rows, out):
    """visibility()'s test of every splat (the splats `rows` where not empty) in its view
    (shadow_cameras.face_of, _filtered) by one compiled loop on every core: the splat's projection,
    extent, bias, search and filter without (N,) temporaries per view (the extent only where a
    search is made: most splats of a scene lie far from any shadow)."""
    cams = np.array([_camera_row(view.camera) for view in views])
    # each texel's depth and alpha side by side: a tap reads one cache line, not two
    texels = scratch.empty((len(views), *views[0].depth.shape, 2), np.float32)
    for k, view in enumerate(views):
        texels[k, ..., 0], texels[k, ..., 1] = view.depth, view.alpha
    occupied = _occupied_cells(texels[..., 0])
    params = np.array(settings, np.float64)
    args = (rows, *_extent_args(cloud, light), cams, texels, occupied, *discs, params, out)
    in_chunks(len(rows) if len(rows) else len(out), lambda lo, hi: kernel(lo, hi, *args))
    return out


def _occupied_cells(depth):
    """(F, GY, GX) uint8: per view, whether any texel within the blocker search's reach of a cell of
    CASTER_CELL texels holds something (a finite depth). A splat whose cell holds nothing there
    finds no blocker (every tap, the clamped ones too, reads a texel of those cells): it is lit,
    exactly as the search would say, without the search."""
    views, h, w = depth.shape
    rows, cols = -(-h // CASTER_CELL), -(-w // CASTER_CELL)
    filled = np.zeros((views, rows * CASTER_CELL, cols * CASTER_CELL), np.uint8)
    filled[:, :h, :w] = np.isfinite(depth)
    cells = filled.reshape(views, rows, CASTER_CELL, cols, CASTER_CELL).max(axis=(2, 4))
    reach = math.ceil(MAX_SEARCH_TEXELS / CASTER_CELL)
    for axis in (1, 2):
        cells = _sliding(np.maximum, cells, axis, reach, 0)
    return np.ascontiguousarray(cells)


def _camera_row(camera):
    """A camera as _visibility_loop reads it: rotation (9), centre (3), fx, fy, cx, cy, orthographic, near."""
    flags = [float(camera.is_orthographic), camera.near]
    return [*camera.rotation.ravel(), *camera.center, camera.fx, camera.fy, camera.cx, camera.cy, *flags]


def _visibility_loop(lo, hi, rows, positions, rotations, log_scales, nx, ny, nz, source, sun, cams, texels, occupied,
                     search_disc, disc, params, out):  # fmt: skip
    """visibility() for splats lo..hi (rows[lo..hi] where rows is not empty) into out: each splat's
    view (face_of: with several, the one looking most nearly at it, none behind them all), then
    _filtered's test there, skipped where the map holds nothing within the search's reach
    (_occupied_cells: lit all the same)."""
    size, sigma_bias, texel_bias = params[0], params[1], params[2]
    plane = params[3] > 0.5 and nx.shape[0] > 0  # without normals (empty columns) the plain test
    facing = params[4] > 0.5 and nx.shape[0] > 0
    h, w = texels.shape[1], texels.shape[2]
    every = rows.shape[0] == 0
    for j in range(lo, hi):
        i = j if every else rows[j]
        if facing and not _facing_one(positions, nx, ny, nz, source, sun, params, i):
            continue  # its seen side gets none of the light: out stays 1
        f = _face_one(positions, i, cams)
        if f < 0:
            continue  # behind an area light: out stays 1
        u, v, z = _texel_one(positions, i, cams, f)
        if not (math.isfinite(u) and math.isfinite(v)):
            continue  # behind a spot light: not in its map
        cx = int(min(max(u, 0.0), w - 1.0) / CASTER_CELL)
        cy = int(min(max(v, 0.0), h - 1.0) / CASTER_CELL)
        if occupied[f, cy, cx] == 0:
            out[i] = 1.0
            continue
        fx, ortho = cams[f, 12], cams[f, 16] > 0.5
        texel = (1.0 if ortho else z) / fx
        sigma, slope = _extent_at(positions, rotations, log_scales, nx, ny, nz, source, sun, i)
        limit = z - sigma_bias * sigma - texel_bias * texel * slope
        if size <= 0.0:
            search = 0.0  # hard: the centre texel only
        elif ortho:
            search = min(max(fx * size * 0.75 * (z - cams[f, 17]), 1.0), MAX_SEARCH_TEXELS)
        else:
            search = min(max(fx * size * 3.0 / max(z, 1e-9), 1.0), MAX_SEARCH_TEXELS)
        gu, gv = _plane_one(nx, ny, nz, i, cams, f, z) if plane else (0.0, 0.0)
        out[i] = _pcss_one(u, v, z, limit, gu, gv, search, texels[f], search_disc, disc, fx * size, ortho)


def _plane_one(nx, ny, nz, i, cams, f, z):
    """_plane_gradient of splat i in view f: its tangent plane's depth change per texel along u, v."""
    n0 = cams[f, 0] * nx[i] + cams[f, 1] * ny[i] + cams[f, 2] * nz[i]
    n1 = cams[f, 3] * nx[i] + cams[f, 4] * ny[i] + cams[f, 5] * nz[i]
    n2 = cams[f, 6] * nx[i] + cams[f, 7] * ny[i] + cams[f, 8] * nz[i]
    if abs(n2) <= 1e-6:
        return 0.0, 0.0
    depth = 1.0 if cams[f, 16] > 0.5 else z
    tu, tv = depth / cams[f, 12], depth / cams[f, 13]
    gu, gv = -n0 / n2 * tu, -n1 / n2 * tv
    size = math.sqrt(gu * gu + gv * gv)
    shrink = min(1.0, MAX_SLOPE * tu / max(size, 1e-300))
    return gu * shrink, gv * shrink


def _face_one(positions, i, cams):
    """face_of for splat i: the view (row of cams, _camera_row) looking most nearly at it; -1
    behind them all (behind an area light)."""
    if cams.shape[0] == 1:
        return 0
    best, f = -math.inf, 0
    for k in range(cams.shape[0]):
        along = 0.0
        for c in range(3):
            along += (positions[i, c] - cams[0, 9 + c]) * cams[k, 6 + c]  # the view's forward
        if along > best:
            best, f = along, k
    return f if best > 0.0 else -1


def _texel_one(positions, i, cams, f):
    """(u, v, z): splat i's centre in view f's map (texels) and its camera z; u and v NaN where
    the view cannot see it (behind a perspective camera)."""
    r0, r1, r2 = positions[i, 0] - cams[f, 9], positions[i, 1] - cams[f, 10], positions[i, 2] - cams[f, 11]
    x = cams[f, 0] * r0 + cams[f, 1] * r1 + cams[f, 2] * r2
    y = cams[f, 3] * r0 + cams[f, 4] * r1 + cams[f, 5] * r2
    z = cams[f, 6] * r0 + cams[f, 7] * r1 + cams[f, 8] * r2
    if cams[f, 16] <= 0.5:
        if not z > 0.0:
            return math.nan, math.nan, z
        x, y = x / z, y / z
    return cams[f, 12] * x + cams[f, 14], cams[f, 13] * y + cams[f, 15], z


def _pcss_one(u, v, z, limit, gu, gv, search, texels, search_disc, disc, scale, ortho):
    """_filtered's blocker search and filter of one point at (u, v) in a map, texels (H,W,2) its
    depth and alpha, each tap's limit moved along the receiver's plane by gu, gv (depth per texel;
    0 without); search 0 tests the centre texel alone (a hard shadow)."""
    h, w = texels.shape[0], texels.shape[1]
    if search == 0.0:
        x = min(max(int(np.floor(u)), 0), w - 1)
        y = min(max(int(np.floor(v)), 0), h - 1)
        return 1.0 - min(max(texels[y, x, 1], 0.0), 1.0) if texels[y, x, 0] < limit else 1.0
    searched = search_disc.shape[0]
    total, weighted = 0.0, 0.0
    for k in range(searched):
        dx, dy = search * search_disc[k, 0], search * search_disc[k, 1]
        x = min(max(int(np.floor(u + dx)), 0), w - 1)
        y = min(max(int(np.floor(v + dy)), 0), h - 1)
        if texels[y, x, 0] < limit + dx * gu + dy * gv:
            total += texels[y, x, 1]
            weighted += texels[y, x, 1] * texels[y, x, 0]
    if total <= 0.0:
        return 1.0
    blocker = weighted / total
    gap = max(z - blocker, 0.0)
    radius = scale * gap if ortho else scale * gap / max(z * blocker, 1e-12)
    radius = max(radius, 0.5)
    taps = disc.shape[0]
    covered = 0.0
    for k in range(taps):
        dx, dy = radius * disc[k, 0], radius * disc[k, 1]
        x = min(max(int(np.floor(u + dx)), 0), w - 1)
        y = min(max(int(np.floor(v + dy)), 0), h - 1)
        if texels[y, x, 0] < limit + dx * gu + dy * gv:
            covered += texels[y, x, 1]
    return 1.0 - min(covered / taps, 1.0)


def _covered(view, uv, limit, disc, radius, gradient=None):
    """(covered fraction (n,), mean blocker depth (n,)) of the taps uv + radius * disc (texels) by
    map texels nearer than `limit` (moved along the receiver's plane by `gradient` (n,2), depth per
    texel, when given), each weighed by its alpha. Taps off the map read its edge."""
    h, w = view.depth.shape
    dx, dy = radius[:, None] * disc[None, :, 0], radius[:, None] * disc[None, :, 1]
    x, y = uv[:, None, 0] + dx, uv[:, None, 1] + dy
    ix = np.clip(np.floor(np.nan_to_num(x, nan=-1.0)), 0, w - 1).astype(np.int64)
    iy = np.clip(np.floor(np.nan_to_num(y, nan=-1.0)), 0, h - 1).astype(np.int64)
    flat = iy * w + ix
    depth = view.depth.ravel()[flat]
    limits = limit[:, None] if gradient is None else limit[:, None] + dx * gradient[:, :1] + dy * gradient[:, 1:]
    blocked = depth < limits
    weight = np.where(blocked, view.alpha.ravel()[flat], 0.0)
    total = weight.sum(axis=1)
    mean_depth = np.where(blocked, depth, 0.0).astype(np.float64) * weight
    blocker = np.where(total > 0, mean_depth.sum(axis=1) / np.maximum(total, 1e-30), np.inf)
    return np.clip(total / disc.shape[0], 0.0, 1.0), blocker
