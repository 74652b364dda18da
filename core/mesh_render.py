"""An unlit triangle rasteriser in NumPy: the reference image of a mesh for mesh-to-splats.

Every (face, pixel) pair inside a face's screen bounding box is a candidate; the pixel's ray is
intersected with the face exactly (3D edge functions against the ray, so barycentrics are
perspective-correct and faces crossing the near plane need no clipping). The z-buffer keeps the
nearest hit per pixel, chunk by chunk of face rows, and the hit's surface colour is looked up once
per pixel. Pixels weigh s x s samples each, and those around them, in scene-linear colour by Cycles'
default pixel filter (a path tracer's pixel filter; a box filter on request). Faces are two-sided
(an emission shader shows both sides). Alpha-cut materials (core.mesh.Material's alpha_mode) are
seen through by depth peeling (rasterize_layers): where a hit is cut out, or part-covering, the same
rasteriser runs again for the hits beyond it, and the layers are composited front to back.

That NumPy path is the readable reference and the fallback. Where numba loads (core.jit), the same
per-candidate arithmetic runs as compiled loops (core/mesh_render_kernels.py) over every core's
share of the pixel rows, with no candidate lists; it gives the same buffers bit for bit.
`rasterize(..., backend=...)` picks one.
"""

from dataclasses import dataclass

import numpy as np

from . import color, jit
from .mesh import Surface, shade, to_display
from .parallel import WORKERS, map_threads
from .spatial import ramp

CANDIDATES_PER_CHUNK = 1 << 21
BACKENDS = ("auto", "compiled", "numpy")
KERNELS = "core.mesh_render_kernels"  # the compiled module, loaded by core.jit
THREADED_PIXELS = 1 << 16  # smaller images are drawn on the calling thread
DEFAULT_PIXEL_FILTER, CYCLES_FILTER_WIDTH = "blackman-harris", 1.5  # Cycles' default pixel filter
MAX_LAYERS = 8  # hits a ray passes through alpha cut-outs, at most: Cycles' default transparent bounces


@dataclass
class MeshRender:
    """color (H,W,3) display sRGB; alpha (H,W) covered fraction; depth (H,W) mean camera z of the
    covered samples (0 where none); face (H*s, W*s) int64 face index per sample, -1 for background;
    samples s per pixel side."""

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    face: np.ndarray
    samples: int


def render_mesh(
    surface,
    camera,
    background=(0.0, 0.0, 0.0),
    supersample=3,
    *,
    pixel_filter=DEFAULT_PIXEL_FILTER,
    filter_width=CYCLES_FILTER_WIDTH,
    backend="auto",
    mix="linear",
    **appearance,
):
    """Render a mesh through a core Camera. `surface` is a core.mesh.Surface, a Mesh, or vertices
    (V,3) with `faces=` and the other appearance arguments of mesh_to_splats.

    Each pixel weighs the supersample x supersample samples around it in linear light by a pixel
    filter of Cycles (`pixel_filter`, `filter_width` in Cycles' units; see filter_taps), by default
    Cycles' default, Blackman-Harris 1.5 px, which reaches 1.5 px into the neighbours ("box": the
    pixel's own samples, equally). Samples past the frame's edge are rendered, as Cycles' rays reach.
    backend: the rasteriser's, as for rasterize().
    mix: "linear" weighs the samples in linear light, as Cycles does; "display" weighs their display
    colours, as a splat renderer blends splats. With a Gaussian filter of the splat renderer's
    low-pass (filter_width 4 * sqrt(LOW_PASS)), "display" gives the image that infinitely many,
    infinitely thin splats would draw: it tells what of a conversion's error is the blending's.
    """
    if mix not in ("linear", "display"):
        raise ValueError(f"mix must be 'linear' or 'display', got {mix!r}")
    surface = _as_surface(surface, appearance)
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    taps, margin = filter_taps(pixel_filter, filter_width, s)
    cam = camera.with_(
        width=camera.width * s + 2 * margin,
        height=camera.height * s + 2 * margin,
        fx=camera.fx * s,
        fy=camera.fy * s,
        cx=camera.cx * s + margin,
        cy=camera.cy * s + margin,
    )
    layers = rasterize_layers(surface, cam, backend=backend)
    face, _, depth = _first_stopping(layers)
    hit = face >= 0
    bg_linear = color.srgb_to_linear(np.asarray(background, np.float64).reshape(3))
    # Front to back through the layers (one for an opaque mesh): what each hit stops of what is
    # left, then the background.
    linear = np.zeros(face.shape + (3,))
    left = np.ones(face.shape)
    for layer_face, layer_bary, _, alpha in layers:
        on = layer_face >= 0
        stopped = left[on] * alpha[on]
        shaded = _shade_hits(surface, cam, layer_face[on], layer_bary[on], np.flatnonzero(on.ravel()))
        linear[on] += stopped[:, None] * shaded
        left[on] -= stopped
    linear += left[..., None] * bg_linear
    h, w = camera.height, camera.width
    filtered = lambda a: _filter_axis(_filter_axis(a, taps, s, h, 0), taps, s, w, 1)  # noqa: E731
    shown = to_display(filtered(linear)) if mix == "linear" else filtered(to_display(linear))
    covered = filtered(1.0 - left)
    mean_depth = np.where(covered > 0, filtered(np.where(hit, depth, 0.0)) / np.maximum(covered, 1e-300), 0.0)
    inside = slice(margin, margin + h * s), slice(margin, margin + w * s)
    return MeshRender(
        shown.astype(np.float32),
        covered.astype(np.float32),
        mean_depth.astype(np.float32),
        face[inside],
        s,
    )


