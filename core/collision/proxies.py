"""Collision proxies: a few large Gaussians per link standing in for a robot's many splats in the
soft overlap (fit_proxies), and how far their overlap is from the splats' own (proxy_error).
(Not core/proxy.py, the triangle mesh that binds splats to a rig.)"""

import math

import numpy as np

from .gaussians import _TINY, DEFAULT_CUTOFF, CollisionInputError, Gaussians, as_gaussians
from .index import as_index
from .overlap import overlap


def fit_proxies(robot, per_link=16, links=None, reference_sigma=None, iterations=10, opacity_weights=True):
    """A few Gaussians per link standing in for the link's splats in the soft overlap.

    Each link's Gaussians are split k-means-like (repeatedly halve the widest cluster along its
    principal axis, then Lloyd iterations), and each cluster becomes one Gaussian by moment
    matching: the overlap of Gaussian i with an environment Gaussian of covariance Sigma_ref, as a
    function of the environment position, is w_i c_i N(mu_i, Sigma_i + Sigma_ref) with
    c_i = (2 pi)^(3/2) sqrt(det(Sigma_i + Sigma_ref)); the proxy matches the mass, mean and
    covariance of that mixture (Sigma_ref cancels from the covariance), so the cost it gives,
    summed over any placement of such environment Gaussians, keeps its total, centre and spread.
    Sigma_ref = reference_sigma^2 I: the environment's typical size (EnvironmentIndex.typical_sigma)
    suits it best; the default is the median robot sigma. Returns Gaussians with
    `links` set; weights carry the matched mass. `proxy_error` measures what they cost.
    """
    robot = as_gaussians(robot, opacity_weights, name="robot")
    links = robot.links if links is None else np.asarray(links)
    links = np.zeros(len(robot), np.int64) if links is None else links.astype(np.int64)
    if per_link < 1:
        raise CollisionInputError(f"per_link must be at least 1, got {per_link}")
    if reference_sigma is None:
        reference_sigma = float(np.median(np.sqrt(np.trace(robot.covs, axis1=1, axis2=2) / 3))) if len(robot) else 0.0
    if reference_sigma <= 0 and len(robot):  # point splats: a size from the robot's extent, or masses vanish
        reference_sigma = 1e-3 * max(float(np.ptp(robot.means, axis=0).max()), 1e-6)
    ref = reference_sigma**2 * np.eye(3)
    mass = robot.weights * (2 * np.pi) ** 1.5 * np.sqrt(np.maximum(np.linalg.det(robot.covs + ref), 0.0))
    means, covs, weights, owner = [], [], [], []
    for link in np.unique(links):
        members = np.flatnonzero(links == link)
        labels = _split_clusters(robot.means[members], mass[members], per_link, iterations)
        for c in np.unique(labels):
            pick = members[labels == c]
            m = mass[pick]
            if m.sum() <= 0:
                continue
            p = m / m.sum()
            mean = p @ robot.means[pick]
            off = robot.means[pick] - mean
            cov = np.einsum("n,nij->ij", p, robot.covs[pick]) + np.einsum("n,ni,nj->ij", p, off, off)
            c_proxy = (2 * np.pi) ** 1.5 * np.sqrt(max(np.linalg.det(cov + ref), _TINY))
            means.append(mean)
            covs.append(cov)
            weights.append(m.sum() / c_proxy)
            owner.append(link)
    if not means:
        return Gaussians(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0, np.int64))
    return Gaussians(np.array(means), np.array(covs), np.array(weights), np.array(owner, np.int64))


def _split_clusters(points, mass, count, iterations):
    """Cluster labels for points: split the widest cluster along its principal axis until there
    are `count` (or every point is its own), then mass-weighted Lloyd iterations."""
    labels = np.zeros(len(points), np.int64)
    n = 1
    while n < min(count, len(points)):
        spread = np.array([_weighted_spread(points[labels == c], mass[labels == c]) for c in range(n)])
        worst = int(np.argmax(spread[:, 0]))
        if spread[worst, 0] <= 0:
            break
        pick = np.flatnonzero(labels == worst)
        axis_, centre = spread[worst, 1:4], spread[worst, 4:7]
        labels[pick[(points[pick] - centre) @ axis_ > 0]] = n
        n += 1
    for _ in range(iterations):
        centres = np.array(
            [np.average(points[labels == c], axis=0, weights=mass[labels == c] + 1e-300) for c in range(n)]
        )
        new = np.argmin(((points[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        if np.array_equal(new, labels) or len(np.unique(new)) < n:
            break
        labels = new
    return labels


def _weighted_spread(points, mass):
    """(mass * largest variance, principal axis (3), weighted centre (3)) of a cluster."""
    if len(points) < 2:
        return np.zeros(7)
    w = mass + 1e-300
    centre = np.average(points, axis=0, weights=w)
    off = points - centre
    vals, vecs = np.linalg.eigh((w[:, None, None] * off[:, :, None] * off[:, None, :]).sum(axis=0) / w.sum())
    return np.concatenate([[w.sum() * vals[-1]], vecs[:, -1], centre])


def proxy_error(robot, proxies, env, cutoff=DEFAULT_CUTOFF, opacity_weights=True):
    """What the proxies cost against the full robot in one configuration: |C_proxy - C_full| / C_full
    (0 when both are 0, inf when only the full cost is 0)."""
    index = as_index(env, opacity_weights)
    full = overlap(robot, index, cutoff, gradient=False, bound=False, opacity_weights=opacity_weights).cost
    approx = overlap(proxies, index, cutoff, gradient=False, bound=False).cost
    if full == 0:
        return 0.0 if approx == 0 else math.inf
    return abs(approx - full) / full
