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
- world: a uniform environment of radiance W gives diffuse albedo * (1 - metallic) * (1 - E) * W and
  specular E * W (white furnace: albedo 1, metallic 0 sends back exactly W), unoccluded;
- two-sided: a normal facing away from the eye is flipped towards it (splats are seen from both
  sides), so a splat's back is lit as its front would be;
- shadows come in as visibility per light (core.shadows): a light's contribution is scaled by it.

Multiple scattering between microfacets (Blender's default Multiscatter GGX) is given back by an
energy compensation of the lobe (multiscatter_compensation; `multiscatter=False` for plain GGX).

Not modelled: clearcoat, sheen, subsurface, transmission, emission, light bouncing between splats,
and the world's occlusion.
"""

import functools
import math
from dataclasses import dataclass

import numpy as np

from . import material
from .arrays import Floats
from .camera import Camera
from .lights import Light, World, incident
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
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    offset = eye - points
    return offset / np.maximum(np.linalg.norm(offset, axis=1, keepdims=True), 1e-300)


def facing(normals: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Normals (N,3) flipped where they face away from the view directions (two-sided splats)."""
    sign = np.where(np.einsum("ij,ij->i", normals, view) < 0.0, -1.0, 1.0)
    return normals * sign[:, None]


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
    scale, bias = _albedo_table()
    x = np.clip(cos_v, 0.0, 1.0) * (TABLE - 1)
    y = np.clip(roughness, 0.0, 1.0) * (TABLE - 1)
    i = np.minimum(x.astype(np.int64), TABLE - 2)
    j = np.minimum(y.astype(np.int64), TABLE - 2)
    fx, fy = x - i, y - j

    def lerp(t):
        return (t[i, j] * (1 - fx) + t[i + 1, j] * fx) * (1 - fy) + (t[i, j + 1] * (1 - fx) + t[i + 1, j + 1] * fx) * fy

    return np.clip(f0 * lerp(scale)[:, None] + lerp(bias)[:, None], 0.0, 1.0)


def multiscatter_compensation(cos_v: np.ndarray, roughness: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """(N,3) factor on the single-scattering GGX lobe for the light it loses to multiple scattering
    between microfacets: 1 + F0 (1 / E1 - 1), E1 the lobe's albedo for F0 = 1 towards the view
    (Turquin's energy compensation). A white metal (F0 = 1) then reflects all of a uniform world, as
    Cycles' Multiscatter GGX nearly does."""
    white = specular_albedo(cos_v, roughness, np.ones((len(cos_v), 3)))[:, :1]
    return 1.0 + f0 * (1.0 / np.maximum(white, 1e-3) - 1.0)


def angular_radius(light: Light, distance: np.ndarray, share: float) -> np.ndarray:
    """The angle (N,) a light's emitter subtends (its half-angle) seen from `distance` (N,): a point or
    spot light's sphere, the sun's disc, or one area sample's patch of `share` m^2 taken as a disc."""
    if light.kind == "sun":
        return np.full(len(distance), 0.5 * light.angle)
    radius = light.radius if light.kind in ("point", "spot") else math.sqrt(share / math.pi)
    return np.arcsin(np.clip(radius / np.maximum(distance, 1e-300), 0.0, 1.0))


def _light_terms(light, points, normal, view, alpha, f0) -> tuple[np.ndarray, np.ndarray]:
    """One light's unshadowed diffuse factor (irradiance on the surface, E cos) and specular radiance,
    (N,3) each. Per emitter only (N,) scalars are summed: the light's colour and Schlick's F0 come in
    once at the end (F = F0 (1 - w) + w)."""
    emitters = incident(light, points)
    share = light.area / len(emitters) if light.kind == "area" else 0.0
    diffuse, tinted, white = (np.zeros(len(points)) for _ in range(3))
    for inc in emitters:  # one emitter, or an area light's 16 samples
        diffuse += inc.strength * np.maximum(np.einsum("ij,ij->i", normal, inc.direction), 0.0)
        widened = np.minimum(np.hypot(alpha, 0.5 * angular_radius(light, inc.distance, share)), 1.0)
        scalar, weight = ggx_parts(normal, view, inc.direction, widened)
        scalar *= inc.strength
        tinted += scalar * (1.0 - weight)
        white += scalar * weight
    specular = (f0 * tinted[:, None] + white[:, None]) * light.color
    return diffuse[:, None] * light.color, specular


def shade(
    cloud: SplatCloud,
    eye: np.ndarray | Camera,
    lights: list[Light],
    world: World | None = None,
    visibility: dict[int, np.ndarray] | None = None,
    *,
    multiscatter: bool = True,
) -> Shading:
    """Shade every splat of `cloud` (which must carry a material: core.material.has_material) for an
    eye at a position (3,) or a Camera, under `lights` and an optional uniform `world`. visibility
    maps a light's index in `lights` to (N,) values in [0,1] (1: unshadowed; lights absent: 1).
    multiscatter: compensate the GGX lobe's lost energy (multiscatter_compensation) as Blender's
    default Multiscatter GGX does; False for the plain single-scattering GGX distribution."""
    normals, albedo = material.normals(cloud), material.albedo(cloud)
    if normals is None or albedo is None:
        raise ValueError("the cloud has no material to shade: it needs albedo and normals (core.material)")
    points = cloud.positions.astype(np.float64)
    n = len(points)
    view = view_directions(eye, points)
    normal = facing(normals, view)
    rough, metal = material.roughness(cloud), material.metallic(cloud)
    alpha = np.maximum(rough * rough, ALPHA_MIN)
    f0 = DIELECTRIC_F0 + (albedo - DIELECTRIC_F0) * metal[:, None]
    cos_v = np.maximum(np.einsum("ij,ij->i", normal, view), 0.0)
    boost = multiscatter_compensation(cos_v, rough, f0) if multiscatter else np.ones((n, 3))
    layer = specular_albedo(cos_v, rough, f0) * boost  # what the specular layer takes from the base
    base = albedo * (1.0 - metal)[:, None] * np.clip(1.0 - layer, 0.0, 1.0)
    diffuse, specular = np.zeros((n, 3)), np.zeros((n, 3))
    lit, seen = np.zeros(n), np.zeros(n)
    for index, light in enumerate(lights):  # a loop over lights
        d, s = _light_terms(light, points, normal, view, alpha, f0)
        d, s = d * base / math.pi, s * boost
        vis = _visibility(visibility, index, n)
        diffuse += vis[:, None] * d
        specular += vis[:, None] * s
        total = (d + s).mean(axis=1)
        lit += total
        seen += vis * total
    if world is not None:
        diffuse += base * world.color
        specular += layer * world.color
    shadow = np.where(lit > 0.0, 1.0 - seen / np.where(lit > 0.0, lit, 1.0), 0.0)
    return Shading(diffuse.astype(np.float32), specular.astype(np.float32), np.clip(shadow, 0, 1).astype(np.float32))


def _visibility(visibility: dict[int, np.ndarray] | None, index: int, n: int) -> Floats:
    if visibility is None or index not in visibility:
        return np.ones(n)
    vis = np.asarray(visibility[index], dtype=np.float64).reshape(-1)
    if vis.shape != (n,) or not np.isfinite(vis).all():
        raise ValueError(f"visibility of light {index} must be {n} finite values, got shape {vis.shape}")
    return np.clip(vis, 0.0, 1.0)
