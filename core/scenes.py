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


def thin_walled_cup(radius=0.04, height=0.09, wall=0.005, n=64):
    """A closed cup (core.mesh.Mesh): outer wall, rim, inner wall and floor `wall` thick; material 0
    (orange) outside, 1 (blue) inside. The hard case of thin walls for mesh conversion: neither side
    may show through the other."""
    from .mesh import Material, Mesh

    inner = radius - wall
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = lambda r, y: np.column_stack([r * np.cos(angle), np.full(n, y), -r * np.sin(angle)])  # noqa: E731
    v = np.concatenate(
        [ring(radius, 0), ring(radius, height), ring(inner, height), ring(inner, wall), [[0, 0, 0]], [[0, wall, 0]]]
    )
    k, k1 = np.arange(n), (np.arange(n) + 1) % n
    band = lambda a, b: np.concatenate(
        [
            np.stack([a + k, a + k1, b + k1], 1),  # noqa: E731
            np.stack([a + k, b + k1, b + k], 1),
        ]
    )
    f = np.concatenate(
        [
            band(0, n),
            band(n, 2 * n),
            band(2 * n, 3 * n),
            np.stack([np.full(n, 4 * n + 1), 3 * n + k, 3 * n + k1], 1),
            np.stack([np.full(n, 4 * n), k1, k], 1),
        ]
    )
    fm = np.concatenate([np.zeros(4 * n), np.ones(3 * n), np.zeros(n)]).astype(int)
    return Mesh(v, f, None, fm, [Material(base_color=(0.8, 0.15, 0.05)), Material(base_color=(0.05, 0.2, 0.9))])
