"""Rectangular area lights integrated (core.ltc): the clipped contour formula against quadrature over
the light, the fitted lobes against the GGX BRDF integrated over the light, and the compiled twin
against the NumPy functions."""

import math

import numpy as np
import pytest
from test_shading import cloud_of, unit

from splatwright.core import jit, ltc
from splatwright.core.lights import AREA_RADIANCE, Light, y_axis
from splatwright.core.shading import ALPHA_MIN, DIELECTRIC_F0, ggx_d, ggx_reflect, shade, specular_albedo

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
METAL = np.array([0.9, 0.6, 0.3])  # the base colour of the metal point the highlights are measured on


def highlight_errors(light, roughness, eyes, reference):
    """(integrated, sampled): the largest error over `eyes` (points, the origin their target) of the
    specular of a metal point (METAL, at the origin, facing +z, of `roughness`) under `light`, the
    light integrated (core.ltc) or sampled, relative to the brightest of reference(view) (3,)."""
    cloud = cloud_of([np.zeros(3)], [UP], [METAL], roughness, 1.0)
    got, sampled, want = [], [], []
    for eye in eyes:  # a loop over a few eyes
        eye = np.array(eye, np.float64)
        got.append(shade(cloud, eye, [light], multiscatter=False).specular[0])
        sampled.append(shade(cloud, eye, [light], multiscatter=False, integrate=False).specular[0])
        want.append(reference(unit(eye)))
    want = np.array(want)
    return tuple(float(np.abs(np.array(values) - want).max() / want.max()) for values in (got, sampled))


def mirror_eyes(towards, half_angle):
    """Eyes 2 m from the origin in the xz plane at the mirror image (about +z) of a round light whose
    centre lies along the unit `towards` (in that plane), and 0.5, 1, 1.5 and 3 of its angular radii
    `half_angle` off it."""
    mirror = math.atan2(-towards[0], towards[2])
    return [
        2.0 * np.array([math.sin(t), 0.0, math.cos(t)]) for t in mirror + half_angle * np.array([0, 0.5, 1, 1.5, 3])
    ]


@pytest.mark.parametrize("roughness", list(LOBE_ERRORS))
@pytest.mark.parametrize("size", [0.5, 1.0])
@pytest.mark.parametrize("shape", ["SQUARE", "DISK"])
def test_smooth_highlight_against_the_brdf_integrated_over_the_light(roughness, size, shape):
    """A metal point under a square or disc light 1.5 m up, seen from six eyes (the mirror image, the
    lobe's tail, grazing views): the specular against the BRDF summed over the light's surface."""
    light = Light("area", power=40.0, shape=shape, size_x=size, position=(0.3, 0.0, 1.5))
    n = 1200 if roughness < 0.1 else 600
    error, sampled = highlight_errors(
        light, roughness, EYES, lambda view: light_quadrature(light, np.zeros(3), UP, view, roughness, METAL, n)[1]
    )
    assert error <= LOBE_ERRORS[roughness], error
    assert sampled > 1.5 * error  # what integrating is for


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


