"""core.shading against float64 references written plainly: the GGX terms one splat at a time with the
math module, the specular lobe's directional albedo by brute-force integration over the hemisphere,
the specular of a small disc light by integrating the BRDF over the disc, and energy checks (white
furnace: the world path, and the same world made of many suns through the lights path)."""

import math

import numpy as np
import pytest

from splatwright.core import SplatCloud
from splatwright.core.camera import Camera
from splatwright.core.lights import Light, World, reachable_discs, sphere_directions
from splatwright.core.material import with_material
from splatwright.core.shading import (
    DIELECTRIC_F0,
    ggx_reflect,
    lobe_sky,
    shade,
    specular_albedo,
)


def cloud_of(positions, normals, albedo, roughness=0.5, metallic=0.0):
    n = len(positions)
    cloud = SplatCloud(
        positions=np.asarray(positions, dtype=np.float64),
        rotations=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        log_scales=np.full((n, 3), -4.0),
        opacity_logits=np.zeros(n),
        sh=np.zeros((n, 1, 3)),
    )
    return with_material(cloud, albedo=albedo, normals=normals, roughness=roughness, metallic=metallic)


def random_cloud(n, rng):
    """n splats in the cube [-1, 1]^3 facing every way, with random albedo, roughness and metallic."""
    positions, normals = rng.uniform(-1.0, 1.0, (n, 3)), unit(rng.normal(size=(n, 3)))
    albedo, roughness, metallic = rng.uniform(0.0, 1.0, (n, 3)), rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 1.0, n)
    return cloud_of(positions, normals, albedo, roughness, metallic)


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def plain_ggx(n, v, l, alpha, f0):
    """f(v, l) * (n.l) for one splat, written out: D G F / (4 n.v)."""
    dot = lambda a, b: sum(x * y for x, y in zip(a, b, strict=True))  # noqa: E731
    cos_v, cos_l = dot(n, v), dot(n, l)
    if cos_l <= 0:
        return [0.0, 0.0, 0.0]
    h = [a + b for a, b in zip(v, l, strict=True)]
    length = math.sqrt(dot(h, h))
    h = [x / length for x in h]
    cos_h, cos_vh = dot(n, h), dot(v, h)
    d = alpha**2 / (math.pi * (cos_h**2 * (alpha**2 - 1) + 1) ** 2)

    def lam(c):
        return (math.sqrt(1 + alpha**2 * (1 - c * c) / (c * c)) - 1) / 2

    g = 1 / (1 + lam(cos_v) + lam(cos_l))
    return [(f + (1 - f) * (1 - cos_vh) ** 5) * d * g / (4 * cos_v) for f in f0]


def test_ggx_equals_the_plain_per_splat_formula():
    rng = np.random.default_rng(3)
    n = 300
    normal = unit(rng.normal(size=(n, 3)))
    view = unit(rng.normal(size=(n, 3)))
    view = np.where((np.einsum("ij,ij->i", normal, view) < 0.05)[:, None], unit(normal + 0.3 * view), view)
    light = unit(rng.normal(size=(n, 3)))
    alpha = rng.uniform(0.01, 1.0, n)
    f0 = rng.uniform(0.02, 1.0, (n, 3))
    got = ggx_reflect(normal, view, light, alpha, f0)
    expected = np.array([plain_ggx(*row) for row in zip(normal, view, light, alpha, f0, strict=True)])
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-14)
    assert (got[np.einsum("ij,ij->i", normal, light) <= 0] == 0).all()


def brute_specular_albedo(cos_v, roughness, f0, steps=800):
    """The GGX lobe's directional albedo: f * cos integrated over the hemisphere on a midpoint grid in
    (cos theta, phi), float64 (no sampling shared with core.shading)."""
    c = (np.arange(steps) + 0.5) / steps
    phi = (np.arange(2 * steps) + 0.5) / (2 * steps) * 2 * math.pi
    cc, pp = (m.ravel() for m in np.meshgrid(c, phi, indexing="ij"))
    s = np.sqrt(1 - cc * cc)
    light = np.stack([s * np.cos(pp), s * np.sin(pp), cc], axis=1)
    m = len(light)
    view = np.tile([math.sqrt(1 - cos_v**2), 0.0, cos_v], (m, 1))
    normal = np.tile([0.0, 0.0, 1.0], (m, 1))
    alpha = max(roughness**2, 1e-3)
    f = ggx_reflect(normal, view, light, np.full(m, alpha), np.tile(f0, (m, 1)))
    return f.sum(axis=0) * (1.0 / steps) * (2 * math.pi / (2 * steps))


