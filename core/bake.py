"""Appearance baking: the SH colours with which fixed splats reproduce a set of reference images.

Positions, shapes and opacities stay as they are; only the SH coefficients x are fitted. With the
geometry fixed a render is affine in x: pixel i of view v is

    sum_j w_ij (0.5 + sum_k Y_k(d_jv) x_jk) + T_i background,

w_ij = T alpha the blending weights, d_jv the direction from view v's eye to splat j (the clamp of
colours at 0 is ignored while fitting). bake_sh solves the least-squares problem over all views,
damped towards a prior (Tikhonov: splats that few views see keep it), by
conjugate gradients on the normal equations (A^T W A + lambda I) x = A^T W b (W: each view's
weight on its pixels), the three colour channels
side by side. The prior (start and damping target) is by default each splat's mean lit colour over
the images, so what the views leave undetermined falls back to the local colour. Each step is one
render and one gather per view:
- A p is a render of the colour field Y p (a degree-0 cloud with those colours, shifted to be
  non-negative so nothing is clamped, the shift taken off again through the alpha);
- A^T r is the residual image gathered through the weights (core.render's `gather`), times Y per
  splat.
Views are small, so each renders on one core, the views spread over the cores.
The preconditioner is a Jacobi estimate: sum over views of the view's weight x Y_k^2 x (sum of
blending weights) x (largest blending weight), an upper bound of A^T W A's diagonal
sum_i W_i w_ij^2 Y_k^2 that follows it closely for splats of one footprint.
"""

import numpy as np

from . import sh as shmod
from .metrics import psnr_from_mse
from .parallel import map_threads
from .render import Shapes, render
from .steps import drain

# Measured on Suzanne lit by Cycles (bench/bake.py's scene, roughness 0.35, 20k splats, 48 views of 128 px,
# damped towards the Base Color; towards the views' mean colours, 0.1 and 30 gave 25.3 / 27.8 / 32.1), held-out
# dB at 0.5x / 1x / 3x: damping 1e-3 and no band damping 22.1 / 26.4 / 31.7 (over-fitted: 31 dB on the
# views fitted); 1e-2 and 10: 23.6 / 27.6 / 32.4; 0.1 and 30: 25.3 / 27.7 / 31.9; 0.5 and 30: 25.0 /
# 27.1 / 31.2. Overlapping splats leave alternating colours that no view fitted sees undetermined.
# With 96 views (bench/bake.py's quick scene, 20k splats made for antialiased rendering), less damping pays:
# SH 2 at 0.1 and 30: the sphere 32.8 / 24.6 / 35.1, Suzanne 29.7 / 30.8 / 38.8; SH 3 at 0.03 and 10: 36.4 /
# 25.2 / 35.8 and 30.2 / 31.3 / 39.8; SH 3 at 0.01 and 3: 35.5 / 25.4 / 36.3 and 29.6 / 31.0 / 40.0; SH 2 at
# 0.01 and 3, the sphere 34.8 / 25.1 / 35.8; SH 3 at 0.003 and 1 over-fits (the sphere's 0.5x 32.8).
DEFAULT_ITERATIONS = 20
DEFAULT_DAMPING = 0.03  # lambda, as a fraction of the median splat's DC diagonal
DEFAULT_BAND_DAMPING = 10.0  # band l's lambda is (1 + this l (l + 1)) times band 0's
# 32 views per distance against 16, bench/bake.py's quick scene (20k splats made for antialiased rendering),
# held-out dB at 0.5x / 1x / 3x: Suzanne (100k) 31.5, 34.4, 31.6 / 33.3, 29.3, 33.0 -> 33.7, 36.0, 34.8 / 34.3,
# 29.7, 32.2 (3x unchanged); the sphere 28.2, 38.6, 30.1 -> 29.8, 40.1, 33.6 at 0.5x, 1x and 3x unchanged.
VIEWS_PER_DISTANCE = 32  # reference views at each distance of core.mesh_refine's view placement
# A highlight comes out right only close to a view it was fitted to (bench/bake.py's quick scene, the sphere
# at 1x: views 21 degrees apart 25.6 dB held out, 544 views 9 degrees apart 27.8, four views 5 degrees
# around each held-out one 32.0): the views a user renders from (a camera path) are fitted too, weighted
# to count PATH_SHARE times as much as the views around together. With the nine held-out views as the
# path, their dB at 0.5x / 1x / 3x: weight 1 each (9 views of 105) the sphere 45.0 / 28.5 / 36.9,
# Suzanne 33.8 / 32.6 / 39.9; share 1: 46.8 / 36.8 / 37.3 and 36.7 / 36.2 / 40.5 (all views fitted
# 35.0 -> 34.6 and 34.6 -> 34.4 dB); share 2.8, the sphere 47.0 / 40.5 / 38.0 (all views 33.9).
PATH_SHARE = 1.0
# bake_splats: Adam's step sizes, the 3DGS reference's (positions: times the cloud's radius; the
# view-dependent SH bands' rate ADAM_SH_REST times the DC's), but the opacity's halved.
ADAM_RATES = {"positions": 1.6e-4, "rotations": 1e-3, "log_scales": 5e-3, "opacity_logits": 2.5e-2, "sh": 2.5e-3}
ADAM_SH_REST = 1.0 / 20.0
_FITTED = tuple(ADAM_RATES)
DEFAULT_STEPS = 1000
REPORT_EVERY = 10


