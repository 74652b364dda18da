"""The fast renderer, both its compiled kernels and its NumPy path, against the float64 brute-force
reference (tests/reference_render.py), the hard cases of the design notes, and image writing."""

import os
import shutil
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from helpers import random_cloud
from reference_render import reference_render

from splatwright.core import SplatCloud, jit
from splatwright.core.camera import Camera
from splatwright.core.render import KERNELS, Shapes, backend_status, render
from splatwright.core.scenes import seed_cube
from splatwright.io import SplatFileError, write_splats
from splatwright.io.exr import read_exr
from splatwright.io.image import write_image

STEP = 1.0 / 255.0


@pytest.fixture(params=["compiled", "numpy"])
def backend(request):
    """Each test taking it runs on the compiled kernels and on the NumPy path."""
    return request.param


def scene(n=300, seed=0, center=(0.0, 0.0, 3.0), spread=0.7, sh_degree=3, log_scale=(-4.0, -1.5)):
    """A random anisotropic SH cloud in front of the cameras below, with non-unit quaternions."""
    c = random_cloud(n, sh_degree=sh_degree, seed=seed, spread=spread)
    rng = np.random.default_rng(seed + 100)
    return c.replace(
        positions=c.positions + np.float32(center), log_scales=rng.uniform(*log_scale, (n, 3)).astype(np.float32)
    )


def perspective(width=64, height=48, fov=60.0, eye=(1.8, 1.2, 4.5), target=(0.0, 0.0, 3.0)):
    return Camera.look_at(eye, target, fov_deg=fov, width=width, height=height)


def orthographic(width=64, height=48):
    return Camera.look_at_ortho((1.8, 1.2, 4.5), (0.0, 0.0, 3.0), ortho_scale=2.5, width=width, height=height)


def assert_matches_reference(cloud, camera, color_tol=STEP, background=(0.0, 0.0, 0.0), **options):
    mode = options.get("mode", "classic")
    got = render(cloud, camera, background=background, return_counts=True, **options)
    ref = reference_render(cloud, camera, background=background, mode=mode, t_min=options.get("t_min", 1e-4))
    assert got.stats["backend"] == options.get("backend", "compiled")
    for name in ("color", "alpha", "depth"):
        assert np.isfinite(getattr(got, name)).all(), f"non-finite {name}"
    assert got.color.shape == (camera.height, camera.width, 3) and got.color.dtype == np.float32
    assert np.abs(got.color - ref["color"]).max() <= color_tol
    assert np.abs(got.alpha - ref["alpha"]).max() <= color_tol
    seen = ref["alpha"] > 0.05
    np.testing.assert_allclose(got.depth[seen], ref["depth"][seen], rtol=1e-3)
    assert (got.depth[ref["alpha"] == 0] == 0).all()
    # the 1/255 and stopping rules pick the same splats (a pixel might flip at float32 round-off)
    assert (got.counts != ref["counts"]).sum() <= 1
    return got, ref


# agreement with the reference -----------------------------------------------------------------


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("make_camera", [perspective, orthographic], ids=["perspective", "orthographic"])
@pytest.mark.parametrize("seed", [0, 1])
def test_random_sh3_scenes_match_the_float64_reference(mode, make_camera, seed, backend):
    got, ref = assert_matches_reference(
        scene(seed=seed), make_camera(), mode=mode, background=(0.2, 0.5, 0.9), backend=backend
    )
    assert ref["alpha"].max() > 0.9 and (ref["counts"] > 3).any()  # a scene with real overlap


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("make_camera", [perspective, orthographic], ids=["perspective", "orthographic"])
def test_random_sh4_scenes_match_the_float64_reference(mode, make_camera, backend):
    """Degree 4 through both paths (the compiled one really compiled) against the reference's own
    literal basis; the fourth band changes the picture, so a path that dropped it would fail."""
    cloud = scene(seed=5, sh_degree=4)
    got, ref = assert_matches_reference(cloud, make_camera(), mode=mode, background=(0.2, 0.5, 0.9), backend=backend)
    if backend == "compiled":
        assert jit.status(KERNELS) == "compiled"
    without = reference_render(cloud.with_sh_degree(3), make_camera(), background=(0.2, 0.5, 0.9), mode=mode)
    assert np.abs(without["color"] - ref["color"]).max() > 20 * STEP


def test_splats_render_by_default_in_the_mode_they_were_made_for(backend):
    made = scene(seed=3).replace(antialiased=True)
    by_default = render(made, perspective(), backend=backend).color
    ref = reference_render(made, perspective(), mode="antialiased")["color"]
    assert np.abs(by_default - ref).max() <= STEP
    classic = render(made, perspective(), mode="classic", backend=backend).color
    assert np.abs(classic - reference_render(made, perspective(), mode="classic")["color"]).max() <= STEP
    assert np.abs(classic - by_default).max() > 10 * STEP  # the two modes differ on this scene


@pytest.mark.parametrize(
    "options",
    [{"tile_size": 8}, {"tile_size": 7, "wave": 3}, {"tile_size": 1}, {"tile_size": 32, "wave": 1000}, {"threads": 1}],
)
def test_speed_options_do_not_change_the_image(options, backend):
    assert_matches_reference(scene(seed=2), perspective(), **options, backend=backend)


def test_float64_precision_agrees_to_round_off(backend):
    got, ref = assert_matches_reference(scene(seed=3), perspective(), precision="float64", backend=backend)
    assert np.abs(got.color - ref["color"]).max() < 1e-6