@pytest.mark.parametrize(
    ("cos_v", "roughness", "f0"),
    [(0.9, 0.5, 0.04), (0.5, 0.3, 0.04), (0.2, 0.8, 0.04), (0.7, 0.6, 1.0), (0.33, 0.95, 0.5), (1.0, 1.0, 1.0)],
)
def test_specular_albedo_table_against_brute_force(cos_v, roughness, f0):
    got = specular_albedo(np.array([cos_v]), np.array([roughness]), np.full((1, 3), f0))[0, 0]
    expected = brute_specular_albedo(cos_v, roughness, np.full(3, f0))[0]
    assert got == pytest.approx(expected, rel=0.02, abs=0.002)


def test_white_furnace_world_returns_the_world_colour():
    rng = np.random.default_rng(4)
    n = 200
    cloud = cloud_of(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), np.ones((n, 3)), rng.uniform(0, 1, n))
    world = World((0.3, 0.5, 0.7))
    out = shade(cloud, np.array([0.0, 0.0, 10.0]), [], world)
    np.testing.assert_allclose(out.radiance, np.tile([0.3, 0.5, 0.7], (n, 1)), rtol=1e-6)
    assert out.diffuse.dtype == np.float32 and out.specular.dtype == np.float32 and (out.shadow == 0).all()
    # a grey diffuse-only splat sends back albedo * world minus what its specular layer reflects instead
    grey = shade(
        cloud_of([[0, 0, 0]], [[0, 0, 1]], [[0.5, 0.5, 0.5]], 1.0), np.array([0, 0, 1.0]), [], world, multiscatter=False
    )
    layer = brute_specular_albedo(1.0, 1.0, np.full(3, DIELECTRIC_F0))[0]
    assert grey.specular[0, 0] == pytest.approx(layer * 0.3, rel=0.02)
    assert grey.diffuse[0, 0] == pytest.approx(0.5 * (1 - layer) * 0.3, rel=0.01)


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_the_world_is_scaled_by_the_share_seen_on_the_eyes_side(backend):
    """A splat seen from the side its normal points to takes the world's first visibility column,
    seen from behind the second: the white furnace's W times that share."""
    cloud = cloud_of([[0, 0, 0], [1, 0, 0]], [[0, 0, 1], [0, 0, -1]], np.ones((2, 3)), 1.0)
    world = World((0.3, 0.5, 0.7))
    seen = {"world": np.array([[0.25, 0.75], [0.4, 0.9]])}
    out = shade(cloud, np.array([0.5, 0.0, 10.0]), [], world, seen, backend=backend)
    np.testing.assert_allclose(out.radiance, [[0.075, 0.125, 0.175], [0.27, 0.45, 0.63]], rtol=1e-5)
    with pytest.raises(ValueError, match="world's visibility"):
        shade(cloud, np.array([0.5, 0.0, 10.0]), [], world, {"world": np.ones(2)}, backend=backend)