PIXEL_FILTERS = ("blackman-harris", "gaussian", "box")  # Cycles' three


def filter_taps(pixel_filter, width, samples):
    """(weights, margin) of one of Cycles' pixel filters on a grid of `samples` per pixel side:
    weights of the samples from `margin` before a pixel's own to `margin` after them, summing to 1.

    As Cycles draws them (measured on a slanted edge it rendered): Blackman-Harris over 2 x `width`
    pixels, a Gaussian of standard deviation width / 4 cut at 1.5 x width, and a box of one pixel
    whatever the width."""
    if pixel_filter not in PIXEL_FILTERS:
        raise ValueError(f"pixel_filter must be one of {PIXEL_FILTERS}, got {pixel_filter!r}")
    if pixel_filter == "box":
        return np.full(samples, 1.0 / samples), 0
    if not width > 0:
        raise ValueError(f"filter_width must be positive, got {width}")
    radius = float(width) * (1.0 if pixel_filter == "blackman-harris" else 1.5)
    margin = int(np.ceil(radius * samples))
    offset = (np.arange(-margin, samples + margin) + 0.5) / samples - 0.5  # from the pixel centre
    if pixel_filter == "gaussian":
        weights = np.exp(-0.5 * (offset / (width / 4)) ** 2)
    else:
        phase = 2 * np.pi * (np.clip(offset / radius, -1, 1) + 1) / 2
        weights = 0.35875 - 0.48829 * np.cos(phase) + 0.14128 * np.cos(2 * phase) - 0.01168 * np.cos(3 * phase)
    weights[np.abs(offset) >= radius] = 0.0
    if weights.sum() <= 0:  # a window narrower than the samples: the nearest
        weights[np.argmin(np.abs(offset))] = 1.0
    return weights / weights.sum(), margin


def _filter_axis(a, taps, samples, pixels, axis):
    """`pixels` filtered values along `axis` of a sample grid: tap k reads every samples-th sample
    from k on (the margin included), so pixel i weighs samples i*samples + k."""
    out = 0.0
    for k, weight in enumerate(taps):
        if weight:
            out = out + weight * np.take(a, np.arange(k, k + pixels * samples, samples), axis=axis)
    return out


def _as_surface(surface, appearance):
    if isinstance(surface, Surface):
        return surface
    if hasattr(surface, "appearance"):
        return Surface(surface.vertices, surface.faces, **surface.appearance())
    faces = appearance.pop("faces")
    return Surface(surface, faces, **appearance)