def opaque_pile(n, seed, spread, log_scales):
    """n splats around the axis (sideways sigma `spread`, depth 2.5..3.5), opacities 0.5..1, the
    first half at logit +1e4 so their alpha clamps at 0.99."""
    rng = np.random.default_rng(seed)
    pile = SplatCloud.from_activated(
        positions=np.column_stack([rng.normal(0, spread, n), rng.normal(0, spread, n), rng.uniform(2.5, 3.5, n)]),
        rotations=rng.normal(size=(n, 4)),
        scales=np.exp(rng.uniform(*log_scales, (n, 3))),
        opacities=rng.uniform(0.5, 1.0, n),
        colors=rng.uniform(0, 1, (n, 3)),
    )
    pile.opacity_logits[: n // 2] = 1e4
    return pile


def test_opaque_pile_stops_at_the_transmittance_limit_and_clamps_alpha(backend):
    """Many opaque splats (logit +1e4: alpha clamps at 0.99) stacked in depth, so most pixels stop
    before T < 1e-4, and the background never shows through."""
    cloud = opaque_pile(200, seed=5, spread=0.15, log_scales=(-3, -1.5))
    got, ref = assert_matches_reference(cloud, perspective(), background=(1.0, 1.0, 1.0), backend=backend)
    stopped = reference_render(cloud, perspective(), t_min=0.0)["counts"] > ref["counts"]
    assert stopped.sum() > 100


def test_two_threads_and_one_thread_give_identical_images_on_a_large_cloud(backend):
    """More than one projection and binning chunk: the parallel paths must not change a bit."""
    cloud = scene(n=70_000, seed=4, spread=0.8, log_scale=(-6, -3.5), sh_degree=1)  # > 1 chunk
    cam = perspective(96, 64)
    a = render(cloud, cam, return_counts=True, threads=2, backend=backend)
    b = render(cloud, cam, return_counts=True, threads=1, backend=backend)
    for name in ("color", "alpha", "depth", "counts"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    pixels = np.random.default_rng(0).integers(0, [96, 64], (300, 2))
    ref = reference_render(cloud, cam, pixels=pixels)
    assert np.abs(a.color[pixels[:, 1], pixels[:, 0]] - ref["color"]).max() <= STEP
    assert (a.counts > 20).any()


# hard cases --------------------------------------------------------------------------------------


def test_near_plane_behind_on_and_across(backend):
    cam = Camera.look_at((0, 0, 0), (0, 0, 1), fov_deg=60, width=48, height=40, near=0.25)
    z = np.array([-1.0, 0.1, 0.25, 0.25 + 2.0**-20, 0.26, 0.3, 0.5, 1.0])  # float32-exact
    n = len(z)
    cloud = SplatCloud.from_activated(
        positions=np.column_stack([np.linspace(-0.05, 0.05, n), np.zeros(n), z]),
        rotations=np.tile([1.0, 0, 0, 0], (n, 1)),
        scales=np.column_stack([np.full(n, 0.3), np.full(n, 0.05), np.full(n, 0.4)]),  # reach across z = 0.2
        opacities=np.full(n, 0.6),
        colors=np.linspace(0, 1, 3 * n).reshape(n, 3),
    )
    got, ref = assert_matches_reference(cloud, cam, backend=backend)
    assert got.stats["visible"] == 5  # z <= near is culled, as in the reference


def test_scales_from_1e_minus_7_to_1e4_in_one_cloud(backend):
    cloud = scene(n=60, seed=6)
    exps = np.linspace(np.log(1e-7), np.log(1e4), 60)
    cloud.log_scales[:] = (exps[:, None] + np.array([0.0, -0.5, 0.3])).astype(np.float32)
    cloud.opacity_logits[:] = np.linspace(-3, 3, 60)
    assert_matches_reference(cloud, perspective(), mode="classic", backend=backend)
    assert_matches_reference(cloud, perspective(), mode="antialiased", backend=backend)


def test_needles_and_pancakes(backend):
    rng = np.random.default_rng(8)
    cloud = scene(n=150, seed=8)
    thin = rng.integers(0, 3, 150)
    scales = np.full((150, 3), 0.15)
    scales[np.arange(150), thin] = 1e-5  # pancakes
    scales[:75] = 1e-5
    scales[np.arange(75), thin[:75]] = 0.3  # needles
    cloud.log_scales[:] = np.log(scales)
    assert_matches_reference(cloud, perspective(), backend=backend)


def test_far_from_origin_renders_like_the_same_scene_at_the_origin(backend):
    base = scene(n=200, seed=9, center=(0, 0, 0), spread=0.5)
    grid = np.round(base.positions * 16) / 16  # exactly representable at 1e6 too
    offset = np.array([1e6, -1e6, 5e5])
    far = base.replace(positions=(grid + offset).astype(np.float32))
    near = base.replace(positions=grid.astype(np.float32))
    assert np.array_equal(far.positions.astype(np.float64) - offset, near.positions)
    eye, target = np.array([1.8, 1.2, 1.5]), np.zeros(3)
    cam_far = Camera.look_at(eye + offset, target + offset, fov_deg=60, width=64, height=48)
    cam_near = Camera.look_at(eye, target, fov_deg=60, width=64, height=48)
    got = render(far, cam_far, backend=backend)
    ref = reference_render(near, cam_near)
    assert np.abs(got.color - ref["color"]).max() <= STEP
    assert ref["alpha"].max() > 0.5


def test_identical_depths_sort_by_index(backend):
    """Overlapping splats at one depth: the earlier index is in front, as with a stable sort."""
    n = 30
    rng = np.random.default_rng(10)
    pos = np.column_stack([rng.normal(0, 0.1, n), rng.normal(0, 0.1, n), np.full(n, 3.0)])
    cloud = SplatCloud.from_activated(
        pos, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.15), np.full(n, 0.9), colors=rng.uniform(0, 1, (n, 3))
    )
    cam = Camera.look_at_ortho((0, 0, 0), (0, 0, 1), ortho_scale=1.0, width=40, height=40)
    got, _ = assert_matches_reference(cloud, cam, backend=backend)
    flipped = cloud[np.arange(n)[::-1]]
    got_flipped, _ = assert_matches_reference(flipped, cam, backend=backend)
    assert np.abs(got.color - got_flipped.color).max() > 0.1  # order matters, and is followed


@pytest.mark.parametrize("width, height, fov", [(1, 1, 60.0), (1, 7, 60.0), (64, 48, 5.0), (64, 48, 160.0)])
def test_tiny_images_and_extreme_fields_of_view(width, height, fov, backend):
    cloud = scene(seed=11, spread=0.3 if fov < 10 else 0.7)
    assert_matches_reference(cloud, perspective(width, height, fov), backend=backend)


def test_off_centre_principal_point(backend):
    cam = perspective()
    shifted = cam.with_(cx=cam.cx + 13.5, cy=cam.cy - 7.25, fy=cam.fy * 1.3)
    assert_matches_reference(scene(seed=12), shifted, backend=backend)


def test_empty_cloud_and_nothing_visible(backend):
    cam = perspective()
    for cloud in (SplatCloud.empty(3), scene(seed=13, center=(0, 0, 30)).replace(opacity_logits=np.full(300, -20))):
        got = render(cloud, cam, background=(0.1, 0.2, 0.3), return_counts=True, backend=backend)
        np.testing.assert_array_equal(got.color, np.broadcast_to(np.float32([0.1, 0.2, 0.3]), (48, 64, 3)))
        assert not got.alpha.any() and not got.depth.any() and not got.counts.any()


def test_non_finite_splats_are_skipped_and_counted(backend):
    cloud = scene(seed=14)
    bad = cloud.copy()
    bad.positions[3, 0] = np.nan
    bad.rotations[5] = np.inf
    bad.log_scales[7, 2] = np.inf
    bad.opacity_logits[9] = np.nan
    bad.sh[11, 4, 1] = -np.inf
    got = render(bad, perspective(), backend=backend)
    clean = render(cloud[np.setdiff1d(np.arange(len(cloud)), [3, 5, 7, 9, 11])], perspective(), backend=backend)
    assert got.stats["skipped_nonfinite"] == 5
    np.testing.assert_array_equal(got.color, clean.color)


def test_shapes_made_once_render_every_view_and_every_shifted_or_recoloured_copy_as_without_them():
    """Shapes computed once (as a refinement's measures and a bake's fit do) give each view the
    image render() gives without them, to the bit, non-finite splats skipped and counted alike, for
    copies with other positions and colours too."""
    cloud = scene(n=2000, seed=15)
    cloud.positions[3, 0] = np.nan
    cloud.rotations[5] = np.inf
    cloud.log_scales[7, 2] = np.inf
    cloud.log_scales[8, 1] = -np.inf
    cloud.opacity_logits[9] = np.nan
    cloud.sh[11, 4, 1] = -np.inf
    cloud.rotations[13] = 0.0  # a zero quaternion: the identity
    shapes = Shapes(cloud)
    shifted = cloud.replace(
        positions=cloud.positions + np.float32([0.05, -0.02, 0.1]),
        sh=np.random.default_rng(2).normal(0, 0.3, cloud.sh.shape).astype(np.float32),
    )
    for camera in (perspective(), perspective(eye=(0.2, -2.5, 1.0)), orthographic()):
        for mode in ("classic", "antialiased"):
            for splats in (cloud, shifted):
                want = render(splats, camera, mode=mode, return_weights=True, threads=1)
                got = render(splats, camera, mode=mode, return_weights=True, threads=1, shapes=shapes)
                for name in ("color", "alpha", "depth", "max_weight"):
                    np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
                assert got.stats["skipped_nonfinite"] == want.stats["skipped_nonfinite"] >= 5


def test_shapes_of_other_splats_are_refused():
    cloud = scene(seed=16)
    shapes = Shapes(cloud)
    other = cloud.replace(rotations=cloud.rotations.copy())  # equal values, but not the arrays they were made from
    with pytest.raises(ValueError, match="shapes were made from other splats"):
        render(other, perspective(), shapes=shapes)
    render(cloud.replace(positions=cloud.positions + 1), perspective(), shapes=shapes)  # the same shapes, moved


def test_rows_draw_a_subset_as_a_copy_of_it_would_be_drawn(backend):
    """A render of some rows (as a shadow map draws a light's casters) is the render of a copy of
    those splats, to the bit, by index or by mask, with and without Shapes; skipped splats count
    among the rows only, and per-splat results keep the whole cloud's numbering."""
    cloud = scene(n=2000, seed=17)
    cloud.positions[3, 0] = np.nan  # drawn, and skipped
    cloud.rotations[4] = np.inf  # not drawn: not counted
    rows = np.flatnonzero(np.random.default_rng(3).random(len(cloud)) < 0.4)
    rows = np.union1d(rows, [3])
    rows = rows[rows != 4]
    mask = np.zeros(len(cloud), bool)
    mask[rows] = True
    copy = cloud[rows]
    for camera in (perspective(), orthographic()):
        want = render(copy, camera, return_weights=True, backend=backend)
        choices = [(rows, None), (mask, None)] + ([(rows, Shapes(cloud))] if backend == "compiled" else [])
        for chosen, shapes in choices:
            got = render(cloud, camera, return_weights=True, backend=backend, rows=chosen, shapes=shapes)
            for name in ("color", "alpha", "depth"):
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
            np.testing.assert_array_equal(got.max_weight[rows], want.max_weight)
            assert got.max_weight.shape == (len(cloud),) and not got.max_weight[~mask].any()
            assert got.stats["skipped_nonfinite"] == want.stats["skipped_nonfinite"] == 1
    assert not render(cloud, perspective(), backend=backend, rows=rows[:0]).alpha.any()


def test_bad_rows_are_refused():
    cloud = scene(seed=18)
    for rows, message in (
        (np.array([0, len(cloud)]), "must index the cloud"),
        (np.array([-1, 2]), "must index the cloud"),
        (np.ones(5, bool), "one value per splat"),
        (np.array([0.5, 1.0]), "splat indices"),
    ):
        with pytest.raises(ValueError, match=message):
            render(cloud, perspective(), rows=rows)


def test_extreme_logits_and_zero_quaternions(backend):
    cloud = scene(seed=15)
    cloud.opacity_logits[::3] = 1e4
    cloud.opacity_logits[1::3] = -1e4
    cloud.rotations[::4] = 0.0
    with np.errstate(over="raise", invalid="raise", divide="raise"):
        got = render(cloud, perspective(), backend=backend)
    assert np.isfinite(got.color).all()
    assert_matches_reference(cloud, perspective(), backend=backend)


def test_no_transmittance_stop_counts_every_footprint_pixel(backend):
    cloud = scene(seed=16)
    got, ref = assert_matches_reference(cloud, perspective(), t_min=0.0, backend=backend)
    assert got.counts.sum() == ref["counts"].sum()


def test_three_sigma_cut_only_drops_faint_tails(backend):
    cloud = scene(seed=17)
    ref = reference_render(cloud, perspective())
    cut = render(cloud, perspective(), max_sigma=3.0, backend=backend)
    err = np.abs(cut.color - ref["color"]).max()
    assert 0 < err < 0.05


def test_bad_options_are_refused():
    for kwargs, message in [
        ({"mode": "fast"}, "mode"),
        ({"tile_size": 0}, "tile_size"),
        ({"precision": "float16"}, "precision"),
        ({"background": (1, 2)}, "background"),
        ({"t_min": 1.0}, "t_min"),
        ({"wave": 0}, "wave"),
    ]:
        with pytest.raises(ValueError, match=message):
            render(scene(n=5), perspective(), **kwargs)


def test_progress_reports_every_tile():
    calls = []
    render(scene(seed=18), perspective(), tile_size=16, progress=lambda done, total, label: calls.append((done, total)))
    assert calls and calls[-1][0] == calls[-1][1] == 4 * 3
    assert all(a[0] <= b[0] for a, b in zip(calls, calls[1:]))


# per-splat weights ---------------------------------------------------------------------------------


def assert_weights_match_reference(cloud, camera, atol=2e-6, **options):
    """max_weight against the reference's float64 per-splat maximum of T * alpha, and the image
    unchanged by asking for it."""
    got = render(cloud, camera, return_weights=True, **options)
    ref = reference_render(cloud, camera, mode=options.get("mode", "classic"), t_min=options.get("t_min", 1e-4))
    assert got.max_weight.shape == (len(cloud),) and got.max_weight.dtype == np.float32
    assert np.isfinite(got.max_weight).all()
    np.testing.assert_array_equal(got.max_weight > 0, ref["max_weight"] > 0)
    np.testing.assert_allclose(got.max_weight, ref["max_weight"], rtol=0, atol=atol)
    plain = render(cloud, camera, **options)
    assert plain.max_weight is None
    np.testing.assert_array_equal(got.color, plain.color)
    return got.max_weight, ref["max_weight"]


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("make_camera", [perspective, orthographic], ids=["perspective", "orthographic"])
def test_max_weights_match_the_float64_reference(mode, make_camera, backend):
    got, want = assert_weights_match_reference(scene(seed=20), make_camera(), mode=mode, backend=backend)
    assert (want > 0.5).any() and (want > 0).sum() > 100 and (want == 0).any()


@pytest.mark.parametrize(
    "options", [{"tile_size": 7, "wave": 3}, {"tile_size": 1}, {"threads": 1}, {"precision": "float64"}, {"t_min": 0.0}]
)
def test_max_weights_do_not_depend_on_speed_options(options, backend):
    atol = 1e-7 if options.get("precision") == "float64" else 2e-6  # float64: float32 output rounding
    assert_weights_match_reference(scene(seed=21), perspective(61, 45), atol=atol, **options, backend=backend)


def test_max_weights_follow_the_stop_rule_and_skip_hidden_faint_and_broken_splats(backend):
    """A pile of splats, half clamped at alpha 0.99, in front of three broad layers of opacity 0.98
    filling the view: every pixel stops before the third layer (0.02^3 < 1e-4), so it and the
    splats behind it get no weight. Then one splat too faint for 1/255, one behind the camera, one
    off-image and one with NaN."""
    n = 80
    pile = opaque_pile(n, seed=22, spread=0.1, log_scales=(-2.5, -1.5))
    back = SplatCloud.from_activated(
        positions=[
            [0, 0, 4.0],
            [0, 0, 4.1],
            [0, 0, 4.2],
            [0, 0, 4.5],
            [0.1, 0.1, 4.6],
            [0.3, 0.2, 2.0],
            [0, 0, -2.0],
            [9.0, 0, 3.0],
            [np.nan, 0, 3.0],
        ],
        rotations=np.tile([1.0, 0, 0, 0], (9, 1)),
        scales=[[100.0] * 3] * 3 + [[0.02] * 3] * 6,
        opacities=[0.98] * 3 + [0.9] * 2 + [1 / 300, 0.9, 0.9, 0.9],
        colors=np.full((9, 3), 0.5),
    )
    cloud = SplatCloud.concatenate([pile, back])
    cam = Camera.look_at((0, 0, 0), (0, 0, 1), fov_deg=30, width=40, height=36)
    with np.errstate(invalid="ignore"):
        got, want = assert_weights_match_reference(cloud, cam, backend=backend)
        unstopped = reference_render(cloud, cam, t_min=0.0)["max_weight"]
    assert (want[: n + 2] > 0).all() and (want[n + 2 :] == 0).all()
    assert (unstopped[n + 2 : n + 5] > 0).all()  # seen but for the stop rule
    assert not got[n + 2 :].any()


def test_max_weights_of_an_empty_or_unseen_cloud_are_zero(backend):
    for cloud in (SplatCloud.empty(3), scene(seed=23, center=(0, 0, 30))):  # behind the camera
        got = render(cloud, perspective(), return_weights=True, backend=backend)
        assert got.max_weight.shape == (len(cloud),) and not got.max_weight.any()


def test_max_weights_count_only_pixels_inside_the_image(backend):
    """Splats centred just beyond the right and bottom edges of an image that is not a whole number
    of tiles: their peak lies in the last tiles' pixels outside the image, which must not count."""
    cam = Camera.look_at_ortho((0, 0, 0), (0, 0, 1), up=(0, -1, 0), ortho_scale=2.0, width=61, height=45)
    pixel = 2.0 / 61
    edge = [[30.5 * pixel + 1.2 * pixel, 0.0, 2.0], [0.0, 22.5 * pixel + 1.2 * pixel, 2.0]]
    cloud = SplatCloud.from_activated(
        edge, np.tile([1.0, 0, 0, 0], (2, 1)), np.full((2, 3), pixel), np.full(2, 0.9), colors=np.full((2, 3), 0.5)
    )
    pixels, _ = cam.project(cloud.positions)
    assert pixels[0, 0] > 61 and pixels[1, 1] > 45  # both centres outside
    got, want = assert_weights_match_reference(cloud, cam, backend=backend)
    assert (want > 0).all() and (want < 0.5 * 0.9).all()  # well below the peak alpha


# gathering an image through the blending weights ----------------------------------------------------


@pytest.mark.parametrize("make_camera", [perspective, orthographic], ids=["perspective", "orthographic"])
@pytest.mark.parametrize("options", [{}, {"tile_size": 7, "threads": 1}, {"precision": "float64", "t_min": 0.0}])
def test_gathered_sums_match_the_float64_reference(make_camera, options, backend):
    """Each splat's sum over pixels of T alpha x image, for a 4-channel image on a camera whose size
    is no whole number of tiles; the image is unchanged by asking for it."""
    cloud, camera = scene(seed=24), make_camera(61, 45)
    image = np.random.default_rng(24).normal(size=(camera.height, camera.width, 4))
    got = render(cloud, camera, gather=image, backend=backend, **options)
    ref = reference_render(cloud, camera, t_min=options.get("t_min", 1e-4), gather=image)
    assert got.gathered.shape == (len(cloud), 4) and got.gathered.dtype == np.float64
    scale = np.abs(ref["gathered"]).max()
    assert scale > 1 and (ref["gathered"] == 0).any()
    np.testing.assert_allclose(got.gathered, ref["gathered"], rtol=0, atol=2e-5 * scale)
    np.testing.assert_array_equal(got.color, render(cloud, camera, backend=backend, **options).color)
    assert render(cloud, camera, backend=backend).gathered is None


def test_gathering_is_the_adjoint_of_rendering_colours(backend):
    """<A x, r> = <x, A^T r>: A renders per-splat colours x (SH degree 0, no background), A^T
    gathers an image r; single-channel images gather into one column."""
    rng = np.random.default_rng(25)
    base, camera = scene(seed=25, sh_degree=0), perspective()
    x = rng.uniform(0, 1, (len(base), 3))
    cloud = base.replace(sh=((x - 0.5) / 0.28209479177387814)[:, None, :].astype(np.float32))
    r = rng.normal(size=(camera.height, camera.width, 3))
    image = render(cloud, camera, background=None, gather=r, backend=backend)
    x32 = 0.5 + 0.28209479177387814 * cloud.sh[:, 0].astype(np.float64)  # the colours as stored
    lhs, rhs = np.vdot(image.color, r), np.vdot(x32, image.gathered)
    assert abs(lhs) > 10 and abs(lhs - rhs) <= 1e-5 * np.abs(image.color * r).sum()
    mono = render(cloud, camera, gather=r[..., 1], backend=backend).gathered
    np.testing.assert_allclose(mono[:, 0], image.gathered[:, 1], rtol=0, atol=1e-6 * np.abs(mono).max())


def test_bad_gather_images_are_refused(backend):
    camera = perspective()
    for bad, word in ((np.zeros((10, 10)), "shape"), (np.full((48, 64, 3), np.nan), "non-finite")):
        with pytest.raises(ValueError, match=word):
            render(scene(n=10), camera, gather=bad, backend=backend)


# the compiled kernels, the fallback and limits ---------------------------------------------------


def test_the_compiled_depth_sort_is_a_stable_argsort():
    """stable_order, the compiled projection's depth sort, against NumPy's stable argsort of the
    same rows: keys over all 32 bits, a few distinct keys (ties stay in row order), keys sharing
    their high bytes or all of them, one row and none."""
    from splatwright.core import jit
    from splatwright.core.render import KERNELS, _check_kernels

    kernels = jit.load(KERNELS, check=_check_kernels)
    rng = np.random.default_rng(12)
    for n, distinct in ((0, 10), (1, 10), (9, 1), (5000, 3), (100_000, 1 << 32), (20_000, 1 << 16), (7000, 1 << 24)):
        keys = rng.integers(0, distinct, n + 100, dtype=np.uint64).astype(np.uint32)
        rows = np.sort(rng.choice(n + 100, n, replace=False)).astype(np.int64)
        out = np.empty_like(rows)
        kernels.stable_order(keys, rows, out)
        np.testing.assert_array_equal(out, rows[np.argsort(keys[rows], kind="stable")])


def test_compiled_kernels_load_here_and_agree_with_the_numpy_path_on_a_large_scene():
    """numba is a dependency of the project, so the compiled path must be the one that runs; on a
    large anisotropic SH-3 scene both paths match the reference at sampled pixels."""
    assert backend_status() == "compiled"
    cloud = scene(n=40_000, seed=30, spread=0.8, log_scale=(-5.5, -3))
    cam = perspective(160, 120)
    fast, slow = render(cloud, cam, return_counts=True), render(cloud, cam, return_counts=True, backend="numpy")
    assert fast.stats["backend"] == "compiled" and slow.stats["backend"] == "numpy"
    assert fast.stats["entries"] == slow.stats["entries"]  # the same tile lists
    assert np.abs(fast.color - slow.color).max() < 0.5 * STEP
    assert (fast.counts != slow.counts).sum() <= 2
    pixels = np.random.default_rng(1).integers(0, [160, 120], (400, 2))
    ref = reference_render(cloud, cam, pixels=pixels)
    assert np.abs(fast.color[pixels[:, 1], pixels[:, 0]] - ref["color"]).max() <= STEP


def run_python(code, **env):
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **env},
    )


