"""Surface normals of splats estimated from their shapes, for relighting captured splats.

A splat that trained onto a surface flattens along it: its shortest axis (the column of its rotation
matrix belonging to its smallest scale) is the surface normal up to sign. The sign comes from who
saw the surface: captured splats were seen from the capture's cameras, so the normal faces them;
without cameras it points away from the cloud's centre (right for convex, closed things only).
A splat whose two smallest scales are alike has no preferred axis: `roundness` says how far to
trust each normal (TOO_ROUND and above: not at all).
"""

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import geometry, material
from . import render as rendering
from .arrays import ArrayLike, Floats, Mask, Positions
from .camera import Camera
from .splats import SplatCloud, bad_rows

# roundness = shortest / middle scale. Disturbing splat covariances as training does (bench/normals.py,
# "roundness" rows) turns the shortest axis by a median 5 deg (p90 10) at 0.1 to 0.5, 9 (p90 18) at
# 0.7, and 25 (p90 58) at 0.9: past 0.7 the axis is mostly noise.
TOO_ROUND = 0.7
# Orientation rules with cameras (bench/normals.py chose the default by flip rate on mesh-made splats).
RULES = ("vote", "head-on", "nearest")
DEFAULT_RULE = "vote"
# Visibility renders are this many pixels on their longer side: the depth test needs no full-size
# image (bench/normals.py: 192 and 256 px flipped the same splats). A splat's largest blending weight
# was no test: a closed surface of mesh-made splats lets through enough light (weights over 1/255)
# that the far side of a sphere counted as seen, and the vote flipped every normal.
VISIBILITY_SIZE = 192
DEPTH_SIGMAS = 1.0  # bench/normals.py: at 3 the striped cup's 5 mm walls show through (31% flipped), at 1 2.2%


@dataclass(frozen=True)
class NormalStats:
    """Angular error of estimated normals against true ones, in degrees (signed: a flipped normal
    counts as its full angle, up to 180); `flips` is the share pointing away (angle over 90)."""

    median: float
    p90: float
    mean: float
    flips: float
    count: int

    def __str__(self) -> str:
        return (
            f"median {self.median:.3g} deg, p90 {self.p90:.3g} deg, mean {self.mean:.3g} deg, "
            f"flips {100 * self.flips:.3g}% of {self.count}"
        )


def _checked(cloud: SplatCloud) -> None:
    """ValueError for a cloud whose normals cannot be estimated: no splats, or values that are not
    finite in the fields a normal depends on."""
    if len(cloud) == 0:
        raise ValueError("cannot estimate normals of an empty splat cloud")
    bad = {name: int(bad_rows(name, getattr(cloud, name)).sum()) for name in ("positions", "rotations", "log_scales")}
    bad = {name: count for name, count in bad.items() if count}
    if bad:
        found = ", ".join(f"{count} with non-finite {name}" for name, count in bad.items())
        raise ValueError(f"cannot estimate normals: {found} (drop them first, e.g. cloud[cloud.finite_mask()])")


def _sorted_axes(cloud: SplatCloud) -> tuple[Floats, Floats]:
    """The rotation matrices (N,3,3) and the order of each splat's scales, smallest first (N,3)."""
    return geometry.quaternions_to_matrices(cloud.rotations), np.argsort(cloud.log_scales, axis=1, kind="stable")


def shortest_axes(cloud: SplatCloud) -> Positions:
    """(N,3) float64 unit vectors along each splat's shortest axis, sign as its rotation gives it."""
    matrices, order = _sorted_axes(cloud)
    return np.take_along_axis(matrices, order[:, None, :1], axis=2)[..., 0]


def roundness(cloud: SplatCloud) -> Floats:
    """(N,) float64 in [0, 1]: each splat's shortest scale over its middle one. 0 is a flat disc whose
    normal is sure; 1 has two equal smallest axes and no normal at all (TOO_ROUND: not to be trusted)."""
    ordered = np.sort(cloud.log_scales.astype(np.float64), axis=1)
    with np.errstate(invalid="ignore"):  # -inf - -inf: two zero scales, as round as can be
        ratio = np.exp(ordered[:, 0] - ordered[:, 1])
    return np.where(np.isnan(ratio), 1.0, ratio)


