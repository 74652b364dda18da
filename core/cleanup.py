"""Clean-up and grading of captured splats: crop to a volume, drop splats by size, grade colours.

Pruning by opacity and by visibility lives in core.economy (`opacity_mask`, `contributions`); what a
change saves and costs is `economy.change_report`.

Crop: `inside_box` keeps splat centres inside an oriented box (a 4x4 matrix taking the unit cube
[-1, 1]^3 to it, as a Blender Empty's cube); `inside_mesh` keeps those inside a closed triangle mesh
by the generalised winding number (Jacobson et al. 2013): the solid angle of every triangle seen from
the point, summed, over 4 pi; inside where it is above 1/2, whichever way the faces wind, and robust
to small holes and overlaps, where ray parity flips on every stray hit.

Grading: every grade is a linear map c -> M c of the colour the splats show, applied in the SH
colours' own space (display sRGB values, as 3DGS stores them). The colour of a splat seen from d is
0.5 + sum_k Y_k(d) sh_k, so the map is exactly sh_k -> M sh_k for every band k (DC included) plus
(M - I) 0.5 / C0 added to the DC term: rendered colours are blended linearly, so grading the splats
then rendering equals grading the render wherever no colour falls below 0 (where the renderer clamps).
"""

import math

import numpy as np

from .sh import C0

# Rec. 709 luma: the grey that saturation keeps and white balance preserves
LUMA = np.array([0.2126, 0.7152, 0.0722])
_CHUNK_PAIRS = 1 << 22  # (point, triangle) pairs per winding-number chunk


class CleanupError(ValueError):
    """A crop volume or a grade that cannot be used; the message says which and why."""


# crop -----------------------------------------------------------------------------------------------


def inside_box(points, box_matrix):
    """(N,) bool: points inside the box that `box_matrix` (4x4) makes of the cube [-1, 1]^3."""
    box_matrix = np.asarray(box_matrix, np.float64)
    if not np.isfinite(box_matrix).all() or abs(np.linalg.det(box_matrix[:3, :3])) < 1e-300:
        raise CleanupError("the crop box has a zero size or a transform holding NaN or Inf")
    inverse = np.linalg.inv(box_matrix)
    local = np.asarray(points, np.float64) @ inverse[:3, :3].T + inverse[:3, 3]
    return (np.abs(local) <= 1.0).all(axis=1)


def winding_numbers(points, vertices, triangles):
    """(N,) generalised winding numbers of a triangle mesh at points: about +-1 inside a closed
    surface (the sign follows the faces' winding), 0 outside. Chunks of points times all triangles."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    corners = vertices[triangles]  # (F,3,3)
    out = np.zeros(len(points))
    step = max(1, _CHUNK_PAIRS // max(len(triangles), 1))
    for start in range(0, len(points), step):
        rel = corners[None] - points[start : start + step, None, None]  # (n,F,3,3)
        a, b, c = rel[:, :, 0], rel[:, :, 1], rel[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("nfi,nfi->nf", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("nfi,nfi->nf", a, b) * lc
            + np.einsum("nfi,nfi->nf", a, c) * lb
            + np.einsum("nfi,nfi->nf", b, c) * la
        )
        out[start : start + step] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4.0 * math.pi)
    return out


def inside_mesh(points, vertices, triangles):
    """(N,) bool: points inside the closed triangle mesh (|winding number| > 1/2); points outside its
    bounding box are not tested."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles).reshape(-1, 3)
    if len(triangles) == 0:
        raise CleanupError("the crop mesh has no faces: it encloses no volume")
    if not np.isfinite(vertices).all():
        raise CleanupError("the crop mesh has vertices holding NaN or Inf")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    near = np.flatnonzero(((points >= lo) & (points <= hi)).all(axis=1))
    inside = np.zeros(len(points), bool)
    inside[near] = np.abs(winding_numbers(points[near], vertices, triangles)) > 0.5
    return inside


# size -----------------------------------------------------------------------------------------------


def size_mask(cloud, min_size=0.0, max_size=math.inf, scale=1.0):
    """Splats whose largest standard deviation, times `scale` (an object's scale), lies in
    [min_size, max_size]: drops needle-thin specks below and huge floaters above."""
    if not 0.0 <= min_size <= max_size:
        raise CleanupError(f"sizes must satisfy 0 <= min <= max, got {min_size!r} and {max_size!r}")
    largest = np.exp(cloud.log_scales.astype(np.float64).max(axis=1)) * scale
    return (largest >= min_size) & (largest <= max_size)


# grading --------------------------------------------------------------------------------------------


def grade_matrix(exposure=0.0, saturation=1.0, hue=0.0, white=(1.0, 1.0, 1.0)):
    """The 3x3 colour map of a grade, applied in this order: white balance (the colour `white`
    becomes the grey of its own luma), saturation (1 keeps, 0 makes grey by Rec. 709 luma), hue
    rotation (`hue` radians about the grey axis), exposure (a gain of 2^exposure)."""
    white = np.asarray(white, np.float64)
    if white.shape != (3,) or not (white > 0).all() or not np.isfinite(white).all():
        raise CleanupError(f"the white balance colour must be three positive numbers, got {white!r}")
    if not all(np.isfinite(x) for x in (exposure, saturation, hue)):
        raise CleanupError("exposure, saturation and hue must be finite")
    balance = np.diag(LUMA @ white / white)
    saturate = saturation * np.eye(3) + (1.0 - saturation) * np.outer(np.ones(3), LUMA)
    axis = np.ones(3) / math.sqrt(3.0)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + math.sin(hue) * cross + (1.0 - math.cos(hue)) * cross @ cross
    return (2.0**exposure) * turn @ saturate @ balance


def grade_sh(sh, matrix, offset=(0.0, 0.0, 0.0)):
    """SH coefficients (N,K,3) of splats whose every colour c becomes matrix @ c + offset: each band
    turned by the matrix, the DC term also moved by ((matrix - I) 0.5 + offset) / C0. float32 out."""
    matrix = np.asarray(matrix, np.float64)
    out = np.asarray(sh, np.float64) @ matrix.T
    out[:, 0] += ((matrix - np.eye(3)) @ np.full(3, 0.5) + np.asarray(offset, np.float64)) / C0
    return out.astype(np.float32)


def graded(cloud, matrix, offset=(0.0, 0.0, 0.0)):
    """`cloud` with its colours graded (see grade_sh); the identity returns the cloud itself."""
    if np.array_equal(matrix, np.eye(3)) and not np.any(offset):
        return cloud
    return cloud.replace(sh=grade_sh(cloud.sh, matrix, offset))
