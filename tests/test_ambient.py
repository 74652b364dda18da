"""The world's occlusion (core.ambient) against closed forms: the cosine-weighted share of the sky
that an opaque disc or sphere straight overhead hides from a floor is sin^2 of its angular radius."""

import math

import numpy as np
import pytest
from shadow_reference import ball_surface, lobe_open_share, plane_cloud, sphere_cloud

from splatwright.core import ambient, lights, material, relight
from splatwright.core.lights import World
from splatwright.core.mesh import Surface
from splatwright.core.splats import SplatCloud


def _with_albedo(cloud):
    return material.with_material(cloud, albedo=np.full((len(cloud), 3), 0.5))


def _centre(cloud, radius=0.08):
    return np.linalg.norm(cloud.positions[:, :2], axis=1) < radius


def _disc(radius, height, sides=64):
    angles = np.arange(sides) * 2 * math.pi / sides
    rim = np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(sides, height)], axis=1)
    faces = np.stack([np.zeros(sides, int), 1 + np.arange(sides), 1 + (np.arange(sides) + 1) % sides], axis=1)
    return Surface(np.vstack([[0.0, 0.0, height], rim]), faces)


def test_directions_share_the_sphere_equally():
    count = 64
    directions = lights.sphere_directions(count)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
    assert np.abs(directions.mean(axis=0)).max() < 0.02
    # any cap of a quarter of the sphere holds about a quarter of the directions
    for axis in np.random.default_rng(0).normal(size=(20, 3)):
        inside = (directions @ (axis / np.linalg.norm(axis)) > 0.5).sum()
        assert abs(inside - count / 4) <= 3
    half = lights.cone_angle(count) / 2
    assert 2 * math.pi * (1 - math.cos(half)) == pytest.approx(4 * math.pi / count)
    assert lights.cone_angle(1) == pytest.approx(math.pi)  # never wider than a hemisphere


def test_an_open_plane_sees_the_whole_world_on_both_sides():
    seen = ambient.world_visibility(_with_albedo(plane_cloud(1.0, 40)))
    assert seen.shape == (1600, 2 + ambient.DIRECTIONS) and seen.dtype == np.float32
    assert seen[:, :2].min() > 0.98  # measured 0.992
    # each direction's too, but within 20 degrees of the plane (grazing: 0.62 just under it)
    steep = np.abs(lights.sphere_directions(ambient.DIRECTIONS)[:, 2]) > math.sin(math.radians(20.0))
    assert seen[:, 2:][:, steep].min() > 0.98


@pytest.mark.parametrize("height", [0.4, 0.8])
def test_an_opaque_disc_overhead_hides_its_cosine_share(height):
    radius = 0.5
    floor = _with_albedo(plane_cloud(1.5, 60))
    seen = ambient.world_visibility(floor, occluders=[_disc(radius, height)])
    expected = height**2 / (height**2 + radius**2)  # 1 - sin^2 of the disc's angular radius
    middle = _centre(floor)
    assert seen[middle, 0].mean() == pytest.approx(expected, abs=0.02)  # measured within 0.01
    assert seen[middle, 1].min() > 0.97  # nothing below the floor
    # far from the disc the floor sees more of the sky
    far = np.linalg.norm(floor.positions[:, :2], axis=1) > 1.3
    assert seen[far, 0].mean() > expected + 0.2


def test_a_mesh_ball_over_a_floor_matches_its_form_factor_everywhere():
    """Every floor splat against the closed form 1 - (r / D)^2 h / D (a ball of radius r whose
    centre is D away and h above the splat), with the default directions: the figures quoted in
    core.ambient (mean |error| 0.011, worst 0.061, mean error +0.001)."""
    floor = _with_albedo(plane_cloud(2.0, 100))
    centre, radius = np.array([0.0, 0.0, 0.9]), 0.5
    seen = ambient.world_visibility(floor, occluders=[ball_surface(centre, radius)])[:, 0]
    offset = centre - floor.positions
    distance = np.linalg.norm(offset, axis=1)
    error = seen - (1 - (radius / distance) ** 2 * offset[:, 2] / distance)
    assert np.abs(error).mean() < 0.015 and np.abs(error).max() < 0.08 and abs(error.mean()) < 0.005


def test_a_splat_sphere_overhead_hides_its_cosine_share():
    radius, height = 0.35, 0.7
    floor = plane_cloud(1.5, 60)
    ball = sphere_cloud((0.0, 0.0, height), radius, 2500)
    cloud = _with_albedo(SplatCloud.concatenate([floor, ball]))
    seen = ambient.world_visibility(cloud)
    expected = 1 - (radius / height) ** 2  # 1 - sin^2 of the sphere's angular radius
    middle = _centre(cloud) & (cloud.positions[:, 2] < 0.01)
    assert seen[middle, 0].mean() == pytest.approx(expected, abs=0.02)  # measured 0.752 for 0.75
    # the sphere's top sees its whole hemisphere, its bottom only what the floor leaves
    top = cloud.positions[:, 2] > height + 0.95 * radius
    assert seen[top, 0].min() > 0.95
    bottom = (cloud.positions[:, 2] < height - 0.95 * radius) & (cloud.positions[:, 2] > 0.01)
    assert seen[bottom, 0].max() < 0.6


