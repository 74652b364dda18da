"""Exact EWA splatting in NumPy, with the conventions of the 3DGS reference rasteriser.

The image is defined per pixel, front to back over splats sorted by camera depth:
alpha = min(0.99, o exp(-d^T Sigma2D^-1 d / 2)), splats with alpha < 1/255 are skipped, compositing
stops before a splat that would take the transmittance T below 1e-4, C += T alpha c, T *= 1 - alpha,
and the final colour is C + T background. Every splat gets an extent that contains all of its
alpha >= 1/255 pixels, so nothing visible is cut off.

How it runs fast without a loop per splat or per pixel:
- projection, covariances and SH colours are vectorised over splats (float64, relative to the camera);
- splats are binned into square tiles, keeping only tiles their ellipse really touches, and a stable
  sort by tile of the depth-ordered (tile, splat) entries gives every tile its front-to-back list;
- tiles are composited in waves of up to `wave` entries per tile. A batch of tiles with similar entry
  counts becomes one dense (entries, tiles, pixels) block: the Gaussian exponent is a quadratic in the
  pixel offset from the tile centre, so it is one small matrix product (entry coefficients x a fixed
  basis), followed by exp, a running product for T over the entry axis and one batched matrix product
  that sums weights times (colour, depth, 1) per pixel. Tiles whose pixels have all stopped drop out
  after each wave, which is where opaque scenes save most of their work. Asked for, the largest weight
  of each entry over its tile's pixels also goes into a per-splat maximum (one more pass);
- batches run on a thread pool: NumPy and BLAS release the GIL for the heavy calls.

That NumPy path is the readable reference and the fallback. Where numba loads (core.jit), the same
three stages, and the final alpha, depth and background of a render without a layer, run as
compiled loops (core/render_kernels.py), which also skip the pixel rows of a tile that a splat's
ellipse does not cross and write the image without per-tile accumulators.
`render(..., backend=...)` picks one; both are tested against the float64 reference.
Here: the public render(), the NumPy projection and the compiled path; the projected records, the
screen geometry and the NumPy binning are in core/render_tiles.py, the NumPy compositing (and the
Layer crossing) in core/render_composite.py, the numbers of the image in core/render_constants.py.

A Layer (a surface rendered by something else: per pixel a colour, an alpha and a camera depth)
joins each pixel's front-to-back list as one more element, before the first splat whose camera z
is not in front of it. In the NumPy path's running product for T that is a factor (1 - layer alpha)
on the splat where the pixel crosses the layer; the compiled path applies it between two entries.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Annotated

import numpy as np
from numpy.typing import NDArray

from . import geometry, jit, scratch
from . import sh as shmod
from .arrays import Floats, Image
from .camera import Camera
from .memory import physical_memory
from .parallel import Pool
from .render_composite import Compositor, LayerCrossing
from .render_constants import (
    AA_MIN_RATIO,
    ALPHA_MIN,
    FRUSTUM_MARGIN,
    LOW_PASS,
    MAX_TILE_SIZE,
    MODES,
    PRECISIONS,
    T_MIN,
    TILE_SIZE,
)
from .render_tiles import (
    Bins,
    Projected,
    bin_tiles,
    new_records,
    record_floats,
    screen_covariance,
    screen_rows,
    stable_argsort,
)
from .splats import SplatCloud, sigmoid

BACKENDS = ("auto", "compiled", "numpy")
KERNELS = "core.render_kernels"  # the compiled module, loaded by core.jit


@dataclass
class RenderResult:
    """A rendered image.

    color: (H,W,3) float32 display sRGB, background included (black when rendered with
        background=None, i.e. colour premultiplied by alpha).
    alpha: (H,W) float32 coverage, 1 - final transmittance.
    depth: (H,W) float32 alpha-weighted expected camera z, sum(w z) / sum(w) over the blended
        splats with weights w = T alpha; 0 where alpha is 0 (no splat), never NaN or Inf.
    counts: (H,W) int32 number of splats blended into each pixel, when requested; else None.
    max_weight: (N,) float32 when requested, else None: each input splat's largest blending weight
        T alpha over all pixels, by the rules above; 0 for splats that reach no pixel (culled,
        off-image, too faint for 1/255, hidden behind pixels that stopped, or non-finite).
    background: the background colour used, or None for a transparent render.
    stats: counts of splats and work (input, skipped_nonfinite, visible, entries, evaluated).
    gathered: (N, C) float64 when rendered with gather=image (H,W,C), else None: for every input
        splat, sum over pixels i of w_i image_i, w_i its blending weight T alpha at pixel i (0 rows
        for splats that reach no pixel). This is the adjoint of rendering a colour field: the image
        is linear in the splats' colours c_j, pixel_i = sum_j w_ij c_j (+ T_i background), so
        <render(c), r> = <c, gathered(r)>, what a least-squares fit of colours needs.
    layer_transmittance: (H,W) float32 when rendered with a layer, else None: T where the pixel
        reached the layer (what the layer's colour was multiplied by). With a layer, `color` and
        `alpha` include it; the splats' own part is color - layer_transmittance * layer.color
        (- (1 - alpha) * background).
    """

    color: Image
    alpha: Annotated[Floats, "(H, W)"]
    depth: Annotated[Floats, "(H, W)"]
    counts: Annotated[NDArray[np.integer], "(H, W)"] | None = None
    max_weight: Annotated[Floats, "(N,)"] | None = None
    gathered: Annotated[Floats, "(N, C)"] | None = None
    background: tuple | None = (0.0, 0.0, 0.0)
    stats: dict = field(default_factory=dict)
    layer_transmittance: np.ndarray | None = None


@dataclass
class Layer:
    """A surface seen with the splats, e.g. meshes rendered by a path tracer: per pixel a colour
    (display sRGB, premultiplied by alpha), an alpha and the camera z of the surface (inf where
    there is none).

    Each pixel composites it front to back as one more element of its list, before the first splat
    whose camera z is >= depth: C += T color, T *= 1 - alpha. It is never clamped, skipped or
    stopped at; a pixel that stopped before reaching it still gives it the T it stopped with, as it
    gives the background. An opaque layer (alpha 1) hides every splat behind it.
    """

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray

    def checked(self, camera):
        """The layer as float32 arrays of the camera's image size, or ValueError naming the problem."""
        shape = (camera.height, camera.width)
        arrays = {}
        for name, want in (("color", shape + (3,)), ("alpha", shape), ("depth", shape)):
            a = np.asarray(getattr(self, name), dtype=np.float32)
            if a.shape != want:
                raise ValueError(
                    f"layer {name} has shape {a.shape}, expected {want} for a {camera.width}x{camera.height} image"
                )
            bad = np.isnan(a) if name == "depth" else ~np.isfinite(a)
            if bad.any():
                raise ValueError(
                    f"layer {name} holds {int(bad.sum())} {'NaN' if name == 'depth' else 'non-finite'} values"
                )
            arrays[name] = a
        if (arrays["alpha"] < 0).any() or (arrays["alpha"] > 1).any():
            raise ValueError("layer alpha must lie in [0, 1]")
        return Layer(**arrays)


def render(
    cloud: SplatCloud,
    camera: Camera,
    background: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
    mode: str | None = None,
    return_counts: bool = False,
    *,
    return_weights: bool = False,
    tile_size: int = TILE_SIZE,
    wave: int = 32,
    t_min: float = T_MIN,
    max_sigma: float | None = None,
    precision: str = "float32",
    threads: int | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    backend: str = "auto",
    layer: "Layer | None" = None,
    gather: Image | None = None,
    shapes: "Shapes | None" = None,
    rows: np.ndarray | None = None,
) -> RenderResult:
    """Render a SplatCloud through a Camera; returns a RenderResult.

    background: display-sRGB colour behind the splats, or None for a transparent render.
    mode: "classic" (the reference rasteriser) or "antialiased" (opacity compensated for the
        0.3 px^2 low-pass, as in Mip-Splatting / gsplat's antialiased mode); None, the mode the
        cloud was made for (cloud.antialiased).
    return_counts, return_weights: also give result.counts, result.max_weight.
    Speed options (the defaults give the exact image): tile_size in pixels; wave, entries per tile
    composited between checks for finished tiles (NumPy path only); t_min, the transmittance stop
    (0 disables it); max_sigma caps each splat's extent in standard deviations (3 mimics the
    reference rasteriser, dropping faint tails); precision "float32" or "float64" for the per-pixel
    work; threads (default: all cores); backend "auto" (compiled kernels where numba loads, else
    NumPy), "compiled" (an error if they cannot load) or "numpy". progress(done_tiles,
    total_tiles, label) is called from the calling thread as tiles finish.
    layer: a Layer composited with the splats in depth order (see Layer), or None.
    gather: an (H,W) or (H,W,C) image to gather through the blending weights into
        result.gathered (see RenderResult), or None.
    shapes: Shapes(cloud), made once for renders of the same splats from many cameras, or None.
    rows: the splats to draw, as indices (M,) or a mask (N,) bool; the others are left out as if the
        cloud lacked them (without copying the cloud: a shadow map draws a light's casters so), but
        per-splat results (max_weight, gathered) still count every splat. None: all.

    Splats with non-finite values are skipped and counted in stats["skipped_nonfinite"];
    stats["backend"] says which path ran. An image whose buffers would not fit in this machine's
    memory is refused (ValueError) before anything is allocated.
    """
    if mode is None:
        mode = "antialiased" if cloud.antialiased else "classic"
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    if int(tile_size) != tile_size or not 1 <= tile_size <= MAX_TILE_SIZE:
        raise ValueError(f"tile_size must be an integer in 1..{MAX_TILE_SIZE}, got {tile_size!r}")
    if int(wave) != wave or wave < 1:
        raise ValueError(f"wave must be a positive integer, got {wave!r}")
    if not 0.0 <= t_min < 1.0:
        raise ValueError(f"t_min must be in [0, 1), got {t_min!r}")
    if max_sigma is not None and not max_sigma > 0:
        raise ValueError(f"max_sigma must be > 0 or None, got {max_sigma!r}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    bg = None if background is None else np.asarray(background, dtype=np.float64).reshape(-1)
    if bg is not None and (bg.shape != (3,) or not np.isfinite(bg).all()):
        raise ValueError(f"background must be three finite numbers (r, g, b), got {background!r}")
    layer = None if layer is None else layer.checked(camera)
    gather = None if gather is None else _checked_gather(gather, camera)
    if shapes is not None and not shapes.fits(cloud):
        raise ValueError("shapes were made from other splats: make them from this cloud (Shapes(cloud))")
    rows = None if rows is None else _checked_rows(rows, len(cloud))
    kernels = None if backend == "numpy" else jit.load(KERNELS, check=_check_kernels)
    if kernels is None and backend == "compiled":
        raise RuntimeError(f"compiled render kernels are not available: {jit.status(KERNELS)}")
    check_image_memory(camera, int(tile_size), return_counts, compiled=kernels is not None)
    return _render(
        kernels,
        cloud,
        camera,
        bg,
        background,
        mode,
        return_counts,
        return_weights,
        int(tile_size),
        int(wave),
        t_min,
        max_sigma,
        PRECISIONS[precision],
        threads,
        progress,
        layer,
        gather,
        shapes,
        rows,
    )


def _checked_rows(rows, n):
    """rows as int64 indices into n splats, or ValueError naming the problem."""
    rows = np.asarray(rows)
    if rows.dtype == np.bool_:
        if rows.shape != (n,):
            raise ValueError(f"a rows mask must have one value per splat ({n}), got shape {rows.shape}")
        return np.flatnonzero(rows)
    if rows.ndim != 1 or not np.issubdtype(rows.dtype, np.integer):
        raise ValueError(f"rows must be splat indices (M,) or a mask (N,), got {rows.dtype} {rows.shape}")
    if len(rows) and not (0 <= rows.min() and rows.max() < n):
        raise ValueError(f"rows must index the cloud's {n} splats, got {rows.min()}..{rows.max()}")
    return np.ascontiguousarray(rows, np.int64)


def _checked_gather(image, camera):
    """The gather image as finite float32 (H, W, C), or ValueError naming the problem."""
    a = np.asarray(image, dtype=np.float32)
    a = a[..., None] if a.ndim == 2 else a
    if a.ndim != 3 or a.shape[:2] != (camera.height, camera.width) or a.shape[2] < 1:
        raise ValueError(
            f"gather image has shape {np.shape(image)}, expected ({camera.height}, {camera.width}) "
            "or (height, width, channels)"
        )
    if not np.isfinite(a).all():
        raise ValueError("gather image holds non-finite values")
    return np.ascontiguousarray(a)


def _render(
    kernels,
    cloud,
    camera,
    bg,
    background,
    mode,
    return_counts,
    return_weights,
    tile_size,
    wave,
    t_min,
    max_sigma,
    dtype,
    threads,
    progress,
    layer=None,
    gather=None,
    shapes=None,
    rows=None,
):
    """The checked render() by the compiled kernels, or by NumPy when kernels is None."""
    with Pool(threads) as pool:
        if kernels is None:
            proj = project(cloud, camera, mode=mode, max_sigma=max_sigma, pool=pool, rows=rows)
            bins = bin_tiles(proj, camera, tile_size, pool=pool)
            crossing = None if layer is None else LayerCrossing(layer, bins, dtype)
            compositor = Compositor(
                proj, bins, camera, dtype, wave, t_min, pool, return_counts, return_weights, crossing, gather
            )
        else:
            proj, spare = _project_compiled(kernels, cloud, camera, mode, max_sigma, pool, shapes, rows)
            order, number = _by_first_tile(proj, camera, tile_size)
            bins = _bin_compiled(kernels, proj, camera, tile_size, pool, number)
            compositor = _CompiledCompositor(
                kernels,
                proj,
                bins,
                order,
                camera,
                dtype,
                t_min,
                pool,
                return_counts,
                return_weights,
                layer,
                spare,
                gather,
            )
        images = compositor.images(progress)
        layer_t = None if layer is None else compositor.layer_transmittance(images[1])
        result = _finish(*images, bg, background, proj, bins, cloud, layer, layer_t, kernels, pool)
    result.stats["evaluated"] = compositor.evaluated
    result.stats["backend"] = "numpy" if kernels is None else "compiled"
    result.max_weight = compositor.max_weight(len(cloud)) if return_weights else None
    result.gathered = None if gather is None else compositor.gathered(len(cloud))
    return result


def _check_kernels(kernels):
    """Run the compiled kernels once on a small scene (compiling them, or loading them from the
    cache) and compare with the NumPy path: a broken build falls back to NumPy, not a wrong image."""

    rng = np.random.default_rng(0)
    n = 64
    cloud = SplatCloud(
        rng.normal(0, 0.3, (n, 3)) + [0, 0, 3],
        rng.normal(size=(n, 4)),
        rng.uniform(-3, -1.5, (n, 3)),
        rng.normal(1, 2, n),
        rng.normal(0, 0.3, (n, 25, 3)),
    )
    camera = Camera.look_at((0.4, 0.3, 0.0), (0, 0, 3), fov_deg=50, width=24, height=20)
    gather = rng.normal(size=(camera.height, camera.width, 2)).astype(np.float32)
    values, widest = _shape_values(kernels, cloud, Pool(1))
    shapes = SimpleNamespace(values=values, widest=widest)  # Shapes, without loading kernels
    for mode in MODES:
        args = (cloud, camera, np.zeros(3), (0, 0, 0), mode, True, True, 8, 32, T_MIN, None, np.float32, 1, None)
        for layer in (None, _check_layer(camera)):
            got, want = _render(kernels, *args, layer, gather), _render(None, *args, layer, gather)
            if (
                np.abs(got.color - want.color).max() > 1e-3
                or np.abs(got.max_weight - want.max_weight).max() > 1e-3
                or np.abs(got.gathered - want.gathered).max() > 1e-3
                or not np.array_equal(_render(kernels, *args, layer, gather, shapes).color, got.color)
            ):
                raise RuntimeError("the compiled render kernels disagree with the NumPy path on a test scene")
    rows = np.arange(1, n, 3)
    for own in (None, shapes):  # a subset, with the kernel's own shapes and with every splat's
        got, want = _render(kernels, *args, None, None, own, rows), _render(None, *args, None, None, None, rows)
        if np.abs(got.color - want.color).max() > 1e-3:
            raise RuntimeError("the compiled render kernels disagree with the NumPy path on a subset of a test scene")


def _check_layer(camera):
    """A half-transparent surface tilted through _check_kernels' scene."""
    shape = (camera.height, camera.width)
    depth = 2.6 + 0.05 * np.arange(camera.width)[None, :] + np.zeros(shape)
    return Layer(np.full(shape + (3,), 0.3), np.full(shape, 0.5), depth).checked(camera)


def kernels_loaded():
    """Whether this process has loaded (or given up on) the compiled kernels: when not, the next
    render first loads them, compiling them if the kernel cache lacks them (jit.cache_dir)."""
    return jit.loaded(KERNELS)


def backend_status():
    """'compiled' when the compiled kernels load here (loading them), else why the NumPy path is used."""
    jit.load(KERNELS, check=_check_kernels)
    return jit.status(KERNELS)


# memory -----------------------------------------------------------------------------------------


def image_bytes(width, height, tile_size=TILE_SIZE, counts=False, compiled=True):
    """Bytes a render of this size holds for its image buffers, whatever the cloud: the result's
    colour, alpha and depth and the working images (the NumPy path keeps five float32
    accumulators and a transmittance per pixel of whole tiles)."""
    pixels = width * height
    per_pixel = 12 + 4 + 4 + (4 if counts else 0)  # the result
    if compiled:
        per_pixel += 12 + 4 + 4 + (4 if counts else 0)  # colour, weight, depth sums
    else:
        tiled = -(-width // tile_size) * tile_size * -(-height // tile_size) * tile_size
        per_pixel += (20 + 4 + 1 + (4 if counts else 0)) * tiled / pixels + 20  # tiles, then one copy
    return int(pixels * per_pixel)


def check_image_memory(camera, tile_size=TILE_SIZE, counts=False, compiled=True):
    """Refuse (ValueError) an image whose buffers alone would take more than this machine's memory."""
    need, have = image_bytes(camera.width, camera.height, tile_size, counts, compiled), physical_memory()
    if have is not None and need > have:
        raise ValueError(
            f"a {camera.width}x{camera.height} render needs {need / 2**30:.1f} GiB for its image "
            f"buffers alone, more than this machine's {have / 2**30:.1f} GiB of memory; render it "
            "in pieces (a camera per piece: smaller width and height, cx and cy shifted)"
        )


# projection -----------------------------------------------------------------------------------

PROJECT_CHUNK = 1 << 16  # splats per projection task
EVERY = np.zeros(0, np.int64)  # the kernels' rows for "every splat, in order"


def project(cloud, camera, mode="classic", max_sigma=None, pool=None, rows=None):
    """Cull and project every splat (or those of `rows`, indices): pixel-space means, conics, extents
    and view-dependent colours of the visible ones, sorted front to back (equal depths keep input
    order)."""
    pool = pool or Pool(1)
    if rows is None:  # slices: views, not copies
        chunks = [slice(i, i + PROJECT_CHUNK) for i in range(0, len(cloud), PROJECT_CHUNK)] or [slice(0, 0)]
    else:
        chunks = [rows[i : i + PROJECT_CHUNK] for i in range(0, len(rows), PROJECT_CHUNK)] or [rows[:0]]
    parts = pool.map(lambda which: _project_chunk(cloud, which, camera, mode, max_sigma), chunks)
    skipped = sum(p.pop("skipped") for p in parts)
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    # Sort keys are float32 depths, as in the reference rasteriser: splats whose depths agree to
    # float32 precision are ties, kept in index order (chunks are in index order), so round-off in
    # a far-from-origin camera pose cannot reorder them.
    # (Positive float32 values sort like their bit patterns: two 16-bit radix passes.)
    order = stable_argsort(cols["z"].astype(np.float32).view(np.uint32), 1 << 32)
    records = new_records(len(order))
    np.take(cols["records"], order, axis=0, out=records[:-1])
    return Projected(cols["index"][order], records, cols["r2"][order], cols["bbox"][order], skipped)


def _project_chunk(cloud, which, camera, mode, max_sigma):
    """Projection of cloud[which] (a slice or indices), unsorted, as columns (float64 unless noted)."""
    idx = np.arange(len(cloud))[which] if isinstance(which, slice) else which
    fields = [getattr(cloud, name)[which] for name in ("positions", "rotations", "log_scales", "opacity_logits")]
    every = fields + [cloud.sh[which]]
    if not all(np.isfinite(f).all() for f in every):  # rare: find the bad splats
        good = np.logical_and.reduce([np.isfinite(f.reshape(len(f), -1)).all(axis=1) for f in every])
        idx, fields = idx[good], [f[good] for f in fields]
    skipped = len(every[-1]) - len(idx)
    positions, rotations, log_scales, logits = fields

    rel = positions.astype(np.float64) - camera.center  # world offsets from the eye
    cam = _rotate(rel, camera.rotation)
    z = cam[:, 2]
    opacity = sigmoid(logits)
    keep = np.flatnonzero((z > camera.near) & (z <= camera.far) & (opacity >= ALPHA_MIN))
    if len(keep) < len(z):
        idx, rel, cam, z, opacity = idx[keep], rel[keep], cam[keep], z[keep], opacity[keep]
        rotations, log_scales = rotations[keep], log_scales[keep]

    u, v, m0, m1 = screen_rows(cam, camera)
    rs = geometry.quaternions_to_matrices(rotations) * np.exp(log_scales.astype(np.float64))[:, None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        _, _, a, b, c, det0 = screen_covariance(m0, m1, rs)
        det = det0 + LOW_PASS * (a + c) + LOW_PASS * LOW_PASS
        if mode == "antialiased":
            opacity = opacity * np.sqrt(np.maximum(AA_MIN_RATIO, det0 / det))
        r2 = 2.0 * np.log(np.maximum(255.0 * opacity, 1e-300))
        if max_sigma is not None:
            r2 = np.minimum(r2, float(max_sigma) ** 2)
        a, c = a + LOW_PASS, c + LOW_PASS
        half_x, half_y = np.sqrt(r2 * a), np.sqrt(r2 * c)
    finite = np.isfinite(det) & np.isfinite(u) & np.isfinite(v)
    skipped += int((~finite).sum())
    box = [
        np.maximum(np.ceil(np.clip(u - half_x - 0.5, -1.0, camera.width)), 0),
        np.maximum(np.ceil(np.clip(v - half_y - 0.5, -1.0, camera.height)), 0),
        np.minimum(np.floor(np.clip(u + half_x - 0.5, -1.0, camera.width)), camera.width - 1),
        np.minimum(np.floor(np.clip(v + half_y - 0.5, -1.0, camera.height)), camera.height - 1),
    ]
    sel = np.flatnonzero(finite & (r2 > 0) & (box[0] <= box[2]) & (box[1] <= box[3]))

    if camera.is_orthographic:  # parallel rays: every splat is seen along the camera axis
        directions = np.broadcast_to(camera.forward, (len(sel), 3))
    else:
        directions = rel[sel]
    rgb = shmod.colors(cloud.sh[idx[sel]], directions) if len(sel) else np.zeros((0, 3))
    d = det[sel]
    records = new_records(len(sel))[:-1]
    records[:, 0], records[:, 1] = u[sel], v[sel]
    records[:, 2], records[:, 3], records[:, 4] = c[sel] / d, -b[sel] / d, a[sel] / d  # the conic
    floats = record_floats(records)
    floats[:, 0], floats[:, 1:4], floats[:, 4], floats[:, 5] = np.log(opacity[sel]), rgb, z[sel], 1.0
    bbox = np.empty((len(sel), 4), dtype=np.int64)
    for k, x in enumerate(box):
        bbox[:, k] = x[sel]
    return {"index": idx[sel], "z": z[sel], "records": records, "r2": r2[sel], "bbox": bbox, "skipped": skipped}


def _rotate(points, rotation):
    """points @ rotation.T, written out: a BLAS product this thin would start BLAS's own threads."""
    out = np.empty_like(points)
    for k in range(3):
        out[:, k] = points[:, 0] * rotation[k, 0] + points[:, 1] * rotation[k, 1] + points[:, 2] * rotation[k, 2]
    return out


# the compiled path -----------------------------------------------------------------------------------


class Shapes:
    """What projecting a cloud's splats needs that no camera changes: each splat's R S (its rotation
    times its scales) and opacity, in float64 (80 bytes a splat). Renders of the same splats from
    many cameras (a refinement's measures, a bake's fit) pass one to render(): the projection
    kernel then runs about 40% faster (the Franka hand's 497k splats on one core: 33 ms a view
    instead of 55, plus 18 ms once for these), a whole 256 px render about 10%. Beside them, each
    splat's widest scale (`widest`, (n,) float64), which a light's maps and a picture's culling
    take their splats' reach from (core.shadow_cameras.reach_and_gap).

    It holds the arrays it was made from, and render() takes it only with a cloud holding those
    very arrays (positions and colours may be others: a shifted or recoloured copy). Arrays changed
    in place afterwards need new Shapes. Without compiled kernels it holds nothing (the NumPy path
    projects as it always does)."""

    FIELDS = ("rotations", "log_scales", "opacity_logits")

    def __init__(self, cloud, threads=None):
        self.sources = tuple(getattr(cloud, name) for name in self.FIELDS)
        kernels = jit.load(KERNELS, check=_check_kernels)
        with Pool(threads) as pool:
            self.values, self.widest = (None, None) if kernels is None else _shape_values(kernels, cloud, pool)

    def fits(self, cloud):
        """Whether `cloud` holds the arrays these were made from."""
        return all(getattr(cloud, name) is source for name, source in zip(self.FIELDS, self.sources))


def _shape_values(kernels, cloud, pool):
    """Shapes' (n, 10) values and (n,) widest scales of `cloud`, chunk by chunk on every core."""
    n = len(cloud)
    fields = [np.ascontiguousarray(getattr(cloud, name), dtype=np.float32) for name in Shapes.FIELDS]
    values, widest = scratch.empty((n, 10)), scratch.empty(n)
    pool.map(
        lambda lo: kernels.shape_range(*fields, EVERY, lo, min(lo + PROJECT_CHUNK, n), values, 0, widest),
        list(range(0, n, PROJECT_CHUNK)),
    )
    return values, widest


def _project_compiled(kernels, cloud, camera, mode, max_sigma, pool, shapes=None, rows=None):
    """project() by the compiled kernel: the same Projected, built chunk by chunk on every core, and
    the (records, bbox) it was projected into before the depth sort, for the compositor to reuse
    (fresh memory costs a page fault per 4 KiB: at 4K, a quarter of the render's time went there)."""
    n = len(cloud) if rows is None else len(rows)
    fields = [
        np.ascontiguousarray(getattr(cloud, name), dtype=np.float32)
        for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh")
    ]
    fields.append(np.zeros((0, 10)) if shapes is None or shapes.values is None else shapes.values)
    records = new_records(n)
    index, depth = scratch.empty(n, np.int64), scratch.empty(n, np.float32)
    r2, bbox = scratch.empty(n), scratch.empty((n, 4), np.int32)
    w, h = camera.width, camera.height
    mx, my = (FRUSTUM_MARGIN - 1) / 2 * w, (FRUSTUM_MARGIN - 1) / 2 * h
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    clip = np.array(
        [
            camera.near,
            camera.far,
            (-camera.cx - mx) / camera.fx,
            (w - camera.cx + mx) / camera.fx,
            (-camera.cy - my) / camera.fy,
            (h - camera.cy + my) / camera.fy,
        ]
    )
    max_r2 = math.inf if max_sigma is None else float(max_sigma) ** 2
    rotation = np.ascontiguousarray(camera.rotation)
    rec32 = records.view(np.float32)

    def run(lo):
        hi = min(lo + PROJECT_CHUNK, n)
        return lo, *kernels.project_range(
            *fields,
            EVERY if rows is None else rows,
            lo,
            hi,
            camera.center,
            rotation,
            intrinsics,
            np.array([w, h]),
            clip,
            camera.is_orthographic,
            mode == "antialiased",
            max_r2,
            records,
            rec32,
            index,
            depth,
            r2,
            bbox,
        )

    parts = pool.map(run, list(range(0, n, PROJECT_CHUNK)))
    rows = np.concatenate([np.arange(lo, lo + count) for lo, count, _ in parts] or [np.zeros(0, np.int64)])
    # float32 depth keys, ties in index order (see project())
    by_depth = scratch.empty(rows.shape, rows.dtype)
    kernels.stable_order(depth.view(np.uint32), rows, by_depth)
    rows = by_depth
    m = len(rows)
    proj = Projected(
        scratch.empty(m, np.int64),
        new_records(m),
        scratch.empty(m),
        scratch.empty((m, 4), np.int32),
        sum(skipped for _, _, skipped in parts),
    )
    bounds = np.linspace(0, m, pool.threads + 1).astype(np.int64)
    pool.map(
        lambda k: kernels.gather(
            rows, bounds[k], bounds[k + 1], records, bbox, r2, index, proj.records, proj.bbox, proj.r2, proj.index
        ),
        list(range(pool.threads)),
    )
    return proj, (records, bbox)


def _bin_compiled(kernels, proj, camera, tile_size, pool, number=None):
    """bin_tiles() by the compiled kernels: count each chunk's entries per tile, then place them.
    Entries hold number[splat] when given (a renumbering of the splats), else the splat."""
    ts = tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    n_tiles, n = tiles_x * tiles_y, len(proj)
    number = np.arange(n, dtype=np.int32) if number is None else number
    bounds = np.linspace(0, n, 2 * pool.threads + 1 if n > 10000 else 2).astype(np.int64)
    chunks = list(range(len(bounds) - 1))
    rec64 = proj.records
    rows = proj.bbox[:, 3] // ts - proj.bbox[:, 1] // ts + 1  # tile rows of each splat
    first_row = np.zeros(n + 1, np.int64)
    np.cumsum(rows, out=first_row[1:])
    spans = scratch.empty((int(first_row[-1]), 2), np.int32)  # tile columns per splat and row
    counts = np.zeros((len(chunks), n_tiles), np.int64)
    pool.map(
        lambda k: kernels.count_tiles(
            rec64, proj.r2, proj.bbox, bounds[k], bounds[k + 1], ts, tiles_x, first_row, spans, counts[k]
        ),
        chunks,
    )
    offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    np.cumsum(counts.sum(axis=0), out=offsets[1:])
    cursor = offsets[:-1] + np.cumsum(counts, axis=0) - counts  # where each chunk's run begins
    entry_splat = scratch.empty(int(offsets[-1]), np.int32)
    pool.map(
        lambda k: kernels.fill_tiles(
            proj.bbox, bounds[k], bounds[k + 1], ts, tiles_x, first_row, spans, number, cursor[k], entry_splat
        ),
        chunks,
    )
    return Bins(ts, tiles_x, tiles_y, entry_splat, offsets)


def _by_first_tile(proj, camera, tile_size):
    """Splat numbers in the order of the block of tiles holding their box's top-left corner (then
    depth): records stored so put a tile's entries near each other in memory. A block is one tile,
    or 2x2, 4x4, ... where that keeps the blocks within one 16-bit radix pass (4K at 8 px tiles:
    one pass instead of two, the same locality). Returns (order, number), number the inverse of
    order."""
    block = tile_size
    while -(-camera.width // block) * -(-camera.height // block) > 1 << 16:
        block *= 2
    blocks_x = -(-camera.width // block)
    order = stable_argsort(proj.bbox[:, 1] // block * blocks_x + proj.bbox[:, 0] // block, 1 << 16)
    number = scratch.empty(len(order), np.int32)
    number[order] = np.arange(len(order), dtype=np.int32)
    return order, number


class _CompiledCompositor:
    """Every tile composited by the compiled kernel, straight into image arrays; the tiles are
    split into runs of similar work, handed to the cores in turn. The kernel reads the records
    in the order `order` (entries number them so)."""

    RUNS_PER_THREAD = 16

    def __init__(
        self,
        kernels,
        proj,
        bins,
        order,
        camera,
        dtype,
        t_min,
        pool,
        want_counts,
        want_weights,
        layer=None,
        spare=None,
        gather=None,
    ):
        self.kernels, self.proj, self.bins, self.order, self.camera = kernels, proj, bins, order, camera
        self.spare = spare  # (records, bbox) at least as long as proj's, free to overwrite
        self.dtype, self.t_min, self.pool = dtype, float(t_min), pool
        h, w = camera.height, camera.width
        self.color = scratch.empty((h, w, 3), np.float32)
        self.weight, self.depth_sum = scratch.empty((h, w), np.float32), scratch.empty((h, w), np.float32)
        self.counts = np.empty((h, w), np.int32) if want_counts else np.zeros((0, 0), np.int32)
        self.peaks = np.zeros(len(bins.entry_splat), np.float32) if want_weights else np.zeros(0, np.float32)
        # the gather image and each entry's sum of weight x image (written by the kernel)
        self.gather_image = np.zeros((0, 0, 0), np.float32) if gather is None else gather
        self.entry_sums = np.zeros(
            (0 if gather is None else len(bins.entry_splat), 0 if gather is None else gather.shape[2])
        )
        # the layer's depth and 1 - alpha, and T where each pixel reached it (written by the kernel)
        empty = np.zeros((0, 0), np.float32)
        self.layer_depth = empty if layer is None else layer.depth
        self.layer_keep = empty if layer is None else 1.0 - layer.alpha
        self.layer_t = empty if layer is None else np.empty((h, w), np.float32)
        self.evaluated = 0

    def layer_transmittance(self, weight):
        return self.layer_t

    def _runs(self):
        """Consecutive tile ranges of about equal entry counts (empty tiles still need writing)."""
        bins = self.bins
        work = bins.offsets + np.arange(bins.n_tiles + 1)  # entries, and one per tile
        parts = self.RUNS_PER_THREAD * self.pool.threads
        cuts = np.searchsorted(work, np.linspace(0, work[-1], parts + 1)[1:-1])
        return [r for r in zip(np.r_[0, cuts], np.r_[cuts, bins.n_tiles]) if r[1] > r[0]]

    def _records(self):
        """The records and boxes in the order the entries number them."""
        proj, n = self.proj, len(self.proj)
        if self.spare is None:
            records, bbox = new_records(n), scratch.empty((n, 4), np.int32)
        else:
            records, bbox = self.spare[0][:n], self.spare[1][:n]
        empty, empty_index = np.zeros(0), np.zeros(0, np.int64)  # r2 and index stay behind
        bounds = np.linspace(0, n, self.pool.threads + 1).astype(np.int64)
        self.pool.map(
            lambda k: self.kernels.gather(
                self.order,
                bounds[k],
                bounds[k + 1],
                proj.records,
                proj.bbox,
                empty,
                empty_index,
                records,
                bbox,
                empty,
                empty_index,
            ),
            list(range(self.pool.threads)),
        )
        return records, bbox

    def images(self, progress=None):
        bins, cam = self.bins, self.camera
        records, bbox = self._records()
        rec32 = records.view(np.float32)
        k = self.kernels.exp_constants(self.dtype)
        ts = bins.tile_size

        def run(span):
            return span, self.kernels.composite_tiles(
                np.arange(*span),
                bins.offsets,
                bins.entry_splat,
                records,
                rec32,
                bbox,
                ts,
                bins.tiles_x,
                cam.width,
                cam.height,
                self.t_min,
                k,
                self.color,
                self.weight,
                self.depth_sum,
                self.counts,
                self.peaks,
                self.layer_depth,
                self.layer_keep,
                self.layer_t,
                self.gather_image,
                self.entry_sums,
            )

        done = 0
        for (lo, hi), evaluated in self.pool.imap(run, self._runs()):
            self.evaluated += evaluated
            done += hi - lo
            if progress is not None:
                progress(done, bins.n_tiles, "render")
        return self.color, self.weight, self.depth_sum, self.counts if self.counts.size else None

    def max_weight(self, n_cloud):
        """(n_cloud,) float32: the largest weight of every input splat, 0 for those not projected."""
        best = np.zeros(len(self.proj), np.float32)
        self.kernels.peak_per_splat(self.bins.entry_splat, self.peaks, best)
        out = np.zeros(n_cloud, np.float32)
        out[self.proj.index[self.order]] = best
        return out

    def gathered(self, n_cloud):
        """(n_cloud, C) float64: the gather image's weighted sum of every input splat."""
        sums = np.zeros((len(self.proj), self.entry_sums.shape[1]))
        self.kernels.sum_per_splat(self.bins.entry_splat, self.entry_sums, sums)
        out = np.zeros((n_cloud, sums.shape[1]))
        out[self.proj.index[self.order]] = sums
        return out


def _finish(
    color,
    weight,
    depth_sum,
    counts,
    bg,
    background,
    proj,
    bins,
    cloud,
    layer=None,
    layer_t=None,
    kernels=None,
    pool=None,
):
    """Image sums (colour and depth weighted by T alpha, and the weight) -> the result; with a layer,
    its colour at the T each pixel reached it with (layer_t) goes in, before the background.
    The compiled kernels (when given) do it on every core of `pool`."""
    if kernels is not None:
        alpha, depth = scratch.empty(weight.shape, np.float32), scratch.empty(weight.shape, np.float32)
        bounds = np.linspace(0, len(weight), pool.threads + 1).astype(np.int64)
        bg32 = np.zeros(0, np.float32) if bg is None else bg.astype(np.float32)
        none = np.zeros((0, 0), np.float32)
        layer_arrays = (
            (none, np.zeros((0, 0, 3), np.float32), none) if layer is None else (layer_t, layer.color, layer.alpha)
        )
        pool.map(
            lambda k: kernels.finish_rows(
                color, weight, depth_sum, bg32, bounds[k], bounds[k + 1], alpha, depth, *layer_arrays
            ),
            list(range(pool.threads)),
        )
    else:
        alpha = np.clip(weight, 0.0, 1.0).astype(np.float32)
        color = np.ascontiguousarray(color, dtype=np.float32)
        if layer is not None:
            color += layer_t[..., None] * layer.color
            alpha = np.clip(alpha + layer_t * layer.alpha, 0.0, 1.0)
        if bg is not None:
            color += (1.0 - alpha)[..., None] * bg.astype(np.float32)
        depth = np.zeros_like(alpha)
        np.divide(depth_sum, weight, out=depth, where=weight > 0)
    stats = {
        "input": len(cloud),
        "skipped_nonfinite": proj.skipped_nonfinite,
        "visible": len(proj),
        "entries": len(bins.entry_splat),
    }
    return RenderResult(
        color=color,
        alpha=alpha,
        depth=depth,
        counts=counts,
        background=None if background is None else tuple(float(x) for x in bg),
        stats=stats,
        layer_transmittance=layer_t,
    )
