"""Equirectangular maps and their light by brute force, for tests/test_environment.py and
bench/relight.py: every pixel a direction as Blender reads the map, its irradiance the sum of the
pixels over each normal's hemisphere; and a white ball's pixels and light under a world's bands and
sun, for tests/test_blender_lights.py and bench/world_light.py."""

import math

import numpy as np


def directions(height, width):
    """(H, W, 3) the directions of an equirectangular map's pixel centres as Blender reads it, rows from
    the bottom, and (H, W) their solid angles (the midpoint rule's, summing to 4 pi)."""
    longitude = math.pi * (1.0 - 2.0 * (np.arange(width) + 0.5) / width)
    latitude = math.pi * ((np.arange(height) + 0.5) / height - 0.5)
    lon, lat = np.meshgrid(longitude, latitude)
    d = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)
    share = np.cos(lat)
    return d, share * 4.0 * math.pi / share.sum()


def sunny_sky(height, width):
    """(H, W, 3) a sky (a blue gradient over a dark ground) with a sun, a 4-degree patch 40 degrees up
    whose irradiance on a surface facing it is 3 pi: most of the light there."""
    d, share = directions(height, width)
    z = d[..., 2:]
    sky = np.where(z > 0, np.array([0.3, 0.5, 0.9]) * (1.0 - 0.5 * z), 0.05)
    sun = d @ np.array([math.cos(math.radians(40)), 0.0, math.sin(math.radians(40))]) > math.cos(math.radians(2.0))
    return sky + sun[..., None] * (3.0 * math.pi / (share * sun).sum()) * np.array([1.0, 0.95, 0.9])


def irradiance(pixels, normals):
    """(N, 3) E(n) / pi of the map `pixels` (H, W, 3) for unit `normals` (N, 3), by brute force."""
    d, share = directions(*pixels.shape[:2])
    cosines = np.maximum(d.reshape(-1, 3) @ np.asarray(normals).T, 0.0)
    return (cosines * share.reshape(-1, 1)).T @ pixels.reshape(-1, 3) / math.pi


def euler_xyz(angles):
    """Blender's Euler XYZ rotation as a matrix: about X first, then Y, then Z."""
    (ca, cb, cc), (sa, sb, sc) = np.cos(angles), np.sin(angles)
    x = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    y = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    z = np.array([[cc, -sc, 0.0], [sc, cc, 0.0], [0.0, 0.0, 1.0]])
    return z @ y @ x


def add_sun(pixels, latitude, longitude, diameter, irradiance):
    """`pixels` (H, W, C) with a sun drawn in: a disc of `diameter` (radians) about the direction at
    `latitude` and `longitude` (radians, as directions() reads a map) whose radiance gives a surface
    facing it `irradiance` (W/m^2) over the disc's pixels, added to their first three channels."""
    d, _ = directions(*pixels.shape[:2])
    ring = math.cos(latitude)
    towards = np.array([ring * math.cos(longitude), ring * math.sin(longitude), math.sin(latitude)])
    disc = d @ towards > math.cos(diameter / 2)
    height, width = pixels.shape[:2]
    row_latitude = math.pi * ((np.arange(height) + 0.5) / height - 0.5)
    solid = np.cos(row_latitude)[:, None] * (2 * math.pi / width) * (math.pi / height)  # each pixel's
    out = np.array(pixels, copy=True)
    out[disc, :3] += irradiance / float((solid * disc).sum())
    return out


def ball_normals(size, ortho_scale):
    """(inside (H,W) bool, normals (M,3)): the pixels of a ball of radius 1 at the origin, seen along
    +Y by an orthographic camera `ortho_scale` wide at `size` x `size` pixels (+Z up, row 0 at the
    top; tests/workers/lights.py's, bench/world_light.py's), clear of its outline's partly covered
    ones, and the ball's normal seen at each."""
    half = 0.5 * ortho_scale
    centres = ((np.arange(size) + 0.5) / size * 2.0 - 1.0) * half
    z, x = np.meshgrid(-centres, centres, indexing="ij")
    inside = x * x + z * z < 0.95**2
    return inside, np.stack([x, -np.sqrt(np.maximum(1.0 - x * x - z * z, 0.0)), z], axis=-1)[inside]


def sun_light(towards, irradiance):
    """The core sun Light shining from `towards` (3,) with `irradiance` (3,) on a surface facing it."""
    from splatwright.core.lights import Light

    power = float(np.max(irradiance))
    return Light("sun", power=power, color=np.asarray(irradiance, np.float64) / power, direction=-np.asarray(towards))


def lambert(coefficients, sun, normals):
    """(M,3) what a white Lambertian surface at `normals` sends back under a world of SH bands
    `coefficients` (core.environment) and a sun Light (or None): the bands' diffuse light plus the
    sun's irradiance over pi."""
    from splatwright.core import environment
    from splatwright.core.lights import irradiance

    lit = environment.diffuse(np.asarray(coefficients, np.float64), normals)
    if sun is not None:
        lit = lit + irradiance(sun, np.zeros_like(normals), normals) / math.pi
    return lit