def test_splats_without_a_material_and_bad_settings():
    bare = plane_cloud(1.0, 10)
    np.testing.assert_array_equal(ambient.world_visibility(bare, directions=8), np.ones((100, 2 + 8), np.float32))
    with pytest.raises(ValueError, match="at least 1 direction"):
        ambient.world_visibility(_with_albedo(bare), directions=0)
    with pytest.raises(ValueError, match="occlusion"):
        World((0.1, 0.1, 0.1), occlusion=-2)
    with pytest.raises(ValueError, match="occlusion"):
        World((0.1, 0.1, 0.1), occlusion=2.5)


def test_the_lit_render_occludes_the_world_it_is_told_to():
    """visibilities() adds the world's share under "world" only for an occluded world that is not
    black, and follows its maps in progress; a lit floor under a disc is darker where the disc hides
    the sky by that share."""
    floor = _with_albedo(plane_cloud(1.5, 40))
    disc = [_disc(0.5, 0.5)]
    steps = []
    visible = relight.visibilities(
        floor, [], World((0.2, 0.2, 0.2), 8), meshes=disc, progress=lambda *s: steps.append(s)
    )
    assert set(visible) == {"world"} and steps[-1][0] == steps[-1][1] and steps[0][2] == "world occlusion"
    assert relight.visibilities(floor, [], World((0.2, 0.2, 0.2)), meshes=disc) == {}
    assert relight.visibilities(floor, [], World((0.0, 0.0, 0.0), 8), meshes=disc) == {}
    rows, open_sky = relight.lit_colors(floor, np.array([0.0, 0.0, 5.0]), [], World((0.2, 0.2, 0.2)), meshes=disc)
    rows, hidden = relight.lit_colors(floor, np.array([0.0, 0.0, 5.0]), [], World((0.2, 0.2, 0.2), 8), meshes=disc)
    ratio = hidden.diffuse[:, 0] / open_sky.diffuse[:, 0]
    np.testing.assert_allclose(ratio, visible["world"][:, 0], rtol=1e-5)


def _lobe_through_disc(points, eye, roughness, radius, height, count=40_000):
    """The share of each floor point's GGX lobe (over `count` directions of the upper hemisphere,
    float64) whose rays miss an opaque disc of `radius` at `height` over the origin."""

    def open_sky(p, up):
        at = p + up * ((height - p[2]) / up[:, 2])[:, None]  # where each ray crosses the disc's plane
        return np.linalg.norm(at[:, :2], axis=1) > radius

    return lobe_open_share(points, eye, roughness, open_sky, 2 * count)


@pytest.mark.parametrize("eye", [(0.0, 0.0, 3.0), (3.0, 0.0, 0.8)])
def test_a_glossy_floor_under_a_disc_reflects_the_sky_its_lobe_sees(eye):
    """A metal floor (roughness 0.35) under an opaque disc (radius 0.5, 0.5 m up), lit by a uniform
    world occluded from core.ambient's 24 directions: the specular world light against its open sky
    is the share of each splat's lobe that misses the disc, by rays (float64): seen from over the
    disc, the mirror directions of the splats under it meet it; seen from the side, they pass
    beside it, and the floor beyond reflects open sky where its cosine-weighted share is lower."""
    radius, height, roughness = 0.5, 0.5, 0.35
    floor = material.with_material(
        plane_cloud(1.5, 40), albedo=np.full((1600, 3), 0.8), roughness=roughness, metallic=1.0
    )
    disc, eye = [_disc(radius, height)], np.asarray(eye)
    visible = relight.visibilities(floor, [], World((0.2, 0.2, 0.2), 24), meshes=disc)
    rows, hidden = relight.lit_colors(floor, eye, [], World((0.2, 0.2, 0.2)), visible=visible)
    rows, open_sky = relight.lit_colors(floor, eye, [], World((0.2, 0.2, 0.2)))
    share = hidden.specular[:, 0] / open_sky.specular[:, 0]
    picks = np.flatnonzero(np.linalg.norm(floor.positions[:, :2], axis=1) < 0.9)[::25]
    want = _lobe_through_disc(floor.positions[picks].astype(np.float64), eye, roughness, radius, height)
    errors = share[picks] - want
    # measured: mean |error| 0.060 and 0.054, worst 0.26 where the mirror direction crosses the
    # disc's rim (24 directions are 40 degrees apart); the cosine-weighted share's 0.12 and 0.17
    cosine = visible["world"][picks, 0]
    assert np.abs(errors).mean() < min(0.07, 0.6 * np.abs(cosine - want).mean()) and np.abs(errors).max() < 0.3
