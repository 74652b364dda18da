"""Polar decomposition, anisotropy, covariance transforms and SplatCloud.transformed against direct
float64 formulas (A p + t, A Sigma A^T, colours along transformed view directions)."""

import warnings

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud, geometry


def random_rotations(rng, n):
    return geometry.quaternions_to_matrices(rng.normal(size=(n, 4)))


def affine(a, t=(0.0, 0.0, 0.0)):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = a, t
    return m


def symmetric_sqrt(m):
    vals, vecs = np.linalg.eigh(m)
    return (vecs * np.sqrt(np.maximum(vals, 0))[..., None, :]) @ np.swapaxes(vecs, -1, -2)


def relative_error(got, want):
    scale = np.abs(want).reshape(len(want), -1).max(axis=1)
    return (np.abs(got - want).reshape(len(want), -1).max(axis=1) / scale).max()


# Small helpers -----------------------------------------------------------------------------------


def test_quaternion_products_compose_rotations(rng):
    a, b = rng.normal(size=(2, 500, 4))
    m = geometry.quaternions_to_matrices
    np.testing.assert_allclose(m(geometry.multiply_quaternions(a, b)), m(a) @ m(b), atol=1e-13)
    # Norms multiply, so a product with a unit quaternion keeps the stored norm.
    np.testing.assert_allclose(
        np.linalg.norm(geometry.multiply_quaternions(a, b), axis=1),
        np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1),
        rtol=1e-13,
    )


def test_determinants(rng):
    m = rng.normal(size=(100, 3, 3))
    np.testing.assert_allclose(geometry.determinants(m), np.linalg.det(m), rtol=1e-12, atol=1e-14)


# Polar decomposition and anisotropy ---------------------------------------------------------------


def check_polar(a, r, s):
    eye = np.broadcast_to(np.eye(3), a.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=1e-12)
    np.testing.assert_allclose(s, np.swapaxes(s, -1, -2), atol=0)
    scale = np.abs(a).max()
    assert np.linalg.eigvalsh(s).min() >= -1e-14 * scale
    np.testing.assert_allclose(r @ s, a, atol=1e-13 * scale)


@pytest.fixture(params=["compiled", "numpy"])
def polar_path(request, monkeypatch):
    """Each test of the polar decomposition runs on the compiled kernel and on the NumPy path."""
    if request.param == "numpy":
        monkeypatch.setattr(geometry, "_polar_kernel", lambda: None)
    elif geometry._polar_kernel() is None:
        pytest.skip("numba is not available: the NumPy path alone runs")
    return request.param


def test_polar_decomposition_of_random_matrices(rng, polar_path):
    a = rng.normal(size=(1000, 3, 3))
    r, s = geometry.polar_decomposition(a)
    check_polar(a, r, s)
    # Independent reference: S = sqrt(A^T A) by eigen-decomposition; R mirrors exactly when A does.
    np.testing.assert_allclose(s, symmetric_sqrt(np.swapaxes(a, 1, 2) @ a), atol=1e-10)
    np.testing.assert_array_equal(np.sign(np.linalg.det(r)), np.sign(np.linalg.det(a)))


def test_polar_decomposition_of_nearly_singular_matrices(rng, polar_path):
    rot = random_rotations(rng, 6)
    flat = [1e-12, 1e-300, 0.0]
    a = np.stack([rot[i] @ np.diag([2.0, 0.5, f]) @ rot[i + 3] for i, f in enumerate(flat)])
    a = np.concatenate([a, [np.outer([1.0, 2.0, 3.0], [0.5, -1.0, 2.0])]])  # rank 1
    r, s = geometry.polar_decomposition(a)
    check_polar(a, r, s)
    assert np.isfinite(r).all() and np.isfinite(s).all()
    # Where A has full rank in double precision the rotation is the unique one: R = rot_i rot_{i+3}.
    np.testing.assert_allclose(r[0], rot[0] @ rot[3], atol=1e-10)


