"""Soft overlap: sum_i sum_j w_i w_j exp(-1/2 d^T (Sigma_i + Sigma_j)^-1 d) over a robot's and an
environment's Gaussians, with its gradients and a bound on what the cutoff dropped (see the
package notes)."""

import math
from dataclasses import dataclass

import numpy as np

from ..splats import SplatCloud
from .gaussians import (
    _SYM,
    BOUND_MARGIN,
    DEFAULT_CUTOFF,
    CollisionInputError,
    Gaussians,
    _gauss_terms,
    _map,
    _sym6,
    as_gaussians,
)
from .index import EnvironmentIndex, as_index


@dataclass
class Overlap:
    """The soft overlap cost of a query and what it cost to compute."""

    cost: float
    per_gaussian: np.ndarray  # (N,) each robot Gaussian's share of the cost
    grad_means: np.ndarray | None = None  # (N,3) dC/dmu_i
    grad_covs: np.ndarray | None = None  # (N,3,3) dC/dSigma_i (symmetric), when asked for
    bound: float = 0.0  # upper bound on what the cutoff dropped (absolute)
    relative_bound: float = 0.0  # bound / cost (inf when the cost is 0 and the bound is not)
    pairs: int = 0  # pairs within the cutoff, evaluated exactly
    cutoff: float = math.inf
    grad_q: np.ndarray | None = None  # (dof,) dC/dq, from overlap_at (robots on kinematic trees)


def _finish(n, parts, want_grad, want_cov):
    per = np.zeros(n)
    grad = np.zeros((n, 3)) if want_grad else None
    gcov = np.zeros((n, 6)) if want_cov else None
    pairs = 0
    for part in parts:
        per += part[0]
        if want_grad:
            grad += part[1]
        if want_cov:
            gcov += part[2]
        pairs += part[3]
    if want_cov:
        full = np.empty((n, 3, 3))
        for k, (a, b) in enumerate(_SYM):
            full[:, a, b] = full[:, b, a] = gcov[:, k]
        gcov = full
    return per, grad, gcov, pairs


def _accumulate(i, n, e, x, want_grad, want_cov):
    per = np.bincount(i, weights=e, minlength=n)
    grad = gcov = None
    if want_grad:
        grad = np.stack([-np.bincount(i, weights=e * xk, minlength=n) for xk in x], axis=1)
    if want_cov:
        gcov = np.stack([0.5 * np.bincount(i, weights=e * x[a] * x[b], minlength=n) for a, b in _SYM], axis=1)
    return per, grad, gcov, len(i)


def overlap(
    robot: "SplatCloud | Gaussians",
    env: "SplatCloud | Gaussians | EnvironmentIndex",
    cutoff: float = DEFAULT_CUTOFF,
    gradient: bool = True,
    cov_gradient: bool = False,
    bound: bool = True,
    opacity_weights: bool = True,
    threads: int | None = None,
) -> "Overlap":
    """Soft overlap C between `robot` and `env` (SplatCloud, Gaussians or a prebuilt
    EnvironmentIndex), its gradient w.r.t. the robot means (and covariances, if asked), and a
    bound on the error of the cutoff. cutoff=inf sums every pair (use `overlap_all_pairs` then)."""
    robot = as_gaussians(robot, opacity_weights, name="robot")
    if not math.isfinite(cutoff):
        env = env.gaussians() if isinstance(env, EnvironmentIndex) else env
        return overlap_all_pairs(robot, env, gradient, cov_gradient, opacity_weights, threads)
    if cutoff <= 0:
        raise CollisionInputError(f"cutoff must be positive, got {cutoff}")
    index = as_index(env, opacity_weights)
    n = len(robot)
    rm = robot.means
    rx, ry, rz = (np.ascontiguousarray(rm[:, a]) for a in range(3))
    rlam = robot.sigma_max**2
    rcov = _sym6(robot.covs)
    c2 = cutoff * cutoff
    visit = cutoff + (BOUND_MARGIN if bound else 0.0)  # pairs the query sees (and accounts for)

    def reach(lv):
        return visit * np.sqrt(rlam + lv.sigma**2)

    def work(i, j):
        dx, dy, dz = rx[i] - index.mx[j], ry[i] - index.my[j], rz[i] - index.mz[j]
        # d^T S^-1 d >= |d|^2 / lmax(S) >= |d|^2 / (lmax_i + lmax_j): a cheap test first
        d2, lam = dx * dx + dy * dy + dz * dz, rlam[i] + index.lam[j]
        close = d2 <= visit * visit * lam
        far = 0.0
        if bound:  # each far term is below its cheap bound
            with np.errstate(divide="ignore", under="ignore"):
                out = ~close
                far = float(np.sum(robot.weights[i[out]] * index.w[j[out]] * np.exp(-0.5 * d2[out] / lam[out])))
        near = np.flatnonzero(close)
        i, j = i[near], j[near]
        d = (dx[near], dy[near], dz[near])
        s = [rc[i] + ec[j] for rc, ec in zip(rcov, index.cov)]
        keep, e, x, skipped = _gauss_terms(d, s, robot.weights[i] * index.w[j], c2, gradient or cov_gradient, bound)
        return (*_accumulate(i[keep], n, e, x, gradient, cov_gradient), far + skipped)

    def unvisited():
        return float(index.skipped_bound(rm, rlam, robot.weights, visit).sum()) if bound else 0.0

    parts, skip = index.query(rm, reach, work, threads, meanwhile=unvisited) if n else ([], 0.0)
    per, grad, gcov, pairs = _finish(n, parts, gradient, cov_gradient)
    skip += sum(part[4] for part in parts)
    relative = skip / per.sum() if per.sum() > 0 else (0.0 if skip == 0 else math.inf)
    return Overlap(float(per.sum()), per, grad, gcov, skip, relative, pairs, cutoff)


def overlap_all_pairs(robot, env, gradient=True, cov_gradient=False, opacity_weights=True, threads=None, chunk=1 << 18):
    """Every pair, no cutoff, in chunks: the exact reference (and the baseline for speed)."""
    robot = as_gaussians(robot, opacity_weights, name="robot")
    env = as_gaussians(env, opacity_weights, name="environment")
    n, m = len(robot), len(env)
    rcov, ecov = _sym6(robot.covs), _sym6(env.covs)
    per_robot = max(1, chunk // max(m, 1))
    spans = [(a, min(a + per_robot, n)) for a in range(0, n, per_robot)] if m else []

    def work(span):
        a, b = span
        i = np.repeat(np.arange(a, b), m)
        j = np.tile(np.arange(m), b - a)
        d = [robot.means[i, k] - env.means[j, k] for k in range(3)]
        s = [rc[i] + ec[j] for rc, ec in zip(rcov, ecov)]
        # q < 1500 keeps every term that does not underflow to exactly 0
        keep, e, x, _ = _gauss_terms(d, s, robot.weights[i] * env.weights[j], 1500.0, gradient or cov_gradient)
        return _accumulate(i[keep], n, e, x, gradient, cov_gradient)

    per, grad, gcov, pairs = _finish(n, _map(work, spans, threads)[0], gradient, cov_gradient)
    return Overlap(float(per.sum()), per, grad, gcov, 0.0, 0.0, pairs, math.inf)
