"""Rectangular area lights integrated (core.ltc): the clipped contour formula against quadrature over
the light, the fitted lobes against the GGX BRDF integrated over the light, and the compiled twin
against the NumPy functions."""

import math

import numpy as np
import pytest
from test_shading import cloud_of, unit

from splatwright.core import jit, ltc
from splatwright.core.lights import AREA_RADIANCE, Light, y_axis
from splatwright.core.shading import ALPHA_MIN, DIELECTRIC_F0, ggx_reflect, shade, specular_albedo

UP = np.array([0.0, 0.0, 1.0])


def light_quadrature(light, point, normal, view=None, roughness=0.5, f0=(0.04, 0.04, 0.04), n=600):
    """(irradiance, specular (3,)) at `point` from a uniform one-sided area light (a rectangle, disc
    or ellipse), by the midpoint rule over n x n cells of its bounding rectangle, those whose centre
    lies on the light (float64): the BRDF integrated over the light, not a formula."""
    sx, sy = light.extent
    u = (np.arange(n) + 0.5) / n - 0.5
    q = light.position + u[:, None, None] * sx * light.x_axis + u[None, :, None] * sy * y_axis(light)
    if light.round:
        q = q[(2 * u[:, None]) ** 2 + (2 * u[None, :]) ** 2 <= 1.0]
    d = (q - point).reshape(-1, 3)
    r = np.linalg.norm(d, axis=1)
    direction = d / r[:, None]
    cos_emit = np.maximum(-(direction @ light.direction), 0.0)
    radiance = AREA_RADIANCE * light.power / light.area
    weight = radiance * cos_emit * (sx * sy / n**2) / r**2  # L dw
    irradiance = float(np.sum(weight * np.maximum(direction @ normal, 0.0)))
    if view is None:
        return irradiance, None
    m = len(direction)
    alpha = np.full(m, max(roughness * roughness, ALPHA_MIN))
    spec = ggx_reflect(np.tile(normal, (m, 1)), np.tile(view, (m, 1)), direction, alpha, np.tile(f0, (m, 1)))
    return irradiance, (weight[:, None] * spec).sum(axis=0)


def test_clipped_contour_formula_is_the_cosines_integral_also_across_the_horizon():
    """Rectangles wholly above a surface and cut by its plane (the case the clipping is for), against
    quadrature over the light: within 2e-4 (the quadrature's own error at a cut)."""
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(40):  # a loop over random lights
        centre = rng.normal(0.0, 1.0, 3) + [0.0, 0.0, 0.3]
        facing = unit(rng.normal(0.0, 1.0, (1, 3)))[0]
        if facing @ -centre <= 0.05:
            facing = -facing  # it faces the point
        light = Light("area", power=10.0, shape="RECTANGLE", size_x=rng.uniform(0.3, 2), size_y=rng.uniform(0.3, 2),
                      position=centre, direction=facing)  # fmt: skip
        exact, _ = light_quadrature(light, np.zeros(3), UP, n=800)
        corners = ltc.vertices(light)[None]
        got = ltc.clipped_share(corners)[0] * math.pi * AREA_RADIANCE * light.power / light.area
        assert got == pytest.approx(exact, rel=2e-4, abs=1e-6 * light.power)
        checked += bool(((corners[0, :, 2] > 0) != (corners[0, 0, 2] > 0)).any())
    assert checked >= 5  # some cut by the plane


# shape -> the largest relative error of a smooth splat's irradiance: a rectangle's is exact (the
# quadrature's own error), an ellipse's that of its polygon (core.ltc.ROUND_SIDES), as measured
DIFFUSE_ERRORS = {"RECTANGLE": 1e-4, "ELLIPSE": 0.004}


@pytest.mark.parametrize("distance", [0.25, 0.5, 1.0, 3.0])
@pytest.mark.parametrize("backend", ["auto", "numpy"])
@pytest.mark.parametrize("shape", list(DIFFUSE_ERRORS))
def test_smooth_splats_diffuse_is_exact_at_every_distance(distance, backend, shape):
    """Where the sampled grid erred by 3% at half a size (tests/test_lights.py), a smooth splat's
    integrated light gives the quadrature's irradiance, tilted normals included."""
    light = Light("area", power=30.0, shape=shape, size_x=1.0, size_y=0.6, position=(0.0, 0.0, distance))
    rng = np.random.default_rng(4)
    points = np.c_[rng.uniform(-1.0, 1.0, (12, 2)), np.zeros(12)]
    normals = unit(rng.normal(0.0, 0.3, (12, 3)) + UP)
    albedo = np.full((12, 3), 0.5)
    eye = np.array([0.2, -0.4, 5.0])
    rough = ltc.ROUGHNESS
    out = shade(cloud_of(points, normals, albedo, rough), eye, [light], multiscatter=False, backend=backend)
    cos_v = np.einsum("ij,ij->i", unit(eye - points), normals)
    layer = specular_albedo(cos_v, np.full(12, rough), np.full((12, 3), DIELECTRIC_F0))
    errors = []
    for k in range(12):  # a loop over a dozen points
        irradiance, _ = light_quadrature(light, points[k], normals[k], n=1200)
        errors.append(np.abs(out.diffuse[k] / (0.5 * (1.0 - layer[k]) * irradiance / math.pi) - 1.0).max())
    assert max(errors) <= DIFFUSE_ERRORS[shape]


