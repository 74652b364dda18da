"""Normals estimated from splat shapes (core.normals): the shortest axis against eigenvectors and the
closed form, orientation rules, visibility, angular error statistics, and bad input."""

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud, economy, geometry, mesh_corpus, mesh_to_splats
from splatwright.core import material as mat
from splatwright.core import normals as nm
from splatwright.core.camera import Camera
from splatwright.core.mesh import Surface


def _random_unit_quaternions(n, rng):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _flat_cloud(positions, rotations, scales, opacity=0.99):
    n = len(positions)
    return SplatCloud.from_activated(positions, rotations, scales, np.full(n, opacity))


def test_shortest_axis_of_rotated_flat_gaussian_is_the_closed_form():
    rng = np.random.default_rng(1)
    n = 500
    q = _random_unit_quaternions(n, rng)
    # A disc flat along its local z: the normal is R e_z, the third column of the rotation matrix.
    w, x, y, z = q.T
    closed = np.column_stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    scales = np.column_stack([rng.uniform(0.5, 2, n), rng.uniform(0.5, 2, n), rng.uniform(0.001, 0.2, n)])
    axes = nm.shortest_axes(_flat_cloud(rng.normal(size=(n, 3)), q * rng.uniform(0.5, 3, (n, 1)), scales))
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", axes, closed)), 1.0, atol=1e-6)


def test_shortest_axis_is_the_covariance_smallest_eigenvector_whichever_axis_is_shortest():
    rng = np.random.default_rng(2)
    n = 400
    q = _random_unit_quaternions(n, rng)
    scales = rng.uniform(0.5, 2, (n, 3))
    short = rng.integers(0, 3, n)
    scales[np.arange(n), short] = rng.uniform(0.01, 0.3, n)
    cloud = _flat_cloud(rng.normal(size=(n, 3)), q, scales)
    cov = cloud.covariances()
    vals, vecs = np.linalg.eigh(cov)  # float64 reference, ascending eigenvalues
    reference = vecs[:, :, 0]
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", nm.shortest_axes(cloud), reference)), 1.0, atol=1e-6)


def test_roundness_is_shortest_over_middle_scale():
    rng = np.random.default_rng(3)
    scales = rng.uniform(0.01, 1, (300, 3))
    cloud = _flat_cloud(rng.normal(size=(300, 3)), _random_unit_quaternions(300, rng), scales)
    s = np.sort(cloud.scales, axis=1)
    np.testing.assert_allclose(nm.roundness(cloud), s[:, 0] / s[:, 1], rtol=1e-5)
    np.testing.assert_array_equal(nm.too_round(cloud), s[:, 0] / s[:, 1] >= nm.TOO_ROUND)


def _sphere_of_splats(n=3000, centre=(3.0, -1.0, 2.0), radius=1.0, seed=4):
    """Flat discs tiling a sphere, each with its local z along the radius, half of them inward."""
    rng = np.random.default_rng(seed)
    i = np.arange(n) + 0.5
    zc = 1 - 2 * i / n
    ring = np.sqrt(1 - zc**2)
    angle = np.pi * (3 - np.sqrt(5)) * i
    radial = np.column_stack([ring * np.cos(angle), ring * np.sin(angle), zc])
    # The rotation taking e_z to +-radial, built from a random tangent frame.
    t1 = np.cross(radial, rng.normal(size=(n, 3)))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    sign = np.where(rng.uniform(size=n) < 0.5, -1.0, 1.0)[:, None]
    t2 = np.cross(sign * radial, t1)
    q = geometry.matrices_to_quaternions(np.stack([t1, t2, sign * radial], axis=2))
    sigma = 0.9 * radius * np.sqrt(4 * np.pi / n)
    scales = np.column_stack([np.full(n, sigma), np.full(n, sigma), np.full(n, 0.02 * sigma)])
    return _flat_cloud(np.asarray(centre) + radius * radial, q, scales), radial


def test_every_rule_orients_a_sphere_outward():
    cloud, radial = _sphere_of_splats()
    centre = np.array([3.0, -1.0, 2.0])
    assert (np.einsum("ij,ij->i", nm.shortest_axes(cloud), radial) < 0).mean() > 0.4  # unoriented
    outward = lambda found: np.einsum("ij,ij->i", found, radial)  # noqa: E731
    assert outward(nm.estimate_normals(cloud)).min() > 0.999  # away from the median
    assert outward(nm.estimate_normals(cloud, centre=centre)).min() > 0.999
    cameras = economy.orbit_views(cloud.positions, count=12, width=128)
    centres = np.array([c.center for c in cameras])
    assert outward(nm.estimate_normals(cloud, cameras=centres, rule="nearest")).min() > 0.999
    for rule in nm.RULES:
        found = nm.estimate_normals(cloud, cameras=cameras, rule=rule)
        assert found.dtype == np.float32 and found.shape == (len(cloud), 3)
        assert outward(found).min() > 0.999, rule
    # A centre outside the sphere turns the near side inward: the rule is only for convex shapes.
    assert (outward(nm.estimate_normals(cloud, centre=centre + [0, 0, 5])) < 0).any()