def test_without_numba_the_numpy_path_renders_and_says_why():
    """As in a Blender without the bundled wheels: numba cannot be imported, rendering still works."""
    done = run_python("""
        import sys

        class NoNumba:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("numba", "llvmlite"):
                    raise ImportError(f"{name} is blocked in this test")
        sys.meta_path.insert(0, NoNumba())

        from splatwright.core.render import Shapes, backend_status, render
        from splatwright.core.camera import Camera
        from splatwright.core.scenes import seed_cube
        result = render(seed_cube(), Camera.look_at((1.8, 1.2, 4.5), (0, 0, 3), width=32, height=24))
        print(result.stats["backend"], result.alpha.max() > 0.5, backend_status())
        try:
            render(seed_cube(), Camera.look_at((1.8, 1.2, 4.5), (0, 0, 3), width=8, height=8), backend="compiled")
        except RuntimeError as exc:
            print("refused:", exc)
    """)
    assert done.returncode == 0, done.stderr
    first, second = done.stdout.splitlines()
    assert first.startswith("numpy True unavailable (ImportError") and "blocked" in first
    assert second.startswith("refused: compiled render kernels are not available")


def test_kernels_can_be_turned_off_and_are_cached_in_the_user_cache_folder(monkeypatch, tmp_path):
    off = run_python(
        """
        from splatwright.core.render import render, backend_status
        from splatwright.core.camera import Camera
        from splatwright.core.scenes import seed_cube
        print(render(seed_cube(2), Camera.look_at((0, 0, -3), (0, 0, 0), width=8, height=8)).stats["backend"],
              backend_status())
    """,
        SPLATWRIGHT_JIT="0",
    )
    assert off.returncode == 0 and off.stdout.split()[0] == "numpy" and "SPLATWRIGHT_JIT=0" in off.stdout, off.stderr
    from splatwright.core import jit

    assert backend_status() == "compiled"
    cached = list(jit.cache_dir().rglob("render_kernels.*.nbi"))
    assert cached and all(jit.cache_dir() in path.parents for path in cached)
    monkeypatch.setenv("SPLATWRIGHT_CACHE_DIR", str(tmp_path))
    assert jit.cache_dir() == tmp_path


