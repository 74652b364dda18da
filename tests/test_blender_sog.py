"""SOG in Blender, whose Python has no Pillow: the extension registers Blender's own WebP codec with
io.image, so SOG files (a bundle, loose images beside a meta.json, a streamed lod-meta.json) written
by our writer here read there exactly as our reader reads them here through Pillow, and SOG files
written there (through io and the export operator) read here through Pillow exactly as our writer's
own with Pillow, for every splat a viewer draws; those of opacity byte 0 are kept without their base
colour, counted in a warning. The decoder gives Pillow's bytes for random images (transparent pixels'
colour kept), the encoder every byte but the colour of fully transparent pixels. A damaged image is
refused."""

import zipfile

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import random_cloud
from PIL import Image
from workers.sog import EXPORTS, FIELDS, READS

from splatwright.core import SplatCloud
from splatwright.io import read_splats, write_splats

pytestmark = [pytest.mark.blender, pytest.mark.slow]
UPRIGHT = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]


def codec_images():
    """{name: (RGBA pixels, Pillow save options)}: random images of odd sizes, with transparent
    pixels of random colour, lossless (exact) and one lossy."""
    rng = np.random.default_rng(80)
    images = {}
    for name, (height, width) in {"one": (1, 1), "odd": (5, 7), "square": (64, 64), "wide": (31, 257)}.items():
        pixels = rng.integers(0, 256, (height, width, 4), dtype=np.uint8)
        pixels[::2, ::3, 3] = 0
        images[name] = pixels, {"lossless": True, "exact": True}
    images["lossy"] = rng.integers(0, 256, (40, 24, 4), dtype=np.uint8), {"quality": 80}
    return images


def encode_images():
    """{name: RGBA pixels} for Blender's encoder: random images of odd sizes with alpha 1 to 255, and
    one with fully transparent pixels too."""
    rng = np.random.default_rng(81)
    images = {}
    for name, (height, width) in {"one": (1, 1), "odd": (5, 7), "square": (64, 64), "wide": (31, 257)}.items():
        pixels = rng.integers(0, 256, (height, width, 4), dtype=np.uint8)
        pixels[..., 3] = np.maximum(pixels[..., 3], 1)
        images[name] = pixels
    images["clear"] = rng.integers(0, 256, (33, 20, 4), dtype=np.uint8)
    images["clear"][::3, ::2, 3] = 0
    return images


def sog_cloud():
    """A cloud of SH degree 3 with 20 splats too faint for sh0's alpha (opacity under 1/510), whose
    colours the image keeps under alpha 0."""
    cloud = random_cloud(400, sh_degree=3, seed=70)
    cloud.opacity_logits[:20] = -9.0
    return cloud