@pytest.mark.parametrize(("roughness", "most"), [(0.2, 0.09), (0.5, 0.05), (1.0, 0.022)])
def test_the_specular_lobe_sees_the_sky_around_its_mirror_direction(roughness, most):
    """lobe_sky from the visibilities of 24 directions against the lobe integrated over 200k
    directions (float64), under 40 skies each open on a random half of the sphere with a soft edge
    (0.4 wide in cosine), views from head-on to 75 degrees: mean |error| at most `most` (measured
    0.084, 0.045, 0.020), each time nearer than the cosine-weighted share a diffuse surface sees
    (0.27, 0.16, 0.023)."""
    rng = np.random.default_rng(0)
    fine = sphere_directions(200_000)
    up = fine[fine[:, 2] > 0]
    normal, alpha = np.array([0.0, 0.0, 1.0]), max(roughness**2, 1e-3)
    sky = lambda d, axis: np.clip((d @ axis) / 0.4 + 0.5, 0.0, 1.0)  # noqa: E731
    lobe_errors, cosine_errors = [], []
    for _ in range(40):
        turn = rng.uniform(0.0, 1.3)
        view, axis = np.array([math.sin(turn), 0.0, math.cos(turn)]), unit(rng.normal(size=3))
        f = ggx_reflect(
            np.tile(normal, (len(up), 1)),
            np.tile(view, (len(up), 1)),
            up,
            np.full(len(up), alpha),
            np.ones((len(up), 3)),
        )
        want = (f[:, 0] * sky(up, axis)).sum() / f[:, 0].sum()
        cosine = (up[:, 2] * sky(up, axis)).sum() / up[:, 2].sum()
        got = lobe_sky(
            sky(sphere_directions(24), axis)[None], normal[None], view[None], np.array([alpha]), np.array([cosine])
        )
        lobe_errors.append(abs(got[0] - want))
        cosine_errors.append(abs(cosine - want))
    assert np.mean(lobe_errors) < min(most, np.mean(cosine_errors))


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_an_open_world_fills_the_lobe_and_a_closed_one_empties_it(backend):
    """Seen directions all 1: the white furnace's W whatever the lobe; all 0: no world light; none
    above the normal's horizon: the cosine-weighted share stands in."""
    rng = np.random.default_rng(4)
    n = 50
    cloud = cloud_of(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), np.ones((n, 3)), rng.uniform(0, 1, n))
    world, eye = World((0.3, 0.5, 0.7)), np.array([0.0, 0.0, 10.0])
    for value in (1.0, 0.0):
        seen = {"world": np.full((n, 2 + 24), value, np.float32)}
        out = shade(cloud, eye, [], world, seen, backend=backend)
        np.testing.assert_allclose(out.radiance, value * np.tile(world.color, (n, 1)), rtol=1e-5, atol=1e-7)
    flat = cloud_of([[0, 0, 0]], [[0, 0, 1]], [[1.0, 1.0, 1.0]], 0.5, 1.0)  # one direction, on its horizon
    below = shade(flat, eye, [], world, {"world": np.array([[0.25, 1.0, 1.0]], np.float32)}, backend=backend)
    np.testing.assert_allclose(below.radiance[0], 0.25 * world.color, rtol=1e-5)


def test_multiscatter_compensation_keeps_a_white_metal_white():
    """With the lost energy given back, a white metal under a uniform world returns the world (single
    scattering alone returns E1 of it, 0.31 at roughness 1 seen head-on, 1 - ln 2 exactly); light
    arriving from a sun is scaled by the same factor 1 / E1."""
    world = World((0.2, 0.4, 0.6))
    for roughness in (0.2, 0.6, 1.0):
        cloud = cloud_of([[0, 0, 0]], [[0, 0, 1]], [[1.0, 1.0, 1.0]], roughness, 1.0)
        full = shade(cloud, np.array([0.0, 0.0, 3.0]), [], world)
        np.testing.assert_allclose(full.radiance[0], [0.2, 0.4, 0.6], rtol=1e-6)
    single = shade(cloud, np.array([0.0, 0.0, 3.0]), [], world, multiscatter=False)
    assert single.radiance[0, 0] == pytest.approx(0.2 * (1 - math.log(2)), rel=1e-3)
    sun = [Light("sun", power=1.0, direction=(0.3, 0.0, -1.0))]
    ratio = (
        shade(cloud, np.array([0.0, 0.0, 3.0]), sun).specular
        / shade(cloud, np.array([0.0, 0.0, 3.0]), sun, multiscatter=False).specular
    )
    np.testing.assert_allclose(ratio, 1 / (1 - math.log(2)), rtol=1e-3)


def fibonacci_hemisphere(count):
    """Nearly uniform unit directions over the upper hemisphere, each covering 2 pi / count sr."""
    i = np.arange(count) + 0.5
    z = 1 - i / count
    r = np.sqrt(1 - z * z)
    phi = math.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def test_a_world_of_suns_through_the_lights_gives_the_furnace_albedo():
    """A metal (F0 = albedo = 1) under 4096 suns from every direction of the hemisphere, each of
    strength W * (2 pi / 4096) (the irradiance of that much sky of radiance W): its specular equals
    the world path's E * W, the lobe's albedo (the lights path and the table agree)."""
    count = 4096
    suns = [Light("sun", power=2 * math.pi / count, direction=-d) for d in fibonacci_hemisphere(count)]
    for roughness, cos_v in ((0.5, 0.8), (0.8, 0.4), (1.0, 1.0)):
        view = np.array([math.sqrt(1 - cos_v**2), 0.0, cos_v])
        cloud = cloud_of([[0, 0, 0]], [[0, 0, 1]], [[1.0, 1.0, 1.0]], roughness, 1.0)
        by_lights = shade(cloud, view * 100.0, suns, multiscatter=False).specular[0, 0]
        by_world = shade(cloud, view * 100.0, [], World((1.0, 1.0, 1.0)), multiscatter=False).specular[0, 0]
        assert by_lights == pytest.approx(by_world, rel=0.02)
        assert by_world <= 1.0