def test_kernel_folders_unused_for_a_month_are_removed_and_in_use_ones_kept(tmp_path):
    """An upgrade compiles its kernels into new folders (one per source version): the old ones go
    once no process has used them for STALE_DAYS; a folder in use is touched and stays."""
    from splatwright.core import jit, render_kernels

    day = 86400
    for name, age in (("core_old", jit.STALE_DAYS + 1), ("core_recent", jit.STALE_DAYS - 1), ("io_new", 0)):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "kernels.f-1.py311.nbi").write_bytes(b"x")
        os.utime(folder, (time.time() - age * day,) * 2)
    jit.prune_stale(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["core_recent", "io_new"]
    # Loading kernels touches their folder, so a month of use never ages it out.
    draw = """
        from splatwright.core.render import render
        from splatwright.core.camera import Camera
        from splatwright.core.scenes import seed_cube
        render(seed_cube(2), Camera.look_at((0, 0, -3), (0, 0, 0), width=8, height=8))
    """
    fresh = tmp_path / "fresh"
    ours = jit.cache_dir() / jit._cache_subpath(render_kernels.__name__, render_kernels.__file__)
    if list(ours.glob("render_kernels.*.nbi")):  # compiled by this run already: loaded, not compiled again
        shutil.copytree(ours, fresh / ours.name)
    assert run_python(draw, SPLATWRIGHT_CACHE_DIR=str(fresh)).returncode == 0
    (folder,) = [p for p in fresh.iterdir() if list(p.glob("render_kernels.*.nbi"))]
    ten_days_ago = time.time() - 10 * day
    os.utime(folder, (ten_days_ago, ten_days_ago))
    assert run_python(draw, SPLATWRIGHT_CACHE_DIR=str(fresh)).returncode == 0
    assert folder.stat().st_mtime > time.time() - day


def test_a_kernels_cache_folder_follows_the_constants_it_imports(tmp_path):
    """numba freezes a kernel's imported constants into its compiled code: the cache folder hashes
    the module and the package modules it imports from (relative imports, transitively, one-line
    and parenthesised), so a constant changed there compiles the kernel again; a module it does not
    import changes nothing."""
    from splatwright.core import jit

    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "sub" / "kernels.py").write_text("from ..constants import (\n    GRID,\n)\nfrom . import helpers\n")
    (package / "sub" / "helpers.py").write_text("from .deeper import SCALE\n")
    (package / "sub" / "deeper.py").write_text("SCALE = 2\n")
    (package / "constants.py").write_text("GRID = 4\n")
    (package / "other.py").write_text("UNUSED = 1\n")
    kernels = package / "sub" / "kernels.py"
    names = [os.path.basename(path) for path in jit.kernel_sources(kernels)]
    assert names == ["constants.py", "deeper.py", "helpers.py", "kernels.py"]
    before = jit._cache_subpath("pkg.sub.kernels", kernels)
    (package / "other.py").write_text("UNUSED = 2\n")
    assert jit._cache_subpath("pkg.sub.kernels", kernels) == before
    for changed in (package / "constants.py", package / "sub" / "deeper.py"):
        changed.write_text(changed.read_text().replace("= ", "= 1 + "))
        after = jit._cache_subpath("pkg.sub.kernels", kernels)
        assert after != before and after.startswith("sub_")
        before = after


