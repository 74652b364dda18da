"""core.lights against closed forms: the inverse-square point light, Blender's spot cone, the sun, and
the sampled area lights against the exact irradiance of a uniform Lambertian polygon (Lambert's
contour integral, evaluated here in float64, one edge at a time). The units themselves are checked
against Cycles in tests/test_blender_lights.py."""

import math

import numpy as np
import pytest

from splatwright.core.lights import (
    AREA_SAMPLES,
    ELLIPSE_SCAN,
    Light,
    World,
    area_points,
    direction_and_distance,
    ellipse_crossings,
    incident,
    irradiance,
    spot_cone,
    spread_factor,
)

UP = np.array([0.0, 0.0, 1.0])


def polygon_irradiance(vertices, radiance, point, normal):
    """Irradiance at `point` (unit `normal`) from a uniform Lambertian polygon of `radiance`, wholly
    above the point's tangent plane: (radiance / 2) * sum over edges of the angle they subtend times
    the normal's component along the edge plane's normal (Lambert's formula)."""
    unit = vertices - point
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    following = np.roll(unit, -1, axis=0)  # each edge from a vertex to the next
    c = np.cross(unit, following)
    s = np.linalg.norm(c, axis=1)
    total = np.sum(np.arctan2(s, np.einsum("ij,ij->i", unit, following)) * (c @ normal) / s)
    return abs(0.5 * radiance * total)


def outline(light, n=4096):
    """The area light's edge as a polygon (an n-gon for discs and ellipses)."""
    sx, sy = light.extent
    y_axis = np.cross(light.x_axis, light.direction)
    if light.round:
        t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        a, b = np.cos(t), np.sin(t)
    else:
        a, b = np.array([-1.0, 1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0, 1.0])
    return light.position + np.outer(0.5 * sx * a, light.x_axis) + np.outer(0.5 * sy * b, y_axis)


def test_point_light_is_power_over_four_pi_over_distance_squared():
    light = Light("point", power=100.0, color=(1.0, 0.5, 0.25), position=(1.0, 2.0, 3.0))
    rng = np.random.default_rng(1)
    points = rng.normal(0, 2, (50, 3))
    normals = rng.normal(0, 1, (50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    got = irradiance(light, points, normals)
    for p, n, e in zip(points, normals, got, strict=True):
        d = np.array([1.0, 2.0, 3.0]) - p
        r = np.linalg.norm(d)
        expected = 100.0 / (4 * math.pi) / r**2 * max(0.0, n @ d / r)
        np.testing.assert_allclose(e, expected * np.array([1.0, 0.5, 0.25]), rtol=1e-12, atol=1e-15)
    direction, distance = direction_and_distance(light, points)
    np.testing.assert_allclose(distance, np.linalg.norm([1.0, 2.0, 3.0] - points, axis=1), rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, rtol=1e-12)


def test_spot_cone_is_blenders_smoothstep_of_the_cosine():
    light = Light("spot", spot_size=math.radians(60.0), spot_blend=0.5)
    cos_half = math.cos(math.radians(30.0))
    width = (1 - cos_half) * 0.5
    for angle_deg, expected in ((0.0, 1.0), (35.0, 0.0), (30.0, 0.0)):
        assert spot_cone(light, np.array([math.cos(math.radians(angle_deg))]))[0] == pytest.approx(expected)
    cos = cos_half + 0.3 * width
    assert spot_cone(light, np.array([cos]))[0] == pytest.approx(3 * 0.3**2 - 2 * 0.3**3, rel=1e-12)
    hard = Light("spot", spot_size=math.radians(60.0), spot_blend=0.0)
    assert list(spot_cone(hard, np.cos(np.radians([29.9, 30.1])))) == [1.0, 0.0]
    # the cone multiplies the point light's irradiance; inside the full cone no cosine falloff
    spot = Light("spot", power=50.0, position=(0, 0, 2), direction=(0, 0, -1), spot_size=math.radians(90.0))
    inside = np.array([[0.5, 0.0, 0.0]])
    point = Light("point", power=50.0, position=(0, 0, 2))
    np.testing.assert_allclose(irradiance(spot, inside, UP[None]), irradiance(point, inside, UP[None]), rtol=1e-12)


def test_sun_gives_its_strength_times_the_cosine():
    sun = Light("sun", power=3.0, direction=(0.0, 1.0, -1.0), color=(1.0, 1.0, 0.5))
    got = irradiance(sun, np.zeros((2, 3)), np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 1.0] / np.sqrt(2)]))
    np.testing.assert_allclose(got, [[3 / math.sqrt(2), 3 / math.sqrt(2), 1.5 / math.sqrt(2)], [3, 3, 1.5]])
    assert np.isinf(direction_and_distance(sun, np.zeros((1, 3)))[1]).all()


