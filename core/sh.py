"""Real spherical harmonics for degrees 0..4: the constants of the 3DGS reference rasteriser for
degrees 0..3, and band 4 in the ordering and signs that continue them (see C4)."""

import functools
import math

import numpy as np

from . import jit
from .parallel import in_chunks

C0 = 0.28209479177387814
MAX_DEGREE = 4
VALID_COUNTS = (1, 4, 9, 16, 25)


def num_coeffs(degree):
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be 0..{MAX_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def degree_of(count):
    """SH degree from the number of coefficients per channel (1, 4, 9, 16, 25)."""
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
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
# Band 4, m = -4..4, each times its polynomial in basis() (unit x, y, z): the real harmonics with the
# Condon-Shortley phase (-1)^m that bands 1..3 carry, normalised like them (integral of Y^2 over the
# sphere is 1). The ordering and signs are gsplat's degree-4 evaluation (sh_coeffs_to_color_fast, from
# Sloan's "Efficient Spherical Harmonic Evaluation"), whose sign pattern Niantic's SPZ coordinate
# flips follow too. Closed forms: 3/4 sqrt(35/pi), 3/4 sqrt(35/(2 pi)), 3/4 sqrt(5/pi),
# 3/4 sqrt(5/(2 pi)), 3/16 sqrt(1/pi), and 3/8 sqrt(5/pi), 3/16 sqrt(35/pi) for m = 2, 4.
C4 = (
    2.5033429417967046,
    -1.7701307697799304,
    0.9461746957575601,
    -0.6690465435572892,
    0.10578554691520431,
    -0.6690465435572892,
    0.47308734787878004,
    -1.7701307697799304,
    0.6258357354491761,
)


def basis(directions, degree, dtype=np.float64):
    """Real SH basis (N, (degree+1)^2) at unit-normalised directions, in the 3DGS ordering and signs.

    Directions are normalised in float64 (they may come from far-apart points); the polynomials are
    evaluated in `dtype`."""
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    d = (d / np.where(norm > 0, norm, 1.0)).astype(dtype, copy=False)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [np.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    if degree >= 4:
        out += _band4(x, y, z)
    return np.stack(out, axis=-1)


def _band4(x, y, z):
    """The nine degree-4 basis functions (m = -4..4) at unit x, y, z."""
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    return [
        C4[0] * xy * (xx - yy),
        C4[1] * yz * (3 * xx - yy),
        C4[2] * xy * (7 * zz - 1),
        C4[3] * yz * (7 * zz - 3),
        C4[4] * (zz * (35 * zz - 30) + 3),
        C4[5] * xz * (7 * zz - 3),
        C4[6] * (xx - yy) * (7 * zz - 1),
        C4[7] * xz * (xx - 3 * yy),
        C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)),
    ]


def _band4_gradient(w, x, y, z):
    """d/d(x, y, z) of the band-4 polynomials of _band4 weighted by w[..., 16:25]."""
    xx, yy, zz = x * x, y * y, z * z
    a, b, c, e, f, g, h, k, m = (C4[i] * w[..., 16 + i] for i in range(9))
    seven1, seven3 = 7 * zz - 1, 7 * zz - 3
    gx = (
        a * y * (3 * xx - yy)
        + 6 * b * x * y * z
        + c * y * seven1
        + g * z * seven3
        + 2 * h * x * seven1
        + 3 * k * z * (xx - yy)
        + 4 * m * x * (xx - 3 * yy)
    )
    gy = (
        a * x * (xx - 3 * yy)
        + 3 * b * z * (xx - yy)
        + c * x * seven1
        + e * z * seven3
        - 2 * h * y * seven1
        - 6 * k * x * y * z
        + 4 * m * y * (yy - 3 * xx)
    )
    gz = (
        b * y * (3 * xx - yy)
        + 14 * c * x * y * z
        + e * y * (21 * zz - 3)
        + f * z * (140 * zz - 60)
        + g * x * (21 * zz - 3)
        + 14 * h * z * (xx - yy)
        + k * x * (xx - 3 * yy)
    )
    return gx, gy, gz