# roughness -> the largest error of a metal's specular under a 0.5 m or 1 m square or disc light,
# relative to the brightest over EYES, of the integrated lobes (the fitted cosines) against the GGX
# BRDF integrated over the light, as measured (the sampled grid's, up to 16 samples: 0.29-0.36 /
# 0.24-0.35 / 0.13-0.30 / 0.05-0.23 / 0.02-0.17 at 0.05 / 0.1 / 0.15 / 0.2 / 0.25).
LOBE_ERRORS = {0.02: 1e-4, 0.05: 2e-4, 0.1: 6e-4, 0.15: 0.003, 0.2: 0.009, 0.25: 0.018}
EYES = [(-0.3, 0.0, 1.0), (-1.2, 0.1, 1.4), (0.5, 0.3, 1.0), (-2.0, -0.5, 0.6), (0.0, 0.0, 1.0), (-3.0, 0.0, 0.3)]


@pytest.mark.parametrize("roughness", list(LOBE_ERRORS))
@pytest.mark.parametrize("size", [0.5, 1.0])
@pytest.mark.parametrize("shape", ["SQUARE", "DISK"])
def test_smooth_highlight_against_the_brdf_integrated_over_the_light(roughness, size, shape):
    """A metal point under a square or disc light 1.5 m up, seen from six eyes (the mirror image, the
    lobe's tail, grazing views): the specular against the BRDF summed over the light's surface."""
    light = Light("area", power=40.0, shape=shape, size_x=size, position=(0.3, 0.0, 1.5))
    albedo = np.array([0.9, 0.6, 0.3])
    cloud = cloud_of([np.zeros(3)], [UP], [albedo], roughness, 1.0)
    got, sampled, reference = [], [], []
    for eye in EYES:  # a loop over six eyes
        eye = np.array(eye)
        got.append(shade(cloud, eye, [light], multiscatter=False).specular[0])
        sampled.append(shade(cloud, eye, [light], multiscatter=False, integrate=False).specular[0])
        n = 1200 if roughness < 0.1 else 600
        reference.append(light_quadrature(light, np.zeros(3), UP, unit(eye), roughness, f0=albedo, n=n)[1])
    got, sampled, reference = np.array(got), np.array(sampled), np.array(reference)
    error = np.abs(got - reference).max() / reference.max()
    assert error <= LOBE_ERRORS[roughness], error
    assert np.abs(sampled - reference).max() / reference.max() > 1.5 * error  # what integrating is for


def test_compiled_rectangles_are_the_numpy_ones():
    if jit.compiled(ltc.__name__, ltc.KERNEL) is None:
        pytest.skip("numba unavailable")
    rng = np.random.default_rng(6)
    n = 300
    lights = [
        Light("area", power=50.0, shape="RECTANGLE", size_x=1.2, size_y=0.5, position=(0.2, 0.1, 1.0),
              direction=(0.2, -0.1, -1.0)),
        Light("area", power=30.0, shape="ELLIPSE", size_x=0.8, size_y=0.4, position=(-0.5, 0.3, 0.6),
              direction=(-0.3, 0.2, -1.0)),
    ]  # fmt: skip
    points = rng.normal(0.0, 1.0, (n, 3)) * [1.5, 1.5, 0.8]  # some behind the light, some cut by its plane
    normals = unit(rng.normal(0.0, 1.0, (n, 3)))
    albedo, rough, metal = rng.uniform(0, 1, (n, 3)), rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    cloud = cloud_of(points, normals, albedo, rough, metal)
    eye = np.array([0.3, -2.0, 1.5])
    fast = shade(cloud, eye, lights)
    slow = shade(cloud, eye, lights, backend="numpy")
    # to 1e-5 of the brightest: the compiled edge term is a polynomial (within 6e-9), which a few
    # points beside the light's plane, whose edges' terms nearly cancel, carry further relatively
    for fast_part, slow_part in ((fast.diffuse, slow.diffuse), (fast.specular, slow.specular)):
        np.testing.assert_allclose(fast_part, slow_part, rtol=1e-5, atol=1e-5 * np.abs(slow_part).max())
    assert (rough <= ltc.ROUGHNESS).sum() > 50  # integrated and sampled splats both


def test_edge_polynomial_is_angle_over_sine_on_the_whole_circle():
    """The compiled edge term's polynomial (and its reflection below c = 0) against acos / sqrt."""
    c = np.linspace(-0.999, 1.0, 20001)
    got = np.array([ltc._angle_over_sine_one.py_func(x) if hasattr(ltc._angle_over_sine_one, "py_func")
                    else ltc._angle_over_sine_one(x) for x in c[::20]])  # fmt: skip
    exact = np.where(c[::20] < 1.0, np.arccos(c[::20]) / np.sqrt(np.maximum(1.0 - c[::20] ** 2, 1e-300)), 1.0)
    error = np.abs(got / exact - 1.0).max()
    assert error < 1e-8, error
    assert error > 1e-10  # the stated accuracy is the polynomial's, not a library call's
