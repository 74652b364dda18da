"""The float64 view every collision query works on (Gaussians; flattened, the six entries of
their covariances), the checks of their inputs, the pair kernel (the floored L D L^T Mahalanobis
form: vectorised, and as the scalar the compiled passes call) and the thread map queries run on."""

import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .. import geometry
from ..splats import SplatCloud

DEFAULT_CUTOFF = 6.0  # Mahalanobis distance beyond which pairs are skipped
BOUND_MARGIN = 1.0  # with a bound, pairs up to cutoff + this are visited and their skipped terms summed
PIVOT_FLOOR = 1e-12  # relative floor on L D L^T pivots (see module notes)
_TINY = 1e-300  # absolute floor, for all-zero covariances (point splats)
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the 6 entries of a symmetric 3x3


class CollisionInputError(ValueError):
    """Inputs that no collision query can use; the message names the array and the problem."""


class CollisionPrecisionWarning(UserWarning):
    """Inputs whose stored precision moves the results: float32 positions far from the origin."""


QUANTISATION_LIMIT = 0.01  # warn when float32 rounds positions by more than this fraction of a splat


def _check_precision(name, positions, sigma):
    """Warn when float32 positions are rounded by more than QUANTISATION_LIMIT of their splat's size
    (at 1e6, float32 steps are 6 cm: centimetre splats there are moved by more than their size)."""
    if positions.dtype != np.float32 or not len(positions):
        return
    step = np.spacing(np.abs(positions).max(axis=1))
    coarse = (step > QUANTISATION_LIMIT * sigma) & (sigma > 0)
    if coarse.any():
        warnings.warn(
            f"{name}: {int(coarse.sum())} splats lie so far from the origin (up to "
            f"{float(np.abs(positions[coarse]).max()):.3g}) that their float32 positions are rounded by "
            f"up to {float(step[coarse].max()):.3g}, more than {QUANTISATION_LIMIT:.0%} of their size, and "
            "collision results shift with them; move the scene nearer the origin, or give "
            "float64 Gaussians",
            CollisionPrecisionWarning,
            stacklevel=4,
        )


def _require_finite(name, values, allow_neg_inf=False):
    values = np.asarray(values)
    bad = ~np.isfinite(values)
    if allow_neg_inf:
        bad &= ~np.isneginf(values)
    if bad.any():
        rows = bad.reshape(len(values), -1).any(axis=1) if values.ndim else bad
        raise CollisionInputError(f"{name}: {int(np.sum(rows))} entries are NaN or infinite")


@dataclass(eq=False)
class Gaussians:
    """N Gaussians in float64: means (N,3), covariances (N,3,3), weights (N,), optional link index
    per Gaussian (N,) int, and the largest standard deviation of each (computed when not given)."""

    means: np.ndarray
    covs: np.ndarray
    weights: np.ndarray = None
    links: np.ndarray = None
    sigma_max: np.ndarray = None

    def __post_init__(self):
        self.means = np.asarray(self.means, dtype=np.float64).reshape(-1, 3)
        n = len(self.means)
        self.covs = np.asarray(self.covs, dtype=np.float64).reshape(n, 3, 3)
        self.weights = np.ones(n) if self.weights is None else np.asarray(self.weights, np.float64).reshape(n)
        if self.links is not None:
            self.links = np.asarray(self.links).reshape(n)
            if not np.issubdtype(self.links.dtype, np.integer) or (n and self.links.min() < 0):
                raise CollisionInputError("links: expected non-negative integers, one per Gaussian")
        for name in ("means", "covs", "weights"):
            _require_finite(f"Gaussians.{name}", getattr(self, name))
        if (self.weights < 0).any():
            raise CollisionInputError(f"Gaussians.weights: {int((self.weights < 0).sum())} are negative")
        self.covs = 0.5 * (self.covs + np.swapaxes(self.covs, 1, 2))
        if self.sigma_max is None:
            eig = np.linalg.eigvalsh(self.covs) if n else np.zeros((0, 3))
            low = eig[:, 0] < -1e-9 * np.maximum(eig[:, 2], _TINY)
            if low.any():
                raise CollisionInputError(f"Gaussians.covs: {int(low.sum())} are not positive semi-definite")
            self.sigma_max = np.sqrt(np.maximum(eig[:, 2], 0.0))
        self.sigma_max = np.asarray(self.sigma_max, np.float64).reshape(n)

    @classmethod
    def from_cloud(cls, cloud, opacity_weights=True, links=None, name="cloud"):
        """The Gaussians of a SplatCloud; weights are opacities (or 1). Zero scales (log -inf) are
        allowed and make point splats; NaN or +Inf anywhere is an error naming the field."""
        for field_name in ("positions", "rotations", "opacity_logits"):
            _require_finite(f"{name}.{field_name}", getattr(cloud, field_name))
        _require_finite(f"{name}.log_scales", cloud.log_scales, allow_neg_inf=True)
        scales = cloud.scales
        _check_precision(name, cloud.positions, scales.max(axis=1) if len(cloud) else np.zeros(0))
        weights = cloud.opacities if opacity_weights else np.ones(len(cloud))
        return cls(
            cloud.positions,
            geometry.covariances(cloud.rotations, scales),
            weights,
            links,
            scales.max(axis=1) if len(cloud) else np.zeros(0),
        )

    def __len__(self):
        return len(self.means)

    def subset(self, index):
        pick = lambda a: None if a is None else a[index]
        return Gaussians(
            self.means[index], self.covs[index], self.weights[index], pick(self.links), self.sigma_max[index]
        )

    def transformed(self, rotations, translations):
        """A rigid motion: mu' = R mu + t and Sigma' = R Sigma R^T, with one rotation (3,3) and
        translation (3,) for all, or one per Gaussian."""
        r = np.asarray(rotations, np.float64)
        t = np.asarray(translations, np.float64)
        means = (r @ self.means[:, :, None])[..., 0] + t
        covs = r @ self.covs @ np.swapaxes(r, -1, -2)
        return Gaussians(means, covs, self.weights, self.links, self.sigma_max)