def _shade_hits(surface, cam, tri, bary, flat_pixels):
    linear = surface.linear_colors(tri, bary)
    if surface.view_dependent:
        rays = _rays(cam, flat_pixels % cam.width, flat_pixels // cam.width) @ cam.rotation
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        rim, has = surface.rim_colors(tri)
        linear = shade(linear, rim, has, np.einsum("ij,ij->i", rays, surface.normal[tri]))
    return linear


def _rays(cam, px, py):
    """Camera-space ray directions (z = 1) through pixel centres; for orthographic, the ray origins."""
    return np.column_stack([(px + 0.5 - cam.cx) / cam.fx, (py + 0.5 - cam.cy) / cam.fy, np.ones(len(px))])


def rasterize(surface, cam, backend="auto", beyond=-np.inf):
    """Nearest face per pixel that stops the ray: (face (H,W) int64, -1 where none; bary (H,W,3);
    depth (H,W)), of the hits at `beyond` camera depth or farther (a clip plane across the view).
    Of faces at the same depth, the lowest index wins. On alpha-cut materials
    (core.mesh.Material.alpha_mode) a hit stops the ray where its Surface.hit_alpha is at least
    1/2 (a MASK's alpha test; a BLEND's, as Cycles' Depth pass takes the first surface at least
    half opaque); cut-out hits are seen through (rasterize_layers).

    backend: "auto" (or None: the compiled kernel where numba loads, else NumPy), "compiled"
    (an error if it cannot load) or "numpy". Both give the same buffers."""
    return _first_stopping(rasterize_layers(surface, cam, backend, beyond=beyond))


def rasterize_layers(surface, cam, backend="auto", max_layers=MAX_LAYERS, beyond=-np.inf):
    """The hits along each pixel's ray, nearest first, as far as alpha-cut materials let it through:
    a list of layers (face (H,W), bary (H,W,3), depth (H,W), alpha (H,W): Surface.hit_alpha, 0
    where no hit), the first every pixel's nearest hit, each next one only where the rays so far
    were not wholly stopped (depth peeling: the same rasteriser again, taking only hits beyond the
    last layer's depth and face). An opaque mesh has one layer; at most `max_layers` (Cycles'
    default transparent bounces), after which what is left sees the background. Hits nearer than
    `beyond` (camera depth) are left out."""
    backend = "auto" if backend is None else backend
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    kernels = None if backend == "numpy" else jit.load(KERNELS, check=_check_kernels)
    if kernels is None and backend == "compiled":
        raise RuntimeError(f"compiled mesh rasteriser is not available: {jit.status(KERNELS)}")
    n = cam.height * cam.width
    zmin, fmin, left = np.full(n, float(beyond)), np.full(n, -1, np.int64), np.ones(n)
    layers = []
    for _ in range(max_layers):
        face, bary, depth = _rasterize(kernels, surface, cam, zmin, fmin)
        hit = np.flatnonzero(face.ravel() >= 0)
        alpha = np.zeros(n)
        alpha[hit] = surface.hit_alpha(face.ravel()[hit], bary.reshape(-1, 3)[hit]) if surface.cut else 1.0
        layers.append((face, bary, depth, alpha.reshape(face.shape)))
        left[hit] *= 1.0 - alpha[hit]
        through = hit[left[hit] > 0]  # rays a cut-out (or a translucent hit) lets on
        if not len(through):
            break
        zmin[:] = np.inf  # every other pixel is done
        zmin[through], fmin[through] = depth.ravel()[through], face.ravel()[through]
    return layers


def _first_stopping(layers):
    """(face, bary, depth) of each pixel's first hit in `layers` with alpha >= 1/2."""
    if len(layers) == 1 and not (layers[0][3][layers[0][0] >= 0] < 0.5).any():
        return layers[0][:3]  # an opaque mesh: its one layer as it is
    face, bary, depth, alpha = (np.array(a) for a in layers[0])
    face[alpha < 0.5] = -1
    for f, b, d, a in layers[1:]:
        take = (face < 0) & (f >= 0) & (a >= 0.5)
        face[take], bary[take], depth[take] = f[take], b[take], d[take]
    depth[face < 0] = 0.0
    return face, bary, depth


def backend_status():
    """'compiled' when the compiled kernel loads here (loading it), else why NumPy is used."""
    jit.load(KERNELS, check=_check_kernels)
    return jit.status(KERNELS)


def _check_kernels(kernels):
    """Run the compiled kernel once on a small scene (compiling it, or loading it from the cache)
    and compare with the NumPy path: a broken build falls back to NumPy, not a wrong image."""
    from .camera import Camera

    rng = np.random.default_rng(0)
    n = 24
    vertices = np.concatenate(
        [rng.normal(0, 0.6, (n, 3)) + [0, 0, 3], [[-3, 0.5, 1.0], [3, 0.6, 1.0], [0, 0.7, 9.0]]]
    )  # through the near plane
    faces = rng.integers(0, n, (40, 3))
    faces = np.concatenate([faces, [[n, n + 1, n + 2]], faces[1:2]])  # and a twin of a seen face
    surface = Surface(vertices, faces)
    for camera in (
        Camera.look_at((0.3, -0.4, 0.0), (0, 0, 3), fov_deg=50, width=24, height=20, near=0.5),
        Camera.look_at_ortho((0.3, -0.4, 0.0), (0, 0, 3), ortho_scale=2.5, width=24, height=20),
    ):
        n = camera.width * camera.height
        peel = np.where(np.arange(n) % 3 == 0, np.inf, -np.inf)
        peel[1::3] = 3.0  # a bound inside the scene: only hits beyond depth 3
        fmin = np.where(np.arange(n) % 2 == 0, 7, -1)
        for bound in ((np.full(n, -np.inf), np.full(n, -1)), (peel, fmin)):
            got, want = _rasterize(kernels, surface, camera, *bound), _rasterize(None, surface, camera, *bound)
            if not all(np.array_equal(g, w) for g, w in zip(got, want)):
                raise RuntimeError("the compiled mesh rasteriser disagrees with the NumPy path on a test scene")


def _rasterize(kernels, surface, cam, zmin, fmin):
    """The nearest hits beyond (zmin, fmin) per flat pixel (rasterize_layers) by the compiled
    kernels, or by NumPy when kernels is None."""
    h, w = cam.height, cam.width
    zbuf = np.full(h * w, np.inf)
    fbuf = np.full(h * w, -1, np.int64)
    bbuf = np.zeros((h * w, 3))
    v = cam.to_camera(surface.vertices)[surface.faces]  # (F,3,3) camera space
    faces, x0, x1, y0, y1 = _screen_boxes(surface, cam, v, _open_box(zmin.reshape(h, w)))
    a, b, c = _edge_functions(v[faces], cam)
    depths = np.ascontiguousarray(v[faces, :, 2])
    if kernels is not None:
        # Row y goes to call y % n: the rows of a face, and so the work, are dealt out evenly.
        n = min(WORKERS, h) if h * w >= THREADED_PIXELS else 1
        map_threads(
            lambda first: kernels.rasterize_rows(
                a,
                b,
                c,
                depths,
                faces,
                x0,
                x1,
                y0,
                y1,
                float(cam.near),
                float(cam.far),
                w,
                first,
                n,
                zmin,
                fmin,
                zbuf,
                fbuf,
                bbuf,
            ),
            range(n),
        )
    else:
        _rasterize_numpy(cam, a, b, c, depths, faces, x0, x1, y0, y1, (zmin, fmin), (zbuf, fbuf, bbuf))
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0)
    return fbuf.reshape(h, w), bbuf.reshape(h, w, 3), depth.reshape(h, w)


