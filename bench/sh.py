"""SH rotation speed against the error it buys.

* One rotation per splat (the articulation hot path), 1M splats of degree 3: the closed form
  (z-y-z Euler angles, D = Z(a) X^T Z(b) X Z(g)) against the straightforward baseline, a least-squares
  fit of the rotated function sampled at 32 directions (vectorised over splats, in chunks); and its
  compiled loop (one splat at a time) against its NumPy path (band by band over rows of splats).
* One rotation for every splat (an object transform): one Wigner-D matrix applied with BLAS against
  a plain einsum with the fitted matrix.
* Covariance transform under a general affine map, needles with axis ratios up to 1e6: SVD of the
  factor A R S (ours) against eigh of A Sigma A^T (decompose_covariances), with the error of the
  thinnest axis.

Error: max |colour difference| against brute force, evaluate(sh, R^T d) in float64, at random d.
"""

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import Row, Timing, print_rows, timeit  # noqa: E402

from splatwright.core import geometry, sh  # noqa: E402

SAMPLES = 32


def _paired(baseline, ours, repeat):
    """Baseline and ours timed alternately, so both meet the same load on a shared machine."""
    pairs = [
        (timeit(baseline, repeat=1, warmup=int(i == 0)), timeit(ours, repeat=1, warmup=int(i == 0)))
        for i in range(repeat)
    ]
    return tuple(_combine([p[side].median for p in pairs]) for side in (0, 1))


def _combine(times):
    return Timing(statistics.median(times), (max(times) - min(times)) / 2, len(times))


def fit_rotated_samples(coeffs, rotations, chunk=1 << 14):
    """Baseline: sample f(R^T s_j) at fixed directions s_j and fit coefficients by least squares."""
    degree = sh.degree_of(coeffs.shape[1])
    dirs = sh._sphere_samples(SAMPLES)
    fit = np.linalg.pinv(sh.basis(dirs, degree))  # (K, samples)
    out = np.empty_like(coeffs)
    for start in range(0, len(coeffs), chunk):
        turned = dirs @ rotations[start : start + chunk]  # rows R^T s_j, (n, samples, 3)
        values = sh.basis(turned, degree) @ coeffs[start : start + chunk].astype(np.float64)
        out[start : start + chunk] = fit @ values
    return out


def colour_error(rotated, coeffs, rotations, rng, count=20000):
    pick = rng.choice(len(coeffs), size=min(count, len(coeffs)), replace=False)
    d = rng.normal(size=(len(pick), 3))
    r = np.broadcast_to(rotations, (len(coeffs), 3, 3))[pick]
    want = sh.evaluate(coeffs[pick].astype(np.float64), np.einsum("nji,nj->ni", r, d))
    return float(np.abs(sh.evaluate(rotated[pick].astype(np.float64), d) - want).max())


def run(quick=False):
    n = 100_000 if quick else 1_000_000
    repeat = 3 if quick else 5
    rng = np.random.default_rng(0)
    coeffs = rng.normal(0, 0.3, (n, 16, 3)).astype(np.float32)
    rotations = geometry.quaternions_to_matrices(rng.normal(size=(n, 4)))
    rows = []

    base, ours = _paired(lambda: fit_rotated_samples(coeffs, rotations), lambda: sh.rotate(coeffs, rotations), repeat)
    rows.append(
        Row(
            "sh",
            f"rotate, one rotation per splat, {n:,} splats, degree 3",
            ours,
            base,
            error={
                "max colour error": colour_error(sh.rotate(coeffs, rotations), coeffs, rotations, rng),
            },
            extra={
                "baseline": f"least squares on {SAMPLES} rotated samples",
                "baseline error": _fmt(colour_error(fit_rotated_samples(coeffs, rotations), coeffs, rotations, rng)),
                "CPU s, all threads": _fmt(_cpu_seconds(lambda: sh.rotate(coeffs, rotations))),
            },
        )
    )

    numpy_way = lambda: sh._rotate_each_numpy(coeffs, rotations, np.empty_like(coeffs))  # noqa: E731
    base, ours = _paired(numpy_way, lambda: sh.rotate(coeffs, rotations), repeat)
    rows.append(
        Row(
            "sh",
            f"rotate, one rotation per splat, {n:,} splats, degree 3: compiled",
            ours,
            base,
            error={"max difference from the NumPy path": np.abs(sh.rotate(coeffs, rotations) - numpy_way()).max()},
            extra={
                "baseline": "the NumPy path (band by band over rows of splats)",
                "CPU s, all threads": _fmt(_cpu_seconds(lambda: sh.rotate(coeffs, rotations))),
            },
        )
    )

    one = rotations[0]
    fitted = sh.fitted_rotation_matrix(one, 3)
    plain = lambda: np.einsum("kj,njc->nkc", fitted, coeffs.astype(np.float64)).astype(np.float32)  # noqa: E731
    base, ours = _paired(plain, lambda: sh.rotate(coeffs, one), repeat)
    rows.append(
        Row(
            "sh",
            f"rotate, one rotation for all, {n:,} splats, degree 3",
            ours,
            base,
            error={
                "max colour error": colour_error(sh.rotate(coeffs, one), coeffs, one, rng),
            },
            extra={
                "baseline": "einsum with the fitted matrix",
                "baseline error": _fmt(colour_error(plain(), coeffs, one, rng)),
            },
        )
    )

    rows.append(_covariance_row(n // 4, repeat, rng))
    return rows


def _covariance_row(n, repeat, rng):
    """Needles 1e-6 thin: SVD of A R S (ours) against eigh of A Sigma A^T (the obvious way)."""
    big = np.exp(rng.uniform(np.log(1e-2), np.log(1e3), n))
    scales = np.stack([big, big * 1e-6, big * rng.uniform(1e-6, 1, n)], axis=1)
    q = rng.normal(size=(n, 4))
    a = geometry.quaternions_to_matrices(rng.normal(size=4)) @ np.diag([1.0, 2.0, 0.5])
    det = np.abs(np.linalg.det(a)) * scales.prod(axis=1)  # exact product of the new scales

    def thin_axis_error(scales_out):
        # The product of the three new scales must equal |det A| * the old product.
        return float(np.abs(np.prod(scales_out, axis=1) / det - 1).max())

    eigh_way = lambda: geometry.decompose_covariances(a @ geometry.covariances(q, scales) @ a.T)  # noqa: E731
    ours_way = lambda: geometry.transform_covariances(a, q, scales)  # noqa: E731
    base, ours = _paired(eigh_way, ours_way, repeat)
    return Row(
        "sh",
        f"covariance transform, general affine, {n:,} needles (axis ratio 1e6)",
        ours,
        base,
        error={
            "thin-axis relative error": thin_axis_error(ours_way()[1]),
        },
        extra={"baseline": "eigh of A Sigma A^T", "baseline error": _fmt(thin_axis_error(eigh_way()[1]))},
    )


def _cpu_seconds(fn, repeat=3):
    """Median CPU time of fn() summed over all threads: on a busy shared machine wall time mostly
    measures the neighbours, CPU time what the work costs."""
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return statistics.median(times)


def _fmt(value):
    return f"{value:.3g}"


if __name__ == "__main__":
    print_rows(run(quick="--quick" in sys.argv))
