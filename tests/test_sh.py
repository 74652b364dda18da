"""SH evaluation, truncation and rotation against independent references: brute-force evaluation at
rotated directions, least-squares fits, and numerical quadrature on the sphere."""

import numpy as np
import pytest

from splatwright.core import geometry, jit, sh


def random_rotations(rng, n):
    return geometry.quaternions_to_matrices(rng.normal(size=(n, 4)))


def axis_angle(axis, angle):
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return geometry.quaternions_to_matrices(np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis])


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def assert_rotates(coeffs, rotations, directions, atol=1e-12):
    """evaluate(rotate(sh, R), d) == evaluate(sh, R^T d), one rotation per splat."""
    rotated = sh.rotate(coeffs, rotations)
    turned_back = np.einsum("nji,nj->ni", rotations, directions)  # R^T d
    np.testing.assert_allclose(sh.evaluate(rotated, directions), sh.evaluate(coeffs, turned_back), rtol=0, atol=atol)


# Basis and truncation ---------------------------------------------------------------------------


def sphere_quadrature(n_theta=12, n_phi=24):
    """Gauss-Legendre in cos(theta) times uniform phi: exact for polynomials of degree < 2 n_theta."""
    z, w = np.polynomial.legendre.leggauss(n_theta)
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - zz**2)
    dirs = np.stack([r * np.cos(pp), r * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    weights = np.repeat(w, n_phi) * (2 * np.pi / n_phi)
    return dirs, weights


@pytest.mark.parametrize("degree", [3, 4])
def test_basis_is_orthonormal_on_the_sphere(degree):
    dirs, weights = sphere_quadrature()
    y = sh.basis(dirs, degree)
    gram = y.T @ (y * weights[:, None])
    np.testing.assert_allclose(gram, np.eye((degree + 1) ** 2), atol=1e-13)


def condon_shortley_harmonics(directions, degree):
    """Real SH from their definition: N_lm P_l^m(cos theta) times sqrt(2) cos(m phi) (m > 0), sqrt(2)
    sin(|m| phi) (m < 0) or 1, with P_l^m = (-1)^m (1 - x^2)^(m/2) d^m/dx^m P_l(x) (Legendre's
    polynomials differentiated by NumPy) and N_lm = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!)."""
    from math import factorial

    x, y, z = unit(directions).T
    theta, phi = np.arccos(np.clip(z, -1, 1)), np.arctan2(y, x)
    out = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            a = abs(m)
            legendre = np.polynomial.Legendre.basis(l).deriv(a)(np.cos(theta))
            p = (-1) ** a * np.sin(theta) ** a * legendre
            norm = np.sqrt((2 * l + 1) / (4 * np.pi) * factorial(l - a) / factorial(l + a))
            turn = np.sqrt(2) * (np.cos(a * phi) if m > 0 else np.sin(a * phi)) if m else 1.0
            out.append(norm * p * turn)
    return np.stack(out, axis=-1)


def test_basis_is_the_condon_shortley_real_harmonics_in_every_band(rng):
    """3DGS's bands 0..3 are the real harmonics with the (-1)^m phase, ordered m = -l..l (sines first);
    band 4 continues them: the same definition fixes its ordering and signs."""
    d = rng.normal(size=(200, 3))
    np.testing.assert_allclose(sh.basis(d, 4), condon_shortley_harmonics(d, 4), rtol=0, atol=1e-13)


def test_degree_4_constants_are_the_closed_forms():
    pi = np.pi
    closed = [
        3 / 4 * np.sqrt(35 / pi),
        -3 / 4 * np.sqrt(35 / (2 * pi)),
        3 / 4 * np.sqrt(5 / pi),
        -3 / 4 * np.sqrt(5 / (2 * pi)),
        3 / 16 * np.sqrt(1 / pi),
        -3 / 4 * np.sqrt(5 / (2 * pi)),
        3 / 8 * np.sqrt(5 / pi),
        -3 / 4 * np.sqrt(35 / (2 * pi)),
        3 / 16 * np.sqrt(35 / pi),
    ]
    np.testing.assert_allclose(sh.C4, closed, rtol=1e-15)
    # gsplat's degree-4 evaluation writes band 4 as recurrences in z and (x + iy)^m; the same
    # numbers at one direction (its literal constants).
    x, y, z = unit(np.array([0.3, -0.5, 0.8]))
    c2, c3, c4 = ((x + 1j * y) ** m for m in (2, 3, 4))
    want = [
        0.6258357354491763 * c4.imag,
        -1.770130769779931 * z * c3.imag,
        (3.31161143515146 * z * z - 0.47308734787878) * c2.imag,
        z * (-4.683325804901025 * z * z + 2.007139630671868) * y,
        1.984313483298443 * z * z * (1.865881662950577 * z * z - 1.119528997770346)
        - 1.006230589874905 * (0.9461746957575601 * z * z - 0.3153915652525201),
        z * (-4.683325804901025 * z * z + 2.007139630671868) * x,
        (3.31161143515146 * z * z - 0.47308734787878) * c2.real,
        -1.770130769779931 * z * c3.real,
        0.6258357354491763 * c4.real,
    ]
    np.testing.assert_allclose(sh.basis([[x, y, z]], 4)[0, 16:], want, rtol=1e-13)


def test_basis_follows_the_reference_constants_and_ordering():
    d = unit(np.array([[0.3, -0.5, 0.8]]))[0]
    x, y, z = d
    c1, c2, c3 = sh.C1, sh.C2, sh.C3
    expected = [
        sh.C0,
        -c1 * y,
        c1 * z,
        -c1 * x,
        c2[0] * x * y,
        c2[1] * y * z,
        c2[2] * (2 * z * z - x * x - y * y),
        c2[3] * x * z,
        c2[4] * (x * x - y * y),
        c3[0] * y * (3 * x * x - y * y),
        c3[1] * x * y * z,
        c3[2] * y * (4 * z * z - x * x - y * y),
        c3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y),
        c3[4] * x * (4 * z * z - x * x - y * y),
        c3[5] * z * (x * x - y * y),
        c3[6] * x * (x * x - 3 * y * y),
    ]
    np.testing.assert_allclose(sh.basis(d * 7.0, 3), expected, rtol=1e-14)  # directions get normalised
    # The constants are the normalisations of the real harmonics: C0 = 1/(2 sqrt(pi)), C1 = sqrt(3/(4 pi)).
    assert sh.C0 == pytest.approx(0.5 / np.sqrt(np.pi), rel=1e-15)
    assert sh.C1 == pytest.approx(np.sqrt(3 / (4 * np.pi)), rel=1e-15)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_basis_gradient_is_the_central_difference_of_the_basis(degree):
    """At directions of any length (basis() normalises them), and zero along the direction."""
    rng = np.random.default_rng(degree)
    d = rng.normal(size=(40, 3)) * np.geomspace(0.01, 100, 40)[:, None]
    weights = rng.normal(size=(40, sh.num_coeffs(degree)))
    got = sh.basis_gradient(weights, d)
    step = 1e-6 * np.linalg.norm(d, axis=1)
    for j in range(3):
        e = np.eye(3)[j] * step[:, None]
        fd = ((sh.basis(d + e, degree) - sh.basis(d - e, degree)) * weights).sum(1) / (2 * step)
        np.testing.assert_allclose(got[:, j] * step, fd * step, rtol=0, atol=1e-13)  # relative to 1 / |d|
    assert np.abs((got * d).sum(1)).max() < 1e-12


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_truncation_keeps_exactly_the_low_bands(rng, degree):
    coeffs = rng.normal(size=(50, 16, 3))
    d = rng.normal(size=(50, 3))
    low = sh.truncate(coeffs, degree)
    assert low.shape == (50, (degree + 1) ** 2, 3)
    # Brute force: the full sum over only the kept basis functions.
    y = sh.basis(d, 3)[:, : (degree + 1) ** 2]
    np.testing.assert_allclose(sh.evaluate(low, d), np.einsum("nk,nkc->nc", y, coeffs[:, : len(y[0])]), atol=1e-13)
    # Band by band, truncation is the L2 projection: the dropped bands are orthogonal to the kept ones.
    dirs, weights = sphere_quadrature()
    one = coeffs[:1]
    full = sh.evaluate(np.repeat(one, len(dirs), 0), dirs)
    kept = sh.evaluate(np.repeat(sh.truncate(one, degree), len(dirs), 0), dirs)
    inner = ((full - kept) * kept * weights[:, None]).sum(axis=0)
    np.testing.assert_allclose(inner, 0, atol=1e-12)
    # Padding back up changes no colour.
    np.testing.assert_allclose(sh.evaluate(sh.truncate(low, 3), d), sh.evaluate(low, d), atol=1e-13)


# Rotation: brute force ---------------------------------------------------------------------------


def test_1000_random_rotations_match_brute_force(rng):
    for _ in range(1000):
        r = random_rotations(rng, 1)[0]
        coeffs = rng.normal(0, 0.5, size=(16, 3))
        d = unit(rng.normal(size=(64, 3)))
        rotated = sh.rotate(coeffs, r)
        assert rotated.shape == (16, 3)
        diff = sh.evaluate(np.broadcast_to(rotated, (64, 16, 3)), d) - sh.evaluate(
            np.broadcast_to(coeffs, (64, 16, 3)), d @ r
        )
        assert np.abs(diff).max() < 1e-12


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_per_splat_rotations_match_brute_force(rng, degree):
    n = 20000  # more than one chunk, so the threaded path runs
    coeffs = rng.normal(0, 0.5, size=(n, (degree + 1) ** 2, 3))
    rotations = random_rotations(rng, n)
    rotations[::5] *= -1  # mirrors among them
    assert_rotates(coeffs, rotations, unit(rng.normal(size=(n, 3))))


def brute_force_rotation(rotation, degree, rng):
    """D with basis(R^T d) = basis(d) D, by least squares over 500 random directions; and the largest
    residual (zero when every band is closed under the rotation)."""
    d = unit(rng.normal(size=(500, 3)))
    before, after = sh.basis(d, degree), sh.basis(d @ rotation, degree)  # rows of d @ R are R^T d
    fit = np.linalg.lstsq(before, after, rcond=None)[0]
    return fit, np.abs(before @ fit - after).max()


def test_degree_4_rotations_and_mirrors_match_a_brute_force_fit(rng):
    """rotation_matrix and rotate at degree 4 against a least-squares fit of the basis at R^T d
    (rotations, mirrors with det -1, the point inversion), one matrix or one per splat."""
    proper = random_rotations(rng, 12)
    mirrors = proper[:6] @ np.diag([1.0, -1.0, 1.0])
    matrices = np.concatenate([proper, mirrors, [-np.eye(3), np.diag([1.0, 1.0, -1.0]), np.eye(3)[[1, 0, 2]]]])
    coeffs = rng.normal(0, 0.5, size=(len(matrices), 25, 3))
    per_splat = sh.rotate(coeffs, matrices)
    for r, c, got in zip(matrices, coeffs, per_splat):
        fit, residual = brute_force_rotation(r, 4, rng)
        assert residual < 1e-12  # band 4 is closed under R
        band = slice(16, 25)
        assert np.abs(fit[band, :16]).max() < 1e-12 and np.abs(fit[:16, band]).max() < 1e-12
        np.testing.assert_allclose(sh.rotation_matrix(r, 4), fit, atol=1e-12)  # rotate: c' = D c
        np.testing.assert_allclose(got, fit @ c, atol=1e-12)
        np.testing.assert_allclose(sh.rotate(c, r), fit @ c, atol=1e-12)
    # odd bands flip under -I, band 4 does not
    np.testing.assert_allclose(sh.rotation_matrix(-np.eye(3), 4)[16:, 16:], np.eye(9), atol=1e-14)


def test_degree_4_band_turns_with_the_x90_that_spz_tabulates():
    """Niantic's SPZ converts Y-up and Z-up frames with a table of D_4(Rx(+90 degrees)) in this
    ordering and these signs: the same matrix (its closed-form entries written out)."""
    r2, r5, r7, r14, r35 = (np.sqrt(v) for v in (2, 5, 7, 14, 35))
    want = np.zeros((9, 9))
    rows = {
        0: {5: -r14 / 4, 7: r2 / 4},
        1: {1: -0.75, 3: r7 / 4},
        2: {5: -r2 / 4, 7: -r14 / 4},
        3: {1: r7 / 4, 3: 0.75},
        4: {4: 3 / 8, 6: r5 / 4, 8: r35 / 8},
        5: {0: r14 / 4, 2: r2 / 4},
        6: {4: r5 / 4, 6: 0.5, 8: -r7 / 4},
        7: {0: -r2 / 4, 2: r14 / 4},
        8: {4: r35 / 8, 6: -r7 / 4, 8: 0.125},
    }
    for i, row in rows.items():
        for j, v in row.items():
            want[i, j] = v
    rx90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(sh.rotation_matrix(rx90, 4)[16:, 16:], want, atol=1e-14)


def test_float32_in_float32_out_within_1e5(rng):
    coeffs = rng.normal(0, 1, size=(1000, 16, 3)).astype(np.float32)
    rotations = random_rotations(rng, 1000)
    d = unit(rng.normal(size=(1000, 3)))
    for rotation in (rotations, rotations[0]):
        rotated = sh.rotate(coeffs, rotation)
        assert rotated.dtype == np.float32
        r = np.broadcast_to(rotation, (1000, 3, 3))
        diff = sh.evaluate(rotated, d) - sh.evaluate(coeffs.astype(np.float64), np.einsum("nji,nj->ni", r, d))
        assert np.abs(diff).max() < 1e-5
    assert sh.rotate(coeffs.astype(np.float64), rotations).dtype == np.float64


def test_identity_changes_nothing(rng):
    coeffs = rng.normal(size=(100, 16, 3))
    np.testing.assert_allclose(sh.rotate(coeffs, np.eye(3)), coeffs, rtol=0, atol=1e-13)
    np.testing.assert_allclose(sh.rotate(coeffs, np.tile(np.eye(3), (100, 1, 1))), coeffs, rtol=0, atol=1e-13)
    as_float32 = coeffs.astype(np.float32)
    np.testing.assert_array_equal(sh.rotate(as_float32, np.eye(3)), as_float32)


def awkward_rotations():
    """Half turns and rotations at the singular points of z-y-z Euler angles (b = 0, b = pi, tiny b)."""
    axes = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -2, 3], [0, 1, 1e-9]]
    yield from (axis_angle(a, np.pi) for a in axes)  # 180 degrees
    yield from (axis_angle([0, 0, 1], t) for t in (0.3, -2.0, np.pi / 2))  # b = 0 exactly
    yield axis_angle([1, 0, 0], np.pi) @ axis_angle([0, 0, 1], 0.7)  # b = pi exactly
    for tiny in (1e-7, 1e-10, 1e-15):
        yield axis_angle([0, 0, 1], 1.1) @ axis_angle([1, 2, 0], tiny) @ axis_angle([0, 0, 1], -0.4)
        yield axis_angle([0, 1, 0], np.pi - tiny) @ axis_angle([0, 0, 1], 2.5)
    yield np.diag([1.0, -1.0, -1.0])


