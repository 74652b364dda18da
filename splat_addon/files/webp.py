"""Blender's own WebP decoder as a WebP codec of io.image, so that SOG files import in Blender, whose
Python has no Pillow (where Pillow imports, io.image prefers it).

The bytes are packed into a hidden image from memory (no temporary file) and read as Non-Color, so
no colour transform touches them; Blender keeps 8-bit images as bytes and hands them out as float
byte * (1/255), bottom row first, which rounding turns back into the bytes exactly.

No encoder is registered: Blender saves WebP at quality 100 losslessly except for the colour of
fully transparent pixels, which it replaces, and SOG's sh0 image keeps a colour there for every splat
of opacity under 1/510. SOG export in Blender therefore stays refused."""

import bpy
import numpy as np

from ...io import image

CODEC_NAME = "Blender"


def decode(data: bytes) -> np.ndarray:
    """(H, W, 4) uint8 RGBA, top row first, of WebP bytes; ValueError if Blender cannot decode them."""
    picture = bpy.data.images.new(".splatwright-webp", 1, 1, alpha=True)
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


def register():
    image.register_webp_codec(image.WebPCodec(CODEC_NAME, decode))


def unregister():
    image.unregister_webp_codec(CODEC_NAME)
