"""Per-splat shading for relighting: the radiance each splat sends towards the eye under Blender's
lights (core.lights) and a uniform world, from its material (core.material).

What is modelled, per splat, vectorised over splats (float64 inside, float32 out):

- diffuse: Lambert, albedo / pi, weighted by (1 - metallic) and by (1 - E(n.v)), the share of light the
  specular layer leaves (E: the specular lobe's directional albedo, see specular_albedo), as Blender's
  Principled BSDF layers its dielectric specular over the diffuse base;
- specular: GGX (Trowbridge-Reitz) microfacets with the height-correlated Smith G, Schlick's Fresnel,
  F0 = mix(0.04, albedo, metallic) (Principled's IOR 1.5 dielectric) and alpha = roughness^2. A light
  of angular radius s widens alpha to hypot(alpha, s/2) (at most 1), so that small spheres, the sun's
  disc and each area-light sample give a highlight of about their size instead of a needle (the
  highlight of a 1 m disc 1.5 m away comes within 12% of the BRDF integrated over the disc at
  roughness 0.3, 4% at 0.45, 1% at 0.7; at 0.1 a 0.5 m disc's is 29% dim: tests/test_shading.py);
  smooth lobes (roughness up to core.ltc.ROUGHNESS) are integrated over the light instead by fitted
  cosines (core.ltc: within 2% of the highlight where the samples or the widened lobe left up to a
  third): an area light without a Spread, its diffuse exactly too, a sphere light or the sun's disc;
- world: a uniform environment of radiance W gives diffuse albedo * (1 - metallic) * (1 - E) * W and
  specular E * W (white furnace: albedo 1, metallic 0 sends back exactly W), each scaled by the share
  of the world the splat sees on its eye's side when that is given (core.ambient), else unoccluded:
  the diffuse by the cosine-weighted share, the specular by its lobe's (lobe_sky); an environment
  map (World.environment) gives in place of W its irradiance over pi at the normal and its
  radiance, filtered by the lobe, towards the view's mirror direction (core.environment);
- two-sided: a normal facing away from the eye is flipped towards it (splats are seen from both
  sides), so a splat's back is lit as its front would be;
- shadows come in as visibility per light (core.shadows): a light's contribution is scaled by it.

Multiple scattering between microfacets (Blender's default Multiscatter GGX) is given back by an
energy compensation of the lobe (multiscatter_compensation; `multiscatter=False` for plain GGX).

Not modelled: clearcoat, sheen, subsurface, transmission, emission, light bouncing between splats.

The NumPy functions are the reference. Where numba loads (core.jit), shade() runs the same sums one
splat at a time in a compiled loop (_shade_loop, float64 as NumPy, on every core): no (N,3) float64
temporaries per emitter, which made NumPy's shading of a 410k-splat frame take about as long as the
frame's render. tests/test_shading.py holds the two to 1e-5.
"""

import functools
import math
from dataclasses import dataclass

import numpy as np

from . import environment, jit, ltc, material, scratch
from .arrays import Floats
from .camera import Camera
from .lights import (
    AREA_GLOSS,
    AREA_GRID,
    AREA_REACH,
    AREA_SPREAD,
    ELLIPSE_BISECTIONS,
    ELLIPSE_SCAN,
    SPREAD_ANGLES,
    SPREAD_SAMPLES,
    Incident,
    Light,
    World,
    area_radiance,
    area_table,
    disc_rings,
    incident,
    sphere_directions,
    spread_terms,
    towards,
    y_axis,
)
from .parallel import in_chunks
from .splats import SplatCloud

DIELECTRIC_F0 = 0.04  # Fresnel at normal incidence of an IOR 1.5 dielectric (Principled's default)
ALPHA_MIN = 1e-3  # the narrowest lobe: a true point light on a mirror would otherwise divide by 0
COS_MIN = 1e-6  # n.v floor: grazing views keep a finite specular (G goes to 0 there anyway)
# specular_albedo's table: TABLE x TABLE nodes over (n.v, roughness), each integrated with
# QUADRATURE x QUADRATURE stratified GGX half-vectors (within 0.5% of brute force, tests/test_shading.py).
TABLE = 32
QUADRATURE = 64


@dataclass(frozen=True, eq=False)
class Shading:
    """Outgoing scene-linear radiance towards the eye per splat: diffuse (N,3) and specular (N,3)
    float32, and shadow (N,) float32, the fraction of the lights' unshadowed light (their mean over
    colour channels, summed over lights) that visibility took away: 0 unshadowed, 1 fully shadowed."""

    diffuse: np.ndarray
    specular: np.ndarray
    shadow: np.ndarray

    @property
    def radiance(self) -> np.ndarray:
        """(N,3) float32: diffuse + specular."""
        return self.diffuse + self.specular


def view_directions(eye: np.ndarray | Camera, points: np.ndarray) -> np.ndarray:
    """Unit vectors (N,3) from points (N,3) towards the eye: a position (3,), or a Camera (its centre,
    or for an orthographic one the reverse of its viewing direction, the same for every point)."""
    if isinstance(eye, Camera):
        if eye.is_orthographic:
            return np.broadcast_to(-eye.forward, points.shape).copy()
        eye = eye.center
    return towards(np.asarray(eye, dtype=np.float64).reshape(3), points)[0]


def seen_from_front(normals: np.ndarray, view: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each normal (N,3) faces its view direction (N,3); a splat seen from behind
    is shaded with its normal flipped (two-sided splats) and sees the world of its back side."""
    return np.einsum("ij,ij->i", normals, view) >= 0.0


def ggx_d(cos_h: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Trowbridge-Reitz normal distribution D(h) (N,) for cos(n, h) and alpha (N,)."""
    a2 = alpha * alpha
    denom = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * denom * denom)