def test_polar_rotation_stopped_early_is_within_1e_12_of_the_svd(rng, polar_path):
    """tolerance=1e-7 (what skinning asks for, its output being float32) saves a Newton step: the
    step after a move below 1e-6 is accurate to about its square."""
    rot = random_rotations(rng, 2000)
    a = np.concatenate(
        [rng.normal(size=(1000, 3, 3)), rot[:1000] @ (np.eye(3) + 0.3 * rng.normal(size=(1000, 3, 3))) @ rot[1000:]]
    )
    u, _, vt = np.linalg.svd(a)
    assert np.abs(geometry.polar_rotation(a, tolerance=1e-7) - u @ vt).max() < 1e-12


def test_polar_decomposition_refuses_bad_input():
    with pytest.raises(ValueError, match="1 matrices hold NaN or Inf"):
        geometry.polar_decomposition(np.array([np.eye(3), np.full((3, 3), np.nan)]))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        geometry.polar_decomposition(np.eye(4))


def test_anisotropy(rng):
    rot = random_rotations(rng, 2)
    similarities = [rot[0], 3.5 * rot[1], 1e-5 * rot[0] @ np.diag([1.0, -1.0, 1.0]), -np.eye(3)]
    assert geometry.anisotropy(np.stack(similarities)).max() < 1e-14
    assert geometry.anisotropy(rot[0] @ np.diag([1.0, 2.0, 3.0]) @ rot[1]) == pytest.approx(2.0, rel=1e-13)
    assert geometry.anisotropy(np.diag([1.0, 1.0, 0.0])) == np.inf
    # The documented bound: over unit u, the angle between u and S^-1 u is at most
    # atan(k / (2 sqrt(1 + k))), and reaches it.
    stretch = np.diag([1.0, 1.3, 2.0])
    k = geometry.anisotropy(stretch)
    u = rng.normal(size=(200000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = u @ np.linalg.inv(stretch)
    cos = np.einsum("ij,ij->i", u, v) / np.linalg.norm(v, axis=1)
    worst = np.arccos(np.clip(cos, -1, 1)).max()
    bound = np.arctan(k / (2 * np.sqrt(1 + k)))
    assert bound * 0.99 < worst <= bound + 1e-12


def test_split_affine_names_the_problem():
    a, t = geometry.split_affine(affine(2 * np.eye(3), (1, 2, 3)))
    np.testing.assert_array_equal(a, 2 * np.eye(3))
    np.testing.assert_array_equal(t, [1, 2, 3])
    np.testing.assert_array_equal(geometry.split_affine(np.eye(3))[1], 0)
    projective = np.eye(4)
    projective[3, 2] = 0.5
    bad = {
        "shape": np.eye(2),
        "NaN or Inf": np.full((4, 4), np.inf),
        "projective": projective,
        "singular": affine(np.diag([1.0, 1.0, 0.0])),
    }
    for problem, m in bad.items():
        with pytest.raises(ValueError, match=problem):
            geometry.split_affine(m)
    with pytest.raises(ValueError, match="singular"):
        geometry.split_affine(np.diag([1.0, 1.0, 1e-14]))


def test_transform_covariances_matches_a_sigma_a_transpose(rng):
    n = 2000
    q = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(-5, 2, (n, 3)))
    a = rng.normal(size=(3, 3))
    q2, s2 = geometry.transform_covariances(a, q, scales)
    want = a @ geometry.covariances(q, scales) @ a.T
    assert relative_error(geometry.covariances(q2, s2), want) < 1e-12
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), 1, atol=1e-14)