def test_half_turns_and_euler_singularities(rng):
    rotations = np.array(list(awkward_rotations()))
    n = len(rotations)
    coeffs = rng.normal(size=(n, 16, 3))
    assert_rotates(coeffs, rotations, unit(rng.normal(size=(n, 3))))
    for r in rotations:  # the single-matrix path too, against the least-squares reference
        np.testing.assert_allclose(sh.rotation_matrix(r, 3), sh.fitted_rotation_matrix(r, 3), atol=1e-12)


def test_mirrors_follow_y_of_minus_d(rng):
    coeffs = rng.normal(size=(1, 16, 3))
    d = unit(rng.normal(size=(1, 3)))
    # The point inversion -I: Y_l(-d) = (-1)^l Y_l(d), so odd bands flip sign.
    signs = np.array([1, -1, -1, -1] + [1] * 5 + [-1] * 7, dtype=float)
    np.testing.assert_allclose(sh.rotate(coeffs, -np.eye(3)), coeffs * signs[None, :, None], atol=1e-14)
    # Mirror planes, and random improper matrices, against brute force.
    mirrors = [np.diag([1.0, 1.0, -1.0]), np.diag([-1.0, 1.0, 1.0]), np.eye(3)[[1, 0, 2]]]
    mirrors += list(random_rotations(rng, 20) @ np.diag([1.0, -1.0, 1.0]))
    for q in mirrors:
        assert np.linalg.det(q) < 0
        assert_rotates(coeffs, q[None], d)
        np.testing.assert_allclose(sh.rotation_matrix(q, 3), sh.fitted_rotation_matrix(q, 3), atol=1e-12)


