"""SOG in Blender, whose Python has no Pillow: the extension registers Blender's own WebP decoder with
io.image, so SOG files (a bundle, loose images beside a meta.json, a streamed lod-meta.json) written
by our writer here read there exactly as our reader reads them here through Pillow. The decoder
gives Pillow's bytes for random images (transparent pixels' colour kept). Export to SOG stays refused
there (Blender's encoder changes the colour of transparent pixels), as does a damaged image."""

import zipfile

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import random_cloud
from PIL import Image
from workers.sog import FIELDS, READS

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


def test_the_extension_registers_a_decoder_and_no_encoder(blender):
    res = blender.step("codec")
    assert res["decoder"] == "Blender" and res["encoder"] is None, res
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


def test_sog_export_is_refused_by_name_and_writes_nothing(blender):
    res = blender.step("refusals")["export"]
    assert res["import"]["result"] == ["FINISHED"], res
    assert res["result"] == ["CANCELLED"] and not res["written"], res
    assert "WebP encoder" in res["error"] and "back.sog" in res["error"] and "Traceback" not in res["error"], res


def test_a_damaged_sog_image_is_refused_by_name(blender):
    res = blender.step("refusals")["damaged"]
    assert res["result"] == ["CANCELLED"] and res["objects"] == 0, res
    assert "damaged.sog" in res["error"] and "sh0.webp is cut short" in res["error"], res