def test_transform_covariances_keeps_thin_axes(rng):
    """Needles and pancakes: spreads of 1e6 within one splat, 1e-7..1e4 over the cloud. The small
    axes keep their accuracy relative to themselves, which eigh of A Sigma A^T would lose."""
    big = np.exp(rng.uniform(np.log(1e-1), np.log(1e4), 300))
    scales = np.stack([big, big * 1e-6, big * rng.uniform(1e-6, 1, 300)], axis=1)
    q = rng.normal(size=(300, 4))
    a = random_rotations(rng, 1)[0] @ np.diag([1.0, 2.0, 0.5]) @ random_rotations(rng, 1)[0]
    _, s2 = geometry.transform_covariances(a, q, scales)
    # References free of cancellation: the product of the new scales is |det A| times the old
    # product, and the largest is the square root of the largest eigenvalue of A Sigma A^T.
    m = a @ (geometry.quaternions_to_matrices(q) * scales[:, None, :])
    det = np.abs(np.linalg.det(a)) * scales.prod(axis=1)
    s_sorted = np.sort(s2, axis=1)
    np.testing.assert_allclose(s_sorted.prod(axis=1), det, rtol=1e-9)
    np.testing.assert_allclose(s_sorted[:, 2], np.sqrt(np.linalg.eigvalsh(m @ np.swapaxes(m, 1, 2))[:, 2]), rtol=1e-12)
    assert s_sorted.min() >= 1e-8


# SplatCloud.transformed ---------------------------------------------------------------------------


def colours_seen_from(cloud, camera):
    return cloud.colors(camera_center=camera)


@pytest.fixture
def similarities(rng):
    rot = random_rotations(rng, 4)
    return {
        "rigid": affine(rot[0], (0.5, -2.0, 3.0)),
        "scaled": affine(2.5 * rot[1], (10.0, 0.0, -1.0)),
        "mirror": affine(0.3 * rot[2] @ np.diag([1.0, -1.0, 1.0]), (0.0, 1.0, 0.0)),
        "shrunk": affine(1e-3 * rot[3]),
        "axes": affine(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])),  # Blender Z-up to Y-up
    }


def test_similarities_are_exact_to_float32_round_off(rng, similarities):
    cloud = random_cloud(3000, sh_degree=3, seed=5)
    cloud.log_scales[:1000] = rng.uniform(np.log(1e-7), np.log(1e4), (1000, 3)).astype(np.float32)
    cameras = rng.normal(0, 4, (5, 3))
    for name, m in similarities.items():
        a, t = m[:3, :3], m[:3, 3]
        out = cloud.transformed(m)
        assert out.positions.dtype == np.float32 and out.sh.dtype == np.float32
        want = cloud.positions.astype(np.float64) @ a.T + t
        np.testing.assert_allclose(out.positions, want, rtol=1e-7, atol=1e-7 * np.abs(want).max(), err_msg=name)
        # Covariances to float32 round-off: half a spacing of the stored log-scales (which reach -23
        # here, where float32 steps by 2e-6), doubled for sigma^2, plus the rotation's round-off.
        want_cov = a @ cloud.covariances() @ a.T
        got_cov = out.covariances()
        tolerance = 1.1 * np.spacing(np.abs(out.log_scales).max(axis=1)) + 3e-7
        error = np.abs(got_cov - want_cov).max(axis=(1, 2)) / np.abs(want_cov).max(axis=(1, 2))
        assert (error <= tolerance).all(), name
        scale = abs(np.linalg.det(a)) ** (1 / 3)
        np.testing.assert_allclose(out.scales, cloud.scales * scale, rtol=2e-6, err_msg=name)
        np.testing.assert_array_equal(out.opacity_logits, cloud.opacity_logits)
        # Colours: a transformed camera sees what the original camera saw.
        for camera in cameras:
            np.testing.assert_allclose(
                colours_seen_from(out, a @ camera + t), colours_seen_from(cloud, camera), atol=2e-6, err_msg=name
            )


def test_rigid_round_trip(rng, similarities):
    cloud = random_cloud(500, seed=3)
    m = similarities["rigid"]
    back = cloud.transformed(m).transformed(np.linalg.inv(m))
    np.testing.assert_allclose(back.positions, cloud.positions, atol=2e-6)
    assert relative_error(back.covariances(), cloud.covariances()) < 1e-6
    np.testing.assert_allclose(back.sh, cloud.sh, atol=2e-6)


