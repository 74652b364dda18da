"""Appearance baking (core/bake.py): SH fitted to images of a cloud with known SH are recovered."""

import numpy as np
import pytest

from splatwright.core import SplatCloud
from splatwright.core import sh as shmod
from splatwright.core.bake import bake_sh, path_weights
from splatwright.core.camera import Camera
from splatwright.core.metrics import psnr
from splatwright.core.render import render


def known_cloud(n, seed, spread, log_scale, opacity, degree=2):
    """Splats whose colours stay in (0, 1) from every direction (no clamp), SH of `degree`."""
    rng = np.random.default_rng(seed)
    k = shmod.num_coeffs(degree)
    sh = np.zeros((n, k, 3))
    sh[:, 0] = shmod.rgb_to_dc(rng.uniform(0.3, 0.7, (n, 3)))
    sh[:, 1:] = rng.normal(0, 0.08, (n, k - 1, 3))
    return SplatCloud.from_activated(
        rng.uniform(-spread, spread, (n, 3)),
        rng.normal(size=(n, 4)),
        np.exp(rng.uniform(*log_scale, (n, 3))),
        rng.uniform(*opacity, n),
        colors=np.zeros((n, 3)),
    ).replace(sh=sh.astype(np.float32))


def cameras_around(count, seed, size=48):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return [
        Camera.look_at(
            3.0 * v, (0, 0, 0), up=(0, 1, 0) if abs(v[1]) < 0.9 else (1, 0, 0), fov_deg=50, width=size, height=size
        )
        for v in d
    ]


def scrambled(cloud, seed):
    noise = np.random.default_rng(seed).normal(0, 0.3, cloud.sh.shape)
    return cloud.replace(sh=(cloud.sh + noise).astype(np.float32))


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_isolated_splats_get_their_coefficients_back(backend):
    """Small splats apart from each other, seen from 40 directions: every coefficient of every
    splat is determined by its own pixels, and comes back from scrambled values."""
    cloud = known_cloud(60, seed=1, spread=1.0, log_scale=(-3.6, -3.2), opacity=(0.5, 0.9))
    cams = cameras_around(40, seed=2)
    info = {}
    fit = bake_sh(
        scrambled(cloud, 3),
        cams,
        [render(cloud, c).color for c in cams],
        iterations=60,
        damping=0.0,
        prior="cloud",
        info=info,
        backend=backend,
    )
    assert info["seen"] == len(cloud) and info["psnr"][0] < 30 and info["psnr"][-1] > 70
    np.testing.assert_allclose(fit.sh, cloud.sh, atol=2e-3)


def test_weighted_views_give_the_weighted_mean_of_what_they_show():
    """Every view twice, once showing one cloud and once another with other SH, the second weighted 3:
    the weighted least squares is (1 x first + 3 x second) / 4, coefficient by coefficient."""
    first = known_cloud(60, seed=1, spread=1.0, log_scale=(-3.6, -3.2), opacity=(0.5, 0.9))
    second = first.replace(sh=known_cloud(60, seed=17, spread=1.0, log_scale=(-3.6, -3.2), opacity=(0.5, 0.9)).sh)
    cams = cameras_around(40, seed=2)
    images = [render(first, c).color for c in cams] + [render(second, c).color for c in cams]
    weights = path_weights(40, 40, share=3.0)
    np.testing.assert_array_equal(weights, [1.0] * 40 + [3.0] * 40)
    fit = bake_sh(first, cams + cams, images, iterations=60, damping=0.0, prior="cloud", weights=weights)
    np.testing.assert_allclose(fit.sh, (first.sh + 3.0 * second.sh) / 4.0, atol=2e-3)


def test_path_weights_give_the_path_its_share():
    np.testing.assert_allclose(path_weights(96, 8), [1.0] * 96 + [12.0] * 8)
    np.testing.assert_allclose(path_weights(96, 8, share=0.5), [1.0] * 96 + [6.0] * 8)
    np.testing.assert_array_equal(path_weights(5, 0), np.ones(5))