def bake_views(vertices, size=256, count=VIEWS_PER_DISTANCE, distances=None):
    """Reference cameras around a mesh for baking: core.mesh_refine's views (a Fibonacci spiral
    at 0.5x, 1x and 3x the distance framing the mesh, or `distances`), `count` per distance."""
    from types import SimpleNamespace

    from .mesh_refine import VIEW_DISTANCES, default_views

    return default_views(
        SimpleNamespace(vertices=np.asarray(vertices, np.float64)),
        size,
        count,
        distances=VIEW_DISTANCES if distances is None else distances,
    )


def path_weights(around, path, share=PATH_SHARE):
    """bake_sh's view weights for `around` views around the mesh followed by `path` views a user
    renders from: 1 each around, the path's together `share` times their total."""
    return np.concatenate([np.ones(around), np.full(path, share * around / path if path else 0.0)])


def bake_sh(cloud, cameras, images, degree=None, *, progress=None, **options):
    """bake_sh_steps run to its end, each step passed to `progress(done, total, label)`."""
    return drain(bake_sh_steps(cloud, cameras, images, degree, **options), progress)


def bake_sh_steps(
    cloud,
    cameras,
    images,
    degree=None,
    *,
    iterations=DEFAULT_ITERATIONS,
    damping=DEFAULT_DAMPING,
    band_damping=DEFAULT_BAND_DAMPING,
    prior="views",
    background=(0.0, 0.0, 0.0),
    mode=None,
    tolerance=1e-6,
    weights=None,
    info=None,
    backend="auto",
    threads=None,
):
    """A generator fitting the SH of `cloud` to `images` seen through `cameras`; yields (done,
    total, label) after the setup and each iteration and returns the cloud with the fitted SH
    (float32, `degree`, default the cloud's own).

    images: one (H,W,3) display-sRGB image per camera, of its size, rendered over `background`.
    weights: one weight per view (default all 1): a view's squared errors count that many times
    (path_weights: the views a user renders from, ahead of the views around).
    prior: where the fit starts and what it is damped towards: "views", each seen splat's mean
    colour over the pixels it blends into (weighted by its weights, every view together, pixels
    taken straight: a view-independent colour), the others keeping the cloud's SH; "cloud", the cloud's own SH. Both
    are padded with zeros to `degree`.
    damping: the Tikhonov weight towards the prior, relative to the median splat's diagonal; band
    l's weight is that times 1 + band_damping l (l + 1) (the sphere's Laplacian: sharp
    view-dependence must be asked for by many views). Stops after `iterations` or once the normal
    residual fell below `tolerance` times its start. `info`, if a dict, receives "psnr" (per iteration, the
    linear model's PSNR over all views, the first entry before fitting), "iterations" and "seen"
    (splats some view gives weight).
    """
    if prior not in ("views", "cloud"):
        raise ValueError(f"prior must be 'views' or 'cloud', got {prior!r}")
    if len(cameras) != len(images) or not len(cameras):
        raise ValueError(f"need one image per camera, got {len(cameras)} cameras and {len(images)} images")
    degree = shmod.degree_of(cloud.sh.shape[1]) if degree is None else int(degree)
    k = shmod.num_coeffs(degree)
    bg = np.asarray(background, np.float64).reshape(3)
    opts = dict(mode=mode, backend=backend, threads=threads)
    weights = _checked_weights(weights, len(cameras))
    views = [
        _View(cam, _checked_image(img, cam, i), degree, w)
        for i, (cam, img, w) in enumerate(zip(cameras, images, weights))
    ]
    x0 = shmod.truncate(cloud.sh.astype(np.float64), degree)
    shape = cloud.replace(sh=np.zeros((len(cloud), 1, 3), np.float32))  # the geometry: colours are set per render
    opts["shapes"] = Shapes(shape, threads)  # and its splats' shapes, the same in every render
    total = iterations + 1

    # setup: the preconditioner, the start and prior, its residual and the gathered right-hand side
    # Views are small: each renders faster whole on one core, the views spread over the cores
    # (bench bake --quick: fits in 41-45 s, not 74-91; 37-39 s with Shapes), summed in their order.
    one = dict(opts, threads=1)
    each = lambda fn: map_threads(fn, views, threads)  # noqa: E731
    diag = np.zeros((len(cloud), k))
    for part in each(lambda view: view.measure(shape, bg, one)):
        diag += part
    seen = diag[:, 0] > 0
    if prior == "views":
        x0 = _seen_colours(shape, views, x0, seen, one, threads)
    rhs = np.zeros_like(x0)
    for view, gathered in zip(
        views, each(lambda view: view.start(shape, x0, one) or view.gather(shape, view.residual, one))
    ):
        rhs += view.back(gathered)
    band = np.floor(np.sqrt(np.arange(k)))
    lam = damping * (np.median(diag[seen, 0]) if seen.any() else 1.0) * (1.0 + band_damping * band * (band + 1))
    lam = lam[None, :, None]
    precond = 1.0 / (diag[:, :, None] + lam)
    history = [_psnr(views)]
    yield 1, total, "bake"

    delta = np.zeros_like(x0)
    g = rhs  # the normal equations' residual
    z = g * precond
    p = z.copy()
    rz = _dot(g, z)
    start = np.sqrt(_dot(g, g))
    done = 0
    for it in range(iterations):
        if (np.sqrt(_dot(g, g)) <= tolerance * np.maximum(start, 1e-300)).all():
            break
        ap = lam * p

        def apply(view):
            q = view.color_image(shape, view.colors(p), one)
            return q, view.gather(shape, q, one)

        images_p = []
        for view, (q, gathered) in zip(views, each(apply)):
            images_p.append(q)
            ap += view.back(gathered)
        curvature = _dot(p, ap)
        step = np.where(curvature > 0, rz / np.where(curvature > 0, curvature, 1.0), 0.0)
        delta += step * p
        g -= step * ap
        for view, q in zip(views, images_p):
            view.residual -= (step * q).astype(np.float32)
        history.append(_psnr(views))
        z = g * precond
        rz_new = _dot(g, z)
        p = z + np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0) * p
        rz = rz_new
        done = it + 1
        yield it + 2, total, "bake"
    if isinstance(info, dict):
        info.update(psnr=history, iterations=done, seen=int(seen.sum()))
    return cloud.replace(sh=(x0 + delta).astype(np.float32))


