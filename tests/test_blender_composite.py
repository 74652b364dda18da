"""Splats and meshes in one picture, headless in every Blender of the version matrix.

The oracle: Cycles renders the plane and sphere alone (the splats hidden), and the float64 brute-force
reference (tests/reference_render.py, no code of core/render.py) composites the splat cloud with that
picture as the final layer at Cycles' own depth; the SPLATWRIGHT engine's F12 output must equal it to
1/255. With flat emission the meshes can also be turned into dense opaque splats: one splat render of
everything must then agree with the composite within the PSNR stated below. Every file is read by
OpenEXR and Pillow.
"""

import numpy as np
import pytest
from blender_session import blender_fixture
from reference_render import reference_render
from workers.composite import EMISSION, SIZE, WORLD, oracle_cloud_arrays

from splatwright.core import SplatCloud
from splatwright.core.camera import Camera
from splatwright.core.color import linear_to_srgb, srgb_to_linear

pytestmark = [pytest.mark.blender, pytest.mark.slow]

STEP = 1.0 / 255.0
EMISSION_PSNR = 38.0  # dB: flat-emission composite against the meshes made of splats, off outlines
EMISSION_PSNR_WHOLE = 22.0  # dB: the same over the whole 192x144 picture, outlines included

blender = blender_fixture("workers.composite")


def exr(path):
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return {name: ch.pixels for part in f.parts for name, ch in part.channels.items()}


def png(path):
    from PIL import Image

    return np.asarray(Image.open(path), dtype=np.float64) / 255.0


def camera(rec):
    x, y, pct = rec["resolution"]
    lens = {
        k: rec[k]
        for k in (
            "lens",
            "sensor_width",
            "sensor_height",
            "sensor_fit",
            "shift_x",
            "shift_y",
            "type",
            "ortho_scale",
            "pixel_aspect_x",
            "pixel_aspect_y",
        )
    }
    return Camera.from_blender(
        np.array(rec["matrix_world"]),
        x * pct // 100,
        y * pct // 100,
        clip_start=rec["clip_start"],
        clip_end=rec["clip_end"],
        **lens,
    )


def display(rgba):
    """Scene-linear premultiplied RGBA -> display-sRGB premultiplied colour and alpha (the curve on the
    straight colour, as the engine treats every colour)."""
    alpha = rgba[..., 3].astype(np.float64)
    straight = np.where(alpha[..., None] > 0, rgba[..., :3] / np.maximum(alpha, 1e-30)[..., None], 0.0)
    return linear_to_srgb(straight) * alpha[..., None], alpha


def linear(color, alpha):
    straight = np.where(alpha[..., None] > 0, color / np.maximum(alpha, 1e-30)[..., None], 0.0)
    return np.concatenate([srgb_to_linear(straight) * alpha[..., None], alpha[..., None]], axis=-1)


def mesh_layer(transparent, opaque=None):
    """A reference surface from Cycles renders of the meshes alone: display colour (premultiplied),
    alpha and depth of the transparent-film render. Given the opaque-film picture too (the world in
    it), the colour is that picture less the world the uncovered part (1 - alpha) lets through, so
    that over the world it is Cycles' own picture and splats behind it cover the world they hide."""
    color, alpha = display(transparent["ViewLayer.Combined"])
    if opaque is not None:
        color = display(opaque["ViewLayer.Combined"])[0] - (1 - alpha)[..., None] * linear_to_srgb(np.array(WORLD))
    return color, alpha, transparent["ViewLayer.Depth.Z"]


def oracle(blender, film):
    """The reference picture: the splat cloud composited by the float64 brute force with Cycles'
    meshes as the layer at Cycles' own depth, over the world colour when the film is opaque (then
    `alpha` is 1 and `coverage` what splats and meshes cover)."""
    meshes = exr(blender.out / "meshes_transparent.exr")
    opaque = film == "opaque"
    layer = mesh_layer(meshes, exr(blender.out / "meshes_opaque.exr") if opaque else None)
    ref = reference_render(
        SplatCloud(**oracle_cloud_arrays()),
        camera(blender.step("oracle")["camera"]),
        background=linear_to_srgb(np.array(WORLD)) if opaque else (0.0, 0.0, 0.0),
        layer=layer,
    )
    ref["coverage"] = ref["alpha"]
    ref["alpha"] = np.ones_like(ref["alpha"]) if opaque else ref["alpha"]
    return ref, meshes