def test_only_our_own_kernels_are_cached_in_our_folder():
    """numba functions of other packages (a peer library in a virtual environment inside the
    project's folder, say) keep numba's own cache place."""
    from numba.core import caching

    from splatwright.core import jit

    jit._install_cache_locator()
    impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
    locator = impl._locator_classes[0]
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(jit.__file__))), ".venv", "peer.py")

    def function(module):
        f = lambda: None  # noqa: E731
        f.__module__ = module
        return f

    assert locator.from_function(function("gsply.formats"), here) is None
    assert locator.from_function(function("splatwright.core.render_kernels"), jit.__file__) is not None


def test_an_image_too_large_for_memory_is_refused_before_anything_is_allocated(backend):
    cam = Camera.look_at((0, 0, 0), (0, 0, 1), width=40000, height=40000)
    with pytest.raises(ValueError, match=r"40000x40000 render needs \d+\.\d GiB .* in pieces"):
        render(scene(n=10), cam, backend=backend)


def test_sub_pixel_splats_cost_rows_of_a_tile_not_whole_tiles():
    """Tiny splats (a fraction of a pixel, widened by the 0.3 px^2 low-pass to about 4 px): the
    compiled compositor evaluates only the tile rows their boxes cross."""
    cloud = scene(n=20_000, seed=31, spread=0.8, log_scale=(-9, -8))
    cam = perspective(128, 96)
    fast, slow = render(cloud, cam), render(cloud, cam, backend="numpy")
    tile_pixels = 64 * fast.stats["entries"]
    assert slow.stats["evaluated"] >= tile_pixels
    assert fast.stats["evaluated"] < 0.6 * tile_pixels


