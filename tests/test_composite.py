"""Splats composited with a surface rendered elsewhere (core.render.Layer) against the float64
brute-force reference, which inserts the surface into each pixel's splat list by depth written out
pixel by pixel (tests/reference_render.py); and the mesh-layer plumbing that needs no Blender."""

import numpy as np
import pytest
from helpers import random_cloud
from reference_render import reference_render

from splatwright.core import SplatCloud
from splatwright.core.camera import Camera
from splatwright.core.render import Layer, render

STEP = 1.0 / 255.0


@pytest.fixture(params=["compiled", "numpy"])
def backend(request):
    """Each test taking it runs on the compiled kernels and on the NumPy path."""
    return request.param


def crossing_scene(n=400, seed=0):
    """A random SH cloud around z = 3 that the surfaces below cut through."""
    c = random_cloud(n, sh_degree=2, seed=seed, spread=0.6)
    rng = np.random.default_rng(seed + 50)
    return c.replace(
        positions=c.positions + np.float32([0, 0, 3.0]), log_scales=rng.uniform(-3.5, -1.8, (n, 3)).astype(np.float32)
    )


def camera(width=64, height=48):
    return Camera.look_at((0.8, 0.5, -0.4), (0.0, 0.0, 3.0), fov_deg=60, width=width, height=height)


def surface(cam, seed=0, alpha=None):
    """A tilted plane through the cloud with a sphere in front of it and a hole (no surface: depth
    inf) in one corner: per pixel premultiplied colour, alpha and camera depth."""
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    depth = 2.7 + 0.02 * (cols - cam.width / 2) + 0.015 * (rows - cam.height / 2)
    ball = (cols - 0.4 * cam.width) ** 2 + (rows - 0.5 * cam.height) ** 2 < (0.2 * cam.height) ** 2
    depth = np.where(ball, 2.4 + 0.01 * np.abs(cols - 0.4 * cam.width), depth)
    depth[: cam.height // 4, : cam.width // 4] = np.inf
    rng = np.random.default_rng(seed)
    a = np.ones(depth.shape) if alpha is None else alpha(rng, depth.shape)
    a[np.isinf(depth)] = 0.0
    color = rng.uniform(0, 1, depth.shape + (3,)) * a[..., None]
    return Layer(color, a, depth)


def compare(cloud, cam, layer, background=(0.0, 0.0, 0.0), **options):
    got = render(cloud, cam, background=background, layer=layer, return_counts=True, **options)
    assert got.stats["backend"] == options.get("backend", "compiled")
    ref = reference_render(
        cloud,
        cam,
        background=(0.0, 0.0, 0.0) if background is None else background,
        layer=(layer.color, layer.alpha, layer.depth),
    )
    assert np.abs(got.color - ref["color"]).max() <= STEP
    assert np.abs(got.alpha - ref["alpha"]).max() <= STEP
    assert np.abs(got.layer_transmittance - ref["layer_t"]).max() <= STEP
    seen = (ref["alpha"] - ref["layer_t"] * layer.alpha) > 0.05  # the splats' own share
    np.testing.assert_allclose(got.depth[seen], ref["depth"][seen], rtol=1e-3)
    assert (got.counts != ref["counts"]).sum() <= 1
    return got, ref


def test_opaque_surface_hides_splats_behind_it_and_takes_what_is_left(backend):
    cloud, cam = crossing_scene(), camera()
    layer = surface(cam)
    got, ref = compare(cloud, cam, layer, backend=backend)
    plain = reference_render(cloud, cam)
    covered = layer.alpha == 1
    # the surface really cuts the cloud: splats behind it show in the plain render, not here
    assert np.abs(plain["color"] - ref["color"])[covered].max() > 0.2
    assert np.abs(got.alpha[covered] - 1).max() < 1e-6
    assert ((got.layer_transmittance > 0.05) & (got.layer_transmittance < 0.95) & covered).sum() > 50


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"tile_size": 7, "wave": 3},
        {"tile_size": 1, "wave": 2},
        {"tile_size": 16, "wave": 1000},
        {"threads": 1},
        {"precision": "float64"},
    ],
)
def test_speed_options_do_not_change_the_composite(options, backend):
    compare(crossing_scene(seed=1), camera(), surface(camera(), seed=1), **options, backend=backend)


def test_translucent_surface_shows_splats_behind_it_through_its_alpha(backend):
    cloud, cam = crossing_scene(seed=2), camera()
    layer = surface(cam, seed=2, alpha=lambda rng, shape: rng.uniform(0.0, 1.0, shape))
    got, ref = compare(cloud, cam, layer, background=(0.1, 0.2, 0.3), backend=backend)
    assert np.isfinite(got.color).all()


def test_transparent_render_and_background_after_the_surface(backend):
    cloud, cam = crossing_scene(seed=3), camera()
    layer = surface(cam, seed=3, alpha=lambda rng, shape: rng.choice([0.0, 0.5, 1.0], shape))
    compare(cloud, cam, layer, background=None, backend=backend)
    compare(cloud, cam, layer, background=(0.9, 0.4, 0.1), backend=backend)