@pytest.mark.parametrize("film", ["opaque", "transparent"])
def test_composite_equals_the_splats_rendered_over_cycles_meshes(blender, film):
    ref, meshes = oracle(blender, film)
    got = exr(blender.out / f"composite_{film}.exr")
    assert got["ViewLayer.Combined"].shape == (SIZE[1], SIZE[0], 4)
    # in display terms (what the PNG holds) every pixel is within 1/255 of the oracle
    got_color, got_alpha = display(got["ViewLayer.Combined"])
    assert np.abs(got_color - ref["color"]).max() <= STEP
    assert np.abs(got_alpha - ref["alpha"]).max() <= STEP
    picture = png(blender.out / f"composite_{film}.png")
    straight = np.where(ref["alpha"][..., None] > 0, ref["color"] / np.maximum(ref["alpha"], 1e-30)[..., None], 0)
    seen = ref["alpha"] > 0.05
    assert np.abs(picture[..., :3][seen] - np.clip(straight[seen], 0, 1)).max() <= 1.01 * STEP
    assert np.abs(picture[..., 3] - ref["alpha"]).max() <= 1.01 * STEP
    # the scene really mixes both: splats hidden behind the meshes, splats over them, bare meshes
    cut = ref["layer_t"] < 0.95
    behind = reference_render(SplatCloud(**oracle_cloud_arrays()), camera(blender.step("oracle")["camera"]))
    assert (cut & (meshes["ViewLayer.Combined"][..., 3] > 0.99)).sum() > 100
    assert (np.abs(behind["color"] - ref["color"]).max(axis=-1) > 0.2).sum() > 100


def test_opaque_film_differs_from_an_opaque_mesh_layer_only_at_partly_covered_pixels(blender):
    """With the film opaque, Cycles' picture (the world in it) is opaque everywhere; taken as the
    layer, it would hide the splats behind a mesh's antialiased outline. Rendering the world apart
    (the Environment pass) shows them through the uncovered part; elsewhere both agree."""
    ref, meshes = oracle(blender, "opaque")
    picture = exr(blender.out / "meshes_opaque.exr")
    opaque = reference_render(
        SplatCloud(**oracle_cloud_arrays()),
        camera(blender.step("oracle")["camera"]),
        layer=(display(picture["ViewLayer.Combined"])[0], np.ones(SIZE[::-1]), meshes["ViewLayer.Depth.Z"]),
    )
    coverage = meshes["ViewLayer.Combined"][..., 3]
    partly = (coverage > 1e-3) & (coverage < 1 - 1e-3)
    error = np.abs(ref["color"] - opaque["color"]).max(axis=-1)
    assert error[~partly].max() <= STEP and partly.sum() > 20


@pytest.mark.parametrize("film", ["opaque", "transparent"])
def test_passes_depth_splats_and_meshes(blender, film):
    ref, meshes = oracle(blender, film)
    got = exr(blender.out / f"composite_{film}.exr")
    # the Meshes pass is Cycles' own picture (the same settings and seed give the same pixels)
    np.testing.assert_allclose(
        got["ViewLayer.Meshes"], exr(blender.out / f"meshes_{film}.exr")["ViewLayer.Combined"], atol=1e-6
    )
    # Depth: the nearer of the splats (where any is blended) and the mesh surface
    surface = meshes["ViewLayer.Depth.Z"]
    splat_alpha = ref["coverage"] - ref["layer_t"] * display(meshes["ViewLayer.Combined"])[1]
    want = np.where(splat_alpha > 1e-4, np.minimum(ref["depth"], surface), surface)
    clear = np.abs(splat_alpha - 1e-4) > 1e-5  # not on the edge of the "any splat" test
    np.testing.assert_allclose(got["ViewLayer.Depth.Z"][clear], want[clear], rtol=2e-4)
    # Splats: what the splats add, with their coverage in front of the meshes; over the meshes (in
    # display terms) they give Combined where the meshes are opaque or absent. (Where a mesh edge is
    # partly transparent, splats seen through it add colour at zero coverage, which a premultiplied
    # pass cannot hold.)
    splats_color, splats_alpha = display(got["ViewLayer.Splats"])
    assert np.abs(splats_alpha - (1 - ref["layer_t"])).max() <= STEP
    mesh_color, mesh_alpha = display(got["ViewLayer.Meshes"])
    coverage = meshes["ViewLayer.Combined"][..., 3]
    whole = (coverage == 1) | (
        (coverage == 0) & (ref["layer_t"] * ref["coverage"] < 1e-9 if film == "opaque" else True)
    )
    over = splats_color + (1 - splats_alpha)[..., None] * mesh_color
    assert np.abs(over - ref["color"])[whole].max() <= STEP
    assert np.abs(splats_alpha + (1 - splats_alpha) * mesh_alpha - ref["alpha"])[whole].max() <= STEP


