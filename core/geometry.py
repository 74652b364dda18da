"""Rotations and covariances, batched: quaternions are w,x,y,z throughout."""

import numpy as np

from . import jit


def normalize_quaternions(q):
    """Unit quaternions; zero or non-finite ones become the identity (validation reports them)."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    good = np.isfinite(norm) & (norm > 1e-30)
    identity = np.zeros_like(q)
    identity[..., 0] = 1.0
    return np.where(good, q / np.where(good, norm, 1.0), identity)


def quaternions_to_matrices(q):
    """(..., 4) w,x,y,z (any norm) -> (..., 3, 3) rotation matrices, float64."""
    w, x, y, z = np.moveaxis(normalize_quaternions(q), -1, 0)
    m = np.empty(w.shape + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - w * z)
    m[..., 0, 2] = 2 * (x * z + w * y)
    m[..., 1, 0] = 2 * (x * y + w * z)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - w * x)
    m[..., 2, 0] = 2 * (x * z - w * y)
    m[..., 2, 1] = 2 * (y * z + w * x)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def matrices_to_quaternions(m):
    """(..., 3, 3) proper rotations -> (..., 4) unit w,x,y,z with w >= 0 (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Pick the largest of 4w^2, 4x^2, 4y^2, 4z^2 per matrix to avoid cancellation.
    cand = np.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1)
    pick = np.argmax(cand, axis=-1)
    q = np.empty(m.shape[:-2] + (4,))
    s = 2.0 * np.sqrt(np.maximum(1.0 + 2.0 * np.take_along_axis(cand, pick[..., None], -1)[..., 0] - trace, 1e-300))
    # s = 4 * (the largest component); the others follow from off-diagonal sums and differences.
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s21, s02, s10 = m[..., 2, 1] + m[..., 1, 2], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1]
    rows = [
        (s / 4, d21 / s, d02 / s, d10 / s),
        (d21 / s, s / 4, s10 / s, s02 / s),
        (d02 / s, s10 / s, s / 4, s21 / s),
        (d10 / s, s02 / s, s21 / s, s / 4),
    ]
    for k, row in enumerate(rows):
        sel = pick == k
        q[sel] = np.stack([c[sel] for c in row], axis=-1)
    q *= np.where(q[..., :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def covariances(rotations, scales):
    """Sigma = R S S^T R^T, float64 (N,3,3), from w,x,y,z quaternions and linear scales."""
    r = quaternions_to_matrices(rotations)
    rs = r * np.asarray(scales, dtype=np.float64)[..., None, :]
    return rs @ np.swapaxes(rs, -1, -2)


def decompose_covariances(cov):
    """Symmetric PSD (...,3,3) -> (w,x,y,z quaternions, linear scales), the inverse of covariances().

    Negative eigenvalues from round-off are clamped to zero; reflections are turned into rotations
    by flipping one eigenvector, which leaves the covariance unchanged.
    """
    cov = np.asarray(cov, dtype=np.float64)
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    vals, vecs = np.linalg.eigh(sym)
    flip = np.linalg.det(vecs) < 0
    vecs[flip, :, 0] *= -1
    return matrices_to_quaternions(vecs), np.sqrt(np.maximum(vals, 0.0))


def multiply_quaternions(a, b):
    """Hamilton products a * b of (..., 4) w,x,y,z quaternions: the rotation b, then a."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def determinants(m):
    """det of (..., 3, 3) matrices by the triple product (no LAPACK call per matrix)."""
    m = np.asarray(m, dtype=np.float64)
    return np.einsum("...i,...i->...", m[..., 0, :], np.cross(m[..., 1, :], m[..., 2, :]))


def _require_finite(a, what):
    bad = ~np.isfinite(a).reshape(a.shape[:-2] + (-1,)).all(axis=-1)
    if bad.any():
        raise ValueError(f"{what}: {int(bad.sum())} matrices hold NaN or Inf")


POLAR_NEWTON_CONDITION = 1e6  # above this condition number the SVD is the safer road


def polar_decomposition(a):
    """A = R S for (..., 3, 3) matrices: R orthogonal (det -1 where A mirrors), S = sym(R^T A)
    symmetric PSD. See polar_rotation for how R is found."""
    a = np.asarray(a, dtype=np.float64)
    r = polar_rotation(a)
    s = np.einsum("...ji,...jk->...ik", r, a)
    return r, 0.5 * (s + np.swapaxes(s, -1, -2))


def polar_rotation(a, tolerance=1e-15):
    """R of the polar decomposition A = R S, for (..., 3, 3) matrices. Newton steps stop once an
    entry moves less than 10 x `tolerance`: the step after that is accurate to about its square, so
    a caller that stores float32 may pass 1e-7 (results within 1e-12 of the SVD's) and save a step.

    Well-conditioned matrices (nearly all, in skinning and object transforms) take Higham's scaled
    Newton iteration R <- (g R + R^-T / g) / 2 with closed-form 3x3 inverses, faster than a batched
    LAPACK SVD. Nearly singular ones take the SVD A = U diag(sigma) V^T, R = U V^T, which keeps R
    orthogonal however thin A is.
    """
    a = np.asarray(a, dtype=np.float64)
    if a.shape[-2:] != (3, 3):
        raise ValueError(f"polar_decomposition needs (..., 3, 3) matrices, got shape {a.shape}")
    _require_finite(a, "polar_decomposition")
    flat = a.reshape(-1, 3, 3)
    kernel = _polar_kernel()
    if kernel is not None:
        r, flags = np.empty_like(flat), np.zeros(len(flat), np.uint8)
        kernel(np.ascontiguousarray(flat), tolerance, POLAR_NEWTON_CONDITION, r, flags)
        singular = np.flatnonzero(flags)
    else:
        r, singular = _polar_rotation_newton(flat, tolerance)
    if len(singular):
        u, _, vt = np.linalg.svd(flat[singular])
        r[singular] = u @ vt
    return r.reshape(a.shape)


def _polar_kernel():
    """The compiled twin of _polar_rotation_newton (core.jit), or None: NumPy then does the work."""
    return jit.compiled(__name__, ("_polar_loop",))


def _polar_loop(m, tolerance, condition, out, singular):
    """_polar_rotation_newton one matrix at a time, as a scalar loop for numba: the same scaled
    Newton steps and stopping rule; singular[i] = 1 (out[i] left unset) where the condition number
    reaches `condition`."""
    for i in range(m.shape[0]):
        a, b, c = m[i, 0, 0], m[i, 0, 1], m[i, 0, 2]
        d, e, f = m[i, 1, 0], m[i, 1, 1], m[i, 1, 2]
        g, h, k = m[i, 2, 0], m[i, 2, 1], m[i, 2, 2]
        for step in range(40):
            c0, c1, c2 = e * k - f * h, f * g - d * k, d * h - e * g
            c3, c4, c5 = c * h - b * k, a * k - c * g, b * g - a * h
            c6, c7, c8 = b * f - c * e, c * d - a * f, a * e - b * d
            det = a * c0 + b * c1 + c * c2
            norm_x = a * a + b * b + c * c + d * d + e * e + f * f + g * g + h * h + k * k
            norm_c = c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3 + c4 * c4 + c5 * c5 + c6 * c6 + c7 * c7 + c8 * c8
            if step == 0 and not np.sqrt(norm_x * norm_c) < condition * abs(det):
                singular[i] = 1
                break
            gamma = np.sqrt(np.sqrt(norm_c / norm_x) / abs(det))
            hg, hi = 0.5 * gamma, 0.5 / (gamma * det)
            na, nb, nc = hg * a + hi * c0, hg * b + hi * c1, hg * c + hi * c2
            nd, ne, nf = hg * d + hi * c3, hg * e + hi * c4, hg * f + hi * c5
            ng, nh, nk = hg * g + hi * c6, hg * h + hi * c7, hg * k + hi * c8
            moved = max(
                abs(na - a),
                abs(nb - b),
                abs(nc - c),
                abs(nd - d),
                abs(ne - e),
                abs(nf - f),
                abs(ng - g),
                abs(nh - h),
                abs(nk - k),
            )
            a, b, c, d, e, f, g, h, k = na, nb, nc, nd, ne, nf, ng, nh, nk
            if moved < 10 * tolerance:
                break
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = a, b, c
        out[i, 1, 0], out[i, 1, 1], out[i, 1, 2] = d, e, f
        out[i, 2, 0], out[i, 2, 1], out[i, 2, 2] = g, h, k


def _polar_rotation_newton(m, tolerance=1e-15, max_iterations=40):
    """Orthogonal polar factors of (n, 3, 3) matrices by scaled Newton steps, and the indices of the
    matrices too close to singular for it (condition number >= POLAR_NEWTON_CONDITION), left unset.

    Works on the nine entries as separate contiguous arrays (elementwise NumPy at memory speed, no
    batched small-matrix calls) and keeps iterating only the matrices that have not converged.
    """
    out = np.empty_like(m)
    x = [np.ascontiguousarray(m[:, i, j]) for i in range(3) for j in range(3)]
    todo = np.arange(len(m))
    singular = np.zeros(0, dtype=np.intp)
    for step in range(max_iterations):
        a, b, c, d, e, f, g, h, k = x
        # cofactors of [[a b c] [d e f] [g h k]]: inverse transpose = cof / det
        cof = [
            e * k - f * h,
            f * g - d * k,
            d * h - e * g,
            c * h - b * k,
            a * k - c * g,
            b * g - a * h,
            b * f - c * e,
            c * d - a * f,
            a * e - b * d,
        ]
        det = a * cof[0] + b * cof[1] + c * cof[2]
        norm_x, norm_cof = sum(v * v for v in x), sum(v * v for v in cof)
        if step == 0:
            # condition number in the Frobenius norm: |A| |A^-1| = sqrt(|A|^2 |cof|^2) / |det|
            with np.errstate(divide="ignore", invalid="ignore"):
                ok = np.sqrt(norm_x * norm_cof) < POLAR_NEWTON_CONDITION * np.abs(det)
            if not ok.all():
                singular, todo = todo[~ok], todo[ok]
                x, cof = [v[ok] for v in x], [v[ok] for v in cof]
                det, norm_x, norm_cof = det[ok], norm_x[ok], norm_cof[ok]
        # Frobenius-norm scaling, gamma = sqrt(|X^-1| / |X|), converges in a few steps at any condition.
        gamma = np.sqrt(np.sqrt(norm_cof / norm_x) / np.abs(det))
        half_g, half_inv = 0.5 * gamma, 0.5 / (gamma * det)
        nxt = [half_g * v + half_inv * w for v, w in zip(x, cof)]
        done = np.maximum.reduce([np.abs(v - w) for v, w in zip(nxt, x)]) < 10 * tolerance
        if done.any():
            out[todo[done]] = np.stack([v[done] for v in nxt], axis=1).reshape(-1, 3, 3)
            todo, nxt = todo[~done], [v[~done] for v in nxt]
        x = nxt
        if len(todo) == 0:
            break
    else:
        out[todo] = np.stack(x, axis=1).reshape(-1, 3, 3)
    return out, singular


def transform_normals(a, normals):
    """Unit surface normals carried through the linear map A ((3,3), or (N,3,3) one per row): the
    inverse transpose A^-T n, renormalised, which keeps them perpendicular to the transformed
    surface under any non-singular A (a mirror included). Zero or non-finite rows stay as they are,
    so validation still reports them."""
    a = np.asarray(a, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    # A^-T n as a row vector is n A^-1; solve instead of invert for the batched case.
    if a.ndim == 2:
        turned = n @ np.linalg.inv(a)
    else:
        turned = np.linalg.solve(np.swapaxes(a, -1, -2), n[..., None])[..., 0]
    length = np.linalg.norm(turned, axis=-1, keepdims=True)
    good = np.isfinite(length) & (length > 1e-30)
    return np.where(good, turned / np.where(good, length, 1.0), n)


def anisotropy(a):
    """How far the linear map A is from a similarity (rotation or mirror times uniform scale):
    sigma_max / sigma_min - 1 over A's singular values, the stretch of its polar part. 0 for
    similarities, inf for singular A.

    It bounds how wrong view-dependent colour gets when a transform rotates SH by the polar rotation
    alone: view directions then deviate by at most atan(k / (2 sqrt(1 + k))) radians, k = anisotropy.
    """
    a = np.asarray(a, dtype=np.float64)
    _require_finite(a, "anisotropy")
    sigma = np.linalg.svd(a, compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = sigma[..., 0] / sigma[..., -1]
    return np.where(sigma[..., -1] > 0, ratio - 1.0, np.inf)


def split_affine(matrix, condition_limit=1e12):
    """(A, t) of an affine map x -> A x + t given as a 4x4 matrix (last row 0 0 0 1) or a 3x3 A.

    Rejects, with the reason, matrices that are malformed, hold NaN/Inf, project (last row not
    0 0 0 1) or collapse space (A singular, or sigma_max / sigma_min above condition_limit).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape not in ((4, 4), (3, 3)):
        raise ValueError(f"transform must be a 4x4 affine or 3x3 linear matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError("transform holds NaN or Inf")
    if m.shape == (4, 4) and not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"transform is projective (last row {m[3].tolist()}, expected [0, 0, 0, 1])")
    a, t = m[:3, :3], (m[:3, 3] if m.shape == (4, 4) else np.zeros(3))
    sigma = np.linalg.svd(a, compute_uv=False)
    if not sigma[-1] > sigma[0] / condition_limit:
        raise ValueError(
            f"transform is singular (singular values {sigma.tolist()}): it would flatten splats to zero thickness"
        )
    return a.copy(), t.copy()


def transform_covariances(a, rotations, scales):
    """The Gaussians N(0, A Sigma A^T) for Sigma = R S S^T R^T, as (w,x,y,z quaternions, scales).

    Takes the SVD of the factor A R S = U diag(sigma) V^T rather than the eigen-decomposition of
    A Sigma A^T: then A Sigma A^T = U diag(sigma)^2 U^T, and sigma keeps its accuracy relative to the
    largest scale (eigh of the product would square the spread: 1e-7 and 1e4 in one splat would
    lose the small axis altogether). A reflected U becomes a rotation by flipping one column.
    """
    factor = np.asarray(a, dtype=np.float64) @ (
        quaternions_to_matrices(rotations) * np.asarray(scales, dtype=np.float64)[..., None, :]
    )
    u, sigma, _ = np.linalg.svd(factor)
    u[determinants(u) < 0, :, 2] *= -1
    return matrices_to_quaternions(u), sigma
