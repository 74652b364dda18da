"""The splats' shadow-casting stand-in (core/shadow_casters.py) against closed forms: each ellipsoid's
surface points satisfy the splat's own quadratic form at the alpha level, the shells are closed and
wound outwards (their signed volume is the ellipsoid's), faint splats are left out."""

import numpy as np
from helpers import quat_matrices, random_cloud

from splatwright.core.shadow_casters import UNIT_FACES, UNIT_VERTICES, ellipsoids, reach


def test_reach_is_where_the_gaussian_falls_to_the_alpha():
    opacity = np.array([0.9, 0.5, 0.3, 0.999])
    r = reach(opacity, 0.5)
    np.testing.assert_allclose(opacity * np.exp(-0.5 * r**2), np.where(opacity > 0.5, 0.5, opacity), rtol=1e-12)
    assert r[1] == 0 and r[2] == 0


def test_each_splat_becomes_its_ellipsoid_at_the_alpha_level():
    cloud = random_cloud(40, sh_degree=0, seed=3)
    vertices, faces = ellipsoids(cloud)
    kept = np.flatnonzero(cloud.opacities > 0.5)
    assert len(kept) and len(kept) < len(cloud)
    n_v, n_f = len(UNIT_VERTICES), len(UNIT_FACES)
    assert vertices.shape == (len(kept) * n_v, 3) and faces.shape == (len(kept) * n_f, 3)
    v = vertices.astype(np.float64).reshape(len(kept), n_v, 3)
    # float64 reference: the Mahalanobis radius of every vertex about its own splat, by the covariance
    q = quat_matrices(cloud.rotations[kept])
    s2 = np.exp(2 * cloud.log_scales[kept].astype(np.float64))
    cov = np.einsum("kij,kj,klj->kil", q, s2, q)
    d = v - cloud.positions[kept].astype(np.float64)[:, None]
    m2 = np.einsum("kvi,kij,kvj->kv", d, np.linalg.inv(cov), d)
    alpha = cloud.opacities[kept].astype(np.float64)[:, None] * np.exp(-0.5 * m2)
    np.testing.assert_allclose(alpha, 0.5, rtol=2e-4)
    # closed, outward: the divergence theorem's volume against the inscribed polyhedron of the unit
    # sphere scaled by the ellipsoid's semi-axes
    tri = v[:, faces[:n_f] % n_v]  # (K, F, 3, 3) corners
    volume = np.einsum("kfi,kfi->kf", tri[:, :, 0], np.cross(tri[:, :, 1], tri[:, :, 2])).sum(axis=1) / 6
    unit = UNIT_VERTICES[UNIT_FACES]
    unit_volume = np.einsum("fi,fi->f", unit[:, 0], np.cross(unit[:, 1], unit[:, 2])).sum() / 6
    semi = np.exp(cloud.log_scales[kept].astype(np.float64)).prod(axis=1) * reach(cloud.opacities[kept]) ** 3
    np.testing.assert_allclose(volume, unit_volume * semi, rtol=1e-4)
    assert unit_volume > 0.6 * 4 / 3 * np.pi


def test_no_splat_opaque_enough_gives_an_empty_mesh():
    cloud = random_cloud(5, sh_degree=0, seed=1)
    cloud = cloud.replace(opacity_logits=np.full(5, -1.0, np.float32))
    vertices, faces = ellipsoids(cloud)
    assert vertices.shape == (0, 3) and faces.shape == (0, 3)


def test_the_finest_shape_within_a_budget():
    """32 triangles a splat while they fit, the octahedron's 8 past that, none past both."""
    from splatwright.core.shadow_casters import BYTES_PER_TRIANGLE, SHAPES, shape_within

    fine, coarse = SHAPES
    assert len(fine[1]) == 32 and len(coarse[1]) == 8
    per = BYTES_PER_TRIANGLE
    assert shape_within(1000, 32 * 1000 * per) is fine
    assert shape_within(1000, 32 * 1000 * per - 1) is coarse
    assert shape_within(1000, 8 * 1000 * per) is coarse
    assert shape_within(1000, 8 * 1000 * per - 1) is None


def test_the_octahedron_stand_in_also_sits_at_the_alpha_level():
    from splatwright.core.shadow_casters import SHAPES

    cloud = random_cloud(40, sh_degree=0, seed=3)
    vertices, faces = ellipsoids(cloud, shape=SHAPES[1])
    kept = np.flatnonzero(cloud.opacities > 0.5)
    assert vertices.shape == (len(kept) * 6, 3) and faces.shape == (len(kept) * 8, 3)
    q = quat_matrices(cloud.rotations[kept])
    s2 = np.exp(2 * cloud.log_scales[kept].astype(np.float64))
    cov = np.einsum("kij,kj,klj->kil", q, s2, q)
    d = vertices.astype(np.float64).reshape(len(kept), 6, 3) - cloud.positions[kept].astype(np.float64)[:, None]
    m2 = np.einsum("kvi,kij,kvj->kv", d, np.linalg.inv(cov), d)
    np.testing.assert_allclose(cloud.opacities[kept].astype(np.float64)[:, None] * np.exp(-0.5 * m2), 0.5, rtol=2e-4)