def basis_gradient(weights, directions):
    """d/d directions of basis(directions) @ weights per row: weights (N, K), directions (N, 3), not
    necessarily unit (basis() normalises them, so the polynomials' gradient at the unit direction u
    is taken through (I - u u^T) / |d|); (N, 3), float64."""
    w = np.asarray(weights, dtype=np.float64)
    degree = degree_of(w.shape[-1])
    d = np.asarray(directions, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    norm = np.where(norm > 0, norm, 1.0)
    u = d / norm
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    gx, gy, gz = (np.zeros_like(x) for _ in range(3))
    if degree >= 1:
        gx, gy, gz = -C1 * w[..., 3], -C1 * w[..., 1], C1 * w[..., 2]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        a, b, c, e, f = (C2[i] * w[..., 4 + i] for i in range(5))
        gx = gx + a * y - 2 * c * x + e * z + 2 * f * x
        gy = gy + a * x + b * z - 2 * c * y - 2 * f * y
        gz = gz + b * y + 4 * c * z + e * x
    if degree >= 3:
        a, b, c, e, f, g, h = (C3[i] * w[..., 9 + i] for i in range(7))
        gx = (
            gx
            + 6 * a * x * y
            + b * y * z
            - 2 * c * x * y
            - 6 * e * x * z
            + f * (4 * zz - 3 * xx - yy)
            + 2 * g * x * z
            + 3 * h * (xx - yy)
        )
        gy = (
            gy
            + 3 * a * (xx - yy)
            + b * x * z
            + c * (4 * zz - xx - 3 * yy)
            - 6 * e * y * z
            - 2 * f * x * y
            - 2 * g * y * z
            - 6 * h * x * y
        )
        gz = gz + b * x * y + 8 * c * y * z + e * (6 * zz - 3 * xx - 3 * yy) + 8 * f * x * z + g * (xx - yy)
    if degree >= 4:
        gx, gy, gz = (g + g4 for g, g4 in zip((gx, gy, gz), _band4_gradient(w, x, y, z)))
    grad = np.stack([gx, gy, gz], axis=-1)  # d/du
    return (grad - (grad * u).sum(-1, keepdims=True) * u) / norm


def evaluate(sh, directions):
    """sum_k Y_k(d) sh_k per splat: (N,K,3) coefficients, (N,3) directions -> (N,3).

    In the coefficients' own precision: float32 SH (as stored) give float32 sums, whose rounding
    (about 1e-6) is far below a display step, at a quarter of the float64 cost."""
    sh = np.asarray(sh)
    dtype = np.float32 if sh.dtype == np.float32 else np.float64
    y = basis(directions, degree_of(sh.shape[1]), dtype)
    return np.einsum("nk,nkc->nc", y, sh.astype(dtype, copy=False))


def colors(sh, directions):
    """Display-sRGB colours max(0, 0.5 + sum_k Y_k(d) sh_k), as the 3DGS rasteriser computes them."""
    return np.maximum(0.0, 0.5 + evaluate(sh, directions))


# Rotation -------------------------------------------------------------------------------------
#
# A rotation R turns the coloured sphere function f into f'(d) = f(R^T d). Every band l is mapped
# onto itself, by a (2l+1)x(2l+1) matrix D_l(R) (the real Wigner-D matrix of this basis), and
# D(R1 R2) = D(R1) D(R2). Two kinds of rotation are cheap in this basis:
#
#  * about z by t: in each band the coefficients of m and -m (m >= 1) multiply K cos(m phi) and
#    K sin(m phi) with the same K, so the complex number c_m + i c_-m turns by e^{i m t}, and m = 0
#    stays;
#  * about x by 90 degrees: a constant matrix X per band (fitted once, below).
#
# Any proper rotation is R = Rz(a) Ry(b) Rz(g) (z-y-z Euler angles), and Ry(b) = Rx(-90) Rz(b) Rx(90),
# so  D(R) = Z(a) X^T Z(b) X Z(g):  three per-splat phase rotations and two products with a constant
# matrix that has one or two non-zeros per row. An improper Q (det -1) is -R with R proper; as
# Y_l(-d) = (-1)^l Y_l(d), D(Q) is D(R) with the odd bands negated.
#
# The work array is (K, C, n): coefficient, channel, splat (splats innermost, so every NumPy operation
# runs over long contiguous rows). Band l fills rows l^2 .. l^2+2l in "working order": m = 0, then
# m = 1..l, then m = -1..-l.

_ORTHOGONALITY_TOLERANCE = 1e-4
_CHUNK = 1 << 13  # splats per work item: keeps the float64 temporaries in cache


def _band_rows(l):
    """Rows of band l in the work array (and indices of band l in 3DGS order)."""
    return slice(l * l, (l + 1) ** 2)


def _working_order(degree):
    """3DGS indices of the coefficients, in the order of the work array's rows."""
    return np.array([l * l + l + m for l in range(degree + 1) for m in [0, *range(1, l + 1), *range(-1, -l - 1, -1)]])


def _sphere_samples(count):
    """Near-uniform unit directions (a Fibonacci spiral)."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def fitted_rotation_matrix(rotation, degree, samples=64):
    """D(R) by least squares on sampled directions: basis(R^T d) = basis(d) D for every d.

    Exact up to round-off (each band is closed under rotation), but slow; rotation_matrix() is the
    fast closed form. Used for the constant X and as an independent reference.
    """
    dirs = _sphere_samples(samples)
    rotated = dirs @ np.asarray(rotation, dtype=np.float64)  # rows are R^T d
    return np.linalg.lstsq(basis(dirs, degree), basis(rotated, degree), rcond=None)[0]


@functools.cache
def _x90(l):
    """D_l(Rx(90 degrees)) in working order (its inverse is its transpose)."""
    rx90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    rows = _working_order(l)[_band_rows(l)]
    d = fitted_rotation_matrix(rx90, l)[np.ix_(rows, rows)]
    d[np.abs(d) < 1e-12] = 0.0
    return d


@functools.cache
def _x90_rows(l, transposed):
    """The non-zeros of X (or X^T) row by row, [(row, [(column, value), ...])]: one or two per row."""
    x = _x90(l).T if transposed else _x90(l)
    return [(i, [(j, x[i, j]) for j in np.flatnonzero(x[i])]) for i in range(len(x))]


def _euler_angles(r):
    """cos and sin of a, b, g with R = Rz(a) Ry(b) Rz(g), from the entries r[i][j] (each (n,)) of
    proper rotations. In complex form, with c, s = cos b, sin b >= 0:

        r22 = c,   r02 + i r12 = s e^{ia},
        r00 + r11 + i (r10 - r01) = (1 + c) e^{i(a+g)},   r11 - r00 - i (r01 + r10) = (1 - c) e^{i(a-g)}.

    a comes from the third column (its direction is arbitrary where s = 0), and g from whichever of
    a+g, a-g has the factor >= 1, so every angle is accurate to round-off even where s is tiny.
    Returns ((cos a, sin a), (cos b, sin b), (cos g, sin g)).
    """
    cb, sb = r[2][2], np.sqrt(r[0][2] ** 2 + r[1][2] ** 2)  # entries are at most 1: no overflow
    safe = np.where(sb > 0, sb, 1.0)
    ca, sa = r[0][2] / safe + (sb == 0), r[1][2] / safe
    # e^{i(a+g)} where c >= 0, else e^{i(a-g)}; then g = (a+g) - a, or g = a - (a-g).
    u = np.where(cb >= 0, 1.0, -1.0)
    x, y = r[1][1] + u * r[0][0], u * r[1][0] - r[0][1]
    size = np.sqrt(x * x + y * y)
    x /= size
    y /= size
    return (ca, sa), (cb, sb), (x * ca + y * sa, u * (y * ca - x * sa))


def _multiples(angle, degree):
    """cos(m t), sin(m t) for m = 1..degree, each (degree, 1, n), from (cos t, sin t)."""
    c, s = angle
    cos, sin = [c], [s]
    for _ in range(degree - 1):
        c_m, s_m = cos[-1], sin[-1]
        cos.append(c_m * c - s_m * s)
        sin.append(s_m * c + c_m * s)
    return np.stack(cos)[:, None, :], np.stack(sin)[:, None, :]


def _spin(work, angle, degree):
    """Z rotation in place: (c_m + i c_-m) *= e^{i m t} in every band."""
    cos, sin = _multiples(angle, degree)
    for l in range(1, degree + 1):
        band = work[_band_rows(l)]
        plus, minus = band[1 : l + 1], band[l + 1 :]
        c, s = cos[:l], sin[:l]
        minus_sin = minus * s
        plus_sin = plus * s
        plus *= c
        plus -= minus_sin
        minus *= c
        minus += plus_sin


def _x_turn(work, degree, inverse=False):
    """X work (or X^T work, which is X^-1 work) band by band, using that X is sparse."""
    out = np.empty_like(work)
    out[0] = work[0]
    for l in range(1, degree + 1):
        band, target = work[_band_rows(l)], out[_band_rows(l)]
        for i, row in _x90_rows(l, inverse):
            (j, v), *rest = row
            np.multiply(band[j], v, out=target[i])
            for j, v in rest:
                target[i] += band[j] * v
    return out


def _rotate_working(work, angles, degree):
    """D(R) = Z(a) X^T Z(b) X Z(g) applied to the work array; returns the result."""
    a, b, g = angles
    _spin(work, g, degree)
    work = _x_turn(work, degree)
    _spin(work, b, degree)
    work = _x_turn(work, degree, inverse=True)
    _spin(work, a, degree)
    return work


def _orthogonality_error(r):
    """max |R R^T - I| per matrix, from the rows r[i] (each (3, n))."""
    err = [np.abs(np.einsum("kn,kn->n", r[i], r[j]) - (i == j)) for i in range(3) for j in range(i, 3)]
    return np.max(err, axis=0)


def _determinant(r):
    return np.einsum("kn,kn->n", r[0], np.cross(r[1], r[2], axis=0))


def _check_rotation_shape(rot):
    if rot.ndim not in (2, 3) or rot.shape[-2:] != (3, 3):
        raise ValueError(f"rotation must have shape (3, 3) or (N, 3, 3), got {rot.shape}")


ROTATE_KERNEL = ("_deviation_one", "_euler_one", "_block_angles", "_block_spin", "_block_x_turn", "_rotate_loop")
ROTATE_BLOCK = 64  # splats turned together, innermost in the work arrays (16: 1.3x the time, 256: as slow)


def _rotate_each(coeffs, rot, out):
    """out[n] = D(rot[n]) coeffs[n] for (n, K, C) coefficients: by Euler angles, in threaded chunks,
    by the compiled twin where it loads (_rotate_loop: a third of NumPy's time, whose rows of a few
    thousand splats leave the cache between its band-by-band operations)."""
    kernel = jit.compiled(__name__, ROTATE_KERNEL)
    if kernel is None or coeffs.shape[1] == 1:  # degree 0 only checks the rotations
        return _rotate_each_numpy(coeffs, rot, out)
    deviation = np.zeros(len(rot))
    order, (columns, values) = _working_order(degree_of(coeffs.shape[1])), _x_tables(coeffs.shape[1])
    args = (coeffs, np.ascontiguousarray(rot), order, columns, values, _ORTHOGONALITY_TOLERANCE, out, deviation)
    in_chunks(len(coeffs), lambda lo, hi: kernel(lo, hi, *args))
    return _checked_rotations(deviation, out)


def _rotate_each_numpy(coeffs, rot, out):
    """_rotate_each by NumPy: the reference of _rotate_loop."""
    degree = degree_of(coeffs.shape[1])
    order = _working_order(degree)
    deviation = np.zeros(len(rot))

    def work(start, stop):
        r = np.ascontiguousarray(np.moveaxis(rot[start:stop], 0, -1))  # r[i][j] is (n,)
        deviation[start:stop] = _orthogonality_error(r)
        if degree == 0:
            out[start:stop] = coeffs[start:stop]
            return
        sign = np.where(_determinant(r) < 0, -1.0, 1.0)
        w = np.empty((len(order), coeffs.shape[2], stop - start))
        for row, k in enumerate(order):
            w[row] = coeffs[start:stop, k].T
        with np.errstate(invalid="ignore", divide="ignore"):  # bad matrices are reported below
            w = _rotate_working(w, _euler_angles(r * sign), degree)
        if (sign < 0).any():
            for l in range(1, degree + 1, 2):
                w[_band_rows(l)] *= sign
        np.moveaxis(out[start:stop], 0, -1)[order] = w

    in_chunks(len(coeffs), work, _CHUNK)
    return _checked_rotations(deviation, out)


def _checked_rotations(deviation, out):
    """out, or ValueError where a rotation's |R R^T - I| (deviation, NaN where not finite) is too large."""
    bad = ~(deviation <= _ORTHOGONALITY_TOLERANCE)
    if bad.any():
        raise ValueError(
            f"rotation must be orthogonal: {int(bad.sum())} of {len(deviation)} matrices are not "
            f"(largest |R R^T - I| is {np.nanmax(np.where(bad, deviation, 0)):.3g}"
            f"{', some are not finite' if np.isnan(deviation).any() else ''}); "
            "geometry.polar_decomposition gives the rotation of a general matrix"
        )
    return out


@functools.cache
def _x_tables(count):
    """X and X^T for every band up to count's degree as the compiled loop reads them: (2, K, W)
    columns and values of each work-array row's non-zeros (W of them at most: two up to band 3,
    three in band 4), the padding pointing at row K, a row of zeros the loop keeps (so a padded slot
    adds 0 * 0, not 0 times a coefficient that may be NaN)."""
    degree = degree_of(count)
    rows = [[(l, i, row) for l in range(1, degree + 1) for i, row in _x90_rows(l, t)] for t in (False, True)]
    width = max(len(row) for side in rows for _, _, row in side)
    columns, values = np.full((2, count, width), count, np.int64), np.zeros((2, count, width))
    columns[:, 0, 0], values[:, 0, 0] = 0, 1.0  # band 0 stays
    for side, band_rows in enumerate(rows):
        for l, i, row in band_rows:
            for slot, (j, v) in enumerate(row):
                columns[side, l * l + i, slot], values[side, l * l + i, slot] = l * l + j, v
    return columns, values


def _deviation_one(rot, i):
    """_orthogonality_error of rot[i]: max |R R^T - I|, NaN where an entry is not finite."""
    worst = 0.0
    for a in range(3):
        for b in range(a, 3):
            dot = rot[i, a, 0] * rot[i, b, 0] + rot[i, a, 1] * rot[i, b, 1] + rot[i, a, 2] * rot[i, b, 2]
            if not math.isfinite(dot):
                return math.nan
            worst = max(worst, abs(dot - (1.0 if a == b else 0.0)))
    return worst


def _euler_one(rot, i, sign):
    """_euler_angles of sign * rot[i]: (cos a, sin a, cos b, sin b, cos g, sin g)."""
    r00, r01, r02 = sign * rot[i, 0, 0], sign * rot[i, 0, 1], sign * rot[i, 0, 2]
    r10, r11, r12 = sign * rot[i, 1, 0], sign * rot[i, 1, 1], sign * rot[i, 1, 2]
    cb, sb = sign * rot[i, 2, 2], math.sqrt(r02 * r02 + r12 * r12)
    safe = sb if sb > 0.0 else 1.0
    ca, sa = r02 / safe + (1.0 if sb == 0.0 else 0.0), r12 / safe
    u = 1.0 if cb >= 0.0 else -1.0
    x, y = r11 + u * r00, u * r10 - r01
    size = math.sqrt(x * x + y * y)
    x, y = x / size, y / size
    return ca, sa, cb, sb, x * ca + y * sa, u * (y * ca - x * sa)


def _block_angles(rot, start, size, tolerance, deviation, ok, sign, angles):
    """For the block's splats start..start+size: each rotation's deviation (into `deviation`),
    whether it is a rotation (ok), its sign (-1 for a mirror) and cos, sin of m times its Euler
    angles g, b, a for m = 1..degree (angles (3, 2, degree + 1, B)); the identity for the block's
    tail past `size` and for matrices that are not rotations (the caller leaves those)."""
    degree = angles.shape[2] - 1
    for j in range(angles.shape[3]):
        ok[j], sign[j] = False, 1.0
        if j < size:
            deviation[start + j] = _deviation_one(rot, start + j)
            ok[j] = deviation[start + j] <= tolerance
        turn = (1.0, 0.0, 1.0, 0.0, 1.0, 0.0)
        if ok[j]:
            i = start + j
            det = (
                rot[i, 0, 0] * (rot[i, 1, 1] * rot[i, 2, 2] - rot[i, 1, 2] * rot[i, 2, 1])
                - rot[i, 0, 1] * (rot[i, 1, 0] * rot[i, 2, 2] - rot[i, 1, 2] * rot[i, 2, 0])
                + rot[i, 0, 2] * (rot[i, 1, 0] * rot[i, 2, 1] - rot[i, 1, 1] * rot[i, 2, 0])
            )
            sign[j] = -1.0 if det < 0.0 else 1.0
            ca, sa, cb, sb, cg, sg = _euler_one(rot, i, sign[j])
            turn = (cg, sg, cb, sb, ca, sa)
        for t in range(3):
            c, s = turn[2 * t], turn[2 * t + 1]
            cm, sm = c, s
            for m in range(1, degree + 1):
                angles[t, 0, m, j], angles[t, 1, m, j] = cm, sm
                cm, sm = cm * c - sm * s, sm * c + cm * s


def _block_spin(work, angles, t):
    """_spin of a block's (K + 1, C, B) work rows by its splats' angle t (_block_angles)."""
    degree = angles.shape[2] - 1
    for m in range(1, degree + 1):
        for l in range(m, degree + 1):
            plus, minus = l * l + m, l * l + l + m
            for k in range(work.shape[1]):
                for j in range(work.shape[2]):
                    p, q = work[plus, k, j], work[minus, k, j]
                    c, s = angles[t, 0, m, j], angles[t, 1, m, j]
                    work[plus, k, j], work[minus, k, j] = p * c - q * s, q * c + p * s


def _block_x_turn(work, out, columns, values):
    """_x_turn of a block's (K + 1, C, B) work rows (the last all zeros) into out's first K rows,
    by each row's non-zeros (_x_tables)."""
    for row in range(columns.shape[0]):
        for k in range(work.shape[1]):
            for j in range(work.shape[2]):
                out[row, k, j] = 0.0
            for slot in range(columns.shape[1]):
                column, value = columns[row, slot], values[row, slot]
                for j in range(work.shape[2]):
                    out[row, k, j] += work[column, k, j] * value


def _rotate_loop(lo, hi, coeffs, rot, order, columns, values, tolerance, out, deviation):
    """_rotate_each_numpy for splats lo..hi, ROTATE_BLOCK splats at a time (the splats innermost,
    as the reference's rows, but a block's work stays in cache): each rotation's deviation from
    orthogonality (the caller raises past `tolerance`; such splats are left), its sign and Euler
    angles, then D(R) = Z(a) X^T Z(b) X Z(g) on its coefficients, the odd bands negated for a
    mirror. Arithmetic in float64 as the reference's."""
    count, channels, block = coeffs.shape[1], coeffs.shape[2], ROTATE_BLOCK
    degree = int(math.sqrt(count)) - 1
    work, spare = np.zeros((count + 1, channels, block)), np.zeros((count + 1, channels, block))  # row K stays 0
    angles, sign, ok = np.empty((3, 2, degree + 1, block)), np.empty(block), np.empty(block, np.bool_)
    for start in range(lo, hi, block):
        size = min(block, hi - start)
        _block_angles(rot, start, size, tolerance, deviation, ok, sign, angles)
        for j in range(block):
            for row in range(count):
                for k in range(channels):
                    work[row, k, j] = coeffs[start + j, order[row], k] if ok[j] else 0.0
        _block_spin(work, angles, 0)
        _block_x_turn(work, spare, columns[0], values[0])
        _block_spin(spare, angles, 1)
        _block_x_turn(spare, work, columns[1], values[1])
        _block_spin(work, angles, 2)
        for j in range(size):
            if ok[j]:
                for l in range(degree + 1):
                    flip = -1.0 if sign[j] < 0.0 and l % 2 == 1 else 1.0  # the odd bands of a mirror
                    for row in range(l * l, (l + 1) * (l + 1)):
                        for k in range(channels):
                            out[start + j, order[row], k] = flip * work[row, k, j]


def rotation_matrix(rotation, degree):
    """Real Wigner-D matrices in this basis: (K, K) for a (3, 3) rotation, (N, K, K) for (N, 3, 3).

    rotate(sh, R)[n] == D[n] @ sh[n]; block diagonal by band with D[0, 0] = 1. Mirrors (det -1) too.
    """
    rot = np.asarray(rotation, dtype=np.float64)
    _check_rotation_shape(rot)
    batch = rot.reshape(-1, 3, 3)
    k = num_coeffs(degree)
    # Column c of D is the image of basis vector c: rotate the identity, one "channel" per column.
    identity = np.broadcast_to(np.eye(k), (len(batch), k, k))
    out = _rotate_each(identity, batch, np.empty((len(batch), k, k)))
    return out.reshape(rot.shape[:-2] + (k, k))


def rotate(sh, rotation):
    """SH coefficients of the rotated colour function: evaluate(rotate(sh, R), d) == evaluate(sh, R^T d).

    sh (N, K, 3) or (K, 3); rotation (3, 3) for every splat or (N, 3, 3) one per splat, orthogonal
    (mirrors with det -1 included). float32 in gives float32 out; the arithmetic is float64.
    """
    sh = np.asarray(sh)
    rot = np.asarray(rotation, dtype=np.float64)
    _check_rotation_shape(rot)
    if sh.ndim not in (2, 3):
        raise ValueError(f"sh must have shape (N, K, 3) or (K, 3), got {sh.shape}")
    coeffs = sh[None] if sh.ndim == 2 else sh
    degree = degree_of(coeffs.shape[1])
    dtype = np.float32 if sh.dtype == np.float32 else np.float64
    if rot.ndim == 2:
        out = _apply_matrix(coeffs, rotation_matrix(rot, degree), np.empty(coeffs.shape, dtype))
        return out[0] if sh.ndim == 2 else out
    if sh.ndim == 2:
        coeffs = np.broadcast_to(coeffs, (len(rot),) + coeffs.shape[1:])
    if len(rot) != len(coeffs):
        raise ValueError(f"{len(rot)} rotations for {len(coeffs)} splats")
    return _rotate_each(coeffs, rot, np.empty(coeffs.shape, dtype))


def _apply_matrix(coeffs, d, out):
    """out[n] = d @ coeffs[n] for one block-diagonal (K, K) matrix: BLAS products band by band."""
    degree = degree_of(d.shape[0])

    def work(start, stop):
        w = np.empty((d.shape[0], coeffs.shape[2], stop - start))
        for k in range(len(w)):
            w[k] = coeffs[start:stop, k].T
        for l in range(1, degree + 1):
            band = w[_band_rows(l)]
            band[...] = (d[_band_rows(l), _band_rows(l)] @ band.reshape(2 * l + 1, -1)).reshape(band.shape)
        np.moveaxis(out[start:stop], 0, -1)[...] = w

    in_chunks(len(coeffs), work, _CHUNK)
    return out