def as_gaussians(x: "SplatCloud | Gaussians", opacity_weights: bool = True, name: str = "cloud") -> "Gaussians":
    return x if isinstance(x, Gaussians) else Gaussians.from_cloud(x, opacity_weights, name=name)


def _sym6(covs):
    """The 6 independent entries of symmetric (N,3,3) matrices, as 6 contiguous arrays."""
    return [np.ascontiguousarray(covs[:, a, b]) for a, b in _SYM]


def _full(c6):
    """(P,3,3) symmetric matrices from their 6 entries."""
    out = np.empty((len(c6[0]), 3, 3))
    for c, (a, b) in zip(c6, _SYM):
        out[:, a, b] = out[:, b, a] = c
    return out


@dataclass
class _Flat:
    """Per-Gaussian arrays as queries use them: coordinates and the 6 covariance entries as
    separate contiguous arrays, the largest variance `lam` and the smallest `nu`."""

    means: list
    cov6: list
    weights: np.ndarray
    lam: np.ndarray
    nu: np.ndarray


def _flatten(x, opacity_weights=True, name="cloud", threads=None):
    if isinstance(x, Gaussians):
        vals = np.linalg.eigvalsh(x.covs) if len(x) else np.zeros((0, 3))
        return _Flat(
            [np.ascontiguousarray(x.means[:, a]) for a in range(3)],
            _sym6(x.covs),
            x.weights,
            np.maximum(vals[:, 2], 0.0),
            np.maximum(vals[:, 0], 0.0),
        )
    for field_name in ("positions", "rotations", "opacity_logits"):
        _require_finite(f"{name}.{field_name}", getattr(x, field_name))
    _require_finite(f"{name}.log_scales", x.log_scales, allow_neg_inf=True)
    n = len(x)

    def chunk(span):
        a, b = span
        r = geometry.quaternions_to_matrices(x.rotations[a:b])
        s = np.exp(x.log_scales[a:b].astype(np.float64))
        var = s * s
        cov6 = [(r[:, i, :] * r[:, j, :] * var).sum(axis=1) for i, j in _SYM]
        return cov6, var.max(axis=1), var.min(axis=1)

    step = max(1, -(-n // (4 * (threads or os.cpu_count() or 1))))
    parts = _map(chunk, [(a, min(a + step, n)) for a in range(0, n, step)], threads)[0] if n else []
    cat = lambda arrays: np.concatenate(arrays) if arrays else np.zeros(0)
    cov6 = [cat([p[0][k] for p in parts]) for k in range(6)]
    weights = x.opacities if opacity_weights else np.ones(n)
    lam = cat([p[1] for p in parts])
    _check_precision(name, x.positions, np.sqrt(lam))
    return _Flat(
        [x.positions[:, a].astype(np.float64) for a in range(3)], cov6, weights, lam, cat([p[2] for p in parts])
    )


# the pair kernel ---------------------------------------------------------------------------------


def _mahalanobis(d, s):
    """q = d^T S^-1 d for P pairs at once, and the factors that give S^-1 d (see _solve).

    d: 3 arrays (P,), s: the 6 entries of S, (P,) each. L D L^T with pivots floored at
    PIVOT_FLOOR * trace(S) keeps flat and needle pairs stable; q may be +inf, never NaN.
    """
    s00, s01, s02, s11, s12, s22 = s
    floor = np.maximum(PIVOT_FLOOR * (s00 + s11 + s22), _TINY)
    with np.errstate(over="ignore", invalid="ignore"):
        d0 = np.maximum(s00, floor)
        l10, l20 = s01 / d0, s02 / d0
        d1 = np.maximum(s11 - l10 * s01, floor)
        t12 = s12 - l20 * s01
        l21 = t12 / d1
        d2 = np.maximum(s22 - l20 * s02 - l21 * t12, floor)
        y0 = d[0]
        y1 = d[1] - l10 * y0
        y2 = d[2] - l20 * y0 - l21 * y1
        z0, z1, z2 = y0 / d0, y1 / d1, y2 / d2
        q = y0 * z0 + y1 * z1 + y2 * z2
    return q, (l10, l20, l21, z0, z1, z2)


def _solve(factors):
    """x = S^-1 d by back substitution, from _mahalanobis's factors (of finite-q pairs)."""
    l10, l20, l21, z0, z1, z2 = factors
    x1 = z1 - l21 * z2
    return [z0 - l10 * x1 - l20 * z2, x1, z2]


def _gauss_terms(d, s, w, limit, want_x, want_skipped=False):
    """Pairs with q = d^T S^-1 d <= limit: their indices, w exp(-q/2) and (if asked) S^-1 d, and
    (if asked) the sum of the terms beyond the limit."""
    q, factors = _mahalanobis(d, s)
    inside = q <= limit
    keep = np.flatnonzero(inside)
    with np.errstate(under="ignore"):
        e = w[keep] * np.exp(-0.5 * q[keep])
        skipped = float(np.sum(w[~inside] * np.exp(-0.5 * q[~inside]))) if want_skipped else 0.0
    x = _solve([f[keep] for f in factors]) if want_x else None
    return keep, e, x, skipped


def _ldl_quadratic(s00, s01, s02, s11, s12, s22, d0, d1, d2, x):
    """d^T S^-1 d for one symmetric S by L D L^T with pivots floored as in _mahalanobis; x gets S^-1 d."""
    floor = max(PIVOT_FLOOR * (s00 + s11 + s22), _TINY)
    p0 = max(s00, floor)
    l10, l20 = s01 / p0, s02 / p0
    p1 = max(s11 - l10 * s01, floor)
    t12 = s12 - l20 * s01
    l21 = t12 / p1
    p2 = max(s22 - l20 * s02 - l21 * t12, floor)
    y0 = d0
    y1 = d1 - l10 * y0
    y2 = d2 - l20 * y0 - l21 * y1
    z0, z1, z2 = y0 / p0, y1 / p1, y2 / p2
    x[2] = z2
    x[1] = z1 - l21 * z2
    x[0] = z0 - l10 * x[1] - l20 * z2
    return y0 * z0 + y1 * z1 + y2 * z2


# threads -----------------------------------------------------------------------------------------


_POOL = {}


def _map(fn, items, threads, meanwhile=None):
    """fn over items on up to `threads` threads (NumPy releases the GIL in the heavy parts), and
    `meanwhile()` on the calling thread as they run; returns (results, meanwhile's result). One pool
    per size is kept, since planners call this thousands of times."""
    threads = min(len(items), threads or os.cpu_count() or 1)
    if threads <= 1:
        return [fn(x) for x in items], meanwhile() if meanwhile else None
    if threads not in _POOL:
        _POOL[threads] = ThreadPoolExecutor(threads)
    futures = [_POOL[threads].submit(fn, x) for x in items]
    extra = meanwhile() if meanwhile else None
    return [f.result() for f in futures], extra