def disc_reference(point, normal, view, light, roughness, f0, rings=400, sectors=800):
    """Diffuse factor and specular of a disc area light by integrating over its surface (midpoint
    rule in (r^2, angle): equal areas), each element a Lambertian patch of radiance P / (pi A)."""
    u = (np.arange(rings) + 0.5) / rings
    t = (np.arange(sectors) + 0.5) / sectors * 2 * math.pi
    uu, tt = (m.ravel() for m in np.meshgrid(u, t, indexing="ij"))
    r = 0.5 * light.size_x * np.sqrt(uu)
    y_axis = np.cross(light.x_axis, light.direction)
    where = light.position + np.outer(r * np.cos(tt), light.x_axis) + np.outer(r * np.sin(tt), y_axis)
    radiance = light.power / (math.pi * light.area)
    d = where - point
    dist = np.linalg.norm(d, axis=1)
    ldir = d / dist[:, None]
    m = len(ldir)
    cos_e = np.maximum(-(ldir @ light.direction), 0)
    cos_l = np.maximum(ldir @ normal, 0)
    de = radiance * cos_e * (light.area / m) / dist**2  # irradiance each element gives, facing it
    diffuse = np.sum(de * cos_l)
    alpha = np.full(m, roughness**2)
    spec = ggx_reflect(np.tile(normal, (m, 1)), np.tile(view, (m, 1)), ldir, alpha, np.tile(f0, (m, 1)))
    return diffuse, (de[:, None] * spec).sum(axis=0)


# (disc diameter m, roughness) -> the largest relative error of the specular measured, for an eye
# that sees the disc's mirror image (the highlight) and one that sees only the lobe's tail: the
# samples (sixteen, or four where they stay within two thirds of each lobe's width: core.lights.area_grids) with
# widened lobes (core.shading) against the BRDF integrated over the disc.
DISC_ERRORS = {
    (0.5, 0.1): 0.30,
    (0.5, 0.3): 0.04,
    (0.5, 0.45): 0.016,
    (0.5, 0.7): 0.007,
    (1.0, 0.3): 0.13,
    (1.0, 0.45): 0.045,
    (1.0, 0.7): 0.009,
}
EYES = {"highlight": (-0.3, 0.0, 1.0), "tail": (-1.2, 0.1, 1.4)}


@pytest.mark.parametrize(("size", "roughness"), list(DISC_ERRORS))
def test_small_disc_light_against_the_brdf_integrated_over_it(size, roughness):
    light = Light("area", power=40.0, shape="DISK", size_x=size, position=(0.3, 0.0, 1.5), direction=(0, 0, -1))
    point = np.zeros(3)
    normal = np.array([0.0, 0.0, 1.0])
    albedo = np.array([0.6, 0.5, 0.4])
    cloud = cloud_of([point], [normal], [albedo], roughness)
    peak = None
    for name, eye in EYES.items():
        eye = np.array(eye)
        view = unit(eye - point)
        out = shade(cloud, eye, [light], multiscatter=False, integrate=False)  # sampled, not core.ltc's
        diffuse, spec = disc_reference(point, normal, view, light, roughness, np.full(3, DIELECTRIC_F0))
        cos_v = np.array([view @ normal])
        layer = specular_albedo(cos_v, np.array([roughness]), np.full((1, 3), DIELECTRIC_F0))[0]
        np.testing.assert_allclose(out.diffuse[0], albedo * (1 - layer) * diffuse / math.pi, rtol=0.005)
        peak = spec if peak is None else peak
        # errors relative to the highlight: the tail's own relative error is large where it is ~0
        assert np.abs(out.specular[0] - spec).max() <= DISC_ERRORS[size, roughness] * peak.max(), name


