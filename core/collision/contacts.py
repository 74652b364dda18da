"""Hard contacts: the exact test of whether two k-sigma ellipsoids overlap (the contact parameter
of the pair), over every candidate pair of a robot and an environment; compiled where numba loads."""

from dataclasses import dataclass

import numpy as np

from .. import jit
from ..arrays import ArrayLike
from ..splats import SplatCloud
from .gaussians import (
    _TINY,
    PIVOT_FLOOR,
    CollisionInputError,
    Gaussians,
    _full,
    _ldl_quadratic,
    _mahalanobis,
    _sym6,
    as_gaussians,
)
from .index import EnvironmentIndex, as_index


def contact_sigma(mean_a, cov_a, mean_b, cov_b, iterations=100):
    """For P pairs of Gaussians, the sigma multiple mu at which their ellipsoids touch: the k-sigma
    ellipsoids {x: (x-m)^T Sigma^-1 (x-m) <= k^2} overlap exactly when k >= mu.

    mu^2 = max over s in [0,1] of s(1-s) d^T (s A + (1-s) B)^-1 d, the contact function of Perram &
    Wertheim (J. Comput. Phys. 58, 1985), which is the separating test of Gilitschenski & Hanebeck
    (FUSION 2012) that Splat-Nav (Chen, Shorinwa et al., 2024) applies to splat maps. Whitening by
    A + B and diagonalising the whitened A turns the bracket into a sum over 3 eigenvalues a_k in
    [0,1]: f(s) = s(1-s) sum e_k^2 / (a_k s + (1-a_k)(1-s)), concave on [0,1], maximised by a
    bracketed Newton iteration on f'(s) = sum e_k^2 ((1-a_k)(1-s)^2 - a_k s^2) / D_k^2.
    """
    d = np.asarray(mean_a, np.float64) - np.asarray(mean_b, np.float64)
    a = np.asarray(cov_a, np.float64)
    c = a + np.asarray(cov_b, np.float64)
    if not len(d):
        return np.zeros(0)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # point splats: mu is inf
        cvals, cvecs = np.linalg.eigh(c)
        floor = np.maximum(PIVOT_FLOOR * cvals.sum(axis=1, keepdims=True), _TINY)
        white = np.swapaxes(cvecs, 1, 2) / np.sqrt(np.maximum(cvals, floor))[:, :, None]  # W C W^T = I
        m = white @ a @ np.swapaxes(white, 1, 2)
        alpha, vecs = np.linalg.eigh(0.5 * (m + np.swapaxes(m, 1, 2)))
        alpha = np.clip(alpha, 0.0, 1.0)
        beta = 1.0 - alpha
        e2 = np.einsum("pji,pj->pi", vecs, np.einsum("pij,pj->pi", white, d)) ** 2
        s = _contact_parameter(alpha, e2, iterations)
        den = alpha * s[:, None] + beta * (1.0 - s[:, None])
        f = s * (1.0 - s) * (e2 / den).sum(axis=1)
    f = np.where((d == 0).all(axis=1), 0.0, np.nan_to_num(f, nan=np.inf, posinf=np.inf))  # coincident: 0
    return np.sqrt(np.maximum(f, 0.0))


def _contact_parameter(alpha, e2, iterations):
    """The s in [0,1] maximising f(s) = s(1-s) sum e_k^2 / (a_k s + (1-a_k)(1-s)): bracketed Newton on
    f'(s), each pair dropped from the work once its step is below 1e-12 (f is flat at its maximum,
    so f is then exact to round-off)."""
    n = len(alpha)
    s, lo, hi = np.full(n, 0.5), np.zeros(n), np.ones(n)
    active = np.arange(n)
    for _ in range(iterations):
        if not len(active):
            break
        a, e, x = alpha[active], e2[active], s[active]
        b, xc = 1.0 - a, x[:, None]
        den = a * xc + b * (1.0 - xc)
        num = b * (1.0 - xc) ** 2 - a * xc**2
        g = (e * num / den**2).sum(axis=1)
        dnum = -2.0 * (b * (1.0 - xc) + a * xc)
        gp = (e * (dnum * den - 2.0 * num * (a - b)) / den**3).sum(axis=1)
        low = np.where(g > 0, x, lo[active])
        high = np.where(g > 0, hi[active], x)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = x - g / gp
        step = np.where((step > low) & (step < high), step, 0.5 * (low + high))
        lo[active], hi[active], s[active] = low, high, step
        active = active[np.abs(step - x) > 1e-12]
    return s


