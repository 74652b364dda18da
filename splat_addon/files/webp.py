"""Blender's own WebP codec as a WebP codec of io.image, so that SOG files import and export in
Blender, whose Python has no Pillow (where Pillow imports, io.image prefers it).

Decoding packs the bytes into a hidden image from memory (no temporary file) and reads it as
Non-Color, so no colour transform touches them; Blender keeps 8-bit images as bytes and hands them
out as float byte * (1/255), bottom row first, which rounding turns back into the bytes exactly.

Encoding sets such an image's bytes the same way and saves it as WebP at quality 100, which Blender
writes losslessly (VP8L) through a temporary file, every byte kept but the colour of fully
transparent pixels, which libwebp replaces there: the codec is registered as not exact (io/sog.py
says what that costs a SOG)."""

import os
import tempfile

import bpy
import numpy as np

from ...io import image

CODEC_NAME = "Blender"
IMAGE_NAME = ".splatwright-webp"


def decode(data: bytes) -> np.ndarray:
    """(H, W, 4) uint8 RGBA, top row first, of WebP bytes; ValueError if Blender cannot decode them."""
    picture = bpy.data.images.new(IMAGE_NAME, 1, 1, alpha=True)
    try:
        picture.pack(data=data, data_len=len(data))
        picture.source = "FILE"
        picture.colorspace_settings.name = "Non-Color"
        width, height = picture.size  # loads the image
        if not picture.has_data or width * height == 0:
            raise ValueError("Blender cannot decode it")
        values = np.empty(width * height * 4, np.float32)
        picture.pixels.foreach_get(values)
    finally:
        bpy.data.images.remove(picture)
    return np.rint(values * 255.0).astype(np.uint8).reshape(height, width, 4)[::-1]


def encode(pixels: np.ndarray) -> bytes:
    """Lossless WebP bytes of (H, W, 4) uint8 RGBA, top row first; fully transparent pixels' colour
    is not kept."""
    height, width, _ = pixels.shape
    picture = bpy.data.images.new(IMAGE_NAME, width, height, alpha=True)  # 8-bit, straight alpha
    try:
        picture.colorspace_settings.name = "Non-Color"
        picture.pixels.foreach_set((pixels[::-1].reshape(-1) / np.float32(255.0)).astype(np.float32))
        picture.file_format = "WEBP"
        with tempfile.TemporaryDirectory(prefix="splatwright-") as folder:
            target = os.path.join(folder, "image.webp")
            picture.save(filepath=target, quality=100)  # quality 100: lossless
            with open(target, "rb") as f:
                return f.read()
    finally:
        bpy.data.images.remove(picture)


def register():
    image.register_webp_codec(image.WebPCodec(CODEC_NAME, decode, encode, exact=False))


def unregister():
    image.unregister_webp_codec(CODEC_NAME)
