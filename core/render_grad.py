"""The renderer's backward pass: an image loss's gradient with respect to every splat parameter.

The image is core.render's (the same culling, EWA projection, low-pass, antialiased opacity, alpha
rule, transmittance stop and depth order), computed tile by tile as dense (pixels, splats) arrays in
float64, and each tile's backward pass runs through the same arrays while they are at hand. The loss
is per pixel (the mean squared error against a target image), so a tile's gradient needs nothing
from other tiles.

Per pixel, with splats k front to back, T_k = prod_{j<k} (1 - alpha_j) and w_k = alpha_k T_k:

    C = sum_k w_k c_k + T_n bg
    dC/dalpha_k = T_k c_k - (sum_{j>k} w_j c_j + T_n bg) / (1 - alpha_k)

and alpha_k = o_k exp(power_k(u_k, v_k, conic_k)), whose chain through the projection back to the
positions, quaternions, log scales and opacity logits is written out per splat in _chain.
Held fixed: which splats pass the alpha and transmittance rules and the 0.99 clamp, and the
Jacobian's frustum clamp (their gradient is zero where they switch). The SH colour's dependence on
the view direction reaches the position through the basis' own gradient (core.sh.basis_gradient).
"""

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import geometry, jit
from . import sh as shmod
from .parallel import WORKERS, map_threads
from .render_constants import AA_MIN_RATIO, ALPHA_MAX, ALPHA_MIN, LOW_PASS, PRECISIONS, T_MIN
from .render_tiles import clamped_ratios, screen_covariance, screen_rows
from .splats import FIELDS, sigmoid

TILE = 16
KERNELS = "core.render_grad_kernels"  # the compiled tile passes, loaded by core.jit
BACKENDS = ("auto", "compiled", "numpy")
# columns of the per-splat sums the tile passes return
UV, CONIC, OPACITY, RGB = slice(0, 2), slice(2, 5), 5, slice(6, 9)


@dataclass
class Gradients:
    """d loss / d parameter, float64, shaped like the cloud's arrays."""

    positions: np.ndarray
    rotations: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray


def mse_gradients(
    cloud, camera, target, background=(0.0, 0.0, 0.0), mode=None, precision="float32", threads=None, backend="auto"
):
    """(image, mean squared error against `target` (H, W, 3), Gradients of that error).

    backend: "compiled" (core/render_grad_kernels.py, float64 throughout), "numpy" (the dense tile
    arrays below) or "auto" (compiled when numba loads). precision: of the NumPy path's per-pixel
    work, "float32" (twice as fast) or "float64"; the per-splat projection and chain rule are
    float64 either way."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    dtype = PRECISIONS[precision]
    mode = mode or ("antialiased" if cloud.antialiased else "classic")
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (camera.height, camera.width, 3):
        raise ValueError(f"target image must be {(camera.height, camera.width, 3)}, got {target.shape}")
    kernels = None if backend == "numpy" else jit.load(KERNELS, check=_check_kernels)
    if kernels is None and backend == "compiled":
        raise RuntimeError(f"compiled backward kernels are not available: {jit.status(KERNELS)}")
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    proj = _Projection(cloud, camera, mode)
    image = np.empty((camera.height, camera.width, 3))
    image[:] = bg  # tiles no splat touches
    tiles = proj.tile_lists()
    share = max(1, int(threads or WORKERS))
    jobs = [np.arange(i, len(tiles.ids), share) for i in range(share)]
    run = _compiled_tiles if kernels is not None else _numpy_tiles
    parts = map_threads(lambda part: run(kernels, proj, tiles, part, target, bg, dtype, image), jobs, threads)
    acc = sum(parts)
    mse = float(np.mean((image - target) ** 2))
    return image, mse, proj.chain(acc, cloud)


def _numpy_tiles(_, proj, tiles, jobs, target, bg, dtype, image):
    """Tiles `jobs` by dense (pixels, splats) arrays: their image, and their gradient sums per splat
    (n, 9: d/du, d/dv, d/d conic a, b, c, d/d opacity, d/d rgb)."""
    camera = proj.camera
    acc = np.zeros((len(proj.index), 9))
    scale = 2.0 / image.size
    for j in jobs:
        ty, tx = divmod(int(tiles.ids[j]), tiles.across)
        y0, x0 = ty * TILE, tx * TILE
        y1, x1 = min(y0 + TILE, camera.height), min(x0 + TILE, camera.width)
        ys, xs = np.mgrid[y0:y1, x0:x1]
        tile = _Tile(
            proj, tiles.members[tiles.starts[j] : tiles.ends[j]], xs.ravel() + 0.5, ys.ravel() + 0.5, bg, dtype
        )
        color = tile.color.reshape(y1 - y0, x1 - x0, 3)
        image[y0:y1, x0:x1] = color
        tile.backward(scale * (color - target[y0:y1, x0:x1]).reshape(-1, 3), acc)
    return acc


def _compiled_tiles(kernels, proj, tiles, jobs, target, bg, _, image):
    """_numpy_tiles by the compiled kernel (float64)."""
    acc = np.zeros((len(proj.index), 9))
    camera = proj.camera
    kernels.tile_passes(
        jobs,
        tiles.ids,
        tiles.starts,
        tiles.ends,
        tiles.members,
        TILE,
        camera.width,
        camera.height,
        proj.uv,
        proj.conic,
        proj.opacity,
        proj.box,
        proj.rgb,
        target,
        bg,
        2.0 / image.size,
        image,
        acc,
    )
    return acc


def _check_kernels(kernels):
    """Run the compiled kernel once on a small scene (compiling it, or loading it from the cache)
    and compare with the NumPy path: a broken build falls back to NumPy, not wrong gradients."""
    from .camera import Camera
    from .splats import SplatCloud

    rng = np.random.default_rng(0)
    n = 64
    cloud = SplatCloud(
        rng.normal(0, 0.3, (n, 3)) + [0, 0, 3],
        rng.normal(size=(n, 4)),
        rng.uniform(-3, -1.5, (n, 3)),
        rng.normal(1, 2, n),
        rng.normal(0, 0.3, (n, 4, 3)),
    )
    camera = Camera.look_at((0.4, 0.3, 0.0), (0, 0, 3), fov_deg=50, width=40, height=20)
    target = rng.uniform(0, 1, (camera.height, camera.width, 3))
    for mode in ("classic", "antialiased"):
        proj = _Projection(cloud, camera, mode)
        tiles, bg = proj.tile_lists(), np.array([0.1, 0.2, 0.3])
        jobs = np.arange(len(tiles.ids))
        images = [np.zeros(target.shape), np.zeros(target.shape)]
        got = _compiled_tiles(kernels, proj, tiles, jobs, target, bg, None, images[0])
        want = _numpy_tiles(None, proj, tiles, jobs, target, bg, np.float64, images[1])
        if not (
            np.allclose(images[0], images[1], atol=1e-9) and np.allclose(got, want, atol=1e-9 * np.abs(want).max())
        ):
            raise RuntimeError("the compiled backward kernel disagrees with the NumPy path on a test scene")


class TileLists(NamedTuple):
    """The tiles some splat touches: tile j is ids[j] (row-major, `across` per row), its splats
    members[starts[j]:ends[j]] (indices into the projection's arrays) front to back."""

    ids: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    members: np.ndarray
    across: int


class _Projection:
    """Every visible splat projected as core.render projects it, with what the chain rule needs."""

    def __init__(self, cloud, camera, mode):
        self.camera = camera
        pos = cloud.positions.astype(np.float64)
        rel = pos - camera.center
        cam = rel @ camera.rotation.T
        z = cam[:, 2]
        opacity = sigmoid(cloud.opacity_logits.astype(np.float64))
        finite = np.logical_and.reduce(
            [np.isfinite(getattr(cloud, name).reshape(len(pos), -1)).all(1) for name in FIELDS]
        )
        keep = np.flatnonzero(finite & (z > camera.near) & (z <= camera.far) & (opacity >= ALPHA_MIN))
        self.index, rel, cam, opacity = keep, rel[keep], cam[keep], opacity[keep]
        self.cam, self.sigmoid = cam, opacity
        self.quats = cloud.rotations[keep].astype(np.float64)
        self.scales = np.exp(cloud.log_scales[keep].astype(np.float64))
        self.rot = geometry.quaternions_to_matrices(self.quats)
        self.rs = self.rot * self.scales[:, None, :]
        self._screen(cam, camera)
        v0, v1, a, b, c, det0 = screen_covariance(self.m0, self.m1, self.rs)
        det = det0 + LOW_PASS * (a + c) + LOW_PASS**2
        self.v0, self.v1, self.abc, self.det0, self.det = v0, v1, (a, b, c), det0, det
        self.ratio = det0 / det
        self.aa = mode == "antialiased"
        o = opacity * np.sqrt(np.maximum(AA_MIN_RATIO, self.ratio)) if self.aa else opacity
        self.opacity = o
        self.conic = np.stack([(c + LOW_PASS) / det, -b / det, (a + LOW_PASS) / det], 1)
        if camera.is_orthographic:
            directions = np.broadcast_to(camera.forward, rel.shape)
        else:
            directions = rel
        self.degree = shmod.degree_of(cloud.sh.shape[1])
        self.basis = shmod.basis(directions, self.degree)
        self.rel, self.sh = rel, cloud.sh[keep].astype(np.float64)
        raw = 0.5 + np.einsum("nk,nkc->nc", self.basis, self.sh)
        self.unclamped = raw > 0
        self.rgb = np.maximum(raw, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            r2 = 2.0 * np.log(np.maximum(255.0 * o, 1e-300))
            half = np.sqrt(np.maximum(r2, 0)[:, None] * (np.stack([a, c], 1) + LOW_PASS))
        self.box = np.concatenate([self.uv - half - 0.5, self.uv + half - 0.5], 1)
        self.visible = (r2 > 0) & np.isfinite(det) & np.isfinite(self.uv).all(1)
        self.depth_order = np.argsort(z[keep].astype(np.float32), kind="stable")

    def _screen(self, cam, camera):
        """Pixel means and the rows of J W (core.render's), and which x/z, y/z the frustum clamp left
        free to follow the position."""
        u, v, self.m0, self.m1 = screen_rows(cam, camera)
        self.uv = np.stack([u, v], 1)
        if not camera.is_orthographic:
            ratios = cam[:, :2] / cam[:, 2:]
            self.free = np.stack(clamped_ratios(*ratios.T, camera), 1) == ratios

    def tile_lists(self):
        """The tiles some splat touches (TileLists: their splats front to back)."""
        cam = self.camera
        nx = -(-cam.width // TILE)
        order = self.depth_order[self.visible[self.depth_order]]
        box = self.box[order]
        lo = np.floor(np.clip(np.ceil(box[:, :2]), 0, None) / TILE).astype(np.int64)
        hi = np.floor(np.minimum(np.floor(box[:, 2:]), [cam.width - 1, cam.height - 1]) / TILE).astype(np.int64)
        inside = (
            (hi >= lo).all(1)
            & (np.floor(box[:, 2:]) >= 0).all(1)
            & (np.ceil(box[:, 0]) <= cam.width - 1)
            & (np.ceil(box[:, 1]) <= cam.height - 1)
        )
        order, lo, hi = order[inside], lo[inside], hi[inside]
        span = hi - lo + 1
        count = span[:, 0] * span[:, 1]
        owner = np.repeat(np.arange(len(order)), count)
        k = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
        tx = lo[owner, 0] + k % span[owner, 0]
        ty = lo[owner, 1] + k // span[owner, 0]
        tile = ty * nx + tx
        by_tile = np.argsort(tile, kind="stable")  # stays front to back within a tile
        tile, members = tile[by_tile], order[owner[by_tile]]
        starts = np.flatnonzero(np.r_[True, tile[1:] != tile[:-1]]) if len(tile) else np.zeros(0, np.int64)
        ends = np.r_[starts[1:], len(tile)].astype(np.int64)
        return TileLists(tile[starts], starts, ends, members, nx)

    def chain(self, acc, cloud):
        """Per-splat gradients of the tiles' sums, back to the cloud's parameters."""
        grad = Gradients(*(np.zeros(getattr(cloud, name).shape) for name in FIELDS))
        k = self.index
        g_rgb = acc[:, RGB] * self.unclamped
        grad.sh[k] = self.basis[:, :, None] * g_rgb[:, None, :]
        g_abc, g_sig = self._opacity_and_conic(acc)
        g_v0, g_v1 = (
            2 * g_abc[0][:, None] * self.v0 + g_abc[1][:, None] * self.v1,
            2 * g_abc[2][:, None] * self.v1 + g_abc[1][:, None] * self.v0,
        )
        g_rs = self.m0[:, :, None] * g_v0[:, None, :] + self.m1[:, :, None] * g_v1[:, None, :]
        g_m0, g_m1 = np.einsum("njk,nk->nj", self.rs, g_v0), np.einsum("njk,nk->nj", self.rs, g_v1)
        grad.log_scales[k] = (g_rs * self.rot).sum(1) * self.scales
        grad.rotations[k] = _quaternion_gradient(self.quats, g_rs * self.scales[:, None, :])
        grad.opacity_logits[k] = g_sig * self.sigmoid * (1 - self.sigmoid)
        grad.positions[k] = self._position_gradient(acc[:, UV], g_m0, g_m1) @ self.camera.rotation
        if self.degree and not self.camera.is_orthographic:
            grad.positions[k] += self._direction_gradient(g_rgb)
        return grad

    def _direction_gradient(self, g_rgb):
        """d loss / d position through the view direction in the SH colour."""
        return shmod.basis_gradient(np.einsum("nkc,nc->nk", self.sh, g_rgb), self.rel)

    def _opacity_and_conic(self, acc):
        """Gradients of a, b, c (Sigma2D before the low-pass) and of the sigmoid of the logit."""
        a, b, c = self.abc
        A, B, C = self.conic.T
        gA, gB, gC = acc[:, CONIC].T
        # conic Q = Sigma'^-1 with Sigma' = Sigma2D + low-pass: dL/dSigma' = -Q G Q, G = [[gA, gB/2], [gB/2, gC]]
        h = gB / 2
        qg00, qg01, qg10, qg11 = A * gA + B * h, A * h + B * gC, B * gA + C * h, B * h + C * gC
        ga, gb, gc = -(qg00 * A + qg01 * B), -2 * (qg00 * B + qg01 * C), -(qg10 * B + qg11 * C)
        g_sig = acc[:, OPACITY]
        if self.aa:
            root = np.sqrt(np.maximum(AA_MIN_RATIO, self.ratio))
            g_ratio = np.where(self.ratio > AA_MIN_RATIO, acc[:, OPACITY] * self.sigmoid / (2 * root), 0.0)
            g_sig = acc[:, OPACITY] * root
            det, det0 = self.det, self.det0
            ga = ga + g_ratio * (c * det - det0 * (c + LOW_PASS)) / det**2
            gc = gc + g_ratio * (a * det - det0 * (a + LOW_PASS)) / det**2
            gb = gb + g_ratio * (-2 * b * (det - det0)) / det**2
        return (ga, gb, gc), g_sig

    def _position_gradient(self, g_uv, g_m0, g_m1):
        """d loss / d camera-space position, through the pixel mean and the Jacobian rows."""
        cam, camera = self.cam, self.camera
        if camera.is_orthographic:
            return np.stack([camera.fx * g_uv[:, 0], camera.fy * g_uv[:, 1], np.zeros(len(cam))], 1)
        x, y, z = cam.T
        r2 = camera.rotation[2]
        g_t = -np.stack([(g_m0 @ r2) * camera.fx / z, (g_m1 @ r2) * camera.fy / z], 1) * self.free
        g_t += g_uv * [camera.fx, camera.fy]
        gz = -((self.m0 * g_m0).sum(1) + (self.m1 * g_m1).sum(1)) / z
        gz -= (g_t[:, 0] * x + g_t[:, 1] * y) / z**2
        return np.stack([g_t[:, 0] / z, g_t[:, 1] / z, gz], 1)


class _Tile:
    """One tile's pixels against its splats, front to back: the colour, then the backward pass."""

    def __init__(self, proj, members, px, py, bg, dtype):
        self.proj, self.members, self.bg, self.dtype = proj, members, bg, dtype
        u, v = proj.uv[members].T
        A, B, C = proj.conic[members].astype(dtype).T
        dx, dy = (px[:, None] - u).astype(dtype), (py[:, None] - v).astype(dtype)
        self.dx, self.dy = dx, dy
        self.gauss = np.exp(-0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy)
        raw = proj.opacity[members].astype(dtype) * self.gauss
        alpha = np.where(raw >= ALPHA_MIN, np.minimum(raw, ALPHA_MAX), 0.0)
        on = np.cumprod(1 - alpha, axis=1) >= T_MIN  # stop before T would drop below T_MIN
        self.alpha = np.where(on, alpha, 0.0)
        self.moving = on & (raw >= ALPHA_MIN) & (raw < ALPHA_MAX)
        t_after = np.cumprod(1 - self.alpha, axis=1)
        self.t_before = np.concatenate([np.ones((len(px), 1), dtype), t_after[:, :-1]], 1)
        self.t_final = t_after[:, -1]
        self.weight = self.alpha * self.t_before
        self.rgb = proj.rgb[members].astype(dtype)
        self.color = self.weight @ self.rgb + self.t_final[:, None] * bg

    def backward(self, g_color, acc):
        p, m = self.proj, self.members
        g_color = g_color.astype(self.dtype)
        acc[m, RGB] += self.weight.T @ g_color
        g_weight = g_color @ self.rgb.T
        behind = np.cumsum((self.weight * g_weight)[:, ::-1], axis=1)[:, ::-1] - self.weight * g_weight
        behind += (self.t_final * (g_color @ self.bg.astype(self.dtype)))[:, None]
        g_alpha = np.where(self.moving, self.t_before * g_weight - behind / (1 - self.alpha), 0.0)
        acc[m, OPACITY] += (g_alpha * self.gauss).sum(0)
        g_power = g_alpha * self.alpha
        dx, dy = self.dx, self.dy
        A, B, C = p.conic[m].astype(self.dtype).T
        acc[m, CONIC] += np.stack(
            [-0.5 * (g_power * dx * dx).sum(0), -(g_power * dx * dy).sum(0), -0.5 * (g_power * dy * dy).sum(0)], 1
        )
        acc[m, UV] += np.stack([(g_power * (A * dx + B * dy)).sum(0), (g_power * (C * dy + B * dx)).sum(0)], 1)


def _quaternion_gradient(q, g_rot):
    """d loss / d q (w, x, y, z, not necessarily unit) from d loss / d R(q / |q|)."""
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    unit = q / norm
    w, x, y, z = unit.T
    g = g_rot.reshape(-1, 9)
    zero = np.zeros_like(w)
    parts = [
        [zero, -2 * z, 2 * y, 2 * z, zero, -2 * x, -2 * y, 2 * x, zero],  # d R / d w
        [zero, 2 * y, 2 * z, 2 * y, -4 * x, -2 * w, 2 * z, 2 * w, -4 * x],  # d R / d x
        [-4 * y, 2 * x, 2 * w, 2 * x, zero, 2 * z, -2 * w, 2 * z, -4 * y],  # d R / d y
        [-4 * z, -2 * w, 2 * x, 2 * w, -4 * z, 2 * y, 2 * x, 2 * y, zero],  # d R / d z
    ]
    g_unit = np.stack([(np.stack(d, 1) * g).sum(1) for d in parts], 1)
    return (g_unit - unit * (unit * g_unit).sum(1, keepdims=True)) / norm