@dataclass
class Contacts:
    """Robot/environment Gaussian pairs whose k-sigma ellipsoids overlap, and a per-link summary."""

    robot: np.ndarray  # (P,) robot Gaussian indices
    env: np.ndarray  # (P,) environment Gaussian indices (the environment's own order)
    sigma: np.ndarray  # (P,) contact_sigma of each pair (<= k)
    k: float
    link_pairs: np.ndarray  # (L,) overlapping pairs per link
    link_gaussians: np.ndarray  # (L,) robot Gaussians of each link that overlap something
    link_min_sigma: np.ndarray  # (L,) the deepest contact per link (inf when none)

    def __len__(self):
        return len(self.robot)


def ellipsoid_contacts(
    robot: "SplatCloud | Gaussians",
    env: "SplatCloud | Gaussians | EnvironmentIndex",
    k: float = 3.0,
    links: ArrayLike | None = None,
    opacity_weights: bool = True,
    threads: int | None = None,
) -> "Contacts":
    """Every robot/environment pair whose k-sigma ellipsoids intersect (exact test, batched), with
    counts and the deepest contact per link (links: per robot Gaussian, default robot.links or 0)."""
    if not k > 0:
        raise CollisionInputError(f"k must be positive, got {k}")
    robot = as_gaussians(robot, opacity_weights, name="robot")
    index = as_index(env, opacity_weights)
    links = robot.links if links is None else np.asarray(links)
    links = np.zeros(len(robot), np.int64) if links is None else links.astype(np.int64)
    if links.shape != (len(robot),):
        raise CollisionInputError(f"links: expected {len(robot)} entries, got shape {links.shape}")
    rs = robot.sigma_max
    rx, ry, rz = (robot.means[:, a] for a in range(3))
    rcov = _sym6(robot.covs)
    rcov6 = np.stack(rcov) if len(robot) else np.zeros((6, 0))
    rx, ry, rz = (np.ascontiguousarray(robot.means[:, a]) for a in range(3))

    def reach(lv):
        return k * (rs + lv.sigma)

    kernel = _contact_kernel()

    def work(i, j):
        if kernel is not None:
            mu = np.empty(len(i))
            kernel(i, j, rx, ry, rz, rcov6, rs, index.mx, index.my, index.mz, index.cov6, index.lam, k, mu)
            hit = np.flatnonzero(mu <= k)
            return i[hit], j[hit], mu[hit]
        d = (rx[i] - index.mx[j], ry[i] - index.my[j], rz[i] - index.mz[j])
        near = np.flatnonzero(d[0] ** 2 + d[1] ** 2 + d[2] ** 2 <= (k * (rs[i] + np.sqrt(index.lam[j]))) ** 2)
        i, j = i[near], j[near]
        # mu^2 >= f(1/2) = d^T (A + B)^-1 d / 2: a cheap necessary condition before the exact test
        q = _mahalanobis([x[near] for x in d], [rc[i] + ec[j] for rc, ec in zip(rcov, index.cov)])[0]
        near = np.flatnonzero(q <= 2 * k * k * (1 + 1e-9))
        i, j = i[near], j[near]
        mu = contact_sigma(
            robot.means[i],
            _full([c[i] for c in rcov]),
            np.column_stack([index.mx[j], index.my[j], index.mz[j]]),
            _full([c[j] for c in index.cov]),
        )
        hit = mu <= k
        return i[hit], j[hit], mu[hit]

    parts = index.query(robot.means, reach, work, threads) if len(robot) else []
    cat = lambda arrays, dtype: np.concatenate(arrays) if arrays else np.zeros(0, dtype)
    i = cat([p[0] for p in parts], np.int64)
    j = cat([p[1] for p in parts], np.int64)
    mu = cat([p[2] for p in parts], np.float64)
    order = np.lexsort((j, i))
    i, j, mu = i[order], j[order], mu[order]
    n_links = int(links.max()) + 1 if len(links) else 0
    min_sigma = np.full(n_links, np.inf)
    np.minimum.at(min_sigma, links[i], mu)
    touched = np.unique(i)
    return Contacts(
        i,
        index.order[j],
        mu,
        float(k),
        np.bincount(links[i], minlength=n_links),
        np.bincount(links[touched], minlength=n_links),
        min_sigma,
    )