def bake_splats(cloud, cameras, images, *, progress=None, **options):
    """bake_splats_steps run to its end, each step passed to `progress(done, total, label)`."""
    return drain(bake_splats_steps(cloud, cameras, images, **options), progress)


def bake_splats_steps(
    cloud,
    cameras,
    images,
    *,
    steps=DEFAULT_STEPS,
    background=(0.0, 0.0, 0.0),
    mode=None,
    weights=None,
    seed=0,
    report_every=REPORT_EVERY,
    info=None,
    threads=None,
):
    """A generator fitting every parameter of `cloud` (positions, rotations, scales, opacities and
    SH) to `images` by Adam steps on the squared error of one view at a time (core.render_grad's
    backward pass); yields (done, total, label) every `report_every` steps and returns the cloud.

    Start from bake_sh's cloud: the steps then refine a look that is already close. Views are
    drawn at random (`seed`), in proportion to `weights` (default all 1). `info`, if a dict,
    receives "psnr": the mean squared error of the views drawn, as PSNR, per REPORT_EVERY steps.
    """
    from .render_grad import mse_gradients

    if int(steps) != steps or steps < 0:
        raise ValueError(f"steps must be a whole number >= 0, got {steps!r}")
    if len(cameras) != len(images) or not len(cameras):
        raise ValueError(f"need one image per camera, got {len(cameras)} cameras and {len(images)} images")
    images = [_checked_image(img, cam, i) for i, (cam, img) in enumerate(zip(cameras, images))]
    weights = _checked_weights(weights, len(cameras))
    rng = np.random.default_rng(seed)
    order = rng.choice(len(cameras), size=steps, p=weights / weights.sum())
    params = {name: getattr(cloud, name).astype(np.float64) for name in _FITTED}
    extent = float(np.linalg.norm(params["positions"] - params["positions"].mean(0), axis=1).max(initial=0.0))
    rates = dict(ADAM_RATES, positions=ADAM_RATES["positions"] * max(extent, 1e-12))
    # the view-dependent bands step slower (the 3DGS reference's rates)
    rates["sh"] = rates["sh"] * np.where(np.arange(cloud.sh.shape[1]) == 0, 1.0, ADAM_SH_REST)[None, :, None]
    adam = {name: (np.zeros_like(v), np.zeros_like(v)) for name, v in params.items()}
    errors, history = [], []
    for step, view in enumerate(order, 1):
        current = cloud.replace(**{name: v.astype(np.float32) for name, v in params.items()})
        _, mse, grad = mse_gradients(current, cameras[view], images[view], background, mode, threads=threads)
        errors.append(mse)
        for name, value in params.items():
            _adam_step(value, getattr(grad, name), *adam[name], rates[name], step)
        if step % REPORT_EVERY == 0 or step == steps:
            history.append(psnr_from_mse(np.mean(errors)))
            errors = []
        if step % report_every == 0 or step == steps:
            yield step, steps, "bake splats"
    if isinstance(info, dict):
        info.update(psnr=history)
    params["rotations"] /= np.linalg.norm(params["rotations"], axis=1, keepdims=True)
    return cloud.replace(**{name: v.astype(np.float32) for name, v in params.items()})


