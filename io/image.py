"""Writing rendered images: 8-bit PNG or float EXR with R, G, B, A and Z.

    write_image("frame.png", result)     # a core.render.RenderResult
    write_image("frame.exr", {"color": rgb, "alpha": a, "depth": z})
    write_image("mask.png", gray)         # or a bare (H,W), (H,W,3) or (H,W,4) array

Colours are display sRGB in [0, 1]. A render made with background=None is transparent: its colour
is premultiplied by alpha, so PNG (which stores straight alpha) gets colour / alpha and an alpha
channel, while EXR (premultiplied by convention) gets the colour as it is. A render over a
background is opaque: PNG gets RGB only, EXR gets the colour and its coverage as A. Files appear
whole or not at all.

Also image sizes from PNG, JPEG and WebP headers (header_size, check_image_size), and the WebP codecs
SOG decodes and encodes through (decode_webp, encode_webp): Pillow's where it imports, else one the
Blender extension registers (register_webp_codec), Blender's own Python having no Pillow.
"""

import io
import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .common import SplatFileError, atomic_write
from .policy import MAX_IMAGE_PIXELS

FORMATS = (".png", ".exr")


def write_image(path, image, half=False):
    """Write a RenderResult, a dict with "color" and optional "alpha"/"depth", or an array.

    half: EXR only, store 16-bit floats instead of 32-bit.
    """
    ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        raise SplatFileError(path, f"unknown image extension '{ext}' (known: {', '.join(FORMATS)})")
    color, alpha, depth, kind = _planes(path, image)
    if ext == ".png":
        _write_png(path, color, None if kind == "opaque" else alpha, kind == "premultiplied")
    else:
        from .exr import write_exr

        if kind == "straight" and alpha is not None:  # EXR colour is premultiplied
            color = color * alpha[..., None]
        channels = {"R": color[..., 0], "G": color[..., 1], "B": color[..., 2]}
        if alpha is not None:
            channels["A"] = alpha
        if depth is not None:
            channels["Z"] = depth
        write_exr(path, channels, half=half)


def _planes(path, image):
    """(color (H,W,3), alpha (H,W) or None, depth (H,W) or None, kind) as float arrays; kind is
    "opaque" (alpha is coverage only: the colour already holds a background), "premultiplied" or
    "straight"."""
    if hasattr(image, "color"):  # a RenderResult
        kind = "premultiplied" if getattr(image, "background", ()) is None else "opaque"
        return (
            _array(path, "color", image.color),
            _array(path, "alpha", image.alpha),
            _array(path, "depth", image.depth),
            kind,
        )
    if isinstance(image, dict):
        if "color" not in image:
            raise SplatFileError(path, "an image dict needs a 'color' entry")
        alpha = image.get("alpha")
        depth = image.get("depth")
        return (
            _array(path, "color", image["color"]),
            None if alpha is None else _array(path, "alpha", alpha),
            None if depth is None else _array(path, "depth", depth),
            "premultiplied" if image.get("premultiplied") else "straight",
        )
    a = _array(path, "image", image)
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2), None, None, "opaque"
    if a.shape[2] == 4:
        return a[..., :3], a[..., 3], None, "straight"
    return a, None, None, "opaque"


_SHAPES = {"color": "(H, W, 3)", "alpha": "(H, W)", "depth": "(H, W)", "image": "(H, W), (H, W, 3) or (H, W, 4)"}


def _array(path, name, values):
    a = np.asarray(values, dtype=np.float64)
    if name == "color":
        ok = a.ndim == 3 and a.shape[2] == 3
    elif name == "image":
        ok = a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))
    else:
        ok = a.ndim == 2
    if not ok or 0 in a.shape:
        raise SplatFileError(path, f"{name} has shape {a.shape}, expected {_SHAPES[name]}")
    bad = ~np.isfinite(a)
    if bad.any():
        raise SplatFileError(path, f"{name} holds {int(bad.sum())} NaN or infinite values")
    return a