def test_point_light_per_splat_plainly():
    rng = np.random.default_rng(5)
    n = 40
    positions = rng.normal(0, 0.5, (n, 3))
    normals = unit(rng.normal(size=(n, 3)))
    albedo = rng.uniform(0, 1, (n, 3))
    rough, metal = rng.uniform(0.2, 1, n), rng.uniform(0, 1, n)
    light = Light("point", power=80.0, color=(1.0, 0.9, 0.7), position=(0.5, 1.0, 2.0), radius=0.0)
    eye = np.array([0.0, -3.0, 1.0])
    out = shade(cloud_of(positions, normals, albedo, rough, metal), eye, [light], multiscatter=False)
    for i in range(n):  # the reference, one splat at a time
        v = unit(eye - positions[i])
        nrm = normals[i] if normals[i] @ v >= 0 else -normals[i]  # two-sided
        to_light = np.array([0.5, 1.0, 2.0]) - positions[i]
        dist = np.linalg.norm(to_light)
        l = to_light / dist
        e = 80.0 / (4 * math.pi * dist**2) * np.array([1.0, 0.9, 0.7])
        f0 = DIELECTRIC_F0 * (1 - metal[i]) + albedo[i] * metal[i]
        spec = np.array(plain_ggx(nrm, v, l, max(rough[i] ** 2, 1e-3), f0)) * e
        layer = specular_albedo(np.array([nrm @ v]), rough[i : i + 1], f0[None])[0]
        diff = albedo[i] * (1 - metal[i]) * (1 - layer) / math.pi * e * max(nrm @ l, 0.0)
        np.testing.assert_allclose(out.specular[i], spec, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(out.diffuse[i], diff, rtol=1e-5, atol=1e-7)


def test_two_sided_visibility_and_shadow():
    light = Light("sun", power=2.0, direction=(0, 0, -1))
    eye = np.array([0.0, 0.0, 5.0])
    up = shade(cloud_of([[0, 0, 0]], [[0, 0, 1]], [[0.8, 0.8, 0.8]]), eye, [light])
    down = shade(cloud_of([[0, 0, 0]], [[0, 0, -1]], [[0.8, 0.8, 0.8]]), eye, [light])
    np.testing.assert_array_equal(up.radiance, down.radiance)  # flipped towards the eye
    two = [light, Light("point", power=50.0, position=(0, 1, 1))]
    cloud = cloud_of([[0, 0, 0]], [[0, 0, 1]], [[0.8, 0.8, 0.8]])
    whole = shade(cloud, eye, two)
    first = shade(cloud, eye, two[:1])
    half = shade(cloud, eye, two, visibility={1: np.array([0.0])})
    np.testing.assert_allclose(half.radiance, first.radiance, rtol=1e-6)
    second_share = 1 - first.radiance.mean() / whole.radiance.mean()
    assert half.shadow[0] == pytest.approx(second_share, rel=1e-5)
    assert shade(cloud, eye, two[:1], visibility={0: np.array([0.25])}).shadow[0] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="visibility of light 0"):
        shade(cloud, eye, two, visibility={0: np.array([0.5, 0.5])})


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_light_linking_leaves_a_light_out_of_the_splats_it_is_not_linked_to(backend):
    """A splat a light is not linked to is shaded as if the light were not there: its light and its
    share of the shadow pass both go (a visibility of 0 would count the light as shadowed)."""
    eye = np.array([0.0, 0.0, 5.0])
    two = [Light("sun", power=2.0, direction=(0, 0, -1)), Light("point", power=50.0, position=(0, 1, 1))]
    cloud = cloud_of([[0, 0, 0], [0.5, 0, 0]], [[0, 0, 1], [0, 0, 1]], [[0.8, 0.6, 0.4]] * 2)
    world = World((0.1, 0.1, 0.1))
    half = {0: np.array([0.5, 0.5])}
    linked = shade(cloud, eye, two, world, half, receivers={1: np.array([True, False])}, backend=backend)
    both = shade(cloud, eye, two, world, half, backend=backend)
    first = shade(cloud, eye, two[:1], world, half, backend=backend)
    np.testing.assert_array_equal(linked.radiance[0], both.radiance[0])  # linked: as before
    np.testing.assert_allclose(linked.radiance[1], first.radiance[1], rtol=1e-6)  # as if only the sun
    assert linked.shadow[1] == pytest.approx(first.shadow[1], rel=1e-6) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="receivers must be 2 values"):
        shade(cloud, eye, two, receivers={1: np.array([True])}, backend=backend)
    with pytest.raises(ValueError, match="light linking names light 5"):
        shade(cloud, eye, two, receivers={5: np.array([True, False])}, backend=backend)


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_a_lights_diffuse_and_specular_weights_scale_its_two_reflections(backend):
    """A light's diffuse and specular weights (Blender's Diffuse and Glossy ray visibility of the
    light) scale its diffuse and specular light alone; a light that gives neither counts as no light
    in the Shadow pass; a negative weight is refused."""
    eye = np.array([0.0, -2.0, 3.0])
    cloud = cloud_of([[0, 0, 0], [0.3, 0.2, 0]], [[0, 0, 1], [0.2, 0, 1]], [[0.8, 0.6, 0.4]] * 2, 0.4, 0.3)
    spec = dict(kind="point", power=50.0, position=(0.5, 1.0, 1.5), radius=0.1)
    plain = shade(cloud, eye, [Light(**spec)], backend=backend)
    weighted = shade(cloud, eye, [Light(**spec, diffuse=2.0, specular=0.5)], backend=backend)
    assert plain.diffuse.min() > 0 and plain.specular.min() > 0
    np.testing.assert_allclose(weighted.diffuse, 2.0 * plain.diffuse, rtol=1e-6)
    np.testing.assert_allclose(weighted.specular, 0.5 * plain.specular, rtol=1e-6)
    glossy_only = shade(cloud, eye, [Light(**spec, diffuse=0.0)], backend=backend)
    assert not glossy_only.diffuse.any()
    np.testing.assert_array_equal(glossy_only.specular, plain.specular)
    sun = Light("sun", power=2.0, direction=(0, 0, -1))
    dark = Light(**spec, diffuse=0.0, specular=0.0)
    shaded = shade(cloud, eye, [sun, dark], visibility={1: np.zeros(2)}, backend=backend)
    np.testing.assert_array_equal(shaded.radiance, shade(cloud, eye, [sun], backend=backend).radiance)
    assert not shaded.shadow.any()  # the dark light's shadow takes no light away
    with pytest.raises(ValueError, match="specular must be finite, >= 0"):
        Light(**spec, specular=-1.0)