def test_empty_surface_gives_the_plain_render(backend):
    cloud, cam = crossing_scene(seed=4), camera()
    shape = (cam.height, cam.width)
    nothing = Layer(np.zeros(shape + (3,)), np.zeros(shape), np.full(shape, np.inf))
    got = render(cloud, cam, layer=nothing, background=(0.2, 0.3, 0.4), backend=backend)
    plain = render(cloud, cam, background=(0.2, 0.3, 0.4), backend=backend)
    np.testing.assert_allclose(got.color, plain.color, atol=1e-6)
    np.testing.assert_allclose(got.alpha, plain.alpha, atol=1e-6)
    np.testing.assert_array_equal(got.depth, plain.depth)
    np.testing.assert_allclose(got.layer_transmittance, 1 - plain.alpha, atol=1e-6)


def test_surface_in_front_of_every_splat_is_all_that_shows_and_saves_the_work(backend):
    cloud, cam = crossing_scene(seed=5), camera()
    shape = (cam.height, cam.width)
    wall = Layer(np.full(shape + (3,), 0.25), np.ones(shape), np.full(shape, 0.5))
    got = render(cloud, cam, layer=wall, background=(1.0, 1.0, 1.0), wave=4, backend=backend)
    assert np.abs(got.color - 0.25).max() < 1e-6 and (got.alpha == 1).all() and (got.layer_transmittance == 1).all()
    # every pixel stops at the wall: only the first wave (NumPy) or alive check (compiled) of each tile is evaluated
    assert got.stats["evaluated"] < 0.3 * render(cloud, cam, wave=4, backend=backend).stats["evaluated"]


def test_pixels_that_stop_on_an_opaque_pile_give_the_surface_their_last_transmittance(backend):
    n = 300
    rng = np.random.default_rng(6)
    pile = SplatCloud.from_activated(  # dense, near-opaque, in front of the surface
        positions=np.column_stack([rng.normal(0, 0.15, n), rng.normal(0, 0.15, n), rng.uniform(2.0, 2.3, n)]),
        rotations=np.tile([1.0, 0, 0, 0], (n, 1)),
        scales=rng.uniform(0.05, 0.2, (n, 3)),
        opacities=rng.uniform(0.5, 1.0, n),
        colors=rng.uniform(0, 1, (n, 3)),
    )
    cloud = pile.replace(opacity_logits=np.where(np.arange(n) < n // 2, np.float32(1e4), pile.opacity_logits))
    cam = Camera.look_at((0, 0, 0), (0, 0, 3), fov_deg=30, width=40, height=40)
    shape = (cam.height, cam.width)
    layer = Layer(np.full(shape + (3,), 0.7), np.ones(shape), np.full(shape, 2.5))
    got, ref = compare(cloud, cam, layer, backend=backend)
    stopped = ref["layer_t"] < 0.011  # stopped on the pile: T between 1e-4 and 0.01 left
    assert stopped.sum() > 20 and (ref["layer_t"][stopped] >= 1e-4).all()


def test_splat_exactly_at_the_surface_depth_goes_behind_it(backend):
    one = SplatCloud.from_activated(
        positions=[[0.0, 0.0, 2.0]],
        rotations=[[1.0, 0, 0, 0]],
        scales=[[0.3] * 3],
        opacities=[0.9],
        colors=[[1.0, 0.0, 0.0]],
    )
    cam = Camera.look_at((0, 0, 0), (0, 0, 2), fov_deg=40, width=8, height=8)
    shape = (8, 8)
    at = Layer(np.zeros(shape + (3,)), np.ones(shape), np.full(shape, np.float32(2.0)))
    assert render(one, cam, layer=at, backend=backend).color.max() == 0
    before = Layer(np.zeros(shape + (3,)), np.ones(shape), np.full(shape, np.nextafter(np.float32(2.0), np.float32(3))))
    assert render(one, cam, layer=before, backend=backend).color[..., 0].max() > 0.5


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda l: l.__setattr__("depth", l.depth[:-1]), ["layer depth", "shape", "(48, 64)"]),
        (lambda l: l.__setattr__("color", l.color[..., :2]), ["layer color", "(48, 64, 3)"]),
        (lambda l: l.depth.__setitem__((3, 4), np.nan), ["layer depth", "1 NaN"]),
        (lambda l: l.color.__setitem__((3, 4, 0), np.inf), ["layer color", "non-finite"]),
        (lambda l: l.alpha.__setitem__((0, 0), 1.5), ["layer alpha", "[0, 1]"]),
    ],
)
def test_bad_layers_are_refused_by_name(change, words):
    layer = surface(camera())
    change(layer)
    with pytest.raises(ValueError) as err:
        render(crossing_scene(n=20), camera(), layer=layer)
    for word in words:
        assert word in str(err.value)
