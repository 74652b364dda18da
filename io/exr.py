"""Multi-channel OpenEXR images: R, G, B, A, Z and any extra named channels, float32 or half.

    write_exr("beauty.exr", {"R": r, "G": g, "B": b, "A": a, "Z": depth}, half=False)
    channels = read_exr("beauty.exr")          # {"R": (H,W) float32, ...}

Uses the OpenEXR package (v3 API). Channel names are free-form ("N.x", "albedo.R", ...); EXR files
list them alphabetically, so the order of the dict is not kept. Files are written atomically.
"""

import warnings

import numpy as np

from .common import SplatFileError, SplatFileWarning, atomic_path

HALF_MAX = float(np.finfo(np.float16).max)  # 65504
EXR_MAGIC = b"\x76\x2f\x31\x01"


def _openexr(path):
    try:
        import OpenEXR
    except ImportError:
        raise SplatFileError(path, "EXR needs the OpenEXR package, which this Python lacks") from None
    return OpenEXR


def _checked_channels(path, channels, half):
    """The channels as C-contiguous float32/float16 arrays, or a SplatFileError naming the bad one."""
    if not channels:
        raise SplatFileError(path, "no channels to write")
    out, shape = {}, None
    for name, values in channels.items():
        if not isinstance(name, str) or not name:
            raise SplatFileError(path, f"channel name {name!r} is not a non-empty string")
        a = np.asarray(values)
        if a.ndim != 2 or 0 in a.shape:
            raise SplatFileError(path, f"channel '{name}' has shape {a.shape}, expected a non-empty (H, W)")
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise SplatFileError(path, f"channel '{name}' has shape {a.shape}, other channels {shape}")
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer) or a.dtype == bool):
            raise SplatFileError(path, f"channel '{name}' has dtype {a.dtype}, expected numbers")
        a = a.astype(np.float32)
        if np.isnan(a).any():
            raise SplatFileError(path, f"channel '{name}' holds {int(np.isnan(a).sum())} NaN values")
        if half:
            # Finite values past the half range would silently turn into infinities.
            big = np.isfinite(a) & (np.abs(a) > HALF_MAX)
            if big.any():
                raise SplatFileError(
                    path,
                    f"channel '{name}' holds {int(big.sum())} values beyond the "
                    f"half-float range (|x| > {HALF_MAX:g}); write it as float32",
                )
            a = a.astype(np.float16)
        out[name] = np.ascontiguousarray(a)
    return out


def write_exr(path, channels, half=False, compression="zip", header=None):
    """Write `channels` ({name: (H,W) array}) as a single-part scanline EXR.

    half: store every channel as 16-bit float (values must fit |x| <= 65504) instead of float32.
    compression: "none", "zip", "zips", "piz", "rle", "pxr24", "dwaa", "dwab", "b44" or "zstd"
    (lossless except pxr24, dwa*, b44). header: extra EXR header attributes, e.g. {"comment": "..."}.
    NaN values are refused; infinities are kept (a common "no depth" marker in Z).
    """
    OpenEXR = _openexr(path)
    pixels = _checked_channels(path, channels, half)
    key = "NO_COMPRESSION" if compression == "none" else f"{str(compression).upper()}_COMPRESSION"
    if not hasattr(OpenEXR, key):
        raise SplatFileError(path, f"unknown EXR compression '{compression}'")
    head = {"compression": getattr(OpenEXR, key), "type": OpenEXR.scanlineimage, **(header or {})}
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(head, pixels).write(str(tmp))
        except (RuntimeError, TypeError, ValueError) as exc:
            raise SplatFileError(path, f"OpenEXR could not write the image: {exc}") from exc


def read_exr(path, part=0, nan="raise"):
    """{channel name: (H,W) float32} of one part of an EXR file (half channels widened exactly).

    Unsigned-int channels (object ids) are converted to float32 too, exactly up to 2^24.
    nan: "raise" (a SplatFileError counting them, as write_exr refuses them) or "keep" (with a
    SplatFileWarning) for channels holding NaN; infinities are kept either way.
    """
    if nan not in ("raise", "keep"):
        raise ValueError(f"nan must be 'raise' or 'keep', got {nan!r}")
    OpenEXR = _openexr(path)
    try:
        with open(path, "rb") as f:
            if f.read(4) != EXR_MAGIC:
                raise SplatFileError(path, "not an OpenEXR file (wrong magic number)")
        image = OpenEXR.File(str(path), separate_channels=True)
    except FileNotFoundError:
        raise SplatFileError(path, "no such file") from None
    except OSError as exc:
        raise SplatFileError(path, f"cannot open: {exc.strerror or exc}") from None
    except (RuntimeError, ValueError, TypeError) as exc:  # ValueError includes UnicodeDecodeError
        raise SplatFileError(path, f"OpenEXR could not read the image (truncated or corrupt?): {exc}") from exc
    parts = image.parts
    if not parts:
        raise SplatFileError(path, "OpenEXR found no readable image part (truncated or corrupt?)")
    if not 0 <= part < len(parts):
        raise SplatFileError(path, f"part {part} requested, the file has {len(parts)}")
    out = {}
    for name, channel in parts[part].channels.items():
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise SplatFileError(
                path, f"channel '{name}' is subsampled ({channel.xSampling}x{channel.ySampling}); not supported"
            )
        pixels = channel.pixels
        if pixels is None or pixels.ndim != 2:
            raise SplatFileError(path, f"channel '{name}' has no flat pixel data (deep images are not supported)")
        out[name] = pixels.astype(np.float32)
    _check_nan(path, out, nan)
    return out


def _check_nan(path, channels, policy):
    counts = {name: int(np.isnan(a).sum()) for name, a in channels.items()}
    detail = ", ".join(f"'{name}' {count}" for name, count in counts.items() if count)
    if not detail:
        return
    if policy == "raise":
        raise SplatFileError(path, f"channels hold NaN values ({detail}); read with nan='keep' to go on anyway")
    warnings.warn(f"{path}: channels hold NaN values ({detail}); kept", SplatFileWarning, stacklevel=3)