def test_orthographic_camera_views_along_its_axis_and_no_material_is_refused():
    cam = Camera.look_at_ortho(eye=(0, 0, 5), target=(0, 0, 0), up=(0, 1, 0))
    light = Light("point", power=100.0, position=(1.0, 0.0, 1.0))
    cloud = cloud_of([[0, 0, 0], [3, 0, 0]], [[0, 0, 1], [0, 0, 1]], [[0.5, 0.5, 0.5]] * 2, 0.3)
    by_camera = shade(cloud, cam, [light])
    far_above = shade(cloud, np.array([0.0, 0.0, 1e7]), [light])  # an eye very far along the axis
    np.testing.assert_allclose(by_camera.specular[0], far_above.specular[0], rtol=1e-4)
    bare = SplatCloud(
        positions=np.zeros((1, 3)),
        rotations=np.array([[1.0, 0, 0, 0]]),
        log_scales=np.zeros((1, 3)),
        opacity_logits=np.zeros(1),
        sh=np.zeros((1, 1, 3)),
    )
    with pytest.raises(ValueError, match="material"):
        shade(bare, cam, [light])


@pytest.mark.parametrize("eye", ["camera", "point", "orthographic"])
def test_compiled_shade_matches_the_numpy_path(eye):
    from splatwright.core import shading

    if shading._shade_kernel() is None:
        pytest.skip("compiled kernels are not available here")
    rng = np.random.default_rng(11)
    n = 2000
    cloud = random_cloud(n, rng)
    lights = [
        Light("point", power=300.0, position=(0.5, -0.4, 2.0), radius=0.2),
        Light("spot", power=500.0, position=(-1.0, 0.5, 2.0), direction=(0.4, -0.2, -1.0), spot_size=0.9),
        Light("spot", power=200.0, position=(0.0, 0.0, 2.5), direction=(0.0, 0.0, -1.0), spot_blend=0.0),
        Light("sun", power=2.0, direction=(0.3, 0.2, -1.0), angle=0.05, color=(1.0, 0.8, 0.6), specular=0.3),
        Light("area", power=100.0, position=(1.0, 1.0, 2.0), direction=(-0.3, -0.3, -1.0), size_x=0.8, diffuse=0.0),
        Light("area", power=80.0, position=(0, -1, 2), size_x=0.6, size_y=0.3, shape="ELLIPSE", x_axis=(0, 1, 0)),
        Light("area", power=90.0, position=(-0.5, 0.5, 1.5), size_x=0.7, spread=math.radians(70.0)),
        # narrow spreads close by: many splats sample the reachable disc (of a disc, a turned rectangle, an ellipse)
        Light("area", power=60.0, position=(0.3, -0.2, 1.2), size_x=0.9, shape="DISK", spread=math.radians(25.0)),
        Light("area", power=50.0, position=(0.0, 0.3, 1.3), size_x=1.2, size_y=0.6, shape="ELLIPSE", spread=0.6),
        Light(
            "area",
            power=60.0,
            position=(-0.2, 0.1, 1.1),
            direction=(0.1, 0.0, -1.0),
            size_x=0.8,
            size_y=0.5,
            shape="RECTANGLE",
            x_axis=(1.0, 1.0, 0.0),
            spread=math.radians(40.0),
        ),
    ]
    for light in lights[-3:]:
        assert reachable_discs(light, cloud.positions)[0].sum() > 100
    visibility = {0: rng.uniform(0.0, 1.0, n), 3: rng.uniform(0.0, 1.0, n), 4: np.zeros(n)}
    # the world's shares on either side, then its visibility towards core.ambient's 24 directions
    visibility["world"] = rng.uniform(0.0, 1.0, (n, 2 + 24)).astype(np.float32)
    cam = Camera.look_at((3, -4, 3), (0, 0, 0), up=(0, 0, 1), fov_deg=50, width=64, height=48)
    if eye == "orthographic":
        cam = Camera(64, 48, 20.0, 20.0, 32, 24, cam.world_to_camera, 0.1, projection="orthographic")
    where = (0.5, -3.0, 1.5) if eye == "point" else cam
    linked = {1: rng.uniform(size=n) < 0.5, 4: rng.uniform(size=n) < 0.3}  # light linking
    mapped = World(environment=np.concatenate([[[1.2, 0.9, 0.7]], rng.normal(0.0, 0.3, (8, 3))]))  # core.environment
    for world, multiscatter, receivers in (
        (World((0.1, 0.2, 0.3)), True, None),
        (mapped, True, None),
        (None, False, linked),
    ):
        args = (cloud, where, lights, world, visibility)
        compiled = shade(*args, multiscatter=multiscatter, receivers=receivers)
        reference = shade(*args, multiscatter=multiscatter, receivers=receivers, backend="numpy")
        for name in ("diffuse", "specular", "shadow"):
            got, want = getattr(compiled, name), getattr(reference, name)
            assert got.dtype == want.dtype == np.float32
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
    # A picture's splats alone (shown): theirs as before on both paths, the others' 0.
    shown = rng.uniform(size=n) < 0.6
    for backend in ("auto", "numpy"):
        part = shade(*args, multiscatter=False, receivers=linked, shown=shown, backend=backend)  # as the last pair
        whole = compiled if backend == "auto" else reference
        for name in ("diffuse", "specular", "shadow"):
            got, want = getattr(part, name), getattr(whole, name)
            assert np.array_equal(got[shown], want[shown]) and (got[~shown] == 0.0).all()
            assert np.abs(want[~shown]).max() > 0.01


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_a_uniform_environment_shades_as_the_world_colour(backend):
    """An environment of band 0 alone (a uniform map) gives exactly the uniform world's shading, its
    colour the map's mean; a map brighter above lights the splats facing up more, by the cosine's
    band-1 share (2/3) on the diffuse of a rough white splat."""
    from splatwright.core.sh import C0, C1

    rng = np.random.default_rng(12)
    cloud = random_cloud(500, rng)
    eye = np.array([0.3, -4.0, 2.0])
    uniform = np.zeros((9, 3))
    uniform[0] = np.array([0.2, 0.3, 0.4]) / C0
    plain = shade(cloud, eye, [], World((0.2, 0.3, 0.4)), backend=backend)
    mapped = shade(cloud, eye, [], World(environment=uniform), backend=backend)
    for name in ("diffuse", "specular"):
        np.testing.assert_allclose(getattr(mapped, name), getattr(plain, name), rtol=1e-6, atol=1e-7)
    sky = uniform.copy()
    sky[2] = np.array([0.2, 0.3, 0.4]) / C0 * 0.5  # band 1's z: L = W (1 + 0.5 sqrt(3) z)
    n = len(cloud)
    up = with_material(cloud, normals=np.tile([0.0, 0.0, 1.0], (n, 1)), roughness=np.ones(n), metallic=np.zeros(n))
    lit, flat = (shade(up, eye, [], World(environment=e), backend=backend).diffuse for e in (sky, uniform))
    want = 1.0 + 2.0 / 3.0 * 0.5 * C1 / C0  # the cosine's band 1 over band 0
    np.testing.assert_allclose(lit / flat, want, rtol=1e-5)