def _rasterize_numpy(cam, a, b, c, depths, faces, x0, x1, y0, y1, bound, buffers):
    """Draw the faces (edge functions, corner depths, boxes) into the flat buffers (zbuf, fbuf,
    bbuf), only hits beyond bound = (zmin, fmin)."""
    w = cam.width
    rows_face = np.repeat(np.arange(len(faces)), y1 - y0)
    rows_y = y0[rows_face] + ramp(y1 - y0)
    # Along a row only x changes: e = a x + (b y + c), the bracket once per row.
    brackets = b[rows_face] * rows_y[:, None] + c[rows_face]
    starts, widths = _row_spans(a[rows_face], brackets, x0[rows_face], x1[rows_face])
    ends = np.cumsum(widths)
    start = 0
    while start < len(rows_face):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + CANDIDATES_PER_CHUNK, "right"))
        stop = max(stop, start + 1)
        rf, ry, rw = rows_face[start:stop], rows_y[start:stop], widths[start:stop]
        px = np.repeat(starts[start:stop], rw) + ramp(rw)
        e = np.repeat(a[rf], rw, axis=0) * px[:, None]
        e += np.repeat(brackets[start:stop], rw, axis=0)
        _keep_nearest(cam, e, np.repeat(rf, rw), depths, faces, px + np.repeat(ry * w, rw), bound, buffers)
        start = stop


