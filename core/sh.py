"""Real spherical harmonics for degrees 0..3, with the constants of the 3DGS reference rasteriser."""

import numpy as np

C0 = 0.28209479177387814
MAX_DEGREE = 3
VALID_COUNTS = (1, 4, 9, 16)


def num_coeffs(degree):
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be 0..{MAX_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def degree_of(count):
    """SH degree from the number of coefficients per channel (1, 4, 9, 16)."""
    if count not in VALID_COUNTS:
        raise ValueError(f"{count} SH coefficients per channel is not (d+1)^2 for d in 0..{MAX_DEGREE}")
    return VALID_COUNTS.index(count)


def rgb_to_dc(rgb):
    """The DC coefficient that shows colour `rgb` (display sRGB) from every direction."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / C0


def dc_to_rgb(dc):
    return 0.5 + C0 * np.asarray(dc, dtype=np.float64)


def truncate(sh, degree):
    """Keep bands 0..degree; a higher degree zero-pads (which does not change any colour)."""
    k = num_coeffs(degree)
    if k <= sh.shape[1]:
        return sh[:, :k]
    pad = np.zeros((sh.shape[0], k - sh.shape[1], sh.shape[2]), dtype=sh.dtype)
    return np.concatenate([sh, pad], axis=1)


C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def basis(directions, degree):
    """Real SH basis (N, (degree+1)^2) at unit-normalised directions, in the 3DGS ordering and signs."""
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    d = d / np.where(norm > 0, norm, 1.0)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [np.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=-1)


def evaluate(sh, directions):
    """sum_k Y_k(d) sh_k per splat: (N,K,3) coefficients, (N,3) directions -> (N,3), float64."""
    sh = np.asarray(sh)
    y = basis(directions, degree_of(sh.shape[1]))
    return np.einsum("nk,nkc->nc", y, sh, optimize=True)


def colors(sh, directions):
    """Display-sRGB colours max(0, 0.5 + sum_k Y_k(d) sh_k), as the 3DGS rasteriser computes them."""
    return np.maximum(0.0, 0.5 + evaluate(sh, directions))