def test_a_dense_cloud_matches_held_out_views_and_keeps_unseen_splats():
    """400 overlapping splats, a little damping: after 40 iterations held-out views match to > 45 dB; a splat no view
    sees keeps its SH (damping), and the fit raises the degree when asked (zero-padded start)."""
    cloud = known_cloud(400, seed=4, spread=0.8, log_scale=(-3.2, -2.2), opacity=(0.3, 0.8))
    hidden = cloud[:1].replace(opacity_logits=np.float32([-8.0]))  # too faint to show
    start = SplatCloud.concatenate([scrambled(cloud, 5), hidden])
    start = start.with_sh_degree(1)
    truth = SplatCloud.concatenate([cloud, hidden])
    cams, held_out = cameras_around(48, seed=6), cameras_around(6, seed=7)
    steps, info = [], {}
    fit = bake_sh(
        start,
        cams,
        [render(truth, c).color for c in cams],
        degree=2,
        iterations=40,
        info=info,
        damping=1e-3,
        band_damping=0.0,
        progress=lambda *step: steps.append(step),
    )
    assert fit.sh.shape == (401, 9, 3)
    assert steps[-1] == (41, 41, "bake") and len(info["psnr"]) == 41
    assert all(b >= a - 1e-6 for a, b in zip(info["psnr"], info["psnr"][1:]))  # CG never loses ground
    worst = min(psnr(render(fit, c).color, render(truth, c).color) for c in held_out)
    assert worst > 45
    np.testing.assert_array_equal(fit.sh[-1, :4], start.sh[-1])
    assert not fit.sh[-1, 4:].any()
    np.testing.assert_array_equal(fit.positions, start.positions)
    np.testing.assert_array_equal(fit.opacity_logits, start.opacity_logits)


def test_views_fitted_on_both_cores_give_the_fit_of_one_core():
    """The views are rendered on every core and their sums taken in the views' order: the same
    coefficients, to the bit, as one core rendering them one after another."""
    cloud = known_cloud(300, seed=14, spread=0.8, log_scale=(-3.2, -2.2), opacity=(0.3, 0.8))
    cams = cameras_around(12, seed=15)
    images = [render(cloud, c).color for c in cams]
    fits = [bake_sh(scrambled(cloud, 16), cams, images, iterations=5, threads=threads) for threads in (1, 2)]
    np.testing.assert_array_equal(fits[0].sh, fits[1].sh)
    assert np.abs(fits[0].sh - scrambled(cloud, 16).sh).max() > 0.01  # the fit moved them


def test_the_prior_is_each_splats_own_colour_where_splats_lie_apart():
    """No iteration: the start is each seen splat's weighted mean of the straight pixel colours, its
    own colour for a splat alone in its pixels (few overlap here), over a coloured background too."""
    cloud = known_cloud(8, seed=13, spread=1.0, log_scale=(-4.0, -3.8), opacity=(0.5, 0.9), degree=0)
    cams, bg = cameras_around(24, seed=14, size=160), (0.3, 0.1, 0.6)
    info = {}
    start = scrambled(cloud, 15).with_sh_degree(1)
    fit = bake_sh(
        start, cams, [render(cloud, c, background=bg).color for c in cams], background=bg, iterations=0, info=info
    )
    assert info["iterations"] == 0 and len(info["psnr"]) == 1
    error = np.abs(shmod.dc_to_rgb(fit.sh[:, 0]) - shmod.dc_to_rgb(cloud.sh[:, 0])).max(axis=1)
    assert np.median(error) < 2e-3 and error.max() < 0.05
    assert not fit.sh[:, 1:].any()
    prior_cloud = bake_sh(
        start, cams, [render(cloud, c, background=bg).color for c in cams], background=bg, iterations=0, prior="cloud"
    )
    np.testing.assert_array_equal(prior_cloud.sh, start.sh)


def test_a_background_is_taken_off_before_fitting():
    cloud = known_cloud(60, seed=8, spread=1.0, log_scale=(-3.6, -3.2), opacity=(0.5, 0.9), degree=0)
    cams, bg = cameras_around(12, seed=9), (0.2, 0.9, 0.4)
    fit = bake_sh(
        scrambled(cloud, 10),
        cams,
        [render(cloud, c, background=bg).color for c in cams],
        background=bg,
        iterations=30,
        damping=0.0,
    )
    np.testing.assert_allclose(fit.sh, cloud.sh, atol=2e-3)


def test_bad_input_is_refused():
    cloud = known_cloud(5, seed=11, spread=1.0, log_scale=(-3, -2), opacity=(0.5, 0.9))
    cams = cameras_around(2, seed=12)
    with pytest.raises(ValueError, match="one image per camera"):
        bake_sh(cloud, cams, [np.zeros((48, 48, 3))])
    with pytest.raises(ValueError, match="image 1 has shape"):
        bake_sh(cloud, cams, [np.zeros((48, 48, 3)), np.zeros((40, 48, 3))])
    with pytest.raises(ValueError, match="non-finite"):
        bake_sh(cloud, cams, [np.zeros((48, 48, 3)), np.full((48, 48, 3), np.nan)])
    for weights in ([1.0], [1.0, np.nan], [1.0, -1.0], [0.0, 0.0]):
        with pytest.raises(ValueError, match="view weights"):
            bake_sh(cloud, cams, [np.zeros((48, 48, 3))] * 2, weights=weights)
    with pytest.raises(ValueError, match="prior"):
        bake_sh(cloud, cams, [np.zeros((48, 48, 3))] * 2, prior="mean")