def test_visibility_hides_a_sheet_behind_another():
    # Two 1 x 1 sheets of flat splats facing a camera on the z axis, at z = 0 and z = 0.5.
    g = np.linspace(-0.5, 0.5, 21)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pos = np.concatenate([np.column_stack([xy, np.zeros(len(xy))]), np.column_stack([xy, np.full(len(xy), 0.5)])])
    q = np.tile([1.0, 0, 0, 0], (len(pos), 1))
    cloud = _flat_cloud(pos, q, np.tile([0.05, 0.05, 0.001], (len(pos), 1)))
    front = Camera.look_at([0, 0, -3.0], [0, 0, 0], up=(0, -1, 0), fov_deg=30, width=128, height=128)
    back = Camera.look_at([0, 0, 3.5], [0, 0, 0.5], up=(0, -1, 0), fov_deg=30, width=128, height=128)
    seen = nm.visibility(cloud, [front, back])
    first = np.arange(len(pos)) < len(xy)
    inner = (np.abs(pos[:, :2]) < 0.4).all(axis=1)  # away from the sheets' rims
    assert seen[first & inner, 0].all() and not seen[~first & inner, 0].any()
    assert seen[~first & inner, 1].all() and not seen[first & inner, 1].any()
    # Each sheet faces the camera that sees it: -z for the first, +z for the second.
    found = nm.estimate_normals(cloud, cameras=[front, back])
    np.testing.assert_allclose(found[first & inner, 2], -1.0, atol=1e-6)
    np.testing.assert_allclose(found[~first & inner, 2], 1.0, atol=1e-6)


# Measured on this mesh (bench/normals.py, the sphere rows): float32 round-off, a few 1e-6 degrees.
MESH_SPHERE_BOUND_DEG = 1e-4


def test_mesh_made_sphere_normals_match_the_source_triangles():
    mesh = mesh_corpus.vertex_coloured_sphere(32, 16)
    cloud = mesh_to_splats.mesh_to_splats(mesh.vertices, mesh.faces, max_splats=3000, calibrate=False)
    true = Surface(mesh.vertices, mesh.faces).normal[cloud.extras["source_triangle"]]
    cameras = economy.orbit_views(cloud.positions, count=8, width=128)
    for options in ({}, {"cameras": cameras}):
        stats = nm.angular_error(nm.estimate_normals(cloud, **options), true)
        assert stats.flips == 0 and stats.count == len(cloud)
        assert stats.median < MESH_SPHERE_BOUND_DEG and stats.p90 < MESH_SPHERE_BOUND_DEG


def test_angular_error_statistics_against_known_angles():
    angles = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 100.0, 179.0, 5.0, 15.0, 25.0])
    t = np.radians(angles)
    true = np.tile([0.0, 0.0, 2.0], (len(angles), 1))
    estimated = np.column_stack([np.sin(t), np.zeros(len(t)), np.cos(t)]) * 3.0
    stats = nm.angular_error(estimated, true)
    assert stats.median == pytest.approx(np.median(angles), abs=1e-9)
    assert stats.p90 == pytest.approx(np.percentile(angles, 90), abs=1e-9)
    assert stats.mean == pytest.approx(angles.mean(), abs=1e-9)
    assert stats.flips == pytest.approx(0.2) and stats.count == 10
    with pytest.raises(ValueError, match="zero-length or not finite"):
        nm.angular_error(np.zeros((2, 3)), true[:2])
    with pytest.raises(ValueError, match="N > 0"):
        nm.angular_error(np.zeros((0, 3)), np.zeros((0, 3)))


def test_estimated_normals_stored_as_the_material_normals():
    cloud, radial = _sphere_of_splats(500)
    stored = nm.with_estimated_normals(cloud)
    np.testing.assert_allclose(mat.normals(stored), nm.estimate_normals(cloud), atol=1e-7)
    assert np.einsum("ij,ij->i", mat.normals(stored), radial).min() > 0.999


def test_bad_input_is_a_clear_value_error():
    with pytest.raises(ValueError, match="empty splat cloud"):
        nm.estimate_normals(SplatCloud.empty())
    cloud = random_cloud(20, sh_degree=0)
    for field in ("positions", "rotations", "log_scales"):
        broken = cloud.copy()
        getattr(broken, field)[3, 1] = np.nan
        with pytest.raises(ValueError, match=f"1 with non-finite {field}"):
            nm.estimate_normals(broken)
    with pytest.raises(ValueError, match="centre must be 3 finite numbers"):
        nm.estimate_normals(cloud, centre=[0, np.nan, 0])
    with pytest.raises(ValueError, match="camera centres"):
        nm.estimate_normals(cloud, cameras=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="unknown orientation rule"):
        nm.estimate_normals(cloud, rule="sideways")