# (shape, distance from the light in units of its size) -> the largest relative error of the sampled
# irradiance against the exact one over points spread within 1.5 light sizes (or distances) sideways,
# as measured (16 samples nearer than two sizes, fewer farther: core.lights.area_grids): the sampling
# is for lights at least about a size away, and keeps within about its error there beyond.
AREA_ERRORS = {
    ("SQUARE", 0.5): 0.03,
    ("SQUARE", 1.0): 0.012,
    ("SQUARE", 2.0): 0.007,
    ("SQUARE", 4.0): 0.007,
    ("DISK", 0.5): 0.021,
    ("DISK", 1.0): 0.004,
    ("DISK", 2.0): 0.0006,
    ("DISK", 4.0): 0.0055,
}


@pytest.mark.parametrize(("shape", "distance"), list(AREA_ERRORS))
def test_sampled_area_light_against_the_exact_polygon_irradiance(shape, distance):
    assert AREA_SAMPLES == 16
    light = Light("area", power=7.0, shape=shape, size_x=1.0, position=(0.0, 0.0, distance))
    rng = np.random.default_rng(2)
    points = np.c_[rng.uniform(-1.5, 1.5, (200, 2)) * max(distance, 1.0), np.zeros(200)]
    got = irradiance(light, points, np.broadcast_to(UP, points.shape))[:, 0]
    radiance = 7.0 / (math.pi * light.area)
    exact = np.array([polygon_irradiance(outline(light), radiance, p, UP) for p in points])
    error = np.abs(got / exact - 1.0).max()
    assert error <= AREA_ERRORS[shape, distance], error
    assert error >= 0.3 * AREA_ERRORS[shape, distance]  # the stated number is the measured one


def test_tilted_rectangle_far_away_emits_power_over_pi_area_times_cosines():
    """Far from a tilted rectangle its light is that of one Lambertian patch, I = L * A * cos: the
    single sample it is drawn with there (core.lights.area_grids)."""
    light = Light(
        "area", power=20.0, shape="RECTANGLE", size_x=0.4, size_y=0.2, position=(0, 0, 0), direction=(1, 0, -1)
    )
    far = np.array([[30.0, 5.0, -40.0]])
    exact = polygon_irradiance(outline(light), 20.0 / (math.pi * 0.08), far[0], -far[0] / np.linalg.norm(far))
    got = irradiance(light, far, -far / np.linalg.norm(far))[0, 0]
    assert len(incident(light, far)) == 1
    assert got == pytest.approx(exact, rel=2e-5)  # measured 1.2e-5: the patch's own size
    cos_emit = (far[0] / np.linalg.norm(far)) @ (np.array([1.0, 0, -1]) / math.sqrt(2))
    assert got == pytest.approx(20.0 / math.pi * cos_emit / (far[0] @ far[0]), rel=1e-3)
    # one-sided: nothing behind it
    assert irradiance(light, -far, far / np.linalg.norm(far)).max() == 0.0