# images -----------------------------------------------------------------------------------------


def test_png_and_exr_hold_what_was_rendered(tmp_path):
    from PIL import Image

    result = render(seed_cube(), perspective(), background=(0.0, 0.0, 0.0))
    write_image(tmp_path / "a.png", result)
    png = np.asarray(Image.open(tmp_path / "a.png"))
    assert png.shape == (48, 64, 3)  # opaque background: no alpha channel
    np.testing.assert_array_equal(png, np.round(np.clip(result.color, 0, 1) * 255).astype(np.uint8))
    write_image(tmp_path / "a.exr", result)
    exr = read_exr(tmp_path / "a.exr")
    assert sorted(exr) == ["A", "B", "G", "R", "Z"]
    np.testing.assert_array_equal(np.stack([exr["R"], exr["G"], exr["B"]], -1), result.color)
    np.testing.assert_array_equal(exr["A"], result.alpha)
    np.testing.assert_array_equal(exr["Z"], result.depth)


def test_transparent_png_stores_straight_colour(tmp_path):
    from PIL import Image

    result = render(seed_cube(), perspective(), background=None)
    write_image(tmp_path / "t.png", result)
    png = np.asarray(Image.open(tmp_path / "t.png")).astype(np.float64) / 255
    assert png.shape == (48, 64, 4)
    np.testing.assert_allclose(png[..., 3], result.alpha, atol=0.5 / 255)
    seen = result.alpha > 0.2
    straight = result.color[seen] / result.alpha[seen][:, None]
    np.testing.assert_allclose(png[..., :3][seen], np.clip(straight, 0, 1), atol=0.5 / 255 + 1e-6)


