"""Collision: soft overlap and its gradients, the cutoff bound, exact ellipsoid contacts, occupancy,
signed distance and proxies, each against float64 brute force, closed forms or finite differences."""

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud, geometry
from splatwright.core import collision as col
from splatwright.core.kinematics import KinematicTree, axis_angle_matrices, transforms

# independent references ---------------------------------------------------------------------------


def brute_overlap(robot, env):
    """Double loop in float64 with a general solver: cost, per robot Gaussian, dC/dmu, dC/dSigma."""
    n = len(robot)
    per, grad, gcov = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3, 3))
    for i in range(n):
        for j in range(len(env)):
            d = robot.means[i] - env.means[j]
            x = np.linalg.solve(robot.covs[i] + env.covs[j], d)
            v = robot.weights[i] * env.weights[j] * np.exp(-0.5 * d @ x)
            per[i] += v
            grad[i] -= v * x
            gcov[i] += 0.5 * v * np.outer(x, x)
    return per.sum(), per, grad, gcov


def gaussians(means, scales, rotations=None, weights=None, links=None):
    """Float64 Gaussians from centres, per-axis sigmas and w,x,y,z quaternions (identity default)."""
    means = np.asarray(means, float)
    rotations = np.tile([1.0, 0, 0, 0], (len(means), 1)) if rotations is None else rotations
    return col.Gaussians(means, geometry.covariances(rotations, np.asarray(scales, float)), weights, links)


def rel(a, b):
    return np.abs(np.asarray(a, float) - b).max() / max(np.abs(b).max(), 1e-300)