def _write_png(path, color, alpha, premultiplied):
    if alpha is not None and alpha.shape != color.shape[:2]:
        raise SplatFileError(path, f"alpha has shape {alpha.shape}, colour {color.shape[:2]}")
    # RGBA only when alpha matters: a transparent render, or an image given with partial alpha.
    with_alpha = alpha is not None and (premultiplied or bool((alpha < 1.0).any()))
    if with_alpha and premultiplied:
        safe = np.where(alpha > 0, alpha, 1.0)
        color = np.where(alpha[..., None] > 0, color / safe[..., None], 0.0)
    planes = [color] + ([alpha[..., None]] if with_alpha else [])
    pixels = np.round(np.clip(np.concatenate(planes, axis=2), 0.0, 1.0) * 255.0).astype(np.uint8)
    with atomic_write(path) as f:
        f.write(png_bytes(pixels))


def png_bytes(pixels):
    """An 8-bit RGB or RGBA PNG of (H, W, 3|4) uint8 pixels, with the standard library alone (Blender's
    Python has no Pillow): every row filter 0 (none), the rows zlib-compressed."""
    h, w, channels = pixels.shape
    rows = np.zeros((h, 1 + w * channels), np.uint8)
    rows[:, 1:] = pixels.reshape(h, w * channels)
    color_type = {3: 2, 4: 6}[channels]

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


# reading image headers ----------------------------------------------------------------------------