def _row_spans(a, bracket, x0, x1, margin=1.0):
    """(first x, count) per row of the pixels of [x0, x1) that can lie inside the face: where its
    three edge functions a x + bracket (a, bracket (R,3)) can share a sign, widened by `margin`
    pixels against round-off (the exact test comes later). Keeps a face's candidates near its own
    area rather than its bounding box's, about half of it."""
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -bracket / a  # where each edge function changes sign
    rising, falling = a > 0, a < 0
    inf = np.inf
    # All >= 0: x above the roots of rising edges and below those of falling ones; all <= 0: reversed.
    lo_pos = np.where(rising, root, -inf).max(axis=1)
    hi_pos = np.where(falling, root, inf).min(axis=1)
    lo_neg = np.where(falling, root, -inf).max(axis=1)
    hi_neg = np.where(rising, root, inf).min(axis=1)
    pos, neg = lo_pos <= hi_pos + 2 * margin, lo_neg <= hi_neg + 2 * margin
    lo = np.minimum(np.where(pos, lo_pos, inf), np.where(neg, lo_neg, inf))
    hi = np.maximum(np.where(pos, hi_pos, -inf), np.where(neg, hi_neg, -inf))
    # Rows with an edge function constant along x (a == 0) keep their box: no root to trust.
    flat = ~(rising | falling).all(axis=1) | ~np.isfinite(root).all(axis=1)
    first = np.where(flat, x0, np.clip(np.ceil(np.nan_to_num(lo - margin, nan=-inf, neginf=-1e18)), x0, x1))
    last = np.where(flat, x1, np.clip(np.floor(np.nan_to_num(hi + margin, nan=inf, posinf=1e18)) + 1, x0, x1))
    first = first.astype(np.int64)
    return first, np.maximum(last.astype(np.int64) - first, 0)


def _edge_functions(v, cam):
    """Per face, (a, b, c), each (F,3): the edge function of the edge opposite corner k at the centre
    of pixel (x, y) is a_k x + b_k y + c_k, proportional to the perspective-correct barycentric k.

    It is r . (v_{k+1} x v_{k+2}) for the pixel's ray r = ((x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1):
    the signed volume of the ray with the edge. Orthographic rays are parallel, from (x, y) in r's
    units; there the corners enter as (x, y, 1), which makes the same product the 2D edge function.
    Faces sharing an edge get exactly opposite values along it (a x b = -(b x a) in floating point
    too), so no pixel centre falls through the crack between them."""
    if cam.is_orthographic:
        v = np.concatenate([v[..., :2], np.ones(v.shape[:-1] + (1,))], axis=-1)
    planes = np.cross(v[:, [1, 2, 0]], v[:, [2, 0, 1]])
    a, b = planes[..., 0] / cam.fx, planes[..., 1] / cam.fy
    return a, b, planes[..., 2] + a * (0.5 - cam.cx) + b * (0.5 - cam.cy)


def _open_box(zmin):
    """(x0, x1, y0, y1): the bounding box of the pixels a peeling pass still draws (zmin < inf)."""
    rows, cols = np.flatnonzero((zmin < np.inf).any(axis=1)), np.flatnonzero((zmin < np.inf).any(axis=0))
    if not len(rows):
        return 0, 0, 0, 0
    return cols[0], cols[-1] + 1, rows[0], rows[-1] + 1


