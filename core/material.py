"""The material a splat carries beside its own colour, for relighting: a scene-linear albedo (the
Base Color), the unit surface normal in the cloud's world frame, and the Principled BSDF's roughness
and metallic. They live in the cloud's extras under fixed names, so selection, joining, copies and
every format that keeps extras keep them too; the splat's SH colour stays the unlit (baked or
captured) look."""

import numpy as np

from .arrays import ArrayLike, Floats, Positions
from .splats import NORMAL_EXTRAS, SplatCloud

ALBEDO = "albedo"
NORMALS = NORMAL_EXTRAS  # ("nx", "ny", "nz"): the PLY convention io/ply.py reads and writes as normals
ROUGHNESS = "roughness"
METALLIC = "metallic"
# Blender's Principled BSDF defaults, used where a cloud has no value of its own.
DEFAULT_ROUGHNESS = 0.5
DEFAULT_METALLIC = 0.0
KEYS = (ALBEDO, *NORMALS, ROUGHNESS, METALLIC)


def normals(cloud: SplatCloud) -> Positions | None:
    """(N,3) float64 unit normals, or None when the cloud has none (all three of nx, ny, nz)."""
    columns = normal_columns(cloud)
    return None if columns is None else np.stack(columns, axis=1)


def normal_columns(cloud: SplatCloud) -> tuple[Floats, Floats, Floats] | None:
    """The normals as three (N,) float64 columns (nx, ny, nz), or None: what a compiled loop reads,
    with no (N,3) copy (float64 columns are passed as they are)."""
    if not all(k in cloud.extras for k in NORMALS):
        return None
    n = len(cloud)
    nx, ny, nz = (np.ascontiguousarray(cloud.extras[k].reshape(n), np.float64) for k in NORMALS)
    return nx, ny, nz


def albedo(cloud: SplatCloud) -> Floats | None:
    """(N,3) float64 scene-linear albedo, or None when the cloud has none."""
    values = cloud.extras.get(ALBEDO)
    return None if values is None else values.astype(np.float64).reshape(len(cloud), 3)


def _scalar(cloud: SplatCloud, key: str, default: float) -> Floats:
    values = cloud.extras.get(key)
    if values is None:
        return np.full(len(cloud), default)
    return values.astype(np.float64).reshape(len(cloud))


def roughness(cloud: SplatCloud) -> Floats:
    """(N,) float64 roughness in [0,1]; DEFAULT_ROUGHNESS where the cloud has none."""
    return _scalar(cloud, ROUGHNESS, DEFAULT_ROUGHNESS)


def metallic(cloud: SplatCloud) -> Floats:
    """(N,) float64 metallic in [0,1]; DEFAULT_METALLIC where the cloud has none."""
    return _scalar(cloud, METALLIC, DEFAULT_METALLIC)


def has_material(cloud: SplatCloud) -> bool:
    """True when the cloud carries both an albedo and normals (enough to shade it)."""
    return ALBEDO in cloud.extras and all(k in cloud.extras for k in NORMALS)


def carried(cloud: SplatCloud) -> np.ndarray:
    """(N,) bool: the splats that carry a material (finite albedo, and a finite normal of non-zero
    length: Blender's own Join fills the normals of splats joined from an object without them with
    zeros); none without one."""
    if not has_material(cloud):
        return np.zeros(len(cloud), bool)
    nx, ny, nz = normal_columns(cloud)  # column by column: reductions along rows of three cost more
    with np.errstate(invalid="ignore", over="ignore"):
        length2 = nx * nx + ny * ny + nz * nz
    finite = np.isfinite(cloud.extras[ALBEDO].reshape(len(cloud), 3))  # as stored: no float64 copy
    return finite[:, 0] & finite[:, 1] & finite[:, 2] & np.isfinite(length2) & (length2 > 1e-12)


def unit_normals(values: ArrayLike) -> Floats:
    """(N,3) float64 rows scaled to unit length; ValueError for non-finite or zero-length rows."""
    values = np.asarray(values, dtype=np.float64)
    length = np.linalg.norm(values, axis=1) if values.size else np.zeros(len(values))
    bad = ~np.isfinite(length) | (length < 1e-30)
    if bad.any():
        raise ValueError(f"{int(bad.sum())} normals are zero-length or not finite")
    return values / length[:, None]


def _checked(name: str, values: ArrayLike, shape: tuple[int, ...], low: float, high: float) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.shape != shape:
        raise ValueError(f"{name} has shape {values.shape}, expected {shape}")
    if not np.isfinite(values).all():
        rows = (~np.isfinite(values)).reshape(len(values), -1).any(axis=1)
        raise ValueError(f"{name} has {int(rows.sum())} non-finite rows")
    if values.size and (values.min() < low or values.max() > high):
        raise ValueError(f"{name} lies in [{values.min():g}, {values.max():g}], expected [{low:g}, {high:g}]")
    return values.astype(np.float32)


def with_material(
    cloud: SplatCloud,
    *,
    albedo: ArrayLike | None = None,
    normals: ArrayLike | None = None,
    roughness: ArrayLike | None = None,
    metallic: ArrayLike | None = None,
) -> SplatCloud:
    """A new cloud whose extras carry the given material parts (others kept as they are): albedo
    (N,3) in [0,1] scene-linear, normals (N,3) any non-zero length (stored unit), roughness and
    metallic (N,) in [0,1] (a scalar is broadcast). ValueError for a wrong shape or value."""
    n = len(cloud)
    extras = dict(cloud.extras)
    if albedo is not None:
        extras[ALBEDO] = _checked("albedo", albedo, (n, 3), 0.0, 1.0)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != (n, 3):
            raise ValueError(f"normals have shape {normals.shape}, expected {(n, 3)}")
        unit = unit_normals(normals).astype(np.float32)
        extras.update({k: unit[:, i].copy() for i, k in enumerate(NORMALS)})
    for key, values in ((ROUGHNESS, roughness), (METALLIC, metallic)):
        if values is not None:
            values = np.broadcast_to(np.asarray(values, dtype=np.float64), (n,))
            extras[key] = _checked(key, values, (n,), 0.0, 1.0)
    return cloud.replace(extras=extras)