def test_the_shading_loops_asin_is_asin_within_float32_rounding():
    """core.shading._asin (the series below ASIN_SERIES, the library's asin above), compiled and
    as plain Python, against math.asin in float64 over [0, 1], the threshold on both sides."""
    from splatwright.core import shading

    shading._shade_kernel()  # compiles the loop's helpers in place where numba loads
    x = np.concatenate([np.linspace(0.0, 1.0, 2001), shading.ASIN_SERIES + np.array([-1e-12, 0.0, 1e-12])])
    want = np.arcsin(x)
    for asin in {shading._asin, getattr(shading._asin, "py_func", shading._asin)}:
        got = np.array([asin(float(v)) for v in x])
        np.testing.assert_allclose(got, want, rtol=3e-8, atol=0.0)


def test_the_numpy_path_shades_in_chunks_as_in_one_piece(monkeypatch):
    """The NumPy path takes the points TERMS_CHUNK at a time (an area light's sample slots, the world's
    directions are arrays per point): chunks that cut the cloud anywhere give the same shading."""
    from splatwright.core import shading

    cloud = random_cloud(50, np.random.default_rng(5))
    lights = [
        Light("area", power=60.0, position=(0.3, -0.2, 1.2), size_x=0.9, shape="DISK", spread=math.radians(25.0)),
        Light("point", power=100.0, position=(0.0, 0.0, 2.0)),
    ]
    # and the world's occlusion, its specular lobe's share from 24 directions
    seen = {"world": np.random.default_rng(6).uniform(0.0, 1.0, (50, 2 + 24)).astype(np.float32)}
    args = (cloud, (2.0, -3.0, 2.0), lights, World((0.1, 0.2, 0.3)), seen)
    whole = shade(*args, backend="numpy")
    monkeypatch.setattr(shading, "TERMS_CHUNK", 7)
    chunked = shade(*args, backend="numpy")
    for name in ("diffuse", "specular", "shadow"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_an_environments_hidden_sky_is_weighed_by_its_light(backend):
    """Splats facing sideways under a roof (every direction above the horizon hidden, core.ambient's 24
    directions) and an environment of a bright sky over a dark ground: the share of the map's
    irradiance they keep is that of the ground they see, each direction weighed by the map's light
    there, against the brute-force integral of the map's bands over the open directions (within the
    24 directions' coarseness); the cosine share alone (half the directions) would keep half of the
    sky's light too."""
    from environment_reference import directions as map_directions

    from splatwright.core import environment

    d, solid = map_directions(128, 256)
    sky = np.where(d[..., 2:] > 0.0, [2.0, 2.2, 2.6], [0.2, 0.15, 0.1])
    world = World(environment=environment.from_equirect(sky), occlusion=24)
    n = 200
    rng = np.random.default_rng(14)
    splats = SplatCloud(
        rng.uniform(-0.1, 0.1, (n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), -4.0), np.zeros(n),
        np.zeros((n, 1, 3)),
    )  # fmt: skip
    sideways = np.tile([1.0, 0.0, 0.0], (n, 1))
    rough = dict(roughness=np.ones(n), metallic=np.zeros(n))
    cloud = with_material(splats, albedo=np.full((n, 3), 0.7), normals=sideways, **rough)
    sky_directions = sphere_directions(24)
    below = (sky_directions[:, 2] < 0.0).astype(np.float32)
    cosines = np.maximum(sky_directions[:, 0], 0.0)
    share = float((cosines * below).sum() / cosines.sum())  # the cosine share of the normal's side
    seen = np.tile(np.concatenate([[share, share], below]), (n, 1)).astype(np.float32)
    eye = np.array([5.0, 0.0, 0.0])
    hidden = shade(cloud, eye, [], world, {"world": seen}, backend=backend).diffuse
    whole = shade(cloud, eye, [], world, backend=backend).diffuse
    ours = (hidden / whole).mean(axis=0)
    bands = environment.radiance(world.environment, d.reshape(-1, 3))
    facing = np.maximum(d.reshape(-1, 3)[:, 0], 0.0) * solid.ravel()
    open_ground = d.reshape(-1, 3)[:, 2] < 0.0
    want = (facing[open_ground, None] * bands[open_ground]).sum(axis=0) / (facing[:, None] * bands).sum(axis=0)
    np.testing.assert_allclose(ours, want, rtol=0.05)  # measured within 1.3%
    assert (share > 2.0 * want).all() and 0.3 < share < 0.7
