"""Test helpers shared by several test modules (tests/ is on sys.path)."""

import numpy as np

from splatwright.core import SplatCloud


def random_cloud(n, sh_degree=3, seed=0, spread=1.0):
    """A random anisotropic cloud with every field populated and non-unit quaternions."""
    rng = np.random.default_rng(seed)
    k = (sh_degree + 1) ** 2
    return SplatCloud(
        positions=rng.normal(0, spread, (n, 3)),
        rotations=rng.normal(0, 1, (n, 4)) * rng.uniform(0.5, 2.0, (n, 1)),
        log_scales=rng.uniform(-4, -1, (n, 3)),
        opacity_logits=rng.normal(0, 2, n),
        sh=rng.normal(0, 0.3, (n, k, 3)),
    )
