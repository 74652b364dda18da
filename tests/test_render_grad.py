"""The renderer's backward pass (core/render_grad.py), compiled and by NumPy, against central
differences of the float64 brute-force reference renderer, and bake_splats fitting geometry to
views of a known cloud."""

import numpy as np
import pytest
from helpers import random_cloud
from reference_render import reference_render
from test_bake import cameras_around, known_cloud

from splatwright.core.bake import bake_sh, bake_splats
from splatwright.core.camera import Camera
from splatwright.core.metrics import psnr
from splatwright.core.render import render
from splatwright.core.render_grad import mse_gradients
from splatwright.core.splats import FIELDS

BACKGROUND = np.array([0.1, 0.2, 0.3])


def overlapping_cloud(degree, seed=3):
    """40 splats crowding a 40x33 view: overlaps, partial opacities, some past the image edges."""
    cloud = random_cloud(40, sh_degree=degree, seed=seed, spread=0.6)
    rng = np.random.default_rng(seed)
    cloud.opacity_logits[:] = rng.uniform(-1.5, 1.0, len(cloud))
    cloud.log_scales[:] = np.log(rng.uniform(0.03, 0.15, (len(cloud), 3)))
    return cloud


CAMERAS = {
    "perspective": Camera.look_at((0.3, -0.4, 2.5), (0, 0, 0), width=40, height=33, fov_deg=50),
    "off-centre": Camera(40, 33, 38.0, 41.0, 12.0, 25.0, Camera.look_at((0.3, -0.4, 2.5), (0, 0, 0)).world_to_camera),
    "orthographic": Camera(
        40,
        33,
        30.0,
        30.0,
        20.0,
        16.5,
        Camera.look_at((1.0, 0.5, 2.5), (0, 0, 0)).world_to_camera,
        projection="orthographic",
    ),
}


def reference_mse(cloud, camera, target, mode):
    return np.mean((reference_render(cloud, camera, BACKGROUND, mode)["color"] - target) ** 2)


