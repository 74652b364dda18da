"""Uncompressed scanline OpenEXR, read with NumPy alone (no OpenEXR package).

Blender's own Python has no EXR reader, and the mesh layer of a SPLATWRIGHT render comes back from
a child Blender as a multilayer EXR it writes uncompressed (codec NONE): one part (Blender 4.2) or
one part per pass (4.3+), FLOAT or HALF channels, one scanline per chunk. This reads exactly that
subset; anything else (compression, tiles, deep data) is refused by name. io/exr.py reads and
writes every EXR through the OpenEXR package.

    channels = read_plain_exr("layer.exr")     # {"ViewLayer.Combined.R": (H,W) float32, ...}
"""

import struct

import numpy as np

from .common import SplatFileError

MAGIC = b"\x76\x2f\x31\x01"
TILED, LONG_NAMES, DEEP, MULTIPART = 0x200, 0x400, 0x800, 0x1000
PIXEL_TYPES = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}


def read_plain_exr(path):
    """{channel name: (H, W) float32} of every part of an uncompressed scanline EXR. Every size the
    headers state is checked against the file before anything is allocated: the pixels a part
    claims, in chunks that do not overlap, must be in the file."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None
    raw = data.tobytes()
    if len(raw) < 8 or raw[:4] != MAGIC:
        raise SplatFileError(path, "not an OpenEXR file (bad magic number)")
    flags = struct.unpack_from("<I", raw, 4)[0]
    if flags & (TILED | DEEP):
        raise SplatFileError(path, "tiled or deep EXR; only scanline images are read here")
    multipart = bool(flags & MULTIPART)
    pos, headers = 8, []
    while True:
        header, pos = _header(path, raw, pos)
        headers.append(header)
        if not multipart or raw[pos : pos + 1] == b"\0":
            pos += multipart
            break
    channels = {}
    for part, header in enumerate(headers):
        if header.get("compression", 0) != 0:
            raise SplatFileError(
                path, f"part {part} is compressed (codec {header['compression']}); only uncompressed EXR is read here"
            )
        x0, y0, x1, y1 = header["dataWindow"]
        width, height = x1 - x0 + 1, y1 - y0 + 1
        line = width * sum(dt.itemsize for _, dt in header["channels"])
        prefix = 4 if multipart else 0
        count = header.get("chunkCount", height)
        # each scanline: an offset in the table, then its own chunk (part number, y, size, pixels)
        if width < 1 or height < 1 or line < 1 or count != height or pos + height * (8 + prefix + 8 + line) > len(raw):
            raise SplatFileError(
                path,
                f"part {part}: a {width} x {height} data window of {len(header['channels'])} channels in "
                f"{count} chunks does not fit the file's {len(raw)} bytes (truncated, empty, or not one "
                "scanline per chunk)",
            )
        offsets = np.frombuffer(raw, "<u8", count, pos).astype(np.int64)
        pos += 8 * count
        channels.update(_scanlines(path, data, raw, offsets, header["channels"], width, height, y0, prefix))
    return channels


def _header(path, raw, pos):
    """One header's attributes we need (channels, compression, dataWindow, chunkCount) and the
    position after its terminating null byte."""
    header = {}
    try:
        while raw[pos] != 0:
            name, pos = _string(raw, pos)
            kind, pos = _string(raw, pos)
            size = struct.unpack_from("<i", raw, pos)[0]
            if not 0 <= size <= len(raw) - pos - 4:
                raise SplatFileError(path, f"EXR header attribute '{name}' of {size} bytes does not fit the file")
            value = raw[pos + 4 : pos + 4 + size]
            pos += 4 + size
            if name == "channels":
                header[name] = _channel_list(path, value)
            elif name == "compression":
                header[name] = value[0]
            elif name == "dataWindow":
                header[name] = struct.unpack("<4i", value)
            elif name == "chunkCount":
                header[name] = struct.unpack("<i", value)[0]
    except SplatFileError:
        raise
    except (IndexError, struct.error, ValueError):
        raise SplatFileError(path, "truncated EXR header") from None
    if "channels" not in header or "dataWindow" not in header:
        raise SplatFileError(path, "EXR header without channels or dataWindow")
    return header, pos + 1


def _string(raw, pos):
    end = raw.index(b"\0", pos)
    return raw[pos:end].decode("utf-8", "replace"), end + 1


def _channel_list(path, value):
    """[(name, dtype)] in file order (alphabetical, as the format requires)."""
    out, pos = [], 0
    while value[pos] != 0:
        name, pos = _string(value, pos)
        pixel_type, _, _, x_sampling, y_sampling = struct.unpack_from("<iB3sii", value, pos)
        pos += 16
        if (x_sampling, y_sampling) != (1, 1) or pixel_type not in PIXEL_TYPES:
            raise SplatFileError(path, f"EXR channel '{name}' is subsampled or of an unknown pixel type")
        out.append((name, PIXEL_TYPES[pixel_type]))
    return out


def _scanlines(path, data, raw, offsets, channel_list, width, height, y0, part_prefix):
    """Every scanline of one part gathered at once: row y's bytes hold each channel's row in turn."""
    line = width * sum(dt.itemsize for _, dt in channel_list)
    ordered = np.sort(offsets)
    if ordered[0] < 0 or ordered[-1] + part_prefix + 8 + line > len(raw):
        raise SplatFileError(path, "EXR chunk table does not fit the file (truncated, or not one scanline per chunk)")
    if (np.diff(ordered) < part_prefix + 8 + line).any():  # overlapping chunks would multiply the file
        raise SplatFileError(path, "EXR chunks overlap; each scanline needs bytes of its own")
    starts = offsets + part_prefix
    ys = data[starts[:, None] + np.arange(8)].view("<i4").astype(np.int64)  # (y, size) of each chunk
    if (ys[:, 1] != line).any() or not np.array_equal(np.sort(ys[:, 0] - y0), np.arange(height)):
        raise SplatFileError(path, "EXR chunks do not hold one uncompressed scanline each")
    first, step = starts[0] + 8, np.diff(starts)
    if len(step) and (step == step[0]).all() and step[0] >= line:  # evenly spaced chunks: one strided view
        rows = np.lib.stride_tricks.as_strided(data[first:], (height, line), (int(step[0]), 1), writeable=False)
    else:
        rows = np.stack([data[s + 8 : s + 8 + line] for s in starts])  # (chunks, line) bytes, chunk by chunk
    image = np.empty((height, line), np.uint8)
    image[ys[:, 0] - y0] = rows
    out, col = {}, 0
    for name, dtype in channel_list:
        size = width * dtype.itemsize
        out[name] = np.ascontiguousarray(image[:, col : col + size]).view(dtype).astype(np.float32)
        col += size
    return out