def _screen_boxes(surface, cam, v, window):
    """Faces in view and their pixel bounding boxes [x0, x1) x [y0, y1), clipped to the image and
    to window = (x0, x1, y0, y1)."""
    z = v[..., 2]
    ok = surface.valid & (z > cam.near).any(axis=1) & (z <= cam.far).any(axis=1)
    in_front = (z > cam.near).all(axis=1)
    if cam.is_orthographic:
        xy = np.stack([cam.fx * v[..., 0] + cam.cx, cam.fy * v[..., 1] + cam.cy], axis=-1)
        in_front = np.ones_like(in_front)
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.stack([cam.fx * v[..., 0] / z + cam.cx, cam.fy * v[..., 1] / z + cam.cy], axis=-1)
    lo = np.where(in_front[:, None], np.nan_to_num(xy.min(axis=1), nan=0.0), 0.0)
    hi = np.where(in_front[:, None], np.nan_to_num(xy.max(axis=1), nan=0.0), [cam.width, cam.height])
    # Pixel i is covered only if its centre i + 0.5 lies in [lo, hi].
    wx0, wx1, wy0, wy1 = window
    x0 = np.clip(np.ceil(lo[:, 0] - 0.5), wx0, wx1).astype(np.int64)
    x1 = np.clip(np.floor(hi[:, 0] - 0.5) + 1, wx0, wx1).astype(np.int64)
    y0 = np.clip(np.ceil(lo[:, 1] - 0.5), wy0, wy1).astype(np.int64)
    y1 = np.clip(np.floor(hi[:, 1] - 0.5) + 1, wy0, wy1).astype(np.int64)
    ok &= (x1 > x0) & (y1 > y0)
    faces = np.flatnonzero(ok)
    return faces, x0[faces], x1[faces], y0[faces], y1[faces]


def _keep_nearest(cam, e, local, depths, faces, pix, bound, buffers):
    """Of the candidates (edge functions e (M,3) of face faces[local] at pixel pix), keep each
    pixel's nearest hit beyond bound = (zmin, fmin) in buffers = (zbuf, fbuf, bbuf) (ties to the
    lower face index). The sums are written out
    term by term, not left to sum or einsum (whose order of adding varies): the compiled kernel
    adds in this order too, so both give the same bits."""
    total = e[:, 0] + e[:, 1] + e[:, 2]
    lowest = np.minimum(np.minimum(e[:, 0], e[:, 1]), e[:, 2])
    highest = np.maximum(np.maximum(e[:, 0], e[:, 1]), e[:, 2])
    inside = np.flatnonzero((total != 0) & ((lowest >= 0) | (highest <= 0)))
    local, pix = local[inside], pix[inside]
    bary = e[inside] / total[inside, None]
    d = depths[local]
    z = bary[:, 0] * d[:, 0] + bary[:, 1] * d[:, 1] + bary[:, 2] * d[:, 2]
    zbuf, fbuf, bbuf = buffers
    zmin, fmin = bound[0][pix], bound[1][pix]
    beyond = (z > zmin) | ((z == zmin) & (faces[local] > fmin))
    keep = np.flatnonzero((z > cam.near) & (z <= cam.far) & beyond)
    # One sort by pixel, then the nearest (and of equals the lowest face) per run of a pixel: a
    # face has at most one candidate per pixel, so exactly one row per pixel is left.
    order = keep[np.argsort(pix[keep])]
    pix, z, tri = pix[order], z[order], faces[local[order]]
    if not len(pix):
        return
    starts = np.flatnonzero(np.concatenate([[True], pix[1:] != pix[:-1]]))
    run = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(pix))))
    nearest = z == np.minimum.reduceat(z, starts)[run]
    lowest_face = np.minimum.reduceat(np.where(nearest, tri, np.iinfo(np.int64).max), starts)[run]
    first = np.flatnonzero(nearest & (tri == lowest_face))
    pix, z, tri, rows = pix[first], z[first], tri[first], order[first]
    closer = (z < zbuf[pix]) | ((z == zbuf[pix]) & (tri < fbuf[pix]))
    pix, rows = pix[closer], rows[closer]
    zbuf[pix], fbuf[pix], bbuf[pix] = z[closer], tri[closer], bary[rows]
