import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud, SplatValidationError, geometry, sh
from splatwright.core.scenes import seed_cube


def test_activated_views_match_closed_forms(cloud):
    np.testing.assert_allclose(cloud.scales, np.exp(cloud.log_scales.astype(np.float64)))
    np.testing.assert_allclose(cloud.opacities, 1 / (1 + np.exp(-cloud.opacity_logits.astype(np.float64))))
    q = cloud.unit_rotations
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    cov = cloud.covariances()
    # Sigma is symmetric positive definite with eigenvalues = scales^2.
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-15)
    eig = np.sort(np.linalg.eigvalsh(cov), axis=1)
    np.testing.assert_allclose(eig, np.sort(cloud.scales**2, axis=1), rtol=1e-9)


def test_opacity_logits_of_1e4_do_not_overflow():
    c = random_cloud(2, sh_degree=0)
    c.opacity_logits[:] = [1e4, -1e4]
    with np.errstate(all="raise"):
        np.testing.assert_array_equal(c.opacities, [1.0, 0.0])


def test_quaternion_round_trip_and_covariance_decomposition(rng):
    q = rng.normal(size=(5000, 4))
    m = geometry.quaternions_to_matrices(q)
    np.testing.assert_allclose(m @ np.swapaxes(m, 1, 2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(geometry.quaternions_to_matrices(geometry.matrices_to_quaternions(m)), m, atol=1e-12)
    scales = np.exp(rng.uniform(-16, 9, (5000, 3)))  # 1e-7 .. 1e4 in one batch
    cov = geometry.covariances(q, scales)
    q2, s2 = geometry.decompose_covariances(cov)
    np.testing.assert_allclose(geometry.covariances(q2, s2), cov, rtol=0, atol=1e-12 * scales.max() ** 2)


def test_zero_quaternion_becomes_identity_and_is_reported():
    c = random_cloud(3, sh_degree=0)
    c.rotations[1] = 0
    np.testing.assert_array_equal(c.unit_rotations[1], [1, 0, 0, 0])
    assert "1 splats with a zero rotation quaternion" in c.problems()
    with pytest.raises(SplatValidationError, match="zero rotation"):
        c.validate()


def test_non_finite_values_are_reported_by_field_and_count():
    c = random_cloud(10, sh_degree=1)
    c.positions[2, 1] = np.nan
    c.positions[3, 0] = np.inf
    c.sh[5, 2, 0] = np.nan
    problems = c.problems()
    assert "2 splats with non-finite positions" in problems
    assert "1 splats with non-finite sh" in problems
    assert c.finite_mask().sum() == 7


def test_shape_errors_name_the_field():
    with pytest.raises(SplatValidationError, match=r"rotations has shape \(4, 3\)"):
        SplatCloud(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(4), np.zeros((4, 1, 3)))
    with pytest.raises(SplatValidationError, match="sh has shape"):
        SplatCloud(np.zeros((4, 3)), np.zeros((4, 4)), np.zeros((4, 3)), np.zeros(4), np.zeros((4, 5, 3)))


def test_sh_degree_4_is_a_valid_cloud_and_5_is_not():
    """K = (d+1)^2 for d in 0..4: 25 coefficients are degree 4, 36 (degree 5) are refused."""
    fields = (np.zeros((4, 3)), np.ones((4, 4)), np.zeros((4, 3)), np.zeros(4))
    assert SplatCloud(*fields, np.zeros((4, 25, 3))).sh_degree == 4
    with pytest.raises(SplatValidationError, match=r"K in \(1, 4, 9, 16, 25\)"):
        SplatCloud(*fields, np.zeros((4, 36, 3)))
    four, one = random_cloud(5, sh_degree=4, seed=1), random_cloud(6, sh_degree=1, seed=2)
    both = SplatCloud.concatenate([one, four])
    assert both.sh_degree == 4 and not both.sh[:5, 4:].any()
    np.testing.assert_array_equal(both.sh[6:], four.sh)
    assert four.with_sh_degree(3).sh.shape == (5, 16, 3) and sh.num_coeffs(4) == 25 and sh.degree_of(25) == 4
    with pytest.raises(ValueError, match="0..4"):
        sh.num_coeffs(5)


def test_select_and_concatenate_keep_fields_and_extras_aligned():
    a, b = random_cloud(20, sh_degree=3, seed=1), random_cloud(30, sh_degree=1, seed=2)
    a.extras["tag"] = np.arange(20)
    b.extras["tag"] = np.arange(100, 130)
    both = SplatCloud.concatenate([a, b])
    assert len(both) == 50 and both.sh_degree == 3
    np.testing.assert_array_equal(both.sh[20:, 4:], 0)
    d = np.random.default_rng(0).normal(size=(50, 3))
    # Padding with zeros keeps every colour.
    np.testing.assert_allclose(both.colors(directions=d)[20:], b.colors(directions=d[20:]), atol=1e-6)
    picked = both[both.extras["tag"] >= 100]
    np.testing.assert_array_equal(picked.positions, b.positions)
    np.testing.assert_array_equal(both[[3]].extras["tag"], [3])


def test_seed_cube_matches_its_definition():
    c = seed_cube()
    assert len(c) == 1000
    np.testing.assert_allclose(c.positions.mean(axis=0), [0, 0, 3], atol=1e-6)
    np.testing.assert_allclose(c.scales, 0.05, rtol=1e-6)
    np.testing.assert_allclose(c.opacities, 0.08, rtol=1e-5)
    np.testing.assert_allclose(c.colors([0, 0, 0]), np.tile([0.2, 0.4, 1.0], (1000, 1)), atol=1e-6)


def test_dc_colour_round_trip():
    rgb = np.random.default_rng(0).uniform(size=(10, 3))
    np.testing.assert_allclose(sh.dc_to_rgb(sh.rgb_to_dc(rgb)), rgb, atol=1e-12)


def test_the_render_mode_splats_were_made_for_travels_with_them():
    made = random_cloud(30, sh_degree=1).replace(antialiased=True)
    turn = np.diag([1.0, -1.0, -1.0, 1.0])
    kept = [
        made[::2],
        made.copy(),
        made.transformed(turn),
        made.with_sh_degree(0),
        SplatCloud.concatenate([made, made[:3]]),
    ]
    assert all(c.antialiased for c in kept) and "antialiased" in repr(made)
    assert not SplatCloud.concatenate([random_cloud(4), random_cloud(5)]).antialiased
    with pytest.raises(ValueError, match="antialiased rendering with splats made for classic"):
        SplatCloud.concatenate([made, random_cloud(4, sh_degree=1)])


def test_a_cloud_from_another_process_keeps_its_arrays_when_replaced():
    """An unpickled float32 array's dtype is an equal but other object, for which np.asarray makes a
    new view: a replaced cloud must still hold the same arrays, or the shapes made for it (which tell
    a cloud by its arrays) refuse its lit copy, as render_lit raised for a cloud from a pickle."""
    import pickle

    from splatwright.core import material, relight
    from splatwright.core.camera import Camera
    from splatwright.core.lights import Light

    cloud = pickle.loads(pickle.dumps(random_cloud(50, sh_degree=1)))
    assert cloud.positions.dtype is not np.dtype(np.float32)  # the case itself
    replaced = cloud.replace(sh=cloud.sh[:, :1])
    assert all(getattr(replaced, name) is getattr(cloud, name) for name in ("positions", "rotations", "log_scales"))
    lit = material.with_material(cloud, albedo=np.full((50, 3), 0.5))
    camera = Camera.look_at((0, -3, 1), (0, 0, 0), up=(0, 0, 1), fov_deg=50, width=32, height=24)
    frame = relight.render_lit(lit, camera, [Light("sun", power=2.0, direction=(0, 0.3, -1))])
    assert frame.alpha.max() > 0.1