def _adam_step(value, grad, first, second, rate, step, beta1=0.9, beta2=0.999, eps=1e-15):
    """Adam (Kingma and Ba), in place."""
    first *= beta1
    first += (1 - beta1) * grad
    second *= beta2
    second += (1 - beta2) * grad * grad
    value -= rate * (first / (1 - beta1**step)) / (np.sqrt(second / (1 - beta2**step)) + eps)


def _seen_colours(cloud, views, x0, seen, opts, threads):
    """x0 with each seen splat's SH replaced by its mean colour over the pixels it blends into:
    sum_i w_i pixel_i / sum_i w_i alpha_i over every view (pixels are premultiplied by their alpha,
    so a lone splat gets its own colour back)."""
    sums = np.zeros((len(cloud), 4))
    gather = lambda view: (
        render(
            cloud,
            view.camera,
            background=None,  # noqa: E731
            gather=np.concatenate([view.target, view.alpha], axis=2),
            **opts,
        ).gathered
    )
    for part in map_threads(gather, views, threads):
        sums += part
    seen = seen & (sums[:, 3] > 0)
    out = x0.copy()
    out[seen] = 0.0
    out[seen, 0] = shmod.rgb_to_dc(sums[seen, :3] / sums[seen, 3:])
    return out


def _checked_image(image, camera, i):
    a = np.asarray(image, np.float32)
    if a.shape != (camera.height, camera.width, 3):
        raise ValueError(f"image {i} has shape {a.shape}, expected ({camera.height}, {camera.width}, 3)")
    if not np.isfinite(a).all():
        raise ValueError(f"image {i} holds non-finite values")
    return a