def round_light_reference(direction, half_angle, view, roughness, f0, radiance, side=1024):
    """The GGX BRDF (Schlick's F, F0 `f0`) times the cosine integrated over a cone of `half_angle`
    about the unit `direction`, of uniform `radiance`, for a surface facing +z seen from `view`: the
    lobe's own half-vectors drawn on a stratified side x side grid, each reflected direction counted
    where it falls in the cone (float64; as sharp a lobe as wanted, unlike a grid over the light)."""
    alpha = max(roughness * roughness, ALPHA_MIN)
    u = (np.arange(side) + 0.5) / side
    u1, u2 = (m.ravel() for m in np.meshgrid(u, u, indexing="ij"))
    cos_h = np.sqrt((1.0 - u1) / (1.0 + (alpha * alpha - 1.0) * u1))
    sin_h = np.sqrt(1.0 - cos_h**2)
    half = np.stack([sin_h * np.cos(2 * math.pi * u2), sin_h * np.sin(2 * math.pi * u2), cos_h], axis=1)
    vh = half @ view
    light = 2.0 * vh[:, None] * half - view
    inside = (light @ direction >= math.cos(half_angle)) & (light[:, 2] > 0.0) & (vh > 0.0)
    m = int(inside.sum())
    spec = ggx_reflect(
        np.tile(UP, (m, 1)), np.tile(view, (m, 1)), light[inside], np.full(m, alpha), np.tile(f0, (m, 1))
    )
    # the estimator of a lobe drawn by D: f cos / pdf, pdf = D (n.h) / (4 v.h)
    cos_hi = cos_h[inside]
    pdf = ggx_d(cos_hi, np.full(m, alpha)) * cos_hi / (4.0 * vh[inside])
    return radiance * (spec / pdf[:, None]).sum(axis=0) / len(u1)


# (radius m, roughness) -> the largest error of the highlight of a point light of that radius 1.5 m
# away, relative to its peak, as measured (the widened lobe's, sampled: 0.33-0.36 at roughness 0.05,
# 0.16-0.35 at 0.1, 0.03-0.22 at 0.2). Near a mirror (roughness 0.05) a wide sphere's rim is the
# polygon's: its 16 sides stray 1.3% of the radius, a lobe's width there.
SPHERE_ERRORS = {
    (0.05, 0.05): 0.013, (0.1, 0.05): 0.05, (0.25, 0.05): 0.16,
    (0.05, 0.1): 0.004, (0.1, 0.1): 0.002, (0.25, 0.1): 0.016,
    (0.05, 0.2): 0.004, (0.1, 0.2): 0.004, (0.25, 0.2): 0.004,
}  # fmt: skip


@pytest.mark.parametrize(("radius", "roughness"), list(SPHERE_ERRORS))
def test_a_sphere_lights_highlight_is_its_disc_integrated(radius, roughness):
    """A metal point under a point light of `radius` 1.5 m up, the eye at its mirror image and out to
    three of its angular radii: the specular against the BRDF over the sphere's cone (a sphere of
    radiance P / (4 pi^2 r^2) is what a point light of power P and that radius is)."""
    position = np.array([0.3, 0.0, 1.5])
    light = Light("point", power=100.0, position=position, radius=radius)
    towards = position / np.linalg.norm(position)
    half_angle = math.asin(radius / np.linalg.norm(position))
    radiance = 100.0 / (4.0 * math.pi**2 * radius**2)
    error, sampled = highlight_errors(
        light,
        roughness,
        mirror_eyes(towards, half_angle),
        lambda view: round_light_reference(towards, half_angle, view, roughness, METAL, radiance),
    )
    assert error <= SPHERE_ERRORS[radius, roughness], error
    assert sampled > 2.0 * error  # what integrating is for


@pytest.mark.parametrize(("angle", "roughness"), [(2.0, 0.05), (5.0, 0.1), (10.0, 0.2)])
def test_the_suns_highlight_is_its_disc_integrated(angle, roughness):
    """A metal point under a sun of `angle` degrees (Blender's Angle: the disc's diameter), the eye
    at its mirror image and out to three of its radii: within 0.4% of the peak (measured 0.30-0.31%),
    where the widened lobe was 12-28% off."""
    sun = Light("sun", power=3.0, direction=(-0.2, 0.0, -1.0), angle=math.radians(angle))
    half_angle = 0.5 * sun.angle
    radiance = 3.0 / (math.pi * math.sin(half_angle) ** 2)
    error, sampled = highlight_errors(
        sun,
        roughness,
        mirror_eyes(-sun.direction, half_angle),
        lambda view: round_light_reference(-sun.direction, half_angle, view, roughness, METAL, radiance),
    )
    assert error <= 0.004, error
    assert sampled > 2.0 * error
