"""Rotations and covariances, batched: quaternions are w,x,y,z throughout."""

import numpy as np


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
