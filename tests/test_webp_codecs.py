"""io.image's WebP codecs, the seam SOG decodes and encodes through: Pillow's where it imports, else
one registered (the Blender extension registers Blender's, tests/test_blender_sog.py), and the header
checks in front of every codec. An encoder that is not exact (it replaces the colour of fully
transparent pixels, as Blender's does) writes a SOG that reads back as Pillow's for every splat a
viewer draws."""

import io
import sys
import warnings
import zipfile

import numpy as np
import pytest
from helpers import random_cloud
from PIL import Image

from splatwright.io import SplatFileError, SplatFileWarning, read_splats, write_splats
from splatwright.io import image as image_io


def webp(pixels, **options):
    buffer = io.BytesIO()
    Image.fromarray(pixels, "RGBA").save(buffer, "WEBP", **({"lossless": True, "exact": True} | options))
    return buffer.getvalue()


def pillow_pixels(data):
    with Image.open(io.BytesIO(data)) as image:
        return np.asarray(image.convert("RGBA"))


def without_pillow(monkeypatch):
    """This Python as Blender's: no Pillow, and no codec but those the test registers."""
    monkeypatch.setitem(sys.modules, "PIL", None)
    monkeypatch.setattr(image_io, "_registered", [])


def test_pillow_codec_keeps_every_byte_transparent_pixels_too():
    pixels = np.random.default_rng(90).integers(0, 256, (9, 13, 4), dtype=np.uint8)
    pixels[::2, :, 3] = 0
    assert image_io.webp_codec("decode").name == image_io.webp_codec("encode").name == "Pillow"
    data = image_io.encode_webp("x.sog", pixels)
    np.testing.assert_array_equal(pillow_pixels(data), pixels)
    np.testing.assert_array_equal(image_io.decode_webp("x.sog", data), pixels)


def test_a_registered_decoder_reads_sog_where_pillow_is_missing(tmp_path, monkeypatch):
    """A decoder that answers from Pillow's decoding of the bundle's images, looked up by their bytes:
    the SOG reads as it reads with Pillow; writing is refused (no encoder), and once the decoder is
    unregistered reading is refused too."""
    path = tmp_path / "a.sog"
    write_splats(path, random_cloud(300, sh_degree=2, seed=91))
    want = read_splats(path)
    with zipfile.ZipFile(path) as bundle:
        answers = {bundle.read(n): pillow_pixels(bundle.read(n)) for n in bundle.namelist() if n.endswith(".webp")}
    asked = []

    def decode(data):
        asked.append(data)
        return answers[data]

    without_pillow(monkeypatch)
    image_io.register_webp_codec(image_io.WebPCodec("answers", decode))
    assert image_io.webp_codec("encode") is None
    got = read_splats(path)
    assert sorted(asked) == sorted(answers)
    for field in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
    with pytest.raises(SplatFileError, match=r"b\.sog: .*a WebP decoder but no encoder"):
        write_splats(tmp_path / "b.sog", want)
    assert not (tmp_path / "b.sog").exists()
    image_io.unregister_webp_codec("answers")
    with pytest.raises(SplatFileError, match=r"a\.sog: .*no WebP codec"):
        read_splats(path)


def test_a_codec_sees_only_webp_of_checked_size(monkeypatch):
    """A codec is never handed data whose header names no WebP, a size past the pixel limit, or more
    bytes than are stored; a codec's failure or a wrong size becomes a SplatFileError."""
    good = webp(np.zeros((8, 8, 4), np.uint8))
    without_pillow(monkeypatch)
    asked = []
    image_io.register_webp_codec(image_io.WebPCodec("spy", lambda data: asked.append(data) or np.zeros((8, 8, 4))))
    png = image_io.png_bytes(np.zeros((8, 8, 4), np.uint8))
    with pytest.raises(SplatFileError, match="x.sog: q.webp is not a WebP image"):
        image_io.decode_webp("x.sog", png, "q.webp")
    with pytest.raises(SplatFileError, match="x.sog: q.webp is cut short: its header claims"):
        image_io.decode_webp("x.sog", good[:-3], "q.webp")
    wide = bytearray(good)
    wide[21:25] = ((16383) | (16383 << 14) | (1 << 28)).to_bytes(4, "little")  # 16384 x 16384, alpha bit
    with pytest.raises(SplatFileError, match="x.sog: q.webp of 16384 x 16384 pixels"):
        image_io.decode_webp("x.sog", bytes(wide), "q.webp")
    assert asked == []
    with pytest.raises(SplatFileError, match=r"q.webp decodes to \(8, 8, 4\), its header says 8 x 8"):
        image_io.decode_webp("x.sog", good, "q.webp")  # float, not uint8
    assert asked == [good]
    image_io.register_webp_codec(image_io.WebPCodec("spy", lambda data: 1 / 0))  # replaces the first
    with pytest.raises(SplatFileError, match="q.webp is not a readable WebP image: division by zero"):
        image_io.decode_webp("x.sog", good, "q.webp")


