"""Image error metrics for comparing renders: float images in [0, 1], (H,W) or (H,W,C)."""

import numpy as np


def psnr(image, reference, peak=1.0):
    """Peak signal-to-noise ratio in dB (inf for identical images)."""
    return psnr_from_mse(np.mean((np.asarray(image, np.float64) - np.asarray(reference, np.float64)) ** 2), peak)


def psnr_from_mse(mse, peak=1.0):
    """PSNR in dB of a mean squared error (inf for 0), for errors pooled over several images."""
    return float("inf") if mse == 0 else float(10.0 * np.log10(peak * peak / mse))


def _box_blur(a, r):
    """Mean over a (2r+1)^2 window with edge replication, via summed-area tables."""
    p = np.pad(a, ((r + 1, r), (r + 1, r)) + ((0, 0),) * (a.ndim - 2), mode="edge")
    s = p.cumsum(0).cumsum(1)
    w = 2 * r + 1
    return (s[w:, w:] - s[:-w, w:] - s[w:, :-w] + s[:-w, :-w]) / (w * w)


def ssim(image, reference, peak=1.0, radius=3):
    """Mean structural similarity (Wang et al. 2004 constants) with a (2r+1)^2 box window."""
    x, y = np.asarray(image, np.float64), np.asarray(reference, np.float64)
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    mx, my = _box_blur(x, radius), _box_blur(y, radius)
    vx = _box_blur(x * x, radius) - mx * mx
    vy = _box_blur(y * y, radius) - my * my
    cxy = _box_blur(x * y, radius) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(s.mean())