def test_general_affine_covariances_and_colours(rng):
    cloud = random_cloud(3000, sh_degree=3, seed=7)
    for _ in range(10):
        a = rng.normal(size=(3, 3))
        t = rng.normal(0, 5, 3)
        out = cloud.transformed(affine(a, t))
        assert relative_error(out.covariances(), a @ cloud.covariances() @ a.T) < 1e-6
        want = cloud.positions.astype(np.float64) @ a.T + t
        np.testing.assert_allclose(out.positions, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
        # SH turn with the polar rotation R: colour seen along d' is the original colour along R^T d'.
        r, _ = geometry.polar_decomposition(a)
        d = rng.normal(size=(len(cloud), 3))
        np.testing.assert_allclose(out.colors(directions=d), cloud.colors(directions=d @ r), atol=2e-6)
        assert geometry.anisotropy(a) > 1e-3


def test_linear_3x3_is_4x4_without_translation(rng):
    cloud = random_cloud(100, seed=2)
    a = rng.normal(size=(3, 3))
    three, four = cloud.transformed(a), cloud.transformed(affine(a))
    for name in ("positions", "rotations", "log_scales", "sh"):
        np.testing.assert_array_equal(getattr(three, name), getattr(four, name))


def test_far_from_the_origin(rng):
    """Positions 1e6 away, moved back near the origin: float64 maths keeps what float32 stored."""
    cloud = random_cloud(1000, sh_degree=1, seed=4)
    cloud.positions[:] += np.float32(1e6)
    rot = random_rotations(rng, 1)[0]
    centre = np.full(3, 1e6)
    m = affine(rot, -rot @ centre)  # rotate about the far centre, land at the origin
    out = cloud.transformed(m)
    want = (cloud.positions.astype(np.float64) - centre) @ rot.T
    np.testing.assert_allclose(out.positions, want, rtol=0, atol=1e-6)


def test_non_finite_splats_stay_reported_without_warnings(rng):
    cloud = random_cloud(20, seed=9)
    cloud.positions[1, 0] = np.nan
    cloud.log_scales[2, 1] = np.inf
    cloud.rotations[3] = np.nan
    cloud.rotations[4] = 0.0  # read as the identity
    cloud.rotations[6] *= np.float32(1e-20)  # tiny but fine: only the direction matters
    cloud.log_scales[5, 2] = -np.inf  # a flat splat (zero thickness) stays flat
    for a in (2.0 * random_rotations(rng, 1)[0], rng.normal(size=(3, 3))):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            out = cloud.transformed(a)
        assert out.problems() == [p for p in cloud.problems() if "zero rotation" not in p]
        assert out.finite_mask()[[0, 4, *range(6, 20)]].all()
        zero = cloud[[4]].replace(rotations=[[1.0, 0.0, 0.0, 0.0]])
        assert relative_error(out[[4]].covariances(), a @ zero.covariances() @ a.T) < 1e-6
        assert relative_error(out[[6]].covariances(), a @ cloud[[6]].covariances() @ a.T) < 1e-6
        assert out.log_scales[5].min() == -np.inf and np.isfinite(out.log_scales[5, :2]).all()


def test_singular_projective_and_nan_transforms_are_refused():
    cloud = random_cloud(10)
    with pytest.raises(ValueError, match="singular"):
        cloud.transformed(np.diag([1.0, 1.0, 0.0, 1.0]))
    projective = np.eye(4)
    projective[3, 0] = 1.0
    with pytest.raises(ValueError, match="projective"):
        cloud.transformed(projective)
    with pytest.raises(ValueError, match="NaN"):
        cloud.transformed(np.full((4, 4), np.nan))


def test_extras_and_empty_clouds_come_along():
    cloud = random_cloud(10, sh_degree=0)
    cloud.extras["tag"] = np.arange(10)
    out = cloud.transformed(np.diag([1.0, 2.0, 3.0]))
    np.testing.assert_array_equal(out.extras["tag"], np.arange(10))
    assert len(SplatCloud.empty(3).transformed(np.diag([1.0, 2.0, 3.0]))) == 0
    assert len(SplatCloud.empty(3).transformed(np.eye(4))) == 0