def _checked_weights(weights, count):
    if weights is None:
        return np.ones(count)
    w = np.asarray(weights, np.float64)
    if w.shape != (count,) or not (np.isfinite(w) & (w >= 0)).all() or not w.any():
        raise ValueError(f"need {count} finite, non-negative view weights, not all 0; got {weights!r}")
    return w


def _dot(a, b):
    """Per-channel inner products of (N, K, 3) arrays: (3,)."""
    return np.einsum("nkc,nkc->c", a, b)


def _psnr(views):
    sq = sum(float(np.square(v.residual, dtype=np.float64).sum()) for v in views)
    return psnr_from_mse(sq / sum(v.residual.size for v in views))


class _View:
    """One reference view: its camera, its weight, the SH basis at its directions to the splats
    (float32) and the residual image of the fit so far."""

    def __init__(self, camera, image, degree, weight=1.0):
        self.camera, self.image, self.degree, self.weight = camera, image, degree, float(weight)
        self.residual = self.basis = None

    def colors(self, x):
        """(N, 3) colours sum_k Y_k x_k of coefficients x (N, K, 3), unclamped."""
        return np.einsum("nk,nkc->nc", self.basis, x)

    def measure(self, cloud, bg, opts):
        """The basis, the splats' coverage (sum of weights), the target (image less background) and
        this view's share of the preconditioner (N, K)."""
        cam = self.camera
        directions = (
            np.broadcast_to(cam.forward, cloud.positions.shape)
            if cam.is_orthographic
            else cloud.positions.astype(np.float64) - cam.center
        )  # as core.render sees them
        self.basis = shmod.basis(directions, self.degree, np.float32)
        out = render(
            cloud, self.camera, background=None, return_weights=True, gather=np.ones(self.image.shape[:2]), **opts
        )
        self.alpha = out.alpha[..., None]
        self.target = (self.image - (1.0 - self.alpha) * bg.astype(np.float32)).astype(np.float32)
        footprint = out.gathered[:, 0] * out.max_weight
        return self.weight * footprint[:, None] * np.square(self.basis, dtype=np.float64)

    def start(self, cloud, x0, opts):
        """The residual image of the starting SH x0."""
        model = self.color_image(cloud, 0.5 + self.colors(x0), opts)
        self.residual = (self.target - model).astype(np.float32)

    def color_image(self, cloud, colors, opts):
        """A x: the image of per-splat colours (N, 3), no background, unclamped."""
        shift, sh = self._shifted(colors)
        out = render(cloud.replace(sh=sh), self.camera, background=None, **opts)
        return out.color - shift * out.alpha[..., None]

    def gather(self, cloud, image, opts):
        """The image gathered through the weights: (N, 3)."""
        return render(cloud, self.camera, background=None, gather=image, **opts).gathered

    def back(self, gathered):
        """A^T W image from its gather: times the basis and the view's weight, (N, K, 3)."""
        return self.weight * self.basis[:, :, None] * gathered[:, None, :]

    @staticmethod
    def _shifted(colors):
        """A shift s >= 0 and degree-0 SH showing colors + s (never below 0, so never clamped)."""
        shift = float(max(0.0, -colors.min())) if colors.size else 0.0
        return shift, shmod.rgb_to_dc(colors + shift)[:, None, :].astype(np.float32)