def test_rotation_matrices_are_an_orthogonal_representation(rng):
    r1, r2 = random_rotations(rng, 2)
    d1, d2, d12 = (sh.rotation_matrix(r, 3) for r in (r1, r2, r1 @ r2))
    np.testing.assert_allclose(d12, d1 @ d2, atol=1e-13)  # D(R1 R2) = D(R1) D(R2)
    np.testing.assert_allclose(d1 @ d1.T, np.eye(16), atol=1e-13)
    mask = np.zeros((16, 16), bool)  # block diagonal by band
    for l in range(4):
        mask[l * l : (l + 1) ** 2, l * l : (l + 1) ** 2] = True
    assert np.abs(d1[~mask]).max() < 1e-14
    batched = sh.rotation_matrix(np.stack([r1, r2]), 2)
    np.testing.assert_allclose(batched, [sh.fitted_rotation_matrix(r, 2) for r in (r1, r2)], atol=1e-12)


def test_band_one_turns_like_a_vector(rng):
    """The band-1 coefficients (-C1 y, C1 z, -C1 x) are a vector a = (-c3, -c1, c2): a' = R a."""
    r = random_rotations(rng, 1)[0]
    c = rng.normal(size=(4, 1))
    rotated = sh.rotate(c, r)
    a = np.array([-c[3, 0], -c[1, 0], c[2, 0]])
    np.testing.assert_allclose([-rotated[3, 0], -rotated[1, 0], rotated[2, 0]], r @ a, atol=1e-14)