def _write_inputs(work):
    from test_new_readers import write_streamed

    (work / "codec").mkdir()
    for name, (pixels, options) in codec_images().items():
        Image.fromarray(pixels, "RGBA").save(work / "codec" / f"{name}.webp", "WEBP", **options)
    np.savez(work / "encode.npz", **encode_images())
    write_splats(work / "a.sog", sog_cloud())
    (work / "loose").mkdir()
    write_splats(work / "loose" / "meta.json", random_cloud(150, sh_degree=1, seed=71))
    (work / "scene").mkdir()
    clouds = [random_cloud(60, sh_degree=2, seed=72), random_cloud(20, sh_degree=2, seed=73)]
    write_streamed(work / "scene", clouds, names=["0_0.sog", "1_0/meta.json"])
    with zipfile.ZipFile(work / "a.sog") as whole, zipfile.ZipFile(work / "damaged.sog", "w") as damaged:
        for name in whole.namelist():
            data = whole.read(name)
            damaged.writestr(name, data[: len(data) // 2] if name == "sh0.webp" else data)


blender = blender_fixture("workers.sog", _write_inputs)


def test_blender_decodes_webp_to_the_bytes_pillow_decodes(blender):
    blender.step("codec")
    got = blender.npz("codec")
    for name, (pixels, options) in codec_images().items():
        with Image.open(blender.work / "codec" / f"{name}.webp") as image:
            pillow = np.asarray(image.convert("RGBA"))
        assert got[name].dtype == np.uint8 and got[name].shape == pixels.shape, name
        np.testing.assert_array_equal(got[name], pillow, err_msg=name)
        if options.get("lossless"):
            np.testing.assert_array_equal(got[name], pixels, err_msg=name)
    assert (codec_images()["square"][0][..., 3] == 0).any()


def test_blender_encodes_webp_losslessly_but_the_colour_of_transparent_pixels(blender):
    """Pillow decodes Blender's WebP to every byte given where alpha is 1 or more; where it is 0, the
    alpha stays and the colour may not."""
    blender.step("codec")
    for name, pixels in encode_images().items():
        data = (blender.out / "encoded" / f"{name}.webp").read_bytes()
        assert data[12:16] == b"VP8L", name  # lossless
        with Image.open(blender.out / "encoded" / f"{name}.webp") as image:
            pillow = np.asarray(image.convert("RGBA"))
        assert pillow.shape == pixels.shape, name
        seen = pixels[..., 3] > 0
        np.testing.assert_array_equal(pillow[seen], pixels[seen], err_msg=name)
        np.testing.assert_array_equal(pillow[..., 3], pixels[..., 3], err_msg=name)
        assert seen.all() == (name != "clear"), name


def test_the_extension_registers_a_codec_whose_encoder_is_not_exact(blender):
    res = blender.step("codec")
    assert res["decoder"] == res["encoder"] == "Blender" and res["exact"] is False, res
    assert res["decoder_unregistered"] is None and res["decoder_again"] == "Blender", res


@pytest.mark.parametrize("key", sorted(READS))
def test_sog_reads_in_blender_exactly_as_outside(blender, key):
    blender.step("reads")
    want = read_splats(blender.work / READS[key])
    got = blender.npz(f"read_{key}")
    for field in FIELDS:
        np.testing.assert_array_equal(got[field], getattr(want, field), err_msg=f"{key} {field}")
    if key == "bundle":
        assert (want.opacities < 1 / 510).sum() == 20  # their colours came from under alpha 0
        assert want.sh_degree == 3 and len(want) == 400


@pytest.mark.parametrize("key", sorted(READS))
def test_sog_imports_as_splat_objects_holding_what_it_reads(blender, key):
    res = blender.step("reads")[key]
    want = read_splats(blender.work / READS[key])
    assert res["result"] == ["FINISHED"] and res["objects"] == 1 and res["count"] == len(want), res
    got = blender.npz(f"object_{key}")
    for field in FIELDS:
        np.testing.assert_array_equal(got[field], getattr(want, field), err_msg=f"{key} {field}")
    # the splats kept in the file's axes (PLY's: y down, z forward), the object turned upright
    np.testing.assert_allclose(got["matrix"], UPRIGHT, atol=1e-7)


@pytest.mark.parametrize("key", sorted(EXPORTS))
def test_sog_written_in_blender_reads_as_pillow_writes_it_for_every_visible_splat(blender, key):
    """The cloud Blender wrote, written here by our writer through Pillow: both read back (through
    Pillow) alike, in the same order, every field of every splat of opacity byte 1 or more; the 20 of
    byte 0 (drawn by no viewer) kept, all but their base colour alike."""
    res = blender.step("exports")
    name, written = EXPORTS[key]
    if key.startswith("operator"):
        assert res["import"]["result"] == ["FINISHED"] and res["import"]["objects"] == 1, res
        assert res[key]["result"] == ["FINISHED"], res[key]
    cloud = SplatCloud(**blender.npz(written))
    write_splats(blender.work / f"pillow_{key}.sog", cloud)
    want = read_splats(blender.work / f"pillow_{key}.sog")
    got = read_splats(blender.out / name)
    visible = np.rint(want.opacities * 255) >= 1
    assert len(got) == len(want) == 400 and (~visible).sum() == 20
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(got, field)[visible], getattr(want, field)[visible], err_msg=field)
        if field != "sh":
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    np.testing.assert_array_equal(got.sh[~visible, 1:], want.sh[~visible, 1:])


@pytest.mark.parametrize("key", ["io_bundle", "io_loose"])
def test_sog_written_in_blender_counts_the_splats_without_their_colour(blender, key):
    path = blender.out / EXPORTS[key][0]
    assert blender.step("exports")[key] == [
        f"SplatFileWarning: {path}: 20 splats of opacity under 1/510 (drawn by no viewer) kept without their "
        "base colour (SH band 0): Blender's WebP encoder replaces the colour of fully transparent pixels"
    ]


def test_a_damaged_sog_image_is_refused_by_name(blender):
    res = blender.step("refusals")["damaged"]
    assert res["result"] == ["CANCELLED"] and res["objects"] == 0, res
    assert "damaged.sog" in res["error"] and "sh0.webp is cut short" in res["error"], res