def test_area_points_cover_the_shape_with_equal_shares():
    for shape, size in (("RECTANGLE", (2.0, 0.5)), ("ELLIPSE", (2.0, 0.5)), ("DISK", (1.0, 9.0))):
        light = Light("area", shape=shape, size_x=size[0], size_y=size[1], direction=(0, 0, -1))
        points, shares = area_points(light)
        assert points.shape == (16, 3) and shares.sum() == pytest.approx(light.area)
        np.testing.assert_allclose(points.mean(axis=0), 0.0, atol=1e-12)  # symmetric about the centre
        sx, sy = light.extent
        assert ((points[:, 0] / (0.5 * sx)) ** 2 + (points[:, 1] / (0.5 * sy)) ** 2 < 1.0).all() or not light.round
    assert len(incident(light, np.zeros((3, 3)) - [0, 0, 1])) == 16


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(kind="torch"), "kind"),
        (dict(kind="point", power=-1.0), "power"),
        (dict(kind="point", power=float("nan")), "power"),
        (dict(kind="point", color=(1.0, 1.0)), "color"),
        (dict(kind="point", color=(1.0, -1.0, 1.0)), "color"),
        (dict(kind="spot", direction=(0.0, 0.0, 0.0)), "direction"),
        (dict(kind="spot", spot_size=0.0), "spot_size"),
        (dict(kind="spot", spot_blend=1.5), "spot_blend"),
        (dict(kind="area", size_x=0.0), "size_x"),
        (dict(kind="area", shape="TRIANGLE"), "shape"),
        (dict(kind="area", x_axis=(0.0, 0.0, 2.0)), "x_axis"),
        (dict(kind="point", position=(0.0, math.inf, 0.0)), "position"),
    ],
)
def test_bad_lights_are_refused_naming_the_field(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Light(**kwargs)


def test_directions_are_normalised_and_the_world_checked():
    light = Light("area", direction=(0.0, 0.0, -5.0), x_axis=(2.0, 0.0, 0.3))
    np.testing.assert_allclose(light.direction, [0, 0, -1])
    np.testing.assert_allclose(light.x_axis, [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(World((0.1, 0.2, 0.3)).color, [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="world"):
        World((0.1, -0.2, 0.3))


@pytest.mark.parametrize("spread_deg", [180.0, 120.0, 60.0, 10.0, 0.5])
def test_an_area_lights_spread_keeps_its_power_within_its_cone(spread_deg):
    """Blender's Spread narrows an area light without changing its power: its far-field intensity
    (irradiance times distance squared, on surfaces facing it) summed over the sphere is the power,
    within the quadrature's error, and nothing leaves past half the spread (Cycles' 1 degree the
    narrowest). A spread of 180 degrees is the plain Lambertian light, to the bit."""
    light = Light("area", power=40.0, size_x=1e-3, position=(0.0, 0.0, 0.0), spread=math.radians(spread_deg))
    half = 0.5 * max(math.radians(spread_deg), math.radians(1.0))
    # rings of points 100 m away, a few inside the cone for the narrowest spreads too
    angles = np.linspace(0.0, min(half * 1.2, 0.5 * math.pi), 4001)[1:-1]
    far = 100.0
    points = far * np.stack([np.sin(angles), np.zeros_like(angles), -np.cos(angles)], axis=1)
    facing = -points / far
    intensity = irradiance(light, points, facing)[:, 0] * far**2
    step = angles[1] - angles[0]
    power = np.sum(intensity * 2.0 * math.pi * np.sin(angles)) * step
    assert power == pytest.approx(40.0, rel=2e-3)
    assert not intensity[angles > half * 1.0001].any()
    if spread_deg == 180.0:
        plain = Light("area", power=40.0, size_x=1e-3, position=(0.0, 0.0, 0.0))
        np.testing.assert_array_equal(intensity, irradiance(plain, points, facing)[:, 0] * far**2)


# (shape, spread in degrees, the light's height over the points in light sizes) -> the largest error
# of the sampled irradiance on a plane below (normals tilted at random towards the light), relative
# to its brightest point, against the same light integrated on a 160 x 160 grid, as measured. A
# narrow spread reaches a point from a small disc of the light: where that disc is smaller than the
# light, the disc itself is sampled (core.lights.spread_samples), else the light's grid (16 samples
# over the whole light had 200% at 30 degrees and half a size, 19% at one; 10 degrees, 15x; an
# ellipse's about 77%, 13% and 290% in the rows below).
SPREAD_ERRORS = {
    ("SQUARE", 90, 0.5): 0.023,
    ("SQUARE", 90, 1.0): 0.02,
    ("SQUARE", 60, 1.0): 0.022,
    ("SQUARE", 30, 0.5): 0.02,
    ("SQUARE", 30, 1.0): 0.022,
    ("SQUARE", 30, 2.0): 0.015,
    ("SQUARE", 10, 0.5): 0.011,
    ("DISK", 90, 0.5): 0.024,
    ("DISK", 30, 0.5): 0.015,
    ("DISK", 30, 1.0): 0.018,
    ("DISK", 30, 2.0): 0.057,
    ("RECTANGLE", 60, 1.0): 0.024,
    ("RECTANGLE", 30, 0.5): 0.018,
    ("RECTANGLE", 10, 0.5): 0.0097,
    ("ELLIPSE", 30, 0.5): 0.024,
    ("ELLIPSE", 30, 1.0): 0.032,
    ("ELLIPSE", 10, 0.5): 0.0047,
}


@pytest.mark.parametrize(("shape", "spread", "height"), list(SPREAD_ERRORS))
def test_a_spread_area_light_sampled_against_a_fine_grid(shape, spread, height):
    light = Light(
        "area", power=10.0, size_x=1.0, size_y=0.5, shape=shape, position=(0, 0, height), spread=math.radians(spread)
    )
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(-1.5, 1.5, (400, 2)) * max(height, 1.0), np.zeros(400)]
    normals = rng.normal(size=(400, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 0.5
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    fine = np.zeros(len(points))
    samples, shares = area_points(light, 160)
    radiance = light.power / (math.pi * light.area)
    for chunk in np.array_split(np.arange(len(samples)), 16):  # a loop over chunks of the fine grid
        offset = samples[chunk, None, :] - points[None]  # (S, N, 3)
        distance2 = np.einsum("sij,sij->si", offset, offset)
        cos_emit = -(offset @ light.direction) / np.sqrt(distance2)
        cos_receive = np.maximum(np.einsum("sij,ij->si", offset, normals), 0.0) / np.sqrt(distance2)
        strength = radiance * shares[chunk, None] * cos_emit * spread_factor(light, cos_emit)
        fine += (strength * cos_receive / distance2).sum(axis=0)
    error = np.abs(irradiance(light, points, normals)[:, 0] - fine).max() / fine.max()
    assert error <= SPREAD_ERRORS[shape, spread, height], error
    assert error >= 0.3 * SPREAD_ERRORS[shape, spread, height]  # the stated number is the measured one


def test_a_rings_crossings_with_an_ellipses_rim_against_a_dense_walk():
    """core.lights.ellipse_crossings (sign changes at ELLIPSE_SCAN steps, then bisection) against
    the crossings of a walk of 100,000 steps around each circle, in float64: each one found is a
    crossing to 1e-4 rad; the only ones missed are pairs within one scan step of each other (the
    circle dips in and out of the rim between two steps: a sliver of arc)."""
    rng = np.random.default_rng(3)
    n = 150
    x0, y0, radius = rng.uniform(-1.0, 1.0, n), rng.uniform(-0.6, 0.6, n), rng.uniform(0.05, 1.2, n)
    a, b = 0.8, 0.35
    got = ellipse_crossings(x0, y0, radius, a, b)
    angle = np.linspace(0.0, 2.0 * math.pi, 100_001)
    crossed = slivers = 0
    for k in range(n):  # a loop over circles: each a dense walk
        x, y = x0[k] + radius[k] * np.cos(angle), y0[k] + radius[k] * np.sin(angle)
        inside = (x / a) ** 2 + (y / b) ** 2 < 1.0
        steps = np.flatnonzero(inside[1:] != inside[:-1])
        want = 0.5 * (angle[steps] + angle[steps + 1])
        found = got[k][np.isfinite(got[k])]
        matched = np.abs(found[:, None] - want[None, :]).min(axis=1, initial=np.inf) if len(want) else found
        assert len(want) <= 4 and (matched < 1e-4).all()
        missed = np.sort(want[np.abs(want[:, None] - found[None, :]).min(axis=1, initial=np.inf) > 1e-4])
        assert len(missed) % 2 == 0 and (np.diff(missed)[::2] < 2.0 * math.pi / ELLIPSE_SCAN).all()
        crossed += len(found) > 0
        slivers += len(missed) // 2
    assert crossed > 50 and slivers < 0.05 * crossed  # most circles cross the rim, few by a sliver
    assert np.isfinite(got).sum(axis=1).max() == 4