def too_round(cloud: SplatCloud) -> Mask:
    """(N,) True for splats too round for their shortest axis to mean a surface normal."""
    return roundness(cloud) >= TOO_ROUND


def robust_centre(positions: Positions) -> Floats:
    """(3,) the per-axis median of the positions: floaters far out do not pull it."""
    return np.median(np.asarray(positions, dtype=np.float64), axis=0)


def estimate_normals(
    cloud: SplatCloud,
    *,
    centre: ArrayLike | None = None,
    cameras: "ArrayLike | Camera | Sequence[Camera] | None" = None,
    rule: str = DEFAULT_RULE,
) -> Positions:
    """(N,3) float32 unit normals: each splat's shortest axis, oriented.

    cameras: camera centres (C,3), or core Cameras, which also say which splats each camera saw
    (a small render of the cloud through it, see visibility). The normal faces the cameras by
    `rule`: "vote" (the default: the sign of the sum over cameras of the cosine to each camera,
    weighted by visibility), "head-on" (towards the camera that sees it most nearly along the
    axis) or "nearest" (towards the nearest camera that sees it). Splats no camera saw, and every
    splat without cameras, point away from `centre` (default: robust_centre of the positions).
    ValueError for an empty cloud, non-finite positions, rotations or log-scales, or bad cameras.
    """
    _checked(cloud)
    if rule not in RULES:
        raise ValueError(f"unknown orientation rule {rule!r}; expected one of {RULES}")
    axes = shortest_axes(cloud)
    positions = cloud.positions.astype(np.float64)
    centre = robust_centre(positions) if centre is None else _point(centre, "centre")
    sign = _away_from(axes, positions, centre)
    if cameras is not None:
        centres, seen = _camera_centres(cloud, cameras)
        towards = _towards_cameras(axes, positions, centres, seen, rule)
        sign = np.where(towards != 0, towards, sign)
    return (axes * sign[:, None]).astype(np.float32)


def _point(value: ArrayLike, name: str) -> Floats:
    point = np.asarray(value, dtype=np.float64)
    if point.shape != (3,) or not np.isfinite(point).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return point


def _away_from(axes: Positions, positions: Positions, centre: Floats) -> Floats:
    """(N,) +-1: the sign that points each axis away from `centre` (+1 for a splat at the centre)."""
    return np.where(np.einsum("ij,ij->i", axes, positions - centre) < 0, -1.0, 1.0)