def test_a_broken_splat_does_not_spread(rng):
    coeffs = rng.normal(size=(10, 16, 3))
    coeffs[3, 5, 1] = np.nan
    before = coeffs.copy()
    rotations = random_rotations(rng, 10)
    rotated = sh.rotate(coeffs, rotations)
    np.testing.assert_array_equal(coeffs, before)  # the input is left alone
    ok = np.arange(10) != 3
    assert np.isfinite(rotated[ok]).all()
    np.testing.assert_allclose(rotated[ok], sh.rotate(coeffs[ok], rotations[ok]), atol=1e-14)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_compiled_rotation_is_its_numpy_reference(rng, dtype):
    """sh._rotate_loop (every splat on its own) against _rotate_each_numpy (band by band over rows
    of splats), degrees 1-4: random rotations and mirrors, and the Euler angles' hard cases, turns
    about z alone (sin b = 0) and z turns after a half turn (cos b = -1), exact and 1e-9 off."""
    if jit.compiled(sh.__name__, sh.ROTATE_KERNEL) is None:
        pytest.skip("numba is not available here")
    turns = [np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]]) for t in (0, 0.3, np.pi, -2)]
    flip = np.diag([1.0, -1.0, -1.0])  # a half turn about x: cos b = -1
    hard = np.array([*turns, *(t @ flip for t in turns), *(t @ flip @ turns[1] for t in turns)])
    axes = unit(rng.normal(size=(len(hard), 3)))
    tiny = geometry.quaternions_to_matrices(np.concatenate([np.ones((len(hard), 1)), 0.5e-9 * axes], axis=1))
    nudged = tiny @ hard
    rotations = np.concatenate([random_rotations(rng, 300), hard, nudged])
    rotations[::7] *= -1  # mirrors among them
    for degree in (1, 2, 3, 4):
        coeffs = rng.normal(0, 0.5, size=(len(rotations), (degree + 1) ** 2, 3)).astype(dtype)
        got = sh._rotate_each(coeffs, rotations, np.empty(coeffs.shape, dtype))
        want = sh._rotate_each_numpy(coeffs, rotations, np.empty(coeffs.shape, dtype))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 if dtype == np.float64 else 1e-6)
    # a coefficient that is not finite spoils what depends on it there, and nothing else
    coeffs[3, 0, 0], coeffs[5, 9, 1] = np.inf, np.nan
    got = sh._rotate_each(coeffs, rotations, np.empty(coeffs.shape, dtype))
    want = sh._rotate_each_numpy(coeffs, rotations, np.empty(coeffs.shape, dtype))
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    assert np.isfinite(got[3, 1:]).all() and np.isfinite(got[5, :, 0]).all()