def mesh_splats(triangles, color, spacing):
    """Flat emission triangles as dense, thin, opaque splats: about one per spacing^2 of area, each
    a disc of sigma `spacing` in the triangle's plane, the emission colour in display sRGB."""
    rng = np.random.default_rng(0)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    normal = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(normal, axis=1)
    count = rng.poisson(area / spacing**2 + 0.5)
    tri = np.repeat(np.arange(len(triangles)), count)
    u, v = rng.uniform(size=(2, len(tri)))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    points = a[tri] + u[:, None] * (b - a)[tri] + v[:, None] * (c - a)[tri]
    n = normal[tri] / np.linalg.norm(normal[tri], axis=1, keepdims=True)
    # the quaternion turning z onto the normal
    axis = np.cross([0.0, 0.0, 1.0], n)
    w = 1.0 + n[:, 2]
    quat = np.column_stack([w, axis])
    quat[w < 1e-9] = [0.0, 1.0, 0.0, 0.0]
    m = len(points)
    return SplatCloud.from_activated(
        positions=points,
        rotations=quat,
        scales=np.tile([spacing, spacing, spacing * 1e-3], (m, 1)),
        opacities=np.full(m, 0.999),
        colors=np.tile(linear_to_srgb(color), (m, 1)),
    )


def silhouettes(image, width=2):
    """Pixels within `width` px of a colour edge of a flat-coloured image."""
    edge = np.zeros(image.shape[:2], bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            edge |= np.abs(np.roll(image, (dy, dx), axis=(0, 1)) - image).max(axis=-1) > 0.05
    for _ in range(width - 1):
        edge |= np.roll(edge, 1, 0) | np.roll(edge, -1, 0) | np.roll(edge, 1, 1) | np.roll(edge, -1, 1)
    return edge


def test_flat_emission_meshes_agree_with_the_meshes_made_of_splats(blender):
    """Away from the meshes' outlines the composite converges to the all-splat picture as the mesh
    splats get denser; at the outlines a dense opaque splat surface is about a pixel wider (the 0.3 px^2
    low-pass summed over many splats) than Cycles' filtered edge, which bounds the whole-image PSNR."""
    from splatwright.core.metrics import psnr
    from splatwright.core.render import render

    rec = blender.step("emission")
    cam = camera(rec["camera"])
    triangles = blender.npz("emission_triangles")
    picture = png(blender.out / "emission.png")[..., :3]
    splats = SplatCloud(**oracle_cloud_arrays())
    inside, whole = [], []
    for spacing in (0.06, 0.015):
        meshes = SplatCloud.concatenate([mesh_splats(triangles[n], np.array(EMISSION[n]), spacing) for n in EMISSION])
        everything = np.clip(render(SplatCloud.concatenate([splats, meshes]), cam).color, 0, 1)
        away = ~silhouettes(np.clip(render(meshes, cam).color, 0, 1))
        inside.append(psnr(everything[away], picture[away]))
        whole.append(psnr(everything, picture))
    assert inside[1] >= EMISSION_PSNR and inside[1] > inside[0] + 3, inside  # closer as the splats get denser
    assert whole[1] >= EMISSION_PSNR_WHOLE, whole


def test_splats_behind_a_translucent_surface_show_through_it(blender):
    """A translucent plane (alpha 0.6) through the cloud, the film opaque. Where the plane is in
    front of the world alone, the composite is exact: splats behind it show through its 40%, the world
    behind them. Where it is in front of the ground as well, a pixel's single depth is the plane's
    and its colour holds both surfaces: splats between the two are hidden (and at outlines, where a
    pixel's colour mixes surfaces at different depths). That is the approximation,
    measured against the float64 reference given the two surfaces one by one (less the difference
    both pictures have without splats, seen through the splats in front: Cycles mixes surfaces in
    linear light, the reference in display terms)."""
    rec = blender.step("translucent")
    cam, cloud = camera(rec["camera"]), SplatCloud(**oracle_cloud_arrays())
    world = linear_to_srgb(np.array(WORLD))
    result = exr(blender.out / "translucent.exr")
    got = display(result["ViewLayer.Combined"])[0]
    meshes = exr(blender.out / "tr_meshes.exr")
    single = reference_render(
        cloud, cam, background=world, layer=mesh_layer(meshes, exr(blender.out / "tr_meshes_opaque.exr"))
    )
    assert np.abs(got - single["color"]).max() <= STEP
    glass, solid = (mesh_layer(exr(blender.out / f"tr_{name}.exr")) for name in ("glass", "solid"))
    both = reference_render(cloud, cam, background=world, layer=[glass, solid])
    invisible = cloud[:1].replace(opacity_logits=np.full(1, -30.0, np.float32))  # the surfaces alone
    bare = reference_render(invisible, cam, background=world, layer=[glass, solid])
    mixing = display(result["ViewLayer.Meshes"])[0] - bare["color"]  # linear vs display mixing, seen at T
    error = np.abs(got - both["color"] - both["layer_t"][..., :1] * mixing).max(axis=-1)
    overlap = (glass[1] > 0.01) & (solid[1] > 0.01)
    outline = ((glass[1] > 0.01) & (glass[1] < 0.59)) | ((solid[1] > 0.01) & (solid[1] < 0.99))
    assert error[~overlap & ~outline].max() <= 2 * STEP
    assert 0.05 < error[overlap].max() <= 1 - 0.6 + STEP  # at most what the plane lets through
    # where the plane is over the world alone, the splats behind it show through its 40%
    through = (glass[1] > 0.5) & (solid[1] < 0.01) & (single["layer_t"] > 0.99)
    assert (np.abs(got - display(result["ViewLayer.Meshes"])[0]).max(axis=-1)[through] > 0.05).sum() > 5


def test_command_verb_gives_the_f12_picture_and_can_leave_meshes_out(blender):
    res = blender.step("command")
    assert res["codes"] == [0, 0] and res["mesh_engine_after"] == "CYCLES"
    f12, verb = exr(blender.out / "f12.exr"), exr(blender.out / "verb_0001.exr")
    for name in ("ViewLayer.Combined", "ViewLayer.Depth.Z", "ViewLayer.Splats", "ViewLayer.Meshes"):
        np.testing.assert_array_equal(verb[name], f12[name])
    # --meshes none: the splats alone over the world colour, the plane and sphere gone
    alone = png(blender.out / "verb_none_0001.png")[..., :3]
    ref = reference_render(
        SplatCloud(**oracle_cloud_arrays()),
        camera(blender.step("oracle")["camera"]),
        background=linear_to_srgb(np.array(WORLD)),
    )
    assert np.abs(alone - np.clip(ref["color"], 0, 1)).max() <= 1.01 * STEP


def test_render_animation_renders_each_frames_meshes(blender):
    res = blender.step("animation")
    assert res["frame_after"] == 1
    frames = {f: exr(blender.out / f"anim_{f:04d}.exr") for f in (1, 2)}
    for f in (1, 2):
        meshes = exr(blender.out / f"anim_meshes_{f}.exr")
        np.testing.assert_allclose(frames[f]["ViewLayer.Meshes"], meshes["ViewLayer.Combined"], atol=1e-6)
        np.testing.assert_allclose(
            frames[f]["ViewLayer.Depth.Z"].min(),
            min(meshes["ViewLayer.Depth.Z"].min(), frames[f]["ViewLayer.Depth.Z"].min()),
        )
    moved = np.abs(frames[1]["ViewLayer.Meshes"] - frames[2]["ViewLayer.Meshes"]).max(axis=-1) > 0.05
    assert moved.sum() > 50


def test_viewport_picture_is_the_splats_over_the_meshes_seen_from_the_region(blender):
    """Rendered shading, headless: the region camera built from the view and projection matrices
    matches the scene camera; a coarse pass comes first, then the full picture, which is the
    float64 reference of the splats composited with the flat-shaded mesh layer; that layer's depth
    is Cycles' depth of the same meshes wherever both cover the whole pixel."""
    res = blender.step("viewport")
    got = blender.npz("viewport")
    cam = camera(res["camera"])
    assert res["scales"][0] == 0.25 and res["scales"][-1] == 1.0 and res["redraws"] >= 2
    assert got["coarse"].shape == (SIZE[1] // 4, SIZE[0] // 4, 4) and got["full"].shape == (SIZE[1], SIZE[0], 4)
    assert res["splats"] == len(oracle_cloud_arrays()["positions"]) and res["triangles"] > 500
    layer = (got["layer_color"], got["layer_alpha"], got["layer_depth"])
    ref = reference_render(SplatCloud(**oracle_cloud_arrays()), cam, background=res["background"], layer=layer)
    color, alpha = display(got["full"])
    assert np.abs(color - ref["color"]).max() <= STEP and (alpha == 1).all()
    cycles = exr(blender.out / "meshes_transparent.exr")
    inside = (cycles["ViewLayer.Combined"][..., 3] == 1) & (got["layer_alpha"] == 1)
    assert inside.sum() > 0.3 * inside.size
    np.testing.assert_allclose(got["layer_depth"][inside], cycles["ViewLayer.Depth.Z"][inside], rtol=1e-3)
