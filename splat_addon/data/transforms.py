"""Where splats stand: an object's world matrix, affine maps of whole clouds (orientations, sizes
and SH turn with the centres), and the record of an object's frame that edit/blender_apply.py reads."""

import numpy as np

from .attributes import splat_count
from .keys import FRAME_RECORD


def probe_indices(count):
    """A few splats spread over the cloud whose centres stand for all of them in a frame record."""
    return sorted({0, count // 3, (2 * count) // 3, count - 1}) if count else []


def probe_centres(obj, indices):
    """(k, 3) float64 centres of the splats `indices` of `obj`'s own data (Object Mode)."""
    position = obj.data.attributes["position"].data
    return np.array([position[i].vector for i in indices], dtype=np.float64).reshape(-1, 3)


def remember_frame(obj):
    """Record `obj`'s matrix_basis and probe centres: edit/blender_apply.py tells from them whether a change to
    both was Blender's Apply. Operators that change a splat object's data and transform together call
    this at once, so their own change is not taken for one."""
    count = splat_count(obj.data)
    indices = probe_indices(count)
    obj[FRAME_RECORD] = {
        "basis": np.array(obj.matrix_basis, dtype=np.float64).ravel().tolist(),
        "count": count,
        "probes": indices,
        "centres": probe_centres(obj, indices).ravel().tolist(),
    }


def world_matrix(obj, depsgraph=None):
    """The object's evaluated world matrix as float64 (4,4)."""
    source = obj.evaluated_get(depsgraph) if depsgraph is not None else obj
    return np.array(source.matrix_world, dtype=np.float64)


def snap_matrix(matrix, tol=1e-6):
    """Blender keeps object rotations as float32 Euler angles, so a quarter turn comes back with
    ~4e-8 residue (cos(pi/2) in float32). A linear part within `tol` of a signed axis permutation is
    snapped to it exactly, so axis conversions cancel and unedited splats export bit for bit."""
    matrix = np.array(matrix, dtype=np.float64)
    linear = matrix[:3, :3]
    rounded = np.round(linear)
    is_permutation = (np.abs(rounded).sum(axis=0) == 1).all() and (np.abs(rounded).sum(axis=1) == 1).all()
    if is_permutation and np.abs(linear - rounded).max() <= tol:
        matrix[:3, :3] = rounded
    return matrix


def transform_cloud(cloud, matrix):
    """`cloud` under the affine 4x4 `matrix`; the identity returns the cloud itself, untouched, and
    a pure translation moves the centres only."""
    matrix = snap_matrix(matrix)
    if not np.isfinite(matrix).all():  # the translation-only path below would spread NaN silently
        raise ValueError("transform holds NaN or Inf")
    if np.array_equal(matrix[:3, :3], np.eye(3)) and np.array_equal(matrix[3], [0, 0, 0, 1]):
        if not matrix[:3, 3].any():
            return cloud
        return cloud.replace(positions=cloud.positions.astype(np.float64) + matrix[:3, 3])
    return cloud.transformed(matrix)
