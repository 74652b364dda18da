"""antimatter15 `.splat`: 32 bytes per splat, no header, no SH beyond the DC colour.

    position  float32 x3   (as stored in the model: no axis change, like the 3DGS PLY it came from)
    scale     float32 x3   linear (exp of the model's log scales)
    colour    uint8 x4     R, G, B = (0.5 + C0 * DC) * 255, A = sigmoid(opacity) * 255
    rotation  uint8 x4     w, x, y, z of the normalised quaternion as q * 128 + 128

Lossy: colour, opacity and rotation are 8 bits, view-dependent SH is dropped (a warning says so).
Values are rounded to nearest and clamped; a reader decodes A / 255, (R / 255 - 0.5) / C0 and
(q - 128) / 128 (the quaternion is left unnormalised, as the model stores quaternions).
"""

import warnings

import numpy as np

from ..core import SplatCloud, geometry
from ..core import sh as shmod
from ..core.splats import logit
from .common import SplatFileError, SplatFileWarning, apply_nonfinite_policy, atomic_write, log_scales_from_linear

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
assert RECORD.itemsize == 32


def file_size(count, sh_degree=0):
    """Bytes of the file write() makes: one record per splat, whatever the SH degree (DC only)."""
    return count * RECORD.itemsize


def to_u8(values):
    """Round to nearest and clamp to 0..255 (NaN -> 0)."""
    return np.clip(np.rint(np.nan_to_num(values, nan=0.0)), 0, 255).astype(np.uint8)


def read(path, nonfinite="raise"):
    """Read a .splat file into a SplatCloud (SH degree 0)."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise SplatFileError(path, f"cannot open: {exc.strerror or exc}") from None
    if len(data) % RECORD.itemsize:
        raise SplatFileError(
            path, f"{len(data)} bytes is not a whole number of 32-byte splats (truncated, or not a .splat file)"
        )
    rec = data.view(RECORD)
    notes = []
    rgba = rec["rgba"].astype(np.float64) / 255.0
    cloud = SplatCloud(
        positions=rec["position"],
        rotations=(rec["rotation"].astype(np.float32) - 128.0) / 128.0,
        log_scales=log_scales_from_linear(rec["scale"], notes),
        opacity_logits=logit(rgba[:, 3]),
        sh=shmod.rgb_to_dc(rgba[:, :3])[:, None, :],
    )
    if notes:
        warnings.warn(f"{path}: " + "; ".join(notes), SplatFileWarning, stacklevel=2)
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


def encode(cloud):
    """The (N,) record array of a cloud."""
    rec = np.empty(len(cloud), RECORD)
    rec["position"] = cloud.positions
    with np.errstate(over="ignore"):
        rec["scale"] = np.exp(cloud.log_scales.astype(np.float64))
    rgba = np.empty((len(cloud), 4))
    rgba[:, :3] = shmod.dc_to_rgb(cloud.sh[:, 0])
    rgba[:, 3] = cloud.opacities
    rec["rgba"] = to_u8(rgba * 255.0)
    rec["rotation"] = to_u8(geometry.normalize_quaternions(cloud.rotations) * 128.0 + 128.0)
    return rec


def write(path, cloud, nonfinite="raise"):
    """Write a .splat file; view-dependent SH (degree > 0) and extras are dropped with a warning."""
    cloud = apply_nonfinite_policy(path, cloud, nonfinite, "write")
    if cloud.extras:
        warnings.warn(
            f"{path}: .splat has no room for extras; {sorted(cloud.extras)} not written", SplatFileWarning, stacklevel=2
        )
    if cloud.sh_degree > 0 and np.any(cloud.sh[:, 1:]):
        warnings.warn(
            f"{path}: .splat stores the DC colour only; SH degree {cloud.sh_degree} view-dependent colour dropped",
            SplatFileWarning,
            stacklevel=2,
        )
    rec = encode(cloud)
    with atomic_write(path) as f:
        f.write(np.ascontiguousarray(rec).data)  # not tofile: it loses a full disk's error on small writes