def _camera_centres(cloud: SplatCloud, cameras) -> tuple[Floats, Mask | None]:
    """Camera centres (C,3) and, for core Cameras, visibility (N,C) (None: every camera sees all)."""
    if isinstance(cameras, Camera):
        cameras = [cameras]
    if isinstance(cameras, (list, tuple)) and cameras and all(isinstance(c, Camera) for c in cameras):
        return np.array([c.center for c in cameras], dtype=np.float64), visibility(cloud, cameras)
    centres = np.asarray(cameras, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 3 or not len(centres) or not np.isfinite(centres).all():
        raise ValueError(f"cameras must be core Cameras or finite camera centres (C,3), got shape {centres.shape}")
    return centres, None


def visibility(cloud: SplatCloud, cameras: Sequence[Camera], size: int = VISIBILITY_SIZE) -> Mask:
    """(N,C) bool: whether each camera saw each splat's centre. A depth test against a render of the
    cloud through the camera scaled to `size` pixels on its longer side: a centre inside the image
    and the clip range is seen where the pixel it falls in is mostly empty or its rendered depth is
    no nearer than the centre by more than DEPTH_SIGMAS of the splat's largest sigma plus two
    pixels' footprint (the surface the splat belongs to blurs the depth by about that much)."""
    positions = cloud.positions.astype(np.float64)
    reach = DEPTH_SIGMAS * np.exp(cloud.log_scales.astype(np.float64).max(axis=1))
    shapes = rendering.Shapes(cloud)
    seen = np.zeros((len(cloud), len(cameras)), bool)
    for k, camera in enumerate(cameras):
        camera = _scaled(camera, size)
        result = rendering.render(cloud, camera, background=None, shapes=shapes)
        pixels, z = camera.project(positions)
        with np.errstate(invalid="ignore"):
            inside = (z > camera.near) & (z <= camera.far) & (pixels >= 0).all(axis=1)
            inside &= (pixels[:, 0] < camera.width) & (pixels[:, 1] < camera.height)
        col, row = (np.where(inside, np.floor(pixels[:, i]), 0).astype(np.int64) for i in (0, 1))
        depth, alpha = result.depth[row, col], result.alpha[row, col]
        footprint = 2.0 / camera.fx * (1.0 if camera.is_orthographic else np.maximum(z, 0.0))
        seen[:, k] = inside & ((alpha < 0.5) | (z <= depth + reach + footprint))
    return seen


def _scaled(camera: Camera, size: int) -> Camera:
    """The camera with its image scaled so its longer side is at most `size` pixels."""
    factor = min(1.0, size / max(camera.width, camera.height))
    if factor == 1.0:
        return camera
    width, height = max(1, round(camera.width * factor)), max(1, round(camera.height * factor))
    sx, sy = width / camera.width, height / camera.height
    return camera.with_(
        width=width, height=height, fx=camera.fx * sx, fy=camera.fy * sy, cx=camera.cx * sx, cy=camera.cy * sy
    )


def _towards_cameras(axes: Positions, positions: Positions, centres: Floats, seen: Mask | None, rule: str) -> Floats:
    """(N,) +-1 facing the cameras by `rule`, 0 where no camera saw the splat. One camera at a time
    (N values each), so memory stays that of a few per-splat arrays."""
    n = len(axes)
    vote, best, pick = np.zeros(n), np.full(n, -np.inf), np.zeros(n)
    for k, c in enumerate(centres):
        offset = c - positions
        distance = np.linalg.norm(offset, axis=1)
        cosine = np.einsum("ij,ij->i", axes, offset) / np.maximum(distance, 1e-30)
        weight = np.ones(n) if seen is None else seen[:, k].astype(np.float64)
        if rule == "vote":
            vote += weight * cosine
            continue
        score = np.abs(cosine) if rule == "head-on" else -distance
        better = (weight > 0) & (score > best)
        best = np.where(better, score, best)
        pick = np.where(better, np.sign(cosine), pick)
    return np.sign(vote) if rule == "vote" else pick


def angular_error(estimated: ArrayLike, true: ArrayLike) -> NormalStats:
    """Angles between estimated and true normals (N,3) (any non-zero lengths), in degrees, signed:
    a flipped normal counts as up to 180 degrees and as a flip. ValueError for mismatched shapes,
    no normals, or non-finite or zero-length rows."""
    a, b = (np.asarray(v, dtype=np.float64) for v in (estimated, true))
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or not len(a):
        raise ValueError(f"need two (N,3) arrays of normals with N > 0, got shapes {a.shape} and {b.shape}")
    la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    bad = ~(np.isfinite(la) & np.isfinite(lb) & (la > 0) & (lb > 0))
    if bad.any():
        raise ValueError(f"{int(bad.sum())} normals are zero-length or not finite")
    # atan2 of |cross| and dot keeps small angles exact, where arccos of a dot near 1 loses them.
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b)))
    return NormalStats(
        median=float(np.median(angle)),
        p90=float(np.percentile(angle, 90)),
        mean=float(angle.mean()),
        flips=float((angle > 90.0).mean()),
        count=len(angle),
    )


def with_estimated_normals(
    cloud: SplatCloud,
    *,
    centre: ArrayLike | None = None,
    cameras: "ArrayLike | Camera | Sequence[Camera] | None" = None,
    rule: str = DEFAULT_RULE,
) -> SplatCloud:
    """The cloud with estimate_normals' normals stored as its material normals (core.material)."""
    found = estimate_normals(cloud, centre=centre, cameras=cameras, rule=rule)
    return material.with_material(cloud, normals=found)