def test_one_coefficient_set_under_many_rotations(rng):
    coeffs = rng.normal(size=(16, 3))
    rotations = random_rotations(rng, 7)
    rotated = sh.rotate(coeffs, rotations)
    assert rotated.shape == (7, 16, 3)
    np.testing.assert_allclose(rotated[3], sh.rotate(coeffs, rotations[3]), atol=1e-14)


def test_bad_rotations_are_refused_with_the_reason(rng):
    coeffs = rng.normal(size=(3, 16, 3))
    rotations = random_rotations(rng, 3)
    sheared = rotations.copy()
    sheared[1] = sheared[1] @ np.array([[1, 0.1, 0], [0, 1, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match=r"orthogonal: 1 of 3 matrices"):
        sh.rotate(coeffs, sheared)
    broken = rotations.copy()
    broken[2, 0, 0] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        sh.rotate(coeffs, broken)
    with pytest.raises(ValueError, match="orthogonal"):
        sh.rotate(coeffs, 2 * np.eye(3))
    with pytest.raises(ValueError, match=r"2 rotations for 3 splats"):
        sh.rotate(coeffs, rotations[:2])
    with pytest.raises(ValueError, match=r"shape \(3, 3\) or \(N, 3, 3\)"):
        sh.rotate(coeffs, np.eye(4))
    with pytest.raises(ValueError, match="SH coefficients per channel"):
        sh.rotate(rng.normal(size=(3, 5, 3)), np.eye(3))