def header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) a PNG, JPEG or WebP image states in its header, from its first bytes alone
    (no decoder is involved); None for other or damaged data."""
    data = bytes(data[: 1 << 16])  # a JPEG's frame header follows its metadata segments
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    if data[:2] == b"\xff\xd8":
        return _jpeg_size(data)
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return _webp_size(data)
    return None


# JPEG start-of-frame markers (every coding process) carry the image size; C4, C8 and CC do not
_JPEG_FRAMES = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(data):
    pos = 2
    while pos + 9 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _JPEG_FRAMES:
            height, width = struct.unpack(">HH", data[pos + 5 : pos + 9])
            return width, height
        if marker in (0x01, *range(0xD0, 0xD9)):  # markers without a length
            pos += 2
            continue
        pos += 2 + struct.unpack(">H", data[pos + 2 : pos + 4])[0]
    return None


def _webp_size(data):
    kind, body = data[12:16], data[20:30]
    if kind == b"VP8 " and len(body) >= 10:
        width, height = struct.unpack("<HH", body[6:10])
        return width & 0x3FFF, height & 0x3FFF
    if kind == b"VP8L" and len(body) >= 5:
        bits = int.from_bytes(body[1:5], "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if kind == b"VP8X" and len(body) >= 10:
        return int.from_bytes(body[4:7], "little") + 1, int.from_bytes(body[7:10], "little") + 1
    return None


def check_image_size(owner: str | os.PathLike, width: int, height: int, what: str = "image") -> None:
    """Refuse (SplatFileError naming `owner`) an image of more than policy.MAX_IMAGE_PIXELS pixels."""
    if width * height > MAX_IMAGE_PIXELS:
        side = int(MAX_IMAGE_PIXELS**0.5)
        raise SplatFileError(
            owner,
            f"{what} of {width} x {height} pixels, more than the {MAX_IMAGE_PIXELS} ({side} x {side}) "
            "textures may have",
        )


# WebP codecs --------------------------------------------------------------------------------------


class WebPCodec(NamedTuple):
    """decode: WebP bytes -> (H, W, 4) uint8 RGBA, top row first. encode: (H, W, 4) uint8 RGBA ->
    lossless WebP bytes that decode to every byte given, or None where the codec has no such encoder.
    exact: False where the encoder keeps every byte but the colour (RGB) of fully transparent pixels
    (alpha 0), which it replaces (Blender's: libwebp's lossless mode without its "exact" option)."""

    name: str
    decode: Callable[[bytes], np.ndarray]
    encode: Callable[[np.ndarray], bytes] | None = None
    exact: bool = True


def _pillow_decode(data):
    from PIL import Image

    with Image.open(io.BytesIO(data)) as image:
        if image.format != "WEBP":
            raise ValueError(f"it decodes as {image.format}")
        return np.asarray(image.convert("RGBA"))


def _pillow_encode(pixels):
    from PIL import Image

    buffer = io.BytesIO()
    # exact: lossless WebP otherwise drops the colour of transparent pixels
    Image.fromarray(pixels, "RGBA").save(buffer, "WEBP", lossless=True, exact=True, quality=50, method=2)
    return buffer.getvalue()


PILLOW = WebPCodec("Pillow", _pillow_decode, _pillow_encode)
_registered: list[WebPCodec] = []


def _pillow_has_webp():
    try:
        from PIL import features
    except ImportError:
        return False
    return features.check("webp")


def register_webp_codec(codec: WebPCodec) -> None:
    """Add a codec (replacing one of its name); webp_codec uses it where Pillow is missing."""
    unregister_webp_codec(codec.name)
    _registered.append(codec)


def unregister_webp_codec(name: str) -> None:
    _registered[:] = [codec for codec in _registered if codec.name != name]


def webp_codec(job: str = "decode") -> WebPCodec | None:
    """The codec that can `job` ("decode" or "encode"): Pillow's where it imports with WebP, else the
    latest registered that can; None if none can."""
    candidates = ([PILLOW] if _pillow_has_webp() else []) + _registered[::-1]
    return next((codec for codec in candidates if getattr(codec, job) is not None), None)


def decode_webp(owner: str | os.PathLike, data: bytes, what: str = "WebP image") -> np.ndarray:
    """(H, W, 4) uint8 RGBA of a WebP image, its size taken from its header and checked
    (check_image_size) before any codec sees it; SplatFileError naming `owner` and `what` otherwise."""
    size = header_size(data) if data[:4] == b"RIFF" and data[8:12] == b"WEBP" else None
    if size is None:
        raise SplatFileError(owner, f"{what} is not a WebP image (its header states no size)")
    width, height = size
    check_image_size(owner, width, height, what)
    # Blender's decoder reports a damaged image only to its log, so what libwebp would refuse from
    # the sizes alone is refused here, for every codec
    claimed = max(8 + int.from_bytes(data[4:8], "little"), 20 + int.from_bytes(data[16:20], "little"))
    if claimed > len(data):
        raise SplatFileError(owner, f"{what} is cut short: its header claims {claimed} bytes, {len(data)} are stored")
    codec = webp_codec("decode")
    if codec is None:
        raise SplatFileError(owner, f"{what} is a WebP image and this Python has no WebP codec (the Pillow package)")
    try:
        pixels = np.asarray(codec.decode(bytes(data)))
    except Exception as exc:  # noqa: BLE001 - codecs raise many types for damaged images
        raise SplatFileError(owner, f"{what} is not a readable WebP image: {exc}") from None
    if pixels.shape != (height, width, 4) or pixels.dtype != np.uint8:
        raise SplatFileError(owner, f"{what} decodes to {pixels.shape}, its header says {width} x {height}")
    return pixels


def encode_webp(owner: str | os.PathLike, pixels: np.ndarray) -> bytes:
    """Lossless WebP bytes of (H, W, 4) uint8 RGBA pixels, every byte kept (but the colour of fully
    transparent pixels where webp_codec("encode") is not exact); SplatFileError naming `owner` where
    no codec can."""
    codec = webp_codec("encode")
    if codec is None or codec.encode is None:
        raise SplatFileError(owner, "this Python has no lossless WebP encoder (the Pillow package)")
    try:
        return codec.encode(np.ascontiguousarray(pixels, np.uint8))
    except (OSError, RuntimeError) as exc:  # Blender's encoder writes a temporary file
        raise SplatFileError(owner, f"cannot encode a WebP image: {exc}") from None