BACKENDS = ["compiled", "numpy"]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("view", sorted(CAMERAS))
def test_image_and_gradients_match_the_reference_renderer(mode, view, backend):
    """The image is the reference's; each parameter's gradient (its three largest entries and three
    more at random) is the central difference of the reference's squared error, at a step of 1e-4
    or, where that step moves a splat across another's depth or the 1/255 alpha rule (the error
    jumps there), of 1e-5."""
    assert_gradients_match_the_reference(overlapping_cloud(degree=3), CAMERAS[view], mode, backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_degree_4_images_and_gradients_match_the_reference_renderer(backend):
    """SH degree 4: its colours, their coefficients' gradients and the positions' gradients through
    the view direction (the fourth band's basis gradient) against the reference's own basis."""
    assert_gradients_match_the_reference(overlapping_cloud(degree=4), CAMERAS["perspective"], "classic", backend)


def assert_gradients_match_the_reference(cloud, camera, mode, backend):
    target = np.random.default_rng(5).uniform(0, 1, (camera.height, camera.width, 3))
    image, mse, grad = mse_gradients(cloud, camera, target, BACKGROUND, mode, precision="float64", backend=backend)
    reference = reference_render(cloud, camera, BACKGROUND, mode)["color"]
    assert np.abs(image - reference).max() < 1e-6
    assert mse == pytest.approx(np.mean((reference - target) ** 2), rel=1e-6)
    rng = np.random.default_rng(0)
    for name in FIELDS:
        g = getattr(grad, name).ravel()
        picks = np.r_[np.argsort(-np.abs(g))[:3], rng.integers(g.size, size=3)]
        for flat in picks:
            fd = [central_difference(cloud, name, flat, step, camera, target, mode) for step in (1e-4, 1e-5)]
            assert min(abs(g[flat] - d) for d in fd) < 5e-3 * np.abs(g).max() + 1e-9, (name, flat, g[flat], fd)


def central_difference(cloud, name, flat, step, camera, target, mode):
    ahead, behind = cloud.copy(), cloud.copy()
    getattr(ahead, name).ravel()[flat] += step
    getattr(behind, name).ravel()[flat] -= step
    taken = float(getattr(ahead, name).ravel()[flat]) - float(getattr(behind, name).ravel()[flat])  # float32
    return (reference_mse(ahead, camera, target, mode) - reference_mse(behind, camera, target, mode)) / taken


@pytest.mark.parametrize("backend", BACKENDS)
def test_opaque_stacks_stop_and_clamp_as_the_renderer_does(backend):
    """Opaque splats stacked along the view: the transmittance stop and the 0.99 clamp switch some
    of them off; the image still matches and the switched-off splats get no gradient."""
    cloud = overlapping_cloud(degree=0, seed=7)
    camera = CAMERAS["perspective"]
    depth = np.linspace(-0.6, 0.6, len(cloud))[:, None]
    cloud.positions[:] = 0.05 * cloud.positions + depth * camera.forward  # a column along the view
    cloud.log_scales[:] = np.log(np.linspace(0.3, 0.05, len(cloud)))[:, None]  # the far ones inside the near ones
    cloud.opacity_logits[:] = 8.0  # alpha clamped at 0.99 near each centre
    target = np.zeros((camera.height, camera.width, 3))
    image, _, grad = mse_gradients(cloud, camera, target, BACKGROUND, "classic", precision="float64", backend=backend)
    reference = reference_render(cloud, camera, BACKGROUND, "classic")
    assert np.abs(image - reference["color"]).max() < 1e-6
    hidden = reference["max_weight"] == 0  # no pixel composites them
    assert hidden.sum() >= 3
    for name in FIELDS:
        assert not getattr(grad, name)[hidden].any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_splats_the_camera_cannot_see_get_no_gradient(backend):
    cloud = overlapping_cloud(degree=1)
    camera = CAMERAS["perspective"]
    cloud.positions[0] = camera.center + 0.01 * camera.forward  # before the near plane
    cloud.positions[1] = [np.nan, 0, 0]
    cloud.positions[2] = camera.center - 3 * camera.forward  # behind the camera
    cloud.log_scales[3] = np.inf
    target = np.full((camera.height, camera.width, 3), 0.5)
    image, _, grad = mse_gradients(cloud, camera, target, BACKGROUND, precision="float64", backend=backend)
    keep = np.r_[False, False, False, False, np.ones(len(cloud) - 4, bool)]
    assert np.abs(image - reference_render(cloud[keep], camera, BACKGROUND)["color"]).max() < 1e-6
    for name in FIELDS:
        assert not getattr(grad, name)[:4].any() and np.isfinite(getattr(grad, name)).all()


def test_a_wrong_target_is_refused():
    with pytest.raises(ValueError, match="target image must be"):
        mse_gradients(overlapping_cloud(0), CAMERAS["perspective"], np.zeros((32, 40, 3)))


def test_bake_splats_moves_splats_back_to_where_the_views_show_them():
    """Views of a known cloud; the same cloud with its splats moved, shrunk or grown and made more
    transparent: Adam steps through the backward pass bring held-out views close to the truth,
    which SH colours alone cannot."""
    truth = known_cloud(150, seed=1, spread=0.6, log_scale=(-3.2, -2.6), opacity=(0.5, 0.9))
    rng = np.random.default_rng(2)
    moved = truth.replace(
        positions=truth.positions + rng.normal(0, 0.03, truth.positions.shape),
        log_scales=truth.log_scales + rng.normal(0, 0.3, truth.log_scales.shape),
        opacity_logits=truth.opacity_logits - 0.7,
    )
    cameras, held = cameras_around(24, seed=3, size=40), cameras_around(4, seed=4, size=40)
    images = [render(truth, c).color for c in cameras]
    truth_held = [render(truth, c).color for c in held]

    def held_psnr(cloud):
        return np.mean([psnr(render(cloud, c).color, t) for c, t in zip(held, truth_held)])

    coloured = bake_sh(moved, cameras, images)
    info = {}
    fitted = bake_splats(coloured, cameras, images, steps=600, info=info)
    assert held_psnr(fitted) > held_psnr(coloured) + 7  # 29.1 -> 37.6 dB
    assert info["psnr"][-1] > info["psnr"][0] + 6
    assert np.median(np.linalg.norm(fitted.positions - truth.positions, axis=1)) < 0.6 * np.median(
        np.linalg.norm(moved.positions - truth.positions, axis=1)
    )


def test_bake_splats_refuses_mismatched_views():
    cloud = overlapping_cloud(0)
    with pytest.raises(ValueError, match="one image per camera"):
        bake_splats(cloud, [CAMERAS["perspective"]], [])
    with pytest.raises(ValueError, match="steps must be"):
        bake_splats(cloud, [CAMERAS["perspective"]], [np.zeros((33, 40, 3))], steps=-1)


def test_a_wrong_backend_is_refused_and_compiled_needs_numba(monkeypatch):
    cloud, camera = overlapping_cloud(0), CAMERAS["perspective"]
    target = np.zeros((camera.height, camera.width, 3))
    with pytest.raises(ValueError, match="backend must be one of"):
        mse_gradients(cloud, camera, target, backend="gpu")
    monkeypatch.setenv("SPLATWRIGHT_JIT", "0")
    with pytest.raises(RuntimeError, match="SPLATWRIGHT_JIT=0"):
        mse_gradients(cloud, camera, target, backend="compiled")
    auto = mse_gradients(cloud, camera, target, precision="float64")  # NumPy then
    assert np.array_equal(auto[0], mse_gradients(cloud, camera, target, precision="float64", backend="numpy")[0])


def test_float32_pixels_give_the_float64_gradients():
    """The NumPy pass in float32 against the compiled one (float64 throughout)."""
    cloud, camera = overlapping_cloud(degree=2), CAMERAS["perspective"]
    target = np.random.default_rng(5).uniform(0, 1, (camera.height, camera.width, 3))
    exact = mse_gradients(cloud, camera, target, BACKGROUND, backend="compiled")
    fast = mse_gradients(cloud, camera, target, BACKGROUND, precision="float32", backend="numpy")
    assert np.abs(fast[0] - exact[0]).max() < 1e-5
    for name in FIELDS:
        g, h = getattr(exact[2], name), getattr(fast[2], name)
        assert np.abs(g - h).max() < 1e-4 * np.abs(g).max()