def test_straight_alpha_arrays_are_premultiplied_in_exr_and_kept_in_png(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(19)
    rgba = rng.uniform(0, 1, (5, 7, 4))
    write_image(tmp_path / "s.png", rgba)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "s.png")), np.round(rgba * 255).astype(np.uint8))
    write_image(tmp_path / "s.exr", rgba)
    exr = read_exr(tmp_path / "s.exr")
    np.testing.assert_allclose(exr["R"], rgba[..., 0] * rgba[..., 3], rtol=1e-6)
    np.testing.assert_allclose(exr["A"], rgba[..., 3], rtol=1e-6)


def test_png_is_written_without_pillow(tmp_path, monkeypatch):
    """Blender's Python has no Pillow: the PNG writer needs only the standard library."""
    from PIL import Image  # the reference reader, taken before it is hidden

    rgb = np.random.default_rng(3).integers(0, 256, (3, 300, 3)) / 255
    monkeypatch.setitem(sys.modules, "PIL", None)
    monkeypatch.setitem(sys.modules, "PIL.Image", None)
    write_image(tmp_path / "n.png", rgb)
    monkeypatch.undo()
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "n.png")), np.round(rgb * 255).astype(np.uint8))


def test_bad_images_are_refused_and_leave_no_file(tmp_path):
    with pytest.raises(SplatFileError, match="NaN"):
        write_image(tmp_path / "x.png", np.full((4, 4, 3), np.nan))
    with pytest.raises(SplatFileError, match="extension"):
        write_image(tmp_path / "x.jpg", np.zeros((4, 4, 3)))
    with pytest.raises(SplatFileError, match="shape"):
        write_image(tmp_path / "x.png", np.zeros((4, 4, 2)))
    assert list(tmp_path.iterdir()) == []