def test_pillow_comes_first_where_it_imports():
    def never(data):
        raise AssertionError("Pillow decodes where it imports")

    image_io.register_webp_codec(image_io.WebPCodec("never", never))
    try:
        pixels = np.arange(4 * 5 * 4, dtype=np.uint8).reshape(4, 5, 4)
        np.testing.assert_array_equal(image_io.decode_webp("x.sog", webp(pixels)), pixels)
    finally:
        image_io.unregister_webp_codec("never")
    assert all(codec.name != "never" for codec in image_io._registered)


FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh")


def faint_cloud():
    """A cloud of SH degree 2 whose first 25 splats have SOG opacity byte 0 (opacity under 1/510)."""
    cloud = random_cloud(500, sh_degree=2, seed=92)
    cloud.opacity_logits[:25] = np.linspace(-30.0, -6.3, 25)
    cloud.opacity_logits[25:] = np.clip(cloud.opacity_logits[25:], -6.0, None)  # byte 1 or more
    return cloud


def junk_transparent_colour(pixels):
    """Pillow's exact encoding of `pixels` with random colour in every fully transparent pixel: what
    an encoder that replaces that colour may store."""
    pixels = pixels.copy()
    clear = pixels[..., 3] == 0
    pixels[clear, :3] = np.random.default_rng(int(clear.sum())).integers(0, 256, (int(clear.sum()), 3))
    return webp(pixels)


def sog_images(path):
    """{image name: (H*W, 4) RGBA} of a .sog bundle, decoded by Pillow."""
    with zipfile.ZipFile(path) as bundle:
        return {n: pillow_pixels(bundle.read(n)).reshape(-1, 4) for n in bundle.namelist() if n.endswith(".webp")}


def test_only_sh0_pixels_of_invisible_splats_are_transparent(tmp_path):
    """The pixels whose colour an inexact encoder loses: in sh0 only, one per splat of opacity byte 0."""
    cloud = faint_cloud()
    write_splats(tmp_path / "a.sog", cloud, order=None)
    for name, pixels in sog_images(tmp_path / "a.sog").items():
        clear = np.flatnonzero(pixels[:, 3] == 0)
        assert clear.tolist() == (list(range(25)) if name == "sh0.webp" else []), name
    assert (sog_images(tmp_path / "a.sog")["quats.webp"][:, 3] >= 252).all()


@pytest.mark.parametrize("name", ["a.sog", "loose/meta.json"])
def test_an_inexact_encoder_writes_what_pillow_writes_for_every_visible_splat(tmp_path, monkeypatch, name):
    """Written through an encoder that replaces the colour of transparent pixels, a SOG keeps every
    splat in Pillow's order; every one of opacity byte 1 or more reads back (through Pillow) exactly as
    from Pillow's own file, the others all but their base colour; one warning counts them."""
    cloud = faint_cloud()
    write_splats(tmp_path / "pillow.sog", cloud)
    want = read_splats(tmp_path / "pillow.sog")
    monkeypatch.setattr(image_io, "_pillow_has_webp", lambda: False)
    monkeypatch.setattr(image_io, "_registered", [])
    image_io.register_webp_codec(image_io.WebPCodec("Junk", pillow_pixels, junk_transparent_colour, exact=False))
    assert image_io.webp_codec("encode").name == "Junk"
    (tmp_path / "loose").mkdir()
    with pytest.warns(SplatFileWarning) as caught:
        write_splats(tmp_path / name, cloud)
    assert len(caught) == 1
    assert str(caught[0].message) == (
        f"{tmp_path / name}: 25 splats of opacity under 1/510 (drawn by no viewer) kept without their base "
        "colour (SH band 0): Junk's WebP encoder replaces the colour of fully transparent pixels"
    )
    got = read_splats(tmp_path / name)
    visible = np.rint(want.opacities * 255) >= 1
    assert len(got) == len(want) == 500 and visible.sum() == 475
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(got, field)[visible], getattr(want, field)[visible], err_msg=field)
        if field != "sh":
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    np.testing.assert_array_equal(got.sh[~visible, 1:], want.sh[~visible, 1:])
    assert (got.sh[~visible, 0] != want.sh[~visible, 0]).any()  # the junk colour, read through the codebook


def test_no_note_where_the_encoder_is_exact_or_no_splat_is_invisible(tmp_path, monkeypatch):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_splats(tmp_path / "a.sog", faint_cloud())  # Pillow's encoder: exact
        monkeypatch.setattr(image_io, "_pillow_has_webp", lambda: False)
        monkeypatch.setattr(image_io, "_registered", [])
        image_io.register_webp_codec(image_io.WebPCodec("Junk", pillow_pixels, junk_transparent_colour, exact=False))
        cloud = faint_cloud()
        cloud.opacity_logits[:25] = -6.0
        write_splats(tmp_path / "b.sog", cloud)
    np.testing.assert_array_equal(read_splats(tmp_path / "b.sog").sh, read_splats(tmp_path / "a.sog").sh)
