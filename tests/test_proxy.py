"""Nearest points of a triangle mesh (core.proxy) against a float64 brute force: Ericson's
closest-point-on-triangle, one point and one triangle at a time."""

import numpy as np
import pytest

from splatwright.core import proxy


def ericson(p, a, b, c):
    """Real-Time Collision Detection 5.1.5, scalar."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab @ ap, ac @ ap
    if d1 <= 0 and d2 <= 0:
        return a
    bp = p - b
    d3, d4 = ab @ bp, ac @ bp
    if d3 >= 0 and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        return a + d1 / (d1 - d3) * ab
    cp = p - c
    d5, d6 = ab @ cp, ac @ cp
    if d6 >= 0 and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        return a + d2 / (d2 - d6) * ac
    va = d3 * d6 - d5 * d4
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b)
    den = 1 / (va + vb + vc)
    return a + ab * vb * den + ac * vc * den


def uv_sphere(rows=14, cols=24):
    u, v = np.meshgrid(np.linspace(0, np.pi, rows), np.linspace(0, 2 * np.pi, cols), indexing="ij")
    verts = np.stack([np.sin(u) * np.cos(v), 1.5 * np.sin(u) * np.sin(v), np.cos(u)], -1).reshape(-1, 3)
    faces = []
    for i in range(rows - 1):
        for j in range(cols - 1):
            a = i * cols + j
            faces += [(a, a + cols, a + 1), (a + 1, a + cols, a + cols + 1)]  # poles: degenerate triangles
    return verts, np.array(faces)


def test_nearest_points_equal_the_brute_force():
    verts, faces = uv_sphere()
    rng = np.random.default_rng(2)
    direction = rng.normal(size=(250, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = np.concatenate(
        [
            direction * rng.uniform(0.9, 1.1, (250, 1)),  # near the surface
            rng.uniform(-4, 4, (60, 3)),
        ]
    )  # inside and far
    found = proxy.closest_points(points, verts, faces)
    best = np.array([min(np.linalg.norm(p - ericson(p, *verts[f])) for f in faces) for p in points])
    np.testing.assert_allclose(found.distance, best, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(found.point - points, axis=1), best, rtol=0, atol=1e-12)
    # the point is where the triangle and barycentrics say
    np.testing.assert_allclose(
        found.point, np.einsum("nk,nki->ni", found.barycentric, verts[faces[found.triangle]]), atol=1e-12
    )
    assert (found.barycentric >= -1e-12).all()
    np.testing.assert_allclose(found.barycentric.sum(axis=1), 1.0, atol=1e-12)


def test_surface_weights_blend_the_corners():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2]])
    weights = np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])
    found = proxy.closest_points([[0.25, 0.25, 0.3], [2.0, 0.0, 0.0]], verts, faces)
    np.testing.assert_allclose(found.barycentric, [[0.5, 0.25, 0.25], [0.0, 1.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(proxy.surface_weights(found, faces, weights), [[0.625, 0.375], [0.0, 1.0]])
    np.testing.assert_allclose(found.distance, [0.3, 1.0])


def test_bad_meshes_are_refused():
    with pytest.raises(proxy.ProxyError, match="no faces"):
        proxy.closest_points(np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(proxy.ProxyError, match="index"):
        proxy.closest_points(np.zeros((2, 3)), np.zeros((3, 3)), [[0, 1, 5]])
    with pytest.raises(proxy.ProxyError, match="NaN"):
        proxy.closest_points([[np.nan, 0, 0]], np.eye(3), [[0, 1, 2]])


def test_falloff_is_a_smoothstep_from_start_to_end():
    d = np.array([0.0, 0.04, 0.05, 0.07, 0.1, 0.13, 0.4])
    s = np.clip((d - 0.04) / 0.06, 0, 1)
    np.testing.assert_allclose(proxy.falloff_strength(d, 0.04, 0.1), 1 - 3 * s**2 + 2 * s**3, atol=1e-15)
    assert proxy.falloff_strength(0.07, 0.04, 0.1) == pytest.approx(0.5)  # halfway, by symmetry
    np.testing.assert_array_equal(proxy.falloff_strength(d, 0.1, 0.1), d <= 0.1)  # start == end: a hard cut
    for start, end in ((0.2, 0.1), (-0.1, 0.1)):
        with pytest.raises(proxy.ProxyError, match="falloff must start"):
            proxy.falloff_strength(d, start, end)