def smith_lambda(cos_t: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """GGX's Smith Lambda (N,) of a direction at cos_t (> 0) to the normal."""
    cos2 = np.maximum(cos_t * cos_t, COS_MIN * COS_MIN)
    tan2 = np.maximum(1.0 - cos2, 0.0) / cos2
    return 0.5 * (np.sqrt(1.0 + alpha * alpha * tan2) - 1.0)


def smith_g(cos_v: np.ndarray, cos_l: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Height-correlated Smith masking-shadowing G2 (N,) = 1 / (1 + Lambda(v) + Lambda(l))."""
    return 1.0 / (1.0 + smith_lambda(cos_v, alpha) + smith_lambda(cos_l, alpha))


def ggx_parts(normal, view, light, alpha) -> tuple[np.ndarray, np.ndarray]:
    """The GGX specular BRDF times the cosine split for Schlick's F: (D G / (4 n.v), 0 where n.l <= 0)
    and the Fresnel weight (1 - v.h)^5, each (N,), so that f(v, l) (n.l) = scalar * (F0 (1 - w) + w)."""
    cos_v = np.maximum(np.einsum("ij,ij->i", normal, view), COS_MIN)
    cos_l = np.einsum("ij,ij->i", normal, light)
    half = view + light
    half /= np.maximum(np.sqrt(np.einsum("ij,ij->i", half, half)), 1e-300)[:, None]
    cos_h = np.clip(np.einsum("ij,ij->i", normal, half), 0.0, 1.0)
    weight = (1.0 - np.clip(np.einsum("ij,ij->i", view, half), 0.0, 1.0)) ** 5
    scalar = ggx_d(cos_h, alpha) * smith_g(cos_v, np.maximum(cos_l, COS_MIN), alpha) / (4.0 * cos_v)
    return np.where(cos_l > 0.0, scalar, 0.0), weight


def ggx_reflect(normal, view, light, alpha, f0) -> np.ndarray:
    """The GGX specular BRDF times the cosine, f(v, l) * (n.l) = D G F / (4 n.v), (N,3), for unit
    normal, view and light directions (N,3), alpha (N,) and F0 (N,3); 0 where n.l <= 0."""
    scalar, weight = ggx_parts(normal, view, light, alpha)
    return scalar[:, None] * (f0 * (1.0 - weight)[:, None] + weight[:, None])


@functools.cache
def _albedo_table() -> tuple[np.ndarray, np.ndarray]:
    """(scale, bias), each (TABLE, TABLE) over (n.v, roughness) grid nodes: the GGX lobe's directional
    albedo is F0 * scale + bias (Schlick's F is linear in F0). Integrated once, by stratified
    sampling of the half-vector from D (the estimator G * F * (v.h) / ((n.v) (n.h)))."""
    cos_v = np.linspace(0.0, 1.0, TABLE)
    cos_v[0] = 1e-3  # a view exactly in the tangent plane reflects nothing useful
    alpha = np.maximum(np.linspace(0.0, 1.0, TABLE) ** 2, ALPHA_MIN)
    u = (np.arange(QUADRATURE) + 0.5) / QUADRATURE
    u1, u2 = (m.ravel() for m in np.meshgrid(u, u, indexing="ij"))
    scale = np.empty((TABLE, TABLE))
    bias = np.empty((TABLE, TABLE))
    for j, a in enumerate(alpha):  # a loop over 32 table columns
        cos_h = 1.0 / np.sqrt(1.0 + a * a * u1 / (1.0 - u1))
        sin_h = np.sqrt(1.0 - cos_h * cos_h)
        phi = 2.0 * math.pi * u2
        h = np.stack([sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h], axis=1)  # (S, 3), normal +z
        v = np.stack([np.sqrt(1.0 - cos_v**2), np.zeros(TABLE), cos_v], axis=1)  # (T, 3)
        vh = v @ h.T  # (T, S)
        cos_l = 2.0 * vh * cos_h[None, :] - cos_v[:, None]  # n.l of l = reflect(v, h)
        ok = (cos_l > 0.0) & (vh > 0.0)
        lam_v = smith_lambda(cos_v, np.full(TABLE, a))[:, None]
        lam_l = smith_lambda(np.maximum(cos_l, COS_MIN).ravel(), np.full(cos_l.size, a)).reshape(cos_l.shape)
        weight = np.where(ok, vh / (cos_v[:, None] * cos_h[None, :] * (1.0 + lam_v + lam_l)), 0.0)
        fresnel = (1.0 - np.clip(vh, 0.0, 1.0)) ** 5
        scale[:, j] = np.mean(weight * (1.0 - fresnel), axis=1)
        bias[:, j] = np.mean(weight * fresnel, axis=1)
    return scale, bias


def specular_albedo(cos_v: np.ndarray, roughness: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """E (N,3): the fraction of light from a uniform environment the GGX lobe reflects towards a view
    at cos_v (N,) to the normal, for roughness (N,) and F0 (N,3); bilinear in a table (_albedo_table)."""
    scale, bias = albedo_parts(cos_v, roughness)
    return np.clip(f0 * scale[:, None] + bias[:, None], 0.0, 1.0)


def albedo_parts(cos_v: np.ndarray, roughness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(scale (N,), bias (N,)): the GGX lobe's directional albedo is F0 * scale + bias, bilinear in
    _albedo_table at each view's n.v (N,) and roughness (N,)."""
    scale, bias = _albedo_table()
    x = np.clip(cos_v, 0.0, 1.0) * (TABLE - 1)
    y = np.clip(roughness, 0.0, 1.0) * (TABLE - 1)
    i = np.minimum(x.astype(np.int64), TABLE - 2)
    j = np.minimum(y.astype(np.int64), TABLE - 2)
    fx, fy = x - i, y - j

    def lerp(t):
        return (t[i, j] * (1 - fx) + t[i + 1, j] * fx) * (1 - fy) + (t[i, j + 1] * (1 - fx) + t[i + 1, j + 1] * fx) * fy

    return lerp(scale), lerp(bias)


def multiscatter_compensation(cos_v: np.ndarray, roughness: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """(N,3) factor on the single-scattering GGX lobe for the light it loses to multiple scattering
    between microfacets: 1 + F0 (1 / E1 - 1), E1 the lobe's albedo for F0 = 1 towards the view
    (Turquin's energy compensation). A white metal (F0 = 1) then reflects all of a uniform world, as
    Cycles' Multiscatter GGX nearly does."""
    white = specular_albedo(cos_v, roughness, np.ones((len(cos_v), 3)))[:, :1]
    return 1.0 + f0 * (1.0 / np.maximum(white, 1e-3) - 1.0)


def angular_radius(light: Light, emitter: Incident) -> np.ndarray:
    """The angle (N,) an emitter (core.lights.incident's) subtends (its half-angle) at the points it
    lights: a point or spot light's sphere, the sun's disc, or an area sample's patch as a disc."""
    if light.kind == "sun":
        return np.full(len(emitter.distance), 0.5 * light.angle)
    return np.arcsin(np.clip(emitter.radius / np.maximum(emitter.distance, 1e-300), 0.0, 1.0))


TERMS_CHUNK = 1 << 15  # points per step of the NumPy path: an area light's 24 sample slots in under 100 MB


def _light_terms(light, points, normal, view, rough, f0, parts, integrate=True) -> tuple[np.ndarray, np.ndarray]:
    """One light's unshadowed diffuse factor (irradiance on the surface, E cos) and specular radiance,
    (N,3) each. Per emitter only (N,) scalars are summed: the light's colour and Schlick's F0 come in
    once at the end (F = F0 (1 - w) + w). Smooth splats' highlights are integrated over the light
    (core.ltc, unless not `integrate`): the lobe's share times its albedo (`parts`, albedo_parts'
    (scale, bias) of every splat), split the same way; under an area light their diffuse too."""
    n = len(points)
    diffuse, tinted, white = (np.zeros(n) for _ in range(3))
    alpha = np.maximum(rough * rough, ALPHA_MIN)
    for lo in range(0, n, TERMS_CHUNK):  # a loop over chunks: an area light's samples are (chunk,) arrays
        part = np.arange(lo, min(lo + TERMS_CHUNK, n))
        if integrate and ltc.integrated(light):  # its smooth splats integrated, the others sampled
            smooth, part = part[rough[part] <= ltc.ROUGHNESS], part[rough[part] > ltc.ROUGHNESS]
            radiance = area_radiance(light)
            form, share = ltc.light_shares(light, points[smooth], normal[smooth], view[smooth], rough[smooth])
            scale, bias = parts[0][smooth], parts[1][smooth]
            diffuse[smooth] = math.pi * radiance * form
            tinted[smooth], white[smooth] = radiance * share * scale, radiance * share * bias
        for inc in incident(light, points[part], alpha[part]):  # one emitter, or an area light's samples
            diffuse[part] += inc.strength * np.maximum(np.einsum("ij,ij->i", normal[part], inc.direction), 0.0)
            half = angular_radius(light, inc)
            widened = np.minimum(np.hypot(alpha[part], 0.5 * half), 1.0)
            scalar, weight = ggx_parts(normal[part], view[part], inc.direction, widened)
            scalar *= inc.strength
            if integrate and light.kind != "area":  # a round light's smooth highlights integrated
                disc = _round_light(half, rough[part]) & (scalar > 0.0)
                scalar[disc] = 0.0
                at = part[disc]
                share = ltc.disc_shares(inc.direction[disc], half[disc], normal[at], view[at], rough[at])
                scale, bias = parts[0][at], parts[1][at]
                radiance = inc.strength[disc] / (math.pi * np.sin(half[disc]) ** 2)
                tinted[at] += radiance * share * scale
                white[at] += radiance * share * bias
            tinted[part] += scalar * (1.0 - weight)
            white[part] += scalar * weight
    specular = (f0 * tinted[:, None] + white[:, None]) * (light.color * light.specular)
    return diffuse[:, None] * (light.color * light.diffuse), specular


def shade(
    cloud: SplatCloud,
    eye: np.ndarray | Camera,
    lights: list[Light],
    world: World | None = None,
    visibility: dict[int | str, np.ndarray] | None = None,
    *,
    receivers: dict[int, np.ndarray] | None = None,
    shown: np.ndarray | None = None,
    multiscatter: bool = True,
    integrate: bool = True,
    backend: str = "auto",
) -> Shading:
    """Shade every splat of `cloud` (which must carry a material: core.material.has_material) for an
    eye at a position (3,) or a Camera, under `lights` and an optional uniform `world`. visibility
    maps a light's index in `lights` to (N,) values in [0,1] (1: unshadowed; lights absent: 1), and
    "world" to the (N,2) share of the world each splat sees on its normal's side and the other, then
    optionally its visibility towards K directions for the specular lobe's share (core.ambient's
    (N, 2 + K); absent: 1).
    receivers: light linking, a light's index to the (N,) bool splats it lights (absent: all); the
    others get none of its light, and it counts as no shadow on them.
    shown: (N,) bool, the splats to shade (absent: all; a picture's, core.relight); the others' terms
    are 0.
    multiscatter: compensate the GGX lobe's lost energy (multiscatter_compensation) as Blender's
    default Multiscatter GGX does; False for the plain single-scattering GGX distribution.
    integrate: smooth lobes integrated over the light (core.ltc); False shades them as rougher ones
    (an area light's samples, a round light's widened lobe).
    backend: "auto" (the compiled kernel where numba loads, core.jit) or "numpy" (the reference)."""
    if not material.has_material(cloud):
        raise ValueError("the cloud has no material to shade: it needs albedo and normals (core.material)")
    kernel = _shade_kernel() if backend != "numpy" else None
    reach = _reach(receivers, len(lights), len(cloud))
    if shown is not None:
        shown = np.asarray(shown, bool).reshape(-1)
        if shown.shape != (len(cloud),):
            raise ValueError(f"shown must be {len(cloud)} values, one per splat, got {shown.shape[0]}")
    if kernel is not None:
        flags = (multiscatter, integrate)
        return _shade_compiled(kernel, cloud, eye, lights, world, visibility, reach, shown, *flags)
    normals, albedo = material.normals(cloud), material.albedo(cloud)
    points = cloud.positions.astype(np.float64)
    n = len(points)
    view = view_directions(eye, points)
    front = seen_from_front(normals, view)
    normal = np.where(front[:, None], normals, -normals)  # the side towards the eye
    rough, metal = material.roughness(cloud), material.metallic(cloud)
    alpha = np.maximum(rough * rough, ALPHA_MIN)
    f0 = DIELECTRIC_F0 + (albedo - DIELECTRIC_F0) * metal[:, None]
    cos_v = np.maximum(np.einsum("ij,ij->i", normal, view), 0.0)
    boost = multiscatter_compensation(cos_v, rough, f0) if multiscatter else np.ones((n, 3))
    layer = specular_albedo(cos_v, rough, f0) * boost  # what the specular layer takes from the base
    parts = albedo_parts(cos_v, rough)  # the lobe's albedo split for F0, for lights integrated (core.ltc)
    base = albedo * (1.0 - metal)[:, None] * np.clip(1.0 - layer, 0.0, 1.0)
    diffuse, specular = np.zeros((n, 3)), np.zeros((n, 3))
    lit, seen = np.zeros(n), np.zeros(n)
    for index, light in enumerate(lights):  # a loop over lights
        d, s = _light_terms(light, points, normal, view, rough, f0, parts, integrate)
        d, s = d * base / math.pi, s * boost
        linked = reach[index] if reach.shape[1] > 1 else reach[index, 0]
        vis = _visibility(visibility, index, n) * linked
        diffuse += vis[:, None] * d
        specular += vis[:, None] * s
        total = (d + s).mean(axis=1)
        lit += linked * total
        seen += vis * total
    if world is not None:
        shares = np.clip(_world_visibility(visibility, n), 0.0, 1.0)
        seen_world = shares[np.arange(n) if len(shares) > 1 else 0, np.where(front, 0, 1)]
        diffuse_light, glossy_light = _world_light(world, normal, view, alpha)
        sky_light = _sky_light(world, shares.shape[1] - 2)
        if sky_light is None:
            glossy = lobe_sky(shares[:, 2:], normal, view, alpha, seen_world) if shares.shape[1] > 2 else seen_world
            diffuse_share, glossy = seen_world[:, None], glossy[:, None]
        else:  # an environment's light: each direction's visibility weighed by its radiance as well
            diffuse_share = cosine_sky(shares[:, 2:], normal, seen_world, sky_light)
            glossy = lobe_sky(shares[:, 2:], normal, view, alpha, seen_world, sky_light)
        diffuse += base * diffuse_light * diffuse_share
        specular += layer * glossy_light * glossy
    shadow = np.where(lit > 0.0, 1.0 - seen / np.where(lit > 0.0, lit, 1.0), 0.0)
    if shown is not None:
        diffuse[~shown], specular[~shown], shadow[~shown] = 0.0, 0.0, 0.0
    return Shading(diffuse.astype(np.float32), specular.astype(np.float32), np.clip(shadow, 0, 1).astype(np.float32))


def _world_light(world: World, normal: np.ndarray, view: np.ndarray, alpha: np.ndarray):
    """(diffuse (N,3) or (3,), glossy): the world's light on a white Lambertian surface facing
    `normal` (N,3) and on a lobe of width `alpha` (N,) seen along `view` (N,3): a uniform world's
    colour both ways, an environment map's (core.environment) at the normal and at the view's
    mirror direction."""
    if world.environment is None:
        return world.color, world.color
    mirror = 2.0 * np.einsum("ij,ij->i", normal, view)[:, None] * normal - view
    return environment.diffuse(world.environment, normal), environment.glossy(world.environment, mirror, alpha)


def lobe_sky(
    seen: np.ndarray,
    normal: np.ndarray,
    view: np.ndarray,
    alpha: np.ndarray,
    open_sky: np.ndarray,
    sky_light: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) the share of a uniform world that each splat's specular lobe sees, from its visibility
    (N,K) in [0, 1] towards the K directions of core.lights.sphere_directions(K) (core.ambient's
    columns 2..), each weighted by the lobe there: GGX's D G / (4 n.v) of alpha (N,) for the normal
    (N,3) facing the eye `view` (N,3), 0 below its horizon. open_sky (N,), the cosine-weighted share
    of that side, stands in where no direction lies above it. With `sky_light` (K,3), an
    environment's radiance towards the directions, (N,3): each direction weighed by it too.

    Against the lobe integrated over 200k directions of a soft-edged sky (a random half of the
    sphere, its edge 0.4 wide in cosine), with 24 directions, mean |error| at roughness 0.2 / 0.35 /
    0.5 / 0.7 / 1: 0.084 / 0.064 / 0.045 / 0.027 / 0.020 (the cosine-weighted share: 0.27 / 0.23 /
    0.16 / 0.080 / 0.023; tests/test_shading.py). Blender's Suzanne (metallic, roughness 0.35)
    against Cycles, world occluded, point light: 32.7 -> 33.9 dB at 0.5x, 33.5 -> 33.9 at 1x (rays
    through the lobe itself against the mesh: 34.1 / 33.9)."""
    k, sky = seen.shape[1], sphere_directions(seen.shape[1])
    light = np.ones((k, 1)) if sky_light is None else np.asarray(sky_light, np.float64)
    out = np.repeat(np.asarray(open_sky, np.float64)[:, None], light.shape[1], axis=1)
    for lo in range(0, len(normal), TERMS_CHUNK):  # a loop over chunks: (chunk * K, 3) temporaries
        part = slice(lo, lo + TERMS_CHUNK)
        m = len(normal[part])
        directions = np.broadcast_to(sky[None], (m, k, 3)).reshape(-1, 3)
        rows = (np.repeat(normal[part], k, 0), np.repeat(view[part], k, 0))
        weight = ggx_parts(*rows, directions, np.repeat(alpha[part], k))[0].reshape(m, k)
        out[part] = _weighed_share(weight, seen[part], light, out[part])
    return out[:, 0] if sky_light is None else out


def cosine_sky(seen: np.ndarray, normal: np.ndarray, open_sky: np.ndarray, sky_light: np.ndarray) -> np.ndarray:
    """(N,3) the share of an environment's irradiance each splat sees, from its visibility (N,K)
    towards the K directions of sphere_directions(K) (as lobe_sky's), each weighed by the cosine to
    the normal (N,3) and by the radiance `sky_light` (K,3) there; open_sky (N,) where none lights it."""
    weight = np.maximum(normal @ sphere_directions(seen.shape[1]).T, 0.0)
    fallback = np.repeat(np.asarray(open_sky, np.float64)[:, None], 3, axis=1)
    return _weighed_share(weight, seen, np.asarray(sky_light, np.float64), fallback)


def _weighed_share(weight, seen, light, fallback):
    """(N,C) sum_k weight seen light / sum_k weight light over the K directions (weight and seen
    (N,K), light (K,C)), fallback (N,C) where the sum is 0."""
    total = weight @ light
    share = (weight * np.clip(seen, 0.0, 1.0)) @ light
    return np.where(total > 0.0, share / np.where(total > 0.0, total, 1.0), fallback)


def _sky_light(world: World, directions: int) -> np.ndarray | None:
    """(K,3) an environment's radiance towards the K directions of the world's occlusion, or None for
    a uniform world (or no directions)."""
    if world.environment is None or directions <= 0:
        return None
    return environment.radiance(world.environment, sphere_directions(directions))


ROUND_LIGHT_MAX = 1.4  # radians: a sphere light wider than this as seen (a splat at its surface) stays sampled


def _round_light(half: np.ndarray, roughness: np.ndarray) -> np.ndarray:
    """(N,) bool: where a sphere light or the sun, seen `half` (N,) radians wide, has its highlight
    integrated (core.ltc.disc_shares) on splats of `roughness` (N,): a smooth lobe, a light with a
    size, not so close that it fills the sky."""
    return (roughness <= ltc.ROUGHNESS) & (half > 0.0) & (half < ROUND_LIGHT_MAX)


def _visibility(visibility: dict[int, np.ndarray] | None, index: int, n: int) -> Floats:
    if visibility is None or index not in visibility:
        return np.ones(n)
    vis = np.asarray(visibility[index], dtype=np.float64).reshape(-1)
    if vis.shape != (n,) or not np.isfinite(vis).all():
        raise ValueError(f"visibility of light {index} must be {n} finite values, got shape {vis.shape}")
    return np.clip(vis, 0.0, 1.0)


def linked_masks(receivers: dict[int, np.ndarray] | None, n: int) -> dict[int, np.ndarray]:
    """Light linking's masks (a light's index to the splats it lights) as (N,) bool arrays;
    ValueError for one that is not one value per splat."""
    out = {}
    for index, mask in (receivers or {}).items():
        mask = np.asarray(mask).reshape(-1)
        if mask.shape != (n,):
            raise ValueError(f"light {index}'s receivers must be {n} values, one per splat, got {mask.shape[0]}")
        out[int(index)] = mask.astype(bool)
    return out


def _reach(receivers: dict[int, np.ndarray] | None, n_lights: int, n: int) -> np.ndarray:
    """(L, N) float64: 1 where a light lights a splat, 0 where its light linking leaves it out; (L, 1)
    ones without linking. ValueError for a light index out of range."""
    masks = linked_masks(receivers, n)
    if not masks:
        return np.ones((n_lights, 1))
    reach = np.ones((n_lights, n))
    for index, mask in masks.items():
        if not 0 <= index < n_lights:
            raise ValueError(f"light linking names light {index}, but there are {n_lights} lights")
        reach[index] = mask
    return reach


def _world_visibility(visibility: dict | None, n: int) -> Floats:
    """(N, 2 + K) float32: visibility["world"] checked (K >= 0 directions, core.ambient's), to be
    clipped to [0, 1] where read; (1,2) ones without it (the whole world for every splat, with no
    (N,2) array made)."""
    if visibility is None or "world" not in visibility:
        return np.ones((1, 2), np.float32)
    seen = np.asarray(visibility["world"], dtype=np.float32)  # as made: a float64 copy of 2 + K columns costs
    if seen.ndim != 2 or seen.shape[0] != n or seen.shape[1] < 2 or not np.isfinite(seen).all():
        raise ValueError(f"the world's visibility must be ({n}, 2 + K) finite values, got shape {seen.shape}")
    return seen


# the compiled path -----------------------------------------------------------------------------------
# The same shading one splat at a time (float64 throughout, as the NumPy path): each light is cut into
# emitters, one row of numbers each (EMITTER_FIELDS), so the loop needs no Light objects.

SUN, POINT, SPOT, AREA = 0, 1, 2, 3
# kind, light index, position (3), direction (3: towards the sun; the spot's or area's axis),
# strength factor, spot cos(size/2) and edge width (an area sample's: 0 and the tan of half its
# light's spread, 0 for none), emitter radius (the sun's: its half angle)
EMITTER_FIELDS = 12
SHADE_KERNEL = (
    "_tan2", "_lambda_sq", "_table_one", "_asin", "_ellipse_rim_one", "_ring_arcs", "_lobe_weight_one",
    "_lobe_sky_one", "_sky_shares_one", "_shade_loop",
)  # fmt: skip
ASIN_SERIES = 0.3  # _asin sums its series below this sine, calls asin above


def _emitters(lights: list[Light]) -> tuple[np.ndarray, np.ndarray]:
    """(E, EMITTER_FIELDS) float64: every light's emitters (an area light's samples on every grid, see
    core.lights.incident: each splat takes those of its own grid), and (L, AREA_GRID + 1, 2) int64:
    the rows [start, stop) of light k's emitters on grid g (any g for a light without a grid), so
    the loop reads a splat's own samples only."""
    rows: list[list[float]] = []
    spans = np.zeros((len(lights), AREA_GRID + 1, 2), np.int64)
    for index, light in enumerate(lights):  # a loop over lights
        spans[index] = len(rows), len(rows) + 1
        if light.kind == "sun":
            rows.append([SUN, index, 0, 0, 0, *(-light.direction), light.power, 0, 0, 0.5 * light.angle])
        elif light.kind in ("point", "spot"):
            cos_half = math.cos(0.5 * light.spot_size)
            kind = SPOT if light.kind == "spot" else POINT
            strength = light.power / (4.0 * math.pi)
            width = (1.0 - cos_half) * light.spot_blend
            rows.append([kind, index, *light.position, *light.direction, strength, cos_half, width, light.radius])
        else:
            table = area_table(light)
            tan_half, spread_scale = spread_terms(light)
            for grid in range(1, AREA_GRID + 1):  # 1 + 4 + 9 + 16 samples
                share = light.area / (grid * grid)
                strength = area_radiance(light) * share * spread_scale
                radius = math.sqrt(share / math.pi)
                spans[index, grid] = len(rows), len(rows) + grid * grid
                for sample in table[grid, : grid * grid]:
                    rows.append([AREA, index, *sample, *light.direction, strength, 0, tan_half, radius])
    return np.array(rows, np.float64).reshape(-1, EMITTER_FIELDS), spans


# An area light's numbers in a row of AREA_FIELDS (0 for other lights): its centre (3), AREA_REACH and
# AREA_GLOSS times its longer side, its axis (3), AREA_SPREAD times that side over tan(spread/2) (0
# without a Spread), from which a splat's grid follows (core.lights.area_grids); its local x and y
# axes (6), half extents (2), 1 for a round shape, tan(spread/2) (0 without a Spread: no reachable
# disc, core.lights.reachable_discs), its area, the radiance (times the spread's scale) a square
# metre of it sends, and the number of its polygon's vertices where its smooth splats' shading is
# integrated (core.ltc.integrated, outline), 0 where it is sampled.
AREA_FIELDS = 22


def _area_terms(lights: list[Light], integrate: bool = True) -> np.ndarray:
    """(L, AREA_FIELDS) float64: every light's row of area terms (see AREA_FIELDS)."""
    rows = []
    for light in lights:  # a loop over lights
        if light.kind != "area":
            rows.append([0.0] * AREA_FIELDS)
            continue
        side = max(light.extent)
        tan_half, spread_scale = spread_terms(light)
        spread = AREA_SPREAD * side / tan_half if tan_half > 0.0 else 0.0
        half_x, half_y = 0.5 * light.extent[0], 0.5 * light.extent[1]
        radiance = area_radiance(light) * spread_scale
        rows.append(
            [*light.position, AREA_REACH * side, AREA_GLOSS * side, *light.direction, spread]
            + [*light.x_axis, *y_axis(light), half_x, half_y, float(light.round), tan_half, light.area, radiance]
            + [float(len(ltc.outline(light)) if integrate and ltc.integrated(light) else 0)]
        )
    return np.array(rows, np.float64).reshape(-1, AREA_FIELDS)


def _shade_compiled(kernel, cloud, eye, lights, world, visibility, reach, shown, multiscatter, integrate):
    """shade() by the compiled kernel, on every core (it releases the GIL). It reads the material's
    columns as they are stored (float32 albedo, float64 normals) rather than (N,3) float64 copies."""
    n = len(cloud)
    normals = material.normal_columns(cloud)
    albedo = np.ascontiguousarray(cloud.extras[material.ALBEDO].reshape(n, 3), np.float32)
    vis = scratch.empty((len(lights), n))
    for index in range(len(lights)):  # a loop over lights
        vis[index] = _visibility(visibility, index, n) if visibility is not None and index in visibility else 1.0
    ortho = isinstance(eye, Camera) and eye.is_orthographic
    if isinstance(eye, Camera):
        eye = -eye.forward if ortho else eye.center
    eye = np.asarray(eye, np.float64).reshape(3)
    # each light's colour in diffuse reflection, then in specular
    colors = np.array([[*light.color * light.diffuse, *light.color * light.specular] for light in lights])
    colors = colors.reshape(-1, 6)
    world_light = np.zeros((1 + environment.COEFFICIENTS, 3))  # the world's colour, its environment's coefficients
    if world is not None:
        world_light[0] = world.color
        if world.environment is not None:
            world_light[1:] = world.environment
    seen_world = _world_visibility(visibility, n)
    sky = sphere_directions(seen_world.shape[1] - 2)  # the directions of its columns 2..
    sky_light = None if world is None else _sky_light(world, len(sky))
    sky_light = np.zeros((0, 3)) if sky_light is None else sky_light
    scale, bias = _albedo_table()
    points = np.ascontiguousarray(cloud.positions, np.float32)
    rough, metal = material.roughness(cloud), material.metallic(cloud)
    diffuse, specular = scratch.empty((n, 3), np.float32), scratch.empty((n, 3), np.float32)
    shadow = scratch.empty(n, np.float32)
    (emitters, spans), terms, rings = _emitters(lights), _area_terms(lights, integrate), disc_rings()
    outlines = np.zeros((len(lights), ltc.ROUND_SIDES, 2))  # each integrated light's polygon (core.ltc)
    for index, light in enumerate(lights):  # a loop over lights
        if terms[index, 21] > 0.0:
            outlines[index, : int(terms[index, 21])] = ltc.outline(light)
    mapped = world is not None and world.environment is not None
    flags = np.array([ortho, multiscatter, world is not None, integrate, mapped])
    shown = np.zeros(0, bool) if shown is None else shown
    in_chunks(
        n,
        lambda lo, hi: kernel(
            lo, hi, shown, points, *normals, albedo, rough, metal, eye, flags, emitters, spans, terms, outlines, rings,
            ltc.INVERSE, colors, vis, reach, world_light, seen_world, sky, sky_light, scale, bias, diffuse, specular,
            shadow,
        ),
    )  # fmt: skip
    return Shading(diffuse, specular, shadow)


def _shade_kernel():
    """The compiled twin of shade (core.jit), or None: NumPy then does the work."""
    if jit.compiled(ltc.__name__, ltc.KERNEL) is None:  # its lights' polygon twins, which the loop calls
        return None
    if jit.compiled(environment.__name__, environment.KERNEL) is None:  # and the environment's
        return None
    return jit.compiled(__name__, SHADE_KERNEL, fast=True)


def _tan2(cos_t):
    """tan^2 of a direction's angle to the normal from its cosine (> 0), as smith_lambda has it."""
    cos2 = max(cos_t * cos_t, COS_MIN * COS_MIN)
    return max(1.0 - cos2, 0.0) / cos2


def _lambda_sq(tan2, alpha2):
    """smith_lambda from tan^2 of the direction's angle and alpha^2 (one square root, no squaring of
    a widened alpha's hypot)."""
    return 0.5 * (math.sqrt(1.0 + alpha2 * tan2) - 1.0)


def _table_one(table, cos_v, roughness):
    """specular_albedo's bilinear lookup of one (n.v, roughness) in a (TABLE, TABLE) table."""
    x = min(max(cos_v, 0.0), 1.0) * (TABLE - 1)
    y = min(max(roughness, 0.0), 1.0) * (TABLE - 1)
    i, j = min(int(x), TABLE - 2), min(int(y), TABLE - 2)
    fx, fy = x - i, y - j
    low = table[i, j] * (1 - fx) + table[i + 1, j] * fx
    high = table[i, j + 1] * (1 - fx) + table[i + 1, j + 1] * fx
    return low * (1 - fy) + high * fy


def _asin(x):
    """math.asin of x in [0, 1] by its Taylor series up to x^11 below ASIN_SERIES (within 3e-8 of it
    relative there: float32 outputs cannot tell), the library's asin above: most emitters subtend a
    small angle, and the series is a few multiplications where asin costs a fifth of an area
    sample's shading."""
    if x >= ASIN_SERIES:
        return math.asin(x)
    x2 = x * x
    tail = 3.0 / 40.0 + x2 * (5.0 / 112.0 + x2 * (35.0 / 1152.0 + x2 * (63.0 / 2816.0)))
    return x * (1.0 + x2 * (1.0 / 6.0 + x2 * tail))


def _ellipse_rim_one(x0, y0, radius, a, b, angle):
    """core.lights.ellipse_rim at one angle."""
    ia2, ib2 = 1.0 / (a * a), 1.0 / (b * b)
    c, s = math.cos(angle), math.sin(angle)
    constant = x0 * x0 * ia2 + y0 * y0 * ib2 + 0.5 * radius * radius * (ia2 + ib2) - 1.0
    twice = 0.5 * radius * radius * (ia2 - ib2) * (2.0 * c * c - 1.0)
    return constant + 2.0 * radius * (x0 * ia2 * c + y0 * ib2 * s) + twice


def _ring_arcs(x0, y0, radius, a, b, round_shape, cuts, lengths):
    """core.lights.ring_arcs of one circle (centre x0, y0 in the light's local x, y; radius > 0) of
    a light of half extents a, b: cuts (9,) the sorted angles of its pieces' starts (and 2 pi),
    lengths (8,) the pieces' lengths inside the light (0 outside). Returns their sum."""
    count = 1
    cuts[0] = 0.0
    if round_shape and a != b:  # an ellipse: core.lights.ellipse_crossings, one crossing at a time
        step = 2.0 * math.pi / ELLIPSE_SCAN
        before = _ellipse_rim_one(x0, y0, radius, a, b, 0.0) < 0.0
        for k in range(ELLIPSE_SCAN):
            low, high = k * step, (k + 1) * step
            after = _ellipse_rim_one(x0, y0, radius, a, b, high) < 0.0
            if after != before and count < 5:
                for _ in range(ELLIPSE_BISECTIONS):
                    middle = 0.5 * (low + high)
                    if (_ellipse_rim_one(x0, y0, radius, a, b, middle) < 0.0) == before:
                        low = middle
                    else:
                        high = middle
                cuts[count] = 0.5 * (low + high)
                count += 1
            before = after
    elif round_shape:
        reach = math.sqrt(x0 * x0 + y0 * y0)
        c = (a * a - reach * reach - radius * radius) / (2.0 * radius * reach) if reach > 0.0 else 2.0
        if abs(c) < 1.0:
            psi, turn = math.atan2(y0, x0), math.acos(c)
            cuts[1], cuts[2], count = psi + turn, psi - turn, 3
    else:
        for k in range(4):
            edge = a if k == 0 else -a if k == 1 else b if k == 2 else -b
            q = (edge - (x0 if k < 2 else y0)) / radius
            if abs(q) < 1.0:
                angle = math.acos(q) if k < 2 else math.asin(q)
                cuts[count], cuts[count + 1] = angle, -angle if k < 2 else math.pi - angle
                count += 2
    for k in range(count):  # into [0, 2 pi), then sorted (insertion: at most 9)
        cuts[k] = cuts[k] % (2.0 * math.pi)
        j = k
        while j > 0 and cuts[j - 1] > cuts[j]:
            cuts[j - 1], cuts[j] = cuts[j], cuts[j - 1]
            j -= 1
    for k in range(count, 9):
        cuts[k] = 2.0 * math.pi  # a full turn closes the last piece
    total = 0.0
    for k in range(8):
        length = cuts[k + 1] - cuts[k]
        middle = cuts[k] + 0.5 * length
        x, y = x0 + radius * math.cos(middle), y0 + radius * math.sin(middle)
        inside = x * x / (a * a) + y * y / (b * b) <= 1.0 if round_shape else abs(x) <= a and abs(y) <= b
        lengths[k] = length if inside else 0.0
        total += lengths[k]
    return total


def _lobe_sky_one(seen, row, sky, m0, m1, m2, v0, v1, v2, tan2_v, alpha, fallback):
    """lobe_sky of one splat: its row of seen, the K directions sky (K,3), the normal m facing the
    eye v, tan2_v the _tan2 of their angle; `fallback` where no direction lies above the normal."""
    a2 = alpha * alpha
    lambda_v = 1.0 + _lambda_sq(tan2_v, a2)  # the view's part of Smith's G, the same for every direction
    total, share = 0.0, 0.0
    for k in range(sky.shape[0]):
        lx, ly, lz = sky[k, 0], sky[k, 1], sky[k, 2]
        cos_l = m0 * lx + m1 * ly + m2 * lz
        if cos_l <= 0.0:
            continue
        weight = _lobe_weight_one(m0, m1, m2, v0, v1, v2, lx, ly, lz, cos_l, lambda_v, a2)
        total += weight
        share += weight * min(max(seen[row, 2 + k], 0.0), 1.0)
    return share / total if total > 0.0 else fallback


def _lobe_weight_one(m0, m1, m2, v0, v1, v2, lx, ly, lz, cos_l, lambda_v, a2):
    """The GGX lobe of alpha^2 `a2` for the normal m facing the eye v, towards the direction l above
    the surface (cos_l = m.l > 0), lambda_v 1 + the view's Smith Lambda: D G / (4 n.v) without the
    factors every direction shares (a2 / (4 pi n.v)), for ratios over directions."""
    hx, hy, hz = v0 + lx, v1 + ly, v2 + lz
    along = m0 * hx + m1 * hy + m2 * hz  # n.h unnormalised, > 0 with v and l above the surface
    cos2_h = min(along * along / max(hx * hx + hy * hy + hz * hz, 1e-300), 1.0)  # no square root
    denom = cos2_h * (a2 - 1.0) + 1.0
    return 1.0 / (denom * denom * (lambda_v + _lambda_sq(_tan2(max(cos_l, COS_MIN)), a2)))


def _sky_shares_one(seen, row, sky, light, m0, m1, m2, v0, v1, v2, tan2_v, alpha, fallback, sums, diffuse, glossy):
    """cosine_sky and lobe_sky (weighed by the radiance `light` (K,3)) of one splat, per colour, into
    diffuse and glossy (3,); sums (4,3) is room for their numerators and denominators."""
    a2 = alpha * alpha
    lambda_v = 1.0 + _lambda_sq(tan2_v, a2)
    sums[:] = 0.0
    for k in range(sky.shape[0]):
        lx, ly, lz = sky[k, 0], sky[k, 1], sky[k, 2]
        cos_l = m0 * lx + m1 * ly + m2 * lz
        if cos_l <= 0.0:
            continue
        lobe = _lobe_weight_one(m0, m1, m2, v0, v1, v2, lx, ly, lz, cos_l, lambda_v, a2)
        visible = min(max(seen[row, 2 + k], 0.0), 1.0)
        for c in range(3):
            sums[0, c] += cos_l * light[k, c]
            sums[1, c] += cos_l * light[k, c] * visible
            sums[2, c] += lobe * light[k, c]
            sums[3, c] += lobe * light[k, c] * visible
    for c in range(3):
        diffuse[c] = sums[1, c] / sums[0, c] if sums[0, c] > 0.0 else fallback
        glossy[c] = sums[3, c] / sums[2, c] if sums[2, c] > 0.0 else fallback


def _shade_loop(lo, hi, shown, points, nx, ny, nz, albedo, rough, metal, eye, flags, emitters, spans, terms,
                outlines, rings, table, colors, vis, reach, world, seen_world, sky, sky_light, scale, bias, diffuse,
                specular, shadow):  # fmt: skip
    """shade() for splats lo..hi (those `shown`, when not empty; 0 for the others), written into
    diffuse, specular (N,3) and shadow (N,)."""
    n_lights = colors.shape[0]
    f0, boost, layer, base = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    out_d, out_s = np.empty(3), np.empty(3)
    cuts, lengths = np.empty(9), np.empty(8)  # a reachable disc's ring pieces (_ring_arcs)
    shape, poly = np.empty((ltc.ROUND_SIDES, 3)), np.empty((ltc.MAX_VERTICES, 3))  # a light's polygons (core.ltc)
    acc = np.empty((n_lights, 3))  # per light: diffuse factor, tinted and white specular sums
    seen_d, seen_s = np.empty(3), np.empty(3)  # the world's light on the diffuse and the glossy lobe
    basis, cosine, lobe = np.empty(environment.COEFFICIENTS), np.array(environment.COSINE), np.ones(3)
    share_d, share_s, sums = np.empty(3), np.empty(3), np.empty((4, 3))  # the world's shares seen, per colour
    for i in range(lo, hi):
        if shown.shape[0] and not shown[i]:
            for c in range(3):
                diffuse[i, c], specular[i, c] = 0.0, 0.0
            shadow[i] = 0.0
            continue
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        if flags[0]:
            v0, v1, v2 = eye[0], eye[1], eye[2]
        else:
            v0, v1, v2 = eye[0] - p0, eye[1] - p1, eye[2] - p2
            length = max(math.sqrt(v0 * v0 + v1 * v1 + v2 * v2), 1e-300)
            v0, v1, v2 = v0 / length, v1 / length, v2 / length
        sign = -1.0 if nx[i] * v0 + ny[i] * v1 + nz[i] * v2 < 0.0 else 1.0
        m0, m1, m2 = nx[i] * sign, ny[i] * sign, nz[i] * sign  # the normal facing the eye
        r, m = rough[i], metal[i]
        alpha = max(r * r, ALPHA_MIN)
        cos_v = max(m0 * v0 + m1 * v1 + m2 * v2, 0.0)
        s_tab, b_tab = _table_one(scale, cos_v, r), _table_one(bias, cos_v, r)
        white_albedo = min(max(s_tab + b_tab, 0.0), 1.0)
        for c in range(3):
            f0[c] = DIELECTRIC_F0 + (albedo[i, c] - DIELECTRIC_F0) * m
            boost[c] = 1.0 + f0[c] * (1.0 / max(white_albedo, 1e-3) - 1.0) if flags[1] else 1.0
            layer[c] = min(max(f0[c] * s_tab + b_tab, 0.0), 1.0) * boost[c]
            base[c] = albedo[i, c] * (1.0 - m) * min(max(1.0 - layer[c], 0.0), 1.0)
        cos_vg = max(cos_v, COS_MIN)
        tan2_v = _tan2(cos_vg)  # the view's part of Smith's Lambda, the same for every emitter
        acc[:] = 0.0
        for k in range(n_lights):
            if terms[k, 21] > 0.5 and r <= ltc.ROUGHNESS:  # a smooth lobe: the light integrated (core.ltc)
                form, share = ltc._light_one(
                    terms, k, outlines, p0, p1, p2, m0, m1, m2, v0, v1, v2, cos_v, r, table, shape, poly
                )
                acc[k, 0] += math.pi * terms[k, 20] * form
                acc[k, 1] += terms[k, 20] * share * s_tab
                acc[k, 2] += terms[k, 20] * share * b_tab
                continue
            g, disc, rho, fx, fy = 0, False, 0.0, 0.0, 0.0  # grid (area lights), reachable disc
            if terms[k, 3] > 0.0:  # an area light: its grid at this splat, as core.lights.area_grids
                dx, dy, dz = terms[k, 0] - p0, terms[k, 1] - p1, terms[k, 2] - p2
                distance = math.sqrt(dx * dx + dy * dy + dz * dz)
                height = -(dx * terms[k, 5] + dy * terms[k, 6] + dz * terms[k, 7])  # over its plane
                g = AREA_GRID  # also at 0 and NaN
                if distance > 0.0:
                    grid = max(np.ceil(terms[k, 3] / distance), np.ceil(terms[k, 4] / (distance * alpha)))
                    if terms[k, 8] > 0.0:  # a Spread: its height over the light's plane matters too
                        grid = max(grid, np.ceil(terms[k, 8] / abs(height))) if height != 0.0 else AREA_GRID
                    g = int(min(max(grid, 1.0), AREA_GRID))
                rho = max(height, 0.0) * terms[k, 18]  # core.lights.reachable_discs
                disc = rho > 0.0 and math.pi * rho * rho < terms[k, 19]
                if disc:  # the splat's foot on the light, in its local x, y
                    fx = -(dx * terms[k, 9] + dy * terms[k, 10] + dz * terms[k, 11])
                    fy = -(dx * terms[k, 12] + dy * terms[k, 13] + dz * terms[k, 14])
            first = spans[k, g, 0]
            kind = emitters[first, 0]
            count = SPREAD_SAMPLES if disc else spans[k, g, 1] - first
            total = 0.0
            for j in range(count):  # the light's emitters: an area light's samples on g, or of its disc
                if disc:
                    ring, share = j // SPREAD_ANGLES, j % SPREAD_ANGLES
                    if share == 0:
                        total = _ring_arcs(
                            fx, fy, rings[ring, 0] * rho, terms[k, 15], terms[k, 16], terms[k, 17] > 0.5, cuts, lengths
                        )
                    if total <= 0.0:
                        continue  # a ring wholly outside the light
                    along, piece = (share + 0.5) / SPREAD_ANGLES * total, 0
                    while piece < 7 and along >= lengths[piece]:  # the piece holding `along`
                        along -= lengths[piece]
                        piece += 1
                    angle = cuts[piece] + along
                    x, y = fx + rings[ring, 0] * rho * math.cos(angle), fy + rings[ring, 0] * rho * math.sin(angle)
                    ex = terms[k, 0] + x * terms[k, 9] + y * terms[k, 12]
                    ey = terms[k, 1] + x * terms[k, 10] + y * terms[k, 13]
                    ez = terms[k, 2] + x * terms[k, 11] + y * terms[k, 14]
                    area = rings[ring, 1] * rings[ring, 0] * rho * rho * total / SPREAD_ANGLES
                    strength, radius = terms[k, 20] * area, math.sqrt(area / math.pi)
                else:
                    e = first + j
                    ex, ey, ez = emitters[e, 2], emitters[e, 3], emitters[e, 4]
                    strength, radius = emitters[e, 8], emitters[e, 11]
                if kind == SUN:
                    lx, ly, lz, distance = emitters[first, 5], emitters[first, 6], emitters[first, 7], math.inf
                    inverse = 0.0
                else:
                    lx, ly, lz = ex - p0, ey - p1, ez - p2
                    distance = math.sqrt(lx * lx + ly * ly + lz * lz)
                    inverse = 1.0 / max(distance, 1e-300)
                    lx, ly, lz = lx * inverse, ly * inverse, lz * inverse
                    out = -(lx * emitters[first, 5] + ly * emitters[first, 6] + lz * emitters[first, 7])  # to the axis
                    if kind == SPOT:
                        cos_half, width = emitters[first, 9], emitters[first, 10]
                        if width <= 0.0:
                            strength *= 1.0 if out > cos_half else 0.0
                        else:
                            x = min(max((out - cos_half) / width, 0.0), 1.0)
                            strength *= x * x * (3.0 - 2.0 * x)
                    elif kind == AREA:
                        strength *= max(out, 0.0)
                        tan_half = emitters[first, 10]
                        if tan_half > 0.0 and out > 0.0:  # its Spread (core.lights.spread_factor)
                            strength *= max(tan_half - math.sqrt(max(1.0 - out * out, 0.0)) / out, 0.0)
                    strength = strength * inverse * inverse if distance > 1e-300 else 0.0
                cos_l = m0 * lx + m1 * ly + m2 * lz
                if cos_l <= 0.0 or strength <= 0.0:  # adds nothing: behind the surface, the emitter or the cone
                    continue
                acc[k, 0] += strength * cos_l
                if kind != SUN:  # the emitter's angular radius (angular_radius)
                    radius = _asin(min(max(radius * inverse, 0.0), 1.0))
                if flags[3] and kind != AREA and 0.0 < radius < ROUND_LIGHT_MAX and r <= ltc.ROUGHNESS:
                    # a round light's smooth highlight, integrated (core.ltc, _round_light)
                    share = ltc._disc_one(
                        lx, ly, lz, math.tan(radius), m0, m1, m2, v0, v1, v2, cos_v, r, table, shape, poly
                    )
                    sine = math.sin(radius)
                    radiance = strength / (math.pi * sine * sine)  # the light's, seen as its disc
                    acc[k, 1] += radiance * share * s_tab
                    acc[k, 2] += radiance * share * b_tab
                    continue
                a2 = min(alpha * alpha + 0.25 * radius * radius, 1.0)  # the widened lobe's alpha^2
                hx, hy, hz = v0 + lx, v1 + ly, v2 + lz
                h_inverse = 1.0 / max(math.sqrt(hx * hx + hy * hy + hz * hz), 1e-300)
                cos_h = min(max((m0 * hx + m1 * hy + m2 * hz) * h_inverse, 0.0), 1.0)
                schlick = 1.0 - min(max((v0 * hx + v1 * hy + v2 * hz) * h_inverse, 0.0), 1.0)
                weight = schlick * schlick * schlick * schlick * schlick
                denom = cos_h * cos_h * (a2 - 1.0) + 1.0
                # D G / (4 n.v), D = a2 / (pi denom^2), G = 1 / (1 + Lambda(v) + Lambda(l)), in one division
                lambdas = 1.0 + _lambda_sq(tan2_v, a2) + _lambda_sq(_tan2(max(cos_l, COS_MIN)), a2)
                value = strength * a2 / (math.pi * denom * denom * lambdas * 4.0 * cos_vg)
                acc[k, 1] += value * (1.0 - weight)
                acc[k, 2] += value * weight
        lit, seen = 0.0, 0.0
        out_d[:] = 0.0
        out_s[:] = 0.0
        for k in range(n_lights):
            linked = reach[k, i] if reach.shape[1] > 1 else reach[k, 0]  # light linking
            visible = min(max(vis[k, i], 0.0), 1.0) * linked
            total = 0.0
            for c in range(3):
                dc = acc[k, 0] * colors[k, c] * base[c] / math.pi
                sc = (f0[c] * acc[k, 1] + acc[k, 2]) * colors[k, 3 + c] * boost[c]
                out_d[c] += visible * dc
                out_s[c] += visible * sc
                total += dc + sc
            lit += linked * total / 3.0
            seen += visible * total / 3.0
        row = i if seen_world.shape[0] > 1 else 0  # one row: the whole world everywhere
        open_sky = min(max(seen_world[row, 0] if sign > 0.0 else seen_world[row, 1], 0.0), 1.0)  # the eye's side
        glossy = open_sky
        weighed = flags[4] and sky_light.shape[0] > 0  # an environment's shares, weighed by its light
        if flags[2] and sky.shape[0] > 0 and not weighed:
            glossy = _lobe_sky_one(seen_world, row, sky, m0, m1, m2, v0, v1, v2, tan2_v, alpha, open_sky)
        for c in range(3):
            share_d[c], share_s[c] = open_sky, glossy
        if weighed:
            _sky_shares_one(
                seen_world, row, sky, sky_light, m0, m1, m2, v0, v1, v2, tan2_v, alpha, open_sky, sums, share_d, share_s
            )
        for c in range(3):
            seen_d[c], seen_s[c] = world[0, c], world[0, c]  # a uniform world: its colour both ways
        if flags[4]:  # an environment map: at the normal and the view's mirror direction (core.environment)
            environment._basis_one(m0, m1, m2, basis)
            lobe[1], lobe[2] = math.exp(-0.5 * alpha * alpha), math.exp(-1.5 * alpha * alpha)
            for c in range(3):
                seen_d[c] = environment._radiance_one(world[1:], basis, cosine, c)
            twice = 2.0 * (m0 * v0 + m1 * v1 + m2 * v2)
            environment._basis_one(twice * m0 - v0, twice * m1 - v1, twice * m2 - v2, basis)
            for c in range(3):
                seen_s[c] = environment._radiance_one(world[1:], basis, lobe, c)
        for c in range(3):
            if flags[2]:
                out_d[c] += base[c] * seen_d[c] * share_d[c]
                out_s[c] += layer[c] * seen_s[c] * share_s[c]
            diffuse[i, c] = out_d[c]
            specular[i, c] = out_s[c]
        shadow[i] = min(max(1.0 - seen / lit, 0.0), 1.0) if lit > 0.0 else 0.0