def _contact_pass(i, j, rx, ry, rz, rc, rs, ex, ey, ez, ec, elam, k, out):
    """out[p] = contact_sigma of robot Gaussian i[p] and environment Gaussian j[p], or inf where the
    bounding spheres or mu^2 >= d^T (A+B)^-1 d / 2 already rule out contact at k sigma.

    The same maximum as contact_sigma, found without eigendecompositions: with K(s) = sA + (1-s)B
    and x = K^-1 d, f = s(1-s) d.x, f' = (1-2s) d.x - s(1-s) u and f'' = -2 d.x - 2(1-2s) u +
    2 s(1-s) w, where u = x.(A-B)x and w = y.K^-1 y, y = (A-B)x; bracketed Newton on f'."""
    x = np.empty(3)
    z = np.empty(3)
    limit = 2.0 * k * k * (1.0 + 1e-9)
    for p in range(len(i)):
        a, b = i[p], j[p]
        d0, d1, d2 = rx[a] - ex[b], ry[a] - ey[b], rz[a] - ez[b]
        reach = k * (rs[a] + np.sqrt(elam[b]))
        out[p] = np.inf
        if d0 * d0 + d1 * d1 + d2 * d2 > reach * reach:
            continue
        a00, a01, a02, a11, a12, a22 = rc[0, a], rc[1, a], rc[2, a], rc[3, a], rc[4, a], rc[5, a]
        b00, b01, b02, b11, b12, b22 = ec[0, b], ec[1, b], ec[2, b], ec[3, b], ec[4, b], ec[5, b]
        q = _ldl_quadratic(a00 + b00, a01 + b01, a02 + b02, a11 + b11, a12 + b12, a22 + b22, d0, d1, d2, x)
        if q > limit:
            continue
        s, lo, hi = 0.5, 0.0, 1.0
        for _ in range(100):
            t = 1.0 - s
            # the blended matrix s A + (1 - s) B, solved against d and against (A - B) x
            m00, m01, m02 = s * a00 + t * b00, s * a01 + t * b01, s * a02 + t * b02
            m11, m12, m22 = s * a11 + t * b11, s * a12 + t * b12, s * a22 + t * b22
            dx = _ldl_quadratic(m00, m01, m02, m11, m12, m22, d0, d1, d2, x)
            y0 = (a00 - b00) * x[0] + (a01 - b01) * x[1] + (a02 - b02) * x[2]
            y1 = (a01 - b01) * x[0] + (a11 - b11) * x[1] + (a12 - b12) * x[2]
            y2 = (a02 - b02) * x[0] + (a12 - b12) * x[1] + (a22 - b22) * x[2]
            u = x[0] * y0 + x[1] * y1 + x[2] * y2
            w = _ldl_quadratic(m00, m01, m02, m11, m12, m22, y0, y1, y2, z)
            g = (1.0 - 2.0 * s) * dx - s * t * u
            gp = -2.0 * dx - 2.0 * (1.0 - 2.0 * s) * u + 2.0 * s * t * w
            if g > 0:
                lo = s
            else:
                hi = s
            step = s - g / gp if gp < 0 else 0.5 * (lo + hi)
            if not lo < step < hi:
                step = 0.5 * (lo + hi)
            done = abs(step - s) <= 1e-12
            s = step
            if done:
                break
        t = 1.0 - s
        f = (
            s
            * t
            * _ldl_quadratic(
                s * a00 + t * b00,
                s * a01 + t * b01,
                s * a02 + t * b02,
                s * a11 + t * b11,
                s * a12 + t * b12,
                s * a22 + t * b22,
                d0,
                d1,
                d2,
                x,
            )
        )
        out[p] = np.sqrt(max(f, 0.0))


def _contact_kernel():
    """The compiled contact pass (core.jit), or None: the NumPy path then does the work."""
    return jit.compiled(__name__, ("_ldl_quadratic", "_contact_pass"))
