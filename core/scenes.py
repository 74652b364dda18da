"""Built-in scenes: small, deterministic, made from code (no binary assets)."""

import numpy as np

from .splats import SplatCloud


def seed_cube(points_per_edge=10, sigma=0.05, color=(0.2, 0.4, 1.0), opacity=0.08, center=(0.0, 0.0, 3.0)):
    """The seed scene: a grid of isotropic splats filling a unit cube (default 10^3 = 1000 splats)."""
    axis = np.linspace(-0.5, 0.5, points_per_edge)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    n = len(grid)
    return SplatCloud.from_activated(
        positions=grid + np.asarray(center, dtype=np.float64),
        rotations=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        scales=np.full((n, 3), sigma),
        opacities=np.full(n, opacity),
        colors=np.tile(color, (n, 1)),
    )