def plane_env(n=3000, seed=0, size=1.0, sigma=(0.01, 0.03)):
    """Flat splats scattered on the z = 0 plane, normals up."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-size, size, (n, 2))
    t = rng.uniform(*sigma, (n, 2))
    scales = np.column_stack([t, 0.2 * t.min(axis=1)])
    angle = rng.uniform(0, np.pi, n)
    q = np.column_stack([np.cos(angle / 2), 0 * angle, 0 * angle, np.sin(angle / 2)])
    return SplatCloud.from_activated(np.column_stack([xy, np.zeros(n)]), q, scales, rng.uniform(0.2, 1.0, n))


# soft overlap ---------------------------------------------------------------------------------------


def test_overlap_matches_double_loop_with_and_without_opacity():
    robot_cloud, env_cloud = random_cloud(25, 0, seed=1, spread=0.1), random_cloud(150, 0, seed=2, spread=0.15)
    for weighted in (True, False):
        robot = col.Gaussians.from_cloud(robot_cloud, weighted)
        env = col.Gaussians.from_cloud(env_cloud, weighted)
        cost, per, grad, gcov = brute_overlap(robot, env)
        for result in (
            col.overlap_all_pairs(robot, env, cov_gradient=True),
            col.overlap(robot, env, cutoff=40.0, cov_gradient=True),
            col.overlap(robot_cloud, env_cloud, cutoff=40.0, cov_gradient=True, opacity_weights=weighted),
        ):
            assert result.cost == pytest.approx(cost, rel=1e-12)
            assert rel(result.per_gaussian, per) < 1e-12
            assert rel(result.grad_means, grad) < 1e-11
            assert rel(result.grad_covs, gcov) < 1e-11
    assert (
        not weighted
        or cost
        < brute_overlap(col.Gaussians.from_cloud(robot_cloud, False), col.Gaussians.from_cloud(env_cloud, False))[0]
    )


def test_gradients_match_central_differences():
    robot = col.Gaussians.from_cloud(random_cloud(6, 0, seed=3, spread=0.05))
    env = col.EnvironmentIndex(random_cloud(300, 0, seed=4, spread=0.1))
    res = col.overlap(robot, env, cutoff=30.0, cov_gradient=True)
    h = 1e-7
    for i in range(len(robot)):
        for a in range(3):
            plus, minus = (
                col.Gaussians(
                    robot.means + s * h * np.eye(3)[a] * (np.arange(6) == i)[:, None], robot.covs, robot.weights
                )
                for s in (1, -1)
            )
            fd = (col.overlap(plus, env, 30.0).cost - col.overlap(minus, env, 30.0).cost) / (2 * h)
            assert res.grad_means[i, a] == pytest.approx(fd, rel=1e-6, abs=1e-9 * abs(res.cost))
        for a, b in ((0, 0), (1, 2), (0, 2)):
            bump = np.zeros((6, 3, 3))
            bump[i, a, b] = bump[i, b, a] = h
            plus, minus = (col.Gaussians(robot.means, robot.covs + s * bump, robot.weights) for s in (1, -1))
            fd = (col.overlap(plus, env, 30.0).cost - col.overlap(minus, env, 30.0).cost) / (2 * h)
            # a symmetric bump of an off-diagonal entry changes both (a,b) and (b,a)
            expect = res.grad_covs[i, a, b] * (1 if a == b else 2)
            assert expect == pytest.approx(fd, rel=1e-5, abs=1e-8 * abs(res.cost))


def test_cutoff_error_stays_under_the_reported_bound():
    env = plane_env(4000)
    rng = np.random.default_rng(5)
    robot = gaussians(
        rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.08], (60, 3)),
        rng.uniform(0.01, 0.03, (60, 3)),
        rng.normal(size=(60, 4)),
        rng.uniform(0.3, 1.0, 60),
    )
    exact = col.overlap_all_pairs(robot, env)
    index = col.EnvironmentIndex(env)
    bounds = []
    for cutoff in (1.5, 2.5, 3.5, 5.0, col.DEFAULT_CUTOFF):
        r = col.overlap(robot, index, cutoff)
        err = exact.cost - r.cost
        assert 0 <= err <= r.bound + 1e-12 * exact.cost  # every skipped term is positive
        assert r.relative_bound == pytest.approx(r.bound / r.cost)
        bounds.append(r.bound)
    assert bounds == sorted(bounds, reverse=True) and bounds[0] > 1e3 * bounds[-1]
    # at the default cutoff the error is far below 1e-6; the bound is looser but still small
    assert err / exact.cost < 1e-6 and r.relative_bound < 1e-4
    assert rel(r.grad_means, exact.grad_means) < 1e-6
    assert col.overlap(robot, index, 8.0).relative_bound < 1e-9


def test_broad_phase_over_scales_from_1e_7_to_1e4():
    rng = np.random.default_rng(6)
    n = 400
    scales = np.exp(rng.uniform(np.log(1e-7), np.log(1e-1), (n, 3)))
    scales[:3] = [[1e4, 1e4, 1e4], [2e3, 1e-7, 5.0], [1e-7, 1e-7, 1e-7]]
    env = gaussians(rng.uniform(-1, 1, (n, 3)), scales, rng.normal(size=(n, 4)), rng.uniform(0, 1, n))
    robot = gaussians(rng.uniform(-1, 1, (40, 3)), rng.uniform(0.01, 0.3, (40, 3)), rng.normal(size=(40, 4)))
    index = col.EnvironmentIndex(env)
    assert len(index.levels) > 5
    exact = col.overlap_all_pairs(robot, env)
    r = col.overlap(robot, index, cutoff=8.0)
    assert abs(r.cost - exact.cost) <= r.bound + 1e-12 * exact.cost
    assert r.relative_bound < 1e-9 and rel(r.per_gaussian, exact.per_gaussian) < 1e-9


def test_flat_and_needle_pairs_match_the_closed_form():
    # Axis-aligned, so Sigma_i + Sigma_j is diagonal and the term is exp(-1/2 sum d_k^2 / s_k).
    rng = np.random.default_rng(7)
    n = 60
    flat = np.column_stack([rng.uniform(0.01, 0.05, (n, 2)), np.full(n, 1e-7)])
    needle = np.column_stack([rng.uniform(0.01, 0.05, n), np.full((n, 2), 1e-7)])
    for scales_r, scales_e in ((flat, flat), (needle, needle), (flat, needle)):
        d = rng.normal(0, 0.03, (n, 3))
        d[: n // 2, 2] = rng.normal(0, 1e-7, n // 2)  # half of them lie in the thin plane
        d[: n // 4, 1] = rng.normal(0, 1e-7, n // 4)
        robot, env = gaussians(d, scales_r), gaussians(np.zeros((n, 3)), scales_e)
        var = scales_r**2 + scales_e**2
        expect = np.exp(-0.5 * (d**2 / var).sum(axis=1))
        got = np.array([col.overlap_all_pairs(robot.subset([k]), env.subset([k])).cost for k in range(n)])
        assert np.isfinite(got).all()
        np.testing.assert_allclose(got, expect, rtol=1e-6, atol=1e-300)
        assert (got[n // 2 :] == 0).any() and (got[: n // 4] > 0).all()
        # the same pairs turned by a random rotation: only the conditioning changes
        r = geometry.quaternions_to_matrices(rng.normal(size=4))
        turned = col.overlap_all_pairs(robot.transformed(r, 0 * d[0]), env.transformed(r, 0 * d[0]).subset([0])).cost
        assert turned == pytest.approx(col.overlap_all_pairs(robot, env.subset([0])).cost, rel=1e-5, abs=1e-200)


def test_coincident_centres_and_point_splats():
    same = gaussians(np.zeros((3, 3)), [[0.1, 0.2, 0.3], [1e-7, 1e-7, 1e-7], [0.0, 0.0, 0.0]], weights=[0.5, 1.0, 0.25])
    r = col.overlap(same, same, cutoff=col.DEFAULT_CUTOFF, cov_gradient=True)
    assert r.cost == pytest.approx(1.75**2, rel=1e-15)  # every term is w_i w_j exp(0)
    assert np.array_equal(r.grad_means, np.zeros((3, 3)))
    points = gaussians([[0, 0, 0], [1e-3, 0, 0]], np.zeros((2, 3)))
    r = col.overlap_all_pairs(points, points, cov_gradient=True)
    assert r.cost == 2.0 and np.isfinite(r.grad_means).all() and np.isfinite(r.grad_covs).all()


def test_far_pairs_underflow_to_exactly_zero():
    robot = gaussians([[0, 0, 0], [0.5, 0, 0]], [[0.01, 0.01, 0.01], [1e-7, 0.02, 0.02]])
    for offset in ([3.0, 0, 0], [0, 0, 1e6], [1e6, 1e6, 0]):
        env = gaussians(np.array([[0, 0, 0], [0.1, 0.2, 0.0]]) + offset, [[0.02, 0.02, 1e-7], [0.01, 0.01, 0.01]])
        for r in (col.overlap(robot, env, cov_gradient=True), col.overlap_all_pairs(robot, env, cov_gradient=True)):
            assert r.cost == 0.0 and r.bound == 0.0
            assert not r.grad_means.any() and not r.grad_covs.any()
        assert r.relative_bound == 0.0


def test_far_from_the_origin_matches_near_the_origin():
    rng = np.random.default_rng(8)
    robot = gaussians(rng.normal(0, 0.05, (20, 3)), rng.uniform(0.01, 0.05, (20, 3)), rng.normal(size=(20, 4)))
    env = gaussians(rng.normal(0, 0.1, (200, 3)), rng.uniform(0.01, 0.05, (200, 3)), rng.normal(size=(200, 4)))
    here = col.overlap(robot, env)
    shift = np.array([1e6, -2e6, 5e5])
    there = col.overlap(robot.transformed(np.eye(3), shift), env.transformed(np.eye(3), shift))
    assert there.cost == pytest.approx(here.cost, rel=1e-9)
    assert rel(there.grad_means, here.grad_means) < 1e-8


def test_empty_clouds():
    empty, some = SplatCloud.empty(), random_cloud(10, 0)
    for robot, env in ((empty, some), (some, empty), (empty, empty)):
        for r in (col.overlap(robot, env), col.overlap_all_pairs(robot, env)):
            assert r.cost == 0.0 and r.grad_means.shape == (len(robot), 3) and r.bound == 0.0
        assert len(col.ellipsoid_contacts(robot, env)) == 0
    assert col.occupancy(empty, np.zeros((2, 3))).values.tolist() == [0.0, 0.0]
    assert col.signed_distance(empty, np.zeros((2, 3)), max_distance=2.0).tolist() == [2.0, 2.0]
    assert len(col.fit_proxies(col.Gaussians(np.zeros((0, 3)), np.zeros((0, 3, 3))))) == 0


def test_bad_input_is_named():
    bad = random_cloud(5, 0)
    bad.positions[2, 1] = np.nan
    with pytest.raises(col.CollisionInputError, match="environment.positions"):
        col.EnvironmentIndex(bad)
    with pytest.raises(col.CollisionInputError, match="robot.positions"):
        col.overlap(bad, random_cloud(5, 0))
    bad = random_cloud(5, 0)
    bad.log_scales[0, 0] = np.inf
    with pytest.raises(col.CollisionInputError, match="log_scales"):
        col.overlap(random_cloud(5, 0), bad)
    with pytest.raises(col.CollisionInputError, match="cutoff"):
        col.overlap(random_cloud(5, 0), random_cloud(5, 0), cutoff=-1.0)
    with pytest.raises(col.CollisionInputError, match="positive semi-definite"):
        col.Gaussians(np.zeros((1, 3)), -np.eye(3)[None])
    with pytest.raises(col.CollisionInputError, match="links"):
        col.pose_robot(col.Gaussians(np.zeros((1, 3)), np.eye(3)[None]), np.eye(4)[None])


def test_opacity_logits_of_1e4_and_zero_scales():
    env = random_cloud(50, 0, seed=9, spread=0.1)
    env.opacity_logits[:10] = -1e4  # opacity exactly 0: dropped from the index
    env.opacity_logits[10:20] = 1e4
    env.log_scales[20:25] = -np.inf  # point splats
    env.rotations[25:27] = 0.0  # zero quaternions: the identity
    robot = random_cloud(10, 0, seed=10, spread=0.1)
    index = col.EnvironmentIndex(env)
    assert sum(lv.count for lv in index.levels) == 40
    np.testing.assert_allclose(
        col.Gaussians.from_cloud(env).covs[25], np.diag(np.exp(2.0 * env.log_scales[25])), rtol=1e-6
    )
    exact = brute_overlap(col.Gaussians.from_cloud(robot), col.Gaussians.from_cloud(env))[0]
    assert col.overlap(robot, index, cutoff=40.0).cost == pytest.approx(exact, rel=1e-12)


# joint space --------------------------------------------------------------------------------------


def small_robot(seed=11):
    t = lambda p, r=np.eye(3): transforms(r, p)
    tree = KinematicTree(
        names=["base", "upper", "slider", "wrist", "finger"],
        parents=[-1, 0, 1, 2, 1],
        origins=[
            t([0.1, 0, 0]),
            t([0, 0, 0.3], axis_angle_matrices([1, 0, 0], 0.3)),
            t([0, 0.2, 0.2]),
            t([0.1, 0.1, 0.1]),
            t([0.05, 0, 0.1]),
        ],
        joint_types=["ball", "revolute", "prismatic", "ball", "continuous"],
        axes=[[1, 0, 0], [0, 1, 0], [0.3, 0, 1], [1, 0, 0], [1, 1, 0]],
    )
    rng = np.random.default_rng(seed)
    local = col.Gaussians.from_cloud(random_cloud(150, 0, seed=seed, spread=0.08), links=rng.integers(0, 5, 150))
    return tree, col.pose_robot(local, tree.rest_transforms())


def test_joint_gradient_matches_central_differences():
    tree, robot = small_robot()
    env = col.EnvironmentIndex(random_cloud(400, 0, seed=12, spread=0.4))
    rng = np.random.default_rng(13)
    for q in (rng.normal(0, 0.4, tree.dof), np.zeros(tree.dof)):  # zero: the ball joints' series branch
        r = col.overlap_at(tree, q, robot, env, cutoff=30.0)
        assert r.cost > 1.0
        h = 1e-6
        fd = [
            (
                col.overlap_at(tree, q + h * e, robot, env, 30.0).cost
                - col.overlap_at(tree, q - h * e, robot, env, 30.0).cost
            )
            / (2 * h)
            for e in np.eye(tree.dof)
        ]
        np.testing.assert_allclose(r.grad_q, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())


def test_posed_robot_matches_rigid_transforms():
    tree, robot = small_robot()
    q = np.random.default_rng(14).normal(0, 0.5, tree.dof)
    deform = tree.forward_kinematics(q) @ np.linalg.inv(tree.rest_transforms())
    posed = col.pose_robot(robot, deform)
    for i in (0, 17, 99):
        m = deform[robot.links[i]]
        np.testing.assert_allclose(posed.means[i], m[:3, :3] @ robot.means[i] + m[:3, 3], atol=1e-14)
        np.testing.assert_allclose(posed.covs[i], m[:3, :3] @ robot.covs[i] @ m[:3, :3].T, atol=1e-16)


# hard contacts ------------------------------------------------------------------------------------


def sphere_points(n):
    """Fibonacci points on the unit sphere."""
    k = np.arange(n) + 0.5
    phi, z = np.pi * (1 + 5**0.5) * k, 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sampled_overlap(ma, ca, mb, cb, t, samples):
    """Do the t-sigma ellipsoids meet? Brute force: the centre of B inside A, or the least
    Mahalanobis radius (w.r.t. B) over sampled boundary points of A within t."""
    la = np.linalg.cholesky(ca + 1e-300 * np.eye(3))
    boundary = ma + t * samples @ la.T
    inv_b = np.linalg.inv(cb)
    m2 = np.einsum("ni,ij,nj->n", boundary - mb, inv_b, boundary - mb)
    return np.sqrt(m2.min()) <= t or (mb - ma) @ np.linalg.solve(ca, mb - ma) <= t * t


def test_contact_sigma_closed_forms():
    rng = np.random.default_rng(15)
    ma, mb = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    sa, sb = rng.uniform(0.05, 1, 50), rng.uniform(0.05, 1, 50)
    mu = col.contact_sigma(ma, sa[:, None, None] ** 2 * np.eye(3), mb, sb[:, None, None] ** 2 * np.eye(3))
    np.testing.assert_allclose(mu, np.linalg.norm(ma - mb, axis=1) / (sa + sb), rtol=1e-12)
    # axis-aligned ellipsoids whose centres lie on a common principal axis touch end to end
    a, b = rng.uniform(0.01, 1, (50, 3)), rng.uniform(0.01, 1, (50, 3))
    gap = rng.uniform(0.1, 3, 50)
    for axis in range(3):
        mb = np.zeros((50, 3))
        mb[:, axis] = gap
        mu = col.contact_sigma(np.zeros((50, 3)), np.eye(3) * a[:, None] ** 2, mb, np.eye(3) * b[:, None] ** 2)
        np.testing.assert_allclose(mu, gap / (a[:, axis] + b[:, axis]), rtol=1e-12)
    assert col.contact_sigma(ma[:1], np.eye(3)[None], ma[:1], np.eye(3)[None])[0] == 0.0


def test_contact_sigma_against_sampled_ellipsoids_including_flat_and_needle():
    rng = np.random.default_rng(16)
    samples = sphere_points(40000)
    n = 24
    scales_a = rng.uniform(0.05, 1, (n, 3))
    scales_b = rng.uniform(0.05, 1, (n, 3))
    scales_a[:6, 2] = 1e-7  # discs
    scales_b[6:12, 1:] = 1e-7  # needles
    ca = geometry.covariances(rng.normal(size=(n, 4)), scales_a)
    cb = geometry.covariances(rng.normal(size=(n, 4)), scales_b)
    ma, mb = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    mu = col.contact_sigma(ma, ca, mb, cb)
    assert np.isfinite(mu).all() and (mu > 0).all()
    for k in range(n):
        # thin ellipsoids are sampled as themselves plus a hair, so only the outer margin is strict
        assert not sampled_overlap(
            ma[k], ca[k] + 1e-20 * np.eye(3), mb[k], cb[k] + 1e-20 * np.eye(3), 0.98 * mu[k], samples
        )
        if k >= 12:
            assert sampled_overlap(ma[k], ca[k], mb[k], cb[k], 1.02 * mu[k], samples)


def test_ellipsoid_contacts_match_all_pairs_and_summarise_links():
    rng = np.random.default_rng(17)
    env = random_cloud(600, 0, seed=18, spread=0.3)
    robot = col.Gaussians.from_cloud(random_cloud(80, 0, seed=19, spread=0.2), links=rng.integers(0, 4, 80))
    k = 2.5
    found = col.ellipsoid_contacts(robot, env, k=k)
    e = col.Gaussians.from_cloud(env)
    i, j = np.repeat(np.arange(80), 600), np.tile(np.arange(600), 80)
    mu = col.contact_sigma(robot.means[i], robot.covs[i], e.means[j], e.covs[j])
    hit = mu <= k
    assert hit.sum() > 50
    assert set(zip(found.robot.tolist(), found.env.tolist())) == set(zip(i[hit].tolist(), j[hit].tolist()))
    np.testing.assert_allclose(np.sort(found.sigma), np.sort(mu[hit]), rtol=1e-12)
    link = robot.links[i[hit]]
    np.testing.assert_array_equal(found.link_pairs, np.bincount(link, minlength=4))
    np.testing.assert_array_equal(found.link_gaussians, [len(np.unique(i[hit][link == c])) for c in range(4)])
    np.testing.assert_allclose(found.link_min_sigma, [mu[hit][link == c].min() for c in range(4)])


# occupancy and signed distance --------------------------------------------------------------------


def test_occupancy_matches_brute_force_within_its_bound():
    env_cloud = plane_env(1500, seed=20, size=0.5)
    env = col.Gaussians.from_cloud(env_cloud)
    rng = np.random.default_rng(21)
    points = rng.uniform([-0.5, -0.5, -0.05], [0.5, 0.5, 0.05], (300, 3))
    density = np.zeros(len(points))
    for j in range(len(env)):
        d = points - env.means[j]
        density += env.weights[j] * np.exp(-0.5 * np.einsum("ni,ij,nj->n", d, np.linalg.inv(env.covs[j]), d))
    bounds = []
    for cutoff in (3.0, 4.0, col.DEFAULT_CUTOFF):
        occ = col.occupancy(env_cloud, points, cutoff=cutoff)
        assert (density - occ.density >= 0).all() and (density - occ.density <= occ.bound + 1e-12).all()
        np.testing.assert_allclose(occ.values, 1 - np.exp(-density), atol=occ.bound.max() + 1e-12)
        bounds.append(occ.bound.max())
    assert 0 < occ.values.max() < 1 and bounds[-1] < 1e-5 < bounds[0]
    full = col.occupancy(env_cloud, points, cutoff=9.0)
    np.testing.assert_allclose(full.density, density, rtol=1e-10, atol=full.bound.max())
    assert full.bound.max() < 1e-12


def test_signed_distance_on_spheres():
    centres = np.array([[0, 0, 0], [0.5, 0, 0], [3, 1, 0]], float)
    sigmas = np.array([0.1, 0.2, 0.05])
    env = gaussians(centres, sigmas[:, None] * np.ones(3))
    rng = np.random.default_rng(22)
    points = np.concatenate([rng.uniform(-1, 4, (3000, 3)), rng.normal(0, 0.2, (1000, 3))])
    k = 3.0
    each = np.linalg.norm(points[:, None] - centres, axis=2) - k * sigmas
    exact = each.min(axis=1)  # exact outside the union
    got = col.signed_distance(env, points, k=k, max_distance=10.0)
    assert np.array_equal(got < 0, exact < 0)
    outside = exact > 0
    np.testing.assert_allclose(got[outside], exact[outside], rtol=1e-12, atol=1e-14)
    single = (each < 0).sum(axis=1) == 1  # inside one sphere only: exact
    np.testing.assert_allclose(got[single], exact[single], rtol=1e-12, atol=1e-14)
    assert (got >= exact - 1e-14).all()  # inside the union: never deeper
    capped = col.signed_distance(env, points, k=k, max_distance=0.25)
    np.testing.assert_allclose(capped, np.minimum(exact, 0.25), rtol=1e-12, atol=1e-14)


def test_signed_distance_outside_an_ellipsoid_against_its_sampled_surface():
    rng = np.random.default_rng(23)
    for scales in ([0.3, 0.1, 0.05], [0.2, 0.2, 1e-7], [0.4, 1e-7, 1e-7]):
        q = rng.normal(size=4)
        env = gaussians([[0.1, 0.2, 0.3]], [scales], q[None])
        points = env.means[0] + rng.normal(0, 1.0, (60, 3))
        surface = env.means[0] + 2.0 * (sphere_points(100000) * scales) @ geometry.quaternions_to_matrices(q).T
        sampled = np.linalg.norm(points[:, None] - surface[None], axis=2).min(axis=1)
        got = col.signed_distance(env, points, k=2.0, max_distance=10.0)
        out = got > 0
        assert out.sum() > 45
        assert (got[out] <= sampled[out] + 1e-12).all()  # samples only overestimate
        np.testing.assert_allclose(got[out], sampled[out], rtol=2e-3, atol=2e-3 * max(scales))


# proxies ------------------------------------------------------------------------------------------


def test_proxies_match_moments_and_converge_to_the_full_cloud():
    rng = np.random.default_rng(24)
    robot = col.Gaussians.from_cloud(random_cloud(120, 0, seed=25, spread=0.1), links=rng.integers(0, 3, 120))
    one = col.fit_proxies(robot, per_link=1, reference_sigma=0.02)
    ref = 0.02**2 * np.eye(3)
    for link in range(3):
        pick = robot.links == link
        mass = robot.weights[pick] * np.array([np.sqrt(np.linalg.det(c + ref)) for c in robot.covs[pick]])
        p = mass / mass.sum()
        mean = p @ robot.means[pick]
        off = robot.means[pick] - mean
        cov = sum(pk * (c + np.outer(o, o)) for pk, c, o in zip(p, robot.covs[pick], off))
        k = np.flatnonzero(one.links == link)[0]
        np.testing.assert_allclose(one.means[k], mean, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(one.covs[k], cov, rtol=1e-10, atol=1e-16)
        assert one.weights[k] == pytest.approx(mass.sum() / np.sqrt(np.linalg.det(cov + ref)), rel=1e-10)
    exact = col.fit_proxies(robot, per_link=200)
    assert len(exact) == 120
    near = col.Gaussians.from_cloud(random_cloud(300, 0, seed=26, spread=0.2))
    full = col.overlap_all_pairs(robot, near).cost
    assert col.overlap_all_pairs(exact, near).cost == pytest.approx(full, rel=1e-12)
    errors = [col.proxy_error(robot, col.fit_proxies(robot, per_link=m), near) for m in (1, 8, 32)]
    assert errors[2] < errors[0] and errors[2] < 0.05


@pytest.mark.filterwarnings("error")
def test_point_and_huge_splats_give_finite_results_without_warnings():
    env = SplatCloud.from_activated(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
        [[1, 0, 0, 0]] * 3,
        [[0, 0, 0], [1e-7, 0.1, 0.1], [1e4, 1e4, 1e-7]],
        [0.5, 0.9, 0.2],
    )
    points = np.array([[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1, 0.05, 0.3], [3, 3, 3.0]])
    sdf = col.signed_distance(env, points, max_distance=2.0)
    assert np.isfinite(sdf).all() and sdf[-1] == 2.0 and (sdf[:3] < 0).all()
    occ = col.occupancy(env, points)
    assert np.isfinite(occ.values).all() and np.isfinite(occ.bound).all()
    assert occ.values[0] == pytest.approx(1 - np.exp(-(0.5 + 0.2)), rel=1e-6)  # the point splat and the disc
    r = col.overlap(env, env, cov_gradient=True)
    assert np.isfinite([r.cost, r.bound]).all() and np.isfinite(r.grad_means).all() and np.isfinite(r.grad_covs).all()
    assert len(col.ellipsoid_contacts(env, env)) >= 3


# far floaters, compiled kernels, precision and bounds ---------------------------------------------


def room_with_floaters(n=20_000, floaters=200, seed=30):
    rng = np.random.default_rng(seed)
    env = plane_env(n, seed=seed, size=1.0)
    far = SplatCloud.from_activated(
        rng.uniform(-500, 500, (floaters, 3)),
        rng.normal(size=(floaters, 4)),
        rng.uniform(0.01, 0.03, (floaters, 3)),
        rng.uniform(0.2, 1.0, floaters),
    )
    one = SplatCloud.from_activated([[1e3, 1e3, 1e3]], [[1, 0, 0, 0]], [[0.02, 0.02, 0.004]], [0.9])
    return env, SplatCloud.concatenate([env, far, one])


def test_far_floaters_leave_the_dense_grids_as_they_were():
    env, with_floaters = room_with_floaters()
    plain, index = col.EnvironmentIndex(env), col.EnvironmentIndex(with_floaters)
    dense = lambda ix: sorted((lv.count, lv.h) for lv in ix.levels if lv.count > 1000)
    assert dense(index) == dense(plain)  # same cells for the splats that matter
    assert sum(lv.count for lv in index.levels) == len(with_floaters)
    rng = np.random.default_rng(31)
    robot = gaussians(
        rng.uniform([-0.3, -0.3, -0.02], [0.3, 0.3, 0.05], (80, 3)),
        rng.uniform(0.005, 0.02, (80, 3)),
        rng.normal(size=(80, 4)),
    )
    a, b = col.ellipsoid_contacts(robot, plain), col.ellipsoid_contacts(robot, index)
    assert len(a) > 20 and set(zip(a.robot, a.env)) == set(zip(b.robot, b.env))
    assert col.overlap(robot, index).cost == pytest.approx(col.overlap(robot, plain).cost, rel=1e-12)


def test_compiled_contacts_match_the_eigen_solution_including_flat_needle_and_point_splats(monkeypatch):
    rng = np.random.default_rng(32)
    n = 3000
    scales_a, scales_b = rng.uniform(0.01, 0.1, (n, 3)), rng.uniform(0.01, 0.1, (n, 3))
    scales_a[:300, 2] = 1e-7  # discs
    scales_b[300:600, 1:] = 1e-7  # needles
    scales_b[600:650] = 0.0  # points
    robot = gaussians(rng.normal(0, 1.0, (n, 3)), scales_a, rng.normal(size=(n, 4)), links=np.arange(n) % 3)
    env = gaussians(robot.means + rng.normal(0, 0.08, (n, 3)), scales_b, rng.normal(size=(n, 4)))
    mu = col.contact_sigma(robot.means, robot.covs, env.means, env.covs)
    found = col.ellipsoid_contacts(robot, env, k=3.0)
    pairs = dict(zip(zip(found.robot.tolist(), found.env.tolist()), found.sigma))
    same = [(i, pairs[(i, i)]) for i in range(n) if (i, i) in pairs]
    assert len(same) > 500 and sum(mu <= 3.0) >= len(same)
    idx, got = np.array(same).T
    idx = idx.astype(int)
    thin = idx < 650  # thinner than the pivot floor: both solutions are at its resolution
    np.testing.assert_allclose(got[~thin], mu[idx[~thin]], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got[thin], mu[idx[thin]], rtol=1e-6)
    from splatwright.core.collision import contacts

    monkeypatch.setattr(contacts, "_contact_kernel", lambda: None)  # the NumPy path finds the same pairs
    numpy_path = col.ellipsoid_contacts(robot, env, k=3.0)
    np.testing.assert_array_equal(numpy_path.robot, found.robot)
    np.testing.assert_array_equal(numpy_path.env, found.env)
    regular = (numpy_path.robot >= 650) & (numpy_path.env >= 650)
    np.testing.assert_allclose(numpy_path.sigma[regular], found.sigma[regular], rtol=1e-10)
    np.testing.assert_allclose(numpy_path.sigma, found.sigma, rtol=1e-3)


def test_signed_distance_among_flat_splats_matches_every_ellipsoid(monkeypatch):
    env_cloud = plane_env(1500, seed=33, size=0.3, sigma=(0.005, 0.02))
    env = col.Gaussians.from_cloud(env_cloud)
    rng = np.random.default_rng(34)
    points = rng.uniform([-0.4, -0.4, -0.3], [0.4, 0.4, 0.3], (150, 3))
    k = 3.0
    from splatwright.core.collision import distance

    brute = np.array([distance._ellipsoid_signed_distance(p - env.means, env.covs, k).min() for p in points])
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(distance, "_bounds_kernel", lambda: None)
        got = col.signed_distance(env_cloud, points, k=k, max_distance=0.25)
        np.testing.assert_allclose(got, np.minimum(brute, 0.25), rtol=1e-12, atol=1e-14)


def test_float32_positions_far_away_warn_that_results_shift():
    cloud = random_cloud(50, 0, seed=35, spread=0.1)
    cloud.log_scales[:] = np.log(0.01)
    far = cloud.replace(positions=(cloud.positions.astype(np.float64) + 1e6).astype(np.float32))
    with pytest.warns(col.CollisionPrecisionWarning, match="50 splats lie so far from the origin"):
        col.EnvironmentIndex(far)
    with pytest.warns(col.CollisionPrecisionWarning, match="rounded by up to 0.0625"):
        col.Gaussians.from_cloud(far)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        col.EnvironmentIndex(cloud)  # near the origin: no warning
        # float64 Gaussians far away keep their precision: the same cost as near the origin
        shift = np.array([1e6, 1e6, 1e6])
        g = col.Gaussians.from_cloud(cloud)
        here = col.overlap(g, g).cost
        assert col.overlap(g.transformed(np.eye(3), shift), g.transformed(np.eye(3), shift)).cost == pytest.approx(
            here, rel=1e-9
        )


def test_reported_bound_is_close_to_what_the_cutoff_dropped():
    env = plane_env(4000)
    rng = np.random.default_rng(36)
    robot = gaussians(
        rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.08], (60, 3)),
        rng.uniform(0.01, 0.03, (60, 3)),
        rng.normal(size=(60, 4)),
        rng.uniform(0.3, 1.0, 60),
    )
    exact = col.overlap_all_pairs(robot, env, gradient=False).cost
    index = col.EnvironmentIndex(env)
    for cutoff in (3.0, col.DEFAULT_CUTOFF):
        r = col.overlap(robot, index, cutoff, gradient=False)
        dropped = exact - r.cost
        assert 0 < dropped <= r.bound <= 30 * dropped  # was 10^3 - 10^4 times looser


def test_joint_gradient_of_mimic_planar_and_floating_joints():
    t = lambda p: transforms(None, p)
    tree = KinematicTree(
        names=["body", "cart", "arm", "twin"],
        parents=[-1, 0, 1, 1],
        origins=[t([0.1, 0, 0]), t([0, 0.1, 0.2]), t([0, 0, 0.3]), t([0.1, 0, 0.3])],
        joint_types=["floating", "planar", "revolute", "prismatic"],
        axes=[[1, 0, 0], [0.3, 0.2, 1], [0, 1, 0], [0, 0, 1]],
        mimic=[None, None, None, ("arm", -0.5, 0.02)],
    )
    assert tree.dof == 10
    rng = np.random.default_rng(37)
    local = col.Gaussians.from_cloud(random_cloud(120, 0, seed=38, spread=0.08), links=rng.integers(0, 4, 120))
    robot = col.pose_robot(local, tree.rest_transforms())
    env = col.EnvironmentIndex(random_cloud(400, 0, seed=39, spread=0.4))
    q = rng.normal(0, 0.3, tree.dof)
    r = col.overlap_at(tree, q, robot, env, cutoff=30.0)
    assert r.cost > 1.0
    h = 1e-6
    cost = lambda x: col.overlap_at(tree, x, robot, env, 30.0).cost
    fd = [(cost(q + h * e) - cost(q - h * e)) / (2 * h) for e in np.eye(tree.dof)]
    np.testing.assert_allclose(r.grad_q, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())


@pytest.mark.filterwarnings("error")
def test_all_zero_covariances_give_point_answers_without_warnings():
    points = gaussians([[0, 0, 0], [0.5, 0, 0], [0, 0, 1e-3]], np.zeros((3, 3)))
    env = gaussians([[0, 0, 0], [0.2, 0, 0]], np.zeros((2, 3)))
    mu = col.contact_sigma(points.means, points.covs, env.means[[0, 0, 1]], env.covs[[0, 0, 1]])
    assert mu.tolist() == [0.0, np.inf, np.inf]  # coincident points touch at any k
    assert col.signed_distance(env, points.means, max_distance=1.0).tolist() == pytest.approx([0.0, 0.3, 1e-3])
    assert col.occupancy(env, points.means).values.tolist() == pytest.approx([1 - np.exp(-1), 0, 0])
    assert col.overlap(points, env, cov_gradient=True).cost == 1.0
    hits = col.ellipsoid_contacts(points, env)
    assert list(zip(hits.robot, hits.env)) == [(0, 0)] and hits.sigma.tolist() == [0.0]
    proxies = col.fit_proxies(points, per_link=2)  # (zero masses made them vanish)
    assert len(proxies) == 2 and np.isfinite(proxies.weights).all() and (proxies.weights > 0).all()