# command line -----------------------------------------------------------------------------------


def test_cli_render_frames_the_cloud_and_follows_an_explicit_camera(tmp_path, capsys):
    from PIL import Image

    from splatwright.cli import main

    cloud = seed_cube()
    write_splats(tmp_path / "cube.ply", cloud)
    assert (
        main(
            ["render", str(tmp_path / "cube.ply"), "-o", str(tmp_path / "auto.png"), "--width", "80", "--height", "60"]
        )
        == 0
    )
    auto = np.asarray(Image.open(tmp_path / "auto.png"))
    assert auto.shape == (60, 80, 3)
    assert auto[0].max() < 40 and auto[-1].max() < 40 and auto[:, 0].max() < 40 and auto[:, -1].max() < 40
    assert auto.max() > 150  # all of the cube inside, borders dark

    args = [
        "render",
        str(tmp_path / "cube.ply"),
        "-o",
        str(tmp_path / "cam.exr"),
        "--width",
        "64",
        "--height",
        "48",
        "--fov",
        "60",
        "--camera-pos",
        "1.8,1.2,4.5",
        "--look-at",
        "0,0,3",
        "--background",
        "0.5,0.5,0.5",
    ]
    assert main(args) == 0
    assert "rendered 1000 of 1000 splats" in capsys.readouterr().out
    exr = read_exr(tmp_path / "cam.exr")
    ref = reference_render(cloud, perspective(), background=(0.5, 0.5, 0.5))
    assert np.abs(np.stack([exr["R"], exr["G"], exr["B"]], -1) - ref["color"]).max() <= STEP
    np.testing.assert_allclose(exr["A"], ref["alpha"], atol=STEP)


def test_the_near_plane_does_not_depend_on_where_the_camera_looks(tmp_path):
    """Splats 0.3 in front of the eye, behind the default near plane of 0.2 only in front of it:
    looking at a point 1 or 100 away along the same ray gives the same image, in Python and in the
    command line, and --near moves the plane."""
    from PIL import Image

    from splatwright.cli import main

    cloud = SplatCloud.from_activated(
        [[0, 0, 0.3], [0.05, 0, 0.15]],
        np.tile([1.0, 0, 0, 0], (2, 1)),
        np.full((2, 3), 0.02),
        np.full(2, 0.9),
        colors=[[1, 0, 0], [0, 1, 0]],
    )
    write_splats(tmp_path / "c.ply", cloud)
    images = {}
    for far in (1, 100):
        cam = Camera.look_at((0, 0, 0), (0, 0, far), width=32, height=24)
        images[far] = render(cloud, cam).color
        out = tmp_path / f"{far}.png"
        assert (
            main(
                [
                    "render",
                    str(tmp_path / "c.ply"),
                    "-o",
                    str(out),
                    "--width",
                    "32",
                    "--height",
                    "24",
                    "--camera-pos",
                    "0,0,0",
                    "--look-at",
                    f"0,0,{far}",
                ]
            )
            == 0
        )
        images[f"cli{far}"] = np.asarray(Image.open(out))
    np.testing.assert_array_equal(images[1], images[100])
    np.testing.assert_array_equal(images["cli1"], images["cli100"])
    assert images[1][..., 0].max() > 0.5 and images[1][..., 1].max() == 0  # the 0.15 splat is culled
    assert (
        main(
            [
                "render",
                str(tmp_path / "c.ply"),
                "-o",
                str(tmp_path / "n.png"),
                "--width",
                "32",
                "--height",
                "24",
                "--camera-pos",
                "0,0,0",
                "--look-at",
                "0,0,1",
                "--near",
                "0.1",
            ]
        )
        == 0
    )
    assert np.asarray(Image.open(tmp_path / "n.png"))[..., 1].max() > 100


def test_framing_a_tiny_cloud_keeps_it_beyond_the_near_plane():
    from splatwright.core.camera import frame_points

    cloud = scene(n=50, seed=32, center=(5, 0, 0), spread=0.01)
    for cam in (frame_points(cloud.positions, 40, 30), frame_points(cloud.positions, 40, 30, ortho_scale=0)):
        assert cam.near == 0.2
        assert render(cloud, cam).stats["visible"] == 50


def test_cli_render_reports_bad_input(tmp_path, capsys):
    from splatwright.cli import main

    assert main(["render", str(tmp_path / "missing.ply"), "-o", str(tmp_path / "x.png")]) == 1
    assert "no such file" in capsys.readouterr().err
    write_splats(tmp_path / "c.ply", seed_cube(2))
    assert main(["render", str(tmp_path / "c.ply"), "-o", str(tmp_path / "x.png"), "--camera-pos", "1,2"]) == 1
    assert "--camera-pos must be 3 finite numbers x,y,z, got 1,2" in capsys.readouterr().err
