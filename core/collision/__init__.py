"""Collision between splat clouds, for planning: soft Gaussian overlap with gradients, exact
ellipsoid contacts, occupancy, signed distance and per-link collision proxies. NumPy only.

Soft overlap between a robot (Gaussians i) and an environment (Gaussians j):

    C = sum_i sum_j w_i w_j exp(-1/2 d^T (Sigma_i + Sigma_j)^-1 d),   d = mu_i - mu_j

with w = opacity (or 1). The environment is indexed once (`EnvironmentIndex`, a sorted grid per
size class); each query visits only pairs whose Mahalanobis distance can be within `cutoff`.
Every skipped pair contributes less than exp(-cutoff^2 / 2), and a pair further apart than R
contributes less than exp(-R^2 / (2 (lmax_i + lmax_j))) because lmax(Sigma_i + Sigma_j) <=
lmax_i + lmax_j; counting the environment around each robot splat ring by ring turns these two
facts into a bound on everything the cutoff dropped, reported with every result.

Near-singular Sigma_i + Sigma_j (flat or needle splats) are factorised with a square-root-free
Cholesky (L D L^T) whose pivots are floored at PIVOT_FLOOR * trace: a direction thinner than
1e-6 of the pair's size is treated as that thin. Float64 rounding of an explicitly formed
covariance already blurs such directions at about 1e-8 of its size, so nothing measurable is lost,
and far pairs underflow to exactly 0 instead of NaN.

The package, bottom up: gaussians.py (the Gaussians, input checks, the pair kernel, the thread
map), index.py (EnvironmentIndex, the broad phase), overlap.py (soft overlap), joints.py (poses
and the gradient with respect to joint values), contacts.py (the exact ellipsoid test),
distance.py (occupancy and signed distance), proxies.py (collision proxies). Every public name is
importable from here.
"""

from .contacts import Contacts, contact_sigma, ellipsoid_contacts
from .distance import Occupancy, occupancy, signed_distance
from .gaussians import (
    BOUND_MARGIN,
    DEFAULT_CUTOFF,
    PIVOT_FLOOR,
    QUANTISATION_LIMIT,
    CollisionInputError,
    CollisionPrecisionWarning,
    Gaussians,
    as_gaussians,
)
from .index import COARSE, EnvironmentIndex, as_index
from .joints import overlap_at, pose_robot
from .overlap import Overlap, overlap, overlap_all_pairs
from .proxies import fit_proxies, proxy_error

__all__ = [
    "BOUND_MARGIN",
    "COARSE",
    "DEFAULT_CUTOFF",
    "PIVOT_FLOOR",
    "QUANTISATION_LIMIT",
    "CollisionInputError",
    "CollisionPrecisionWarning",
    "Contacts",
    "EnvironmentIndex",
    "Gaussians",
    "Occupancy",
    "Overlap",
    "as_gaussians",
    "as_index",
    "contact_sigma",
    "ellipsoid_contacts",
    "fit_proxies",
    "occupancy",
    "overlap",
    "overlap_all_pairs",
    "overlap_at",
    "pose_robot",
    "proxy_error",
    "signed_distance",
]
