"""An environment map (Blender's world Environment Texture) as light for relit splats: its radiance
L as spherical harmonics of bands 0-2, nine coefficients per colour in core.sh's basis (the 3DGS
ordering and signs, orthonormal over the sphere).

Nine coefficients carry what a diffuse surface and a rough lobe see of a map: the clamped cosine
filters a map's bands by pi, 2 pi / 3 and pi / 4 and the rest by at most pi / 24, so the irradiance
E(n) = sum_l A_l L_lm Y_lm(n) of bands 0-2 is within a few percent of the whole map's for natural
light (Ramamoorthi and Hanrahan 2001; tests/test_environment.py measures the bands' share of a sky
with a sun). A glossy lobe takes the map's radiance towards its mirror direction, filtered as a
von Mises-Fisher lobe of the GGX width alpha (sharpness 2 / alpha^2, bands attenuated by
exp(-l (l + 1) alpha^2 / 4)); its total then comes from core.shading's specular albedo, as a uniform
world's does. Where the world is occluded (core.ambient), each of its directions' visibility is
weighed by the map's light there as well as by the cosine or the lobe (core.shading's cosine_sky,
lobe_sky): under a roof a splat keeps the ground's light, not half the sky's.

A sun in the map is what nine coefficients hold worst (a sky with a 4-degree sun: 8.2% of the
brightest irradiance off, tests/test_environment.py) and what a relit picture needs most (its
shadows, its highlight). light_of takes it out (sun_of: a brightest pixel SUN_CONTRAST times the
map's mean or more) as a sun light of the map's own direction, irradiance, colour and size, and
reads the rest of the map with the sky around the sun in its place: together within 0.5%. A sun
too small for a map's pixels (a sky's half-degree disc, rendered) is measured in a close view of it
instead (sun_in_view; peak_direction finds it in a map holding it).

An equirectangular map is read as Blender reads one: row 0 at the bottom (latitude -90 degrees),
column u at longitude pi (1 - 2u) from +X towards +Y (u = 0.5 looks along +X, 0.25 along +Y),
each pixel its share of the sphere.

Each evaluation has a scalar twin (`_..._one`) for the compiled shading loop, written the same way.
"""

import math
from typing import Annotated, NamedTuple

import numpy as np

from . import sh
from .lights import Light

COEFFICIENTS = 9  # bands 0-2
COSINE = (1.0, 2.0 / 3.0, 0.25)  # the clamped cosine's bands over pi (Funk-Hecke): E / pi from L
BAND_OF = (0, 1, 1, 1, 2, 2, 2, 2, 2)
ROWS = 64  # map rows per step of the projection: no (H, W) float64 temporaries for a large map
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float32)  # scene-linear Rec. 709
# A sun in a map: its brightest pixel SUN_CONTRAST times the map's mean luminance or more (a clear
# sky's sun is thousands of times its sky; an overcast sky's brightest patch a few times), the pixels
# within SUN_CAP of it brighter than SUN_LEVEL times the mean, the sky behind it the ring out to
# SUN_RING times SUN_CAP.
SUN_CONTRAST = 50.0
SUN_SHARE = 0.05  # ... and its irradiance facing it at least this share of pi x the map's mean (a glint is no sun)
SUN_LEVEL = 10.0
SUN_CAP = math.radians(6.0)
SUN_RING = 1.5
KERNEL = ("_basis_one", "_radiance_one")

Environment = Annotated[np.ndarray, "(9, 3) float64"]


def from_equirect(rows: Annotated[np.ndarray, "(H, W, C>=3)"], replaced: "Patch | None" = None) -> Environment:
    """(9, 3) the SH coefficients of an equirectangular map's radiance (its first three channels,
    scene-linear; rows from the bottom, see the module notes), integrated over its pixels as the
    midpoint rule does, the pixels' solid angles scaled to sum to 4 pi (so band 0 is the map's mean
    over the sphere exactly). Separable: per row, the sums of its pixels times 1, cos and sin of
    the longitude and of twice it, then each coefficient's latitude factor. replaced: pixels read
    with other values (a sun's, sun_of), the map itself unchanged."""
    height, width = rows.shape[:2]
    if height == 0 or width == 0 or rows.ndim != 3 or rows.shape[2] < 3:
        raise ValueError(f"an environment map needs rows of pixels with 3 colours, got shape {rows.shape}")
    longitude = math.pi * (1.0 - 2.0 * (np.arange(width) + 0.5) / width)
    waves = np.stack([np.ones(width), *_waves(longitude, 1), *_waves(longitude, 2)])
    latitude = math.pi * ((np.arange(height) + 0.5) / height - 0.5)
    share = np.cos(latitude)
    share *= 4.0 * math.pi / (share.sum() * width)  # each pixel's solid angle: rows of equal latitude span
    sums = np.empty((height, 5, 3))
    for lo in range(0, height, ROWS):  # a loop over bands of rows
        band = np.array(rows[lo : lo + ROWS, :, :3], np.float64)  # a copy: `replaced` writes into it
        if not np.isfinite(band).all():
            raise ValueError("the environment map has pixels that are not finite numbers")
        if replaced is not None:
            here = (replaced.rows >= lo) & (replaced.rows < lo + ROWS)
            band[replaced.rows[here] - lo, replaced.columns[here]] = replaced.values[here]
        sums[lo : lo + ROWS] = np.einsum("hwc,fw->hfc", band, waves)
    c, s = np.cos(latitude), np.sin(latitude)
    one, cos1, sin1, cos2, sin2 = (sums[:, f] for f in range(5))
    c1, c2 = sh.C1, sh.C2
    terms = [
        sh.C0 * one,
        -c1 * c[:, None] * sin1,
        c1 * s[:, None] * one,
        -c1 * c[:, None] * cos1,
        c2[0] * 0.5 * (c * c)[:, None] * sin2,  # x y = cos^2 sin(2 phi) / 2
        c2[1] * (c * s)[:, None] * sin1,
        c2[2] * (2 * s * s - c * c)[:, None] * one,
        c2[3] * (c * s)[:, None] * cos1,
        c2[4] * (c * c)[:, None] * cos2,  # x^2 - y^2 = cos^2 cos(2 phi)
    ]
    return np.stack([(share[:, None] * term).sum(axis=0) for term in terms])


class Patch(NamedTuple):
    """Pixels of a map read with other values: row and column indices (P,) and the values (P, 3)."""

    rows: np.ndarray
    columns: np.ndarray
    values: np.ndarray


def light_of(rows: Annotated[np.ndarray, "(H, W, C>=3)"]) -> tuple[Environment, Light | None]:
    """(the map's coefficients, its sun or None): a sun that stands out of the map (sun_of) becomes
    a sun light, with shadows and its own highlights, and leaves the coefficients (read with the sky
    around it in its place); else the whole map's coefficients."""
    found = sun_of(rows)
    if found is None:
        return from_equirect(rows), None
    sun, patch = found
    return from_equirect(rows, patch), sun


def sun_of(rows: Annotated[np.ndarray, "(H, W, C>=3)"]) -> tuple[Light, Patch] | None:
    """(a sun light, the pixels it takes with the sky around it in their place) of an equirectangular
    map (read as from_equirect reads it), or None. The sun is the pixels within SUN_CAP of the
    brightest one brighter than SUN_LEVEL times the map's mean luminance, less the mean of the ring
    around them (SUN_RING: the sky behind the sun): its irradiance on a surface facing it is the sum
    of that excess over their solid angles, its direction their mean weighed by it, its diameter that
    of a uniform disc of the same spread. There is one where the brightest pixel is SUN_CONTRAST
    times the mean or more and the sun's irradiance SUN_SHARE of a uniform map's of that mean."""
    height, width = rows.shape[:2]
    latitude = math.pi * ((np.arange(height) + 0.5) / height - 0.5)
    share = np.cos(latitude) * 4.0 * math.pi / (np.cos(latitude).sum() * width)  # each pixel's solid angle
    luminance = _luminance(rows)
    mean = float(share @ luminance.sum(axis=1, dtype=np.float64)) / (4.0 * math.pi)
    peak = int(np.argmax(luminance))
    if not (mean > 0.0 and luminance.flat[peak] >= SUN_CONTRAST * mean):
        return None
    reach = SUN_CAP * SUN_RING
    centre = _pixel_direction(*divmod(peak, width), height, width)
    near = np.flatnonzero(np.abs(latitude - math.asin(centre[2])) <= reach + math.pi / height)  # rows it may touch
    longitude = math.pi * (1.0 - 2.0 * (np.arange(width) + 0.5) / width)
    band = np.stack(np.broadcast_arrays(*_direction(latitude[near, None], longitude[None])), axis=-1)  # (R, W, 3)
    apart = np.arccos(np.clip(band @ centre, -1.0, 1.0))
    pixels = np.asarray(rows[near][..., :3], np.float64)
    sun = (apart < SUN_CAP) & (luminance[near] > SUN_LEVEL * mean)
    ring = (apart >= SUN_CAP) & (apart < reach)
    weights = np.broadcast_to(share[near, None], apart.shape)
    sky = (weights[ring, None] * pixels[ring]).sum(axis=0) / max(weights[ring].sum(), 1e-300)
    excess = np.maximum(pixels[sun] - sky, 0.0) * weights[sun, None]  # (P, 3) radiance x solid angle
    if not float(excess.sum(axis=0) @ LUMINANCE) >= SUN_SHARE * math.pi * mean:  # a glint, or no excess at all
        return None
    row_index, column_index = np.nonzero(sun)
    patch = Patch(near[row_index], column_index, np.broadcast_to(sky, (len(row_index), 3)))
    return _sun_light(excess, band[sun]), patch


def _sun_light(excess: Annotated[np.ndarray, "(P, 3)"], directions: Annotated[np.ndarray, "(P, 3)"]) -> Light:
    """The sun light of pixels looking along `directions` whose radiance over the sky behind them,
    times their solid angles, is `excess`: its irradiance on a surface facing it their sum, its
    direction their mean weighed by their luminance, its diameter that of a uniform disc of the same
    angular spread."""
    irradiance = excess.sum(axis=0)
    strength = excess @ LUMINANCE
    direction = strength @ directions
    direction /= np.linalg.norm(direction)
    spread = np.arccos(np.clip(directions @ direction, -1.0, 1.0))
    radius = math.sqrt(2.0 * float(strength @ spread**2) / float(strength.sum()))  # a uniform disc's mean is r^2 / 2
    power = float(irradiance.max())
    return Light("sun", color=irradiance / power, power=power, direction=-direction, angle=2.0 * radius)


def peak_direction(rows: Annotated[np.ndarray, "(H, W, C>=3)"]) -> Annotated[np.ndarray, "(3,)"]:
    """The direction of an equirectangular map's brightest pixel (by luminance; read as from_equirect
    reads the map): where a close view finds a sun too small for the map's pixels (sun_in_view)."""
    height, width = rows.shape[:2]
    return _pixel_direction(*divmod(int(np.argmax(_luminance(rows))), width), height, width)


def _luminance(rows):
    """(H, W) float32 luminance of a map's pixels, a band of rows at a time (no float32 copy of a
    large map's colours)."""
    height, width = rows.shape[:2]
    luminance = np.empty((height, width), np.float32)
    for lo in range(0, height, ROWS):  # a loop over bands of rows
        luminance[lo : lo + ROWS] = np.asarray(rows[lo : lo + ROWS, :, :3], np.float32) @ LUMINANCE
    return luminance


def sun_in_view(
    excess: Annotated[np.ndarray, "(H, W, C>=3)"], directions: Annotated[np.ndarray, "(H, W, 3)"], solid_angles
) -> Light | None:
    """The sun a close view shows as `excess` radiance over the sky behind it (a picture of the sun
    less the sky's light there), its pixels looking along `directions` and spanning
    `solid_angles` (H, W) (core.camera.Camera.pixel_rays), or None where it shows none: a sun disc a
    map's pixels are too coarse to measure (a sky's half-degree sun in a 128-pixel map takes a
    fraction of one, and a few samples a pixel measure its light to tens of percent)."""
    radiance = np.maximum(np.asarray(excess, np.float64)[..., :3], 0.0)
    bright = radiance @ LUMINANCE > 0.0
    if not bright.any():
        return None
    return _sun_light(radiance[bright] * np.asarray(solid_angles, np.float64)[bright, None], directions[bright])


def _direction(latitude, longitude):
    """x, y, z of the unit directions at `latitude` and `longitude`."""
    return np.cos(latitude) * np.cos(longitude), np.cos(latitude) * np.sin(longitude), np.sin(latitude)


def _pixel_direction(row, column, height, width):
    """(3,) the direction of pixel (row from the bottom, column)."""
    latitude = math.pi * ((row + 0.5) / height - 0.5)
    longitude = math.pi * (1.0 - 2.0 * (column + 0.5) / width)
    return np.array(_direction(latitude, longitude), np.float64)


def _waves(angle, multiple):
    """cos and sin of `multiple` times `angle`."""
    return np.cos(multiple * angle), np.sin(multiple * angle)


def with_sun(environment: Environment, sun: Light) -> Environment:
    """The coefficients with a sun light (light_of's) given back as a point of the map: its
    irradiance on a surface facing it, E, is a delta of that weight towards it (-direction)."""
    towards = -np.asarray(sun.direction, np.float64)
    return environment + np.outer(sh.basis(towards[None], 2)[0], sun.power * np.asarray(sun.color, np.float64))


def mean(environment: Environment) -> np.ndarray:
    """(3,) the map's mean radiance over the sphere: its band 0."""
    return np.asarray(environment[0], np.float64) * sh.C0


def rotated(environment: Environment, rotation: np.ndarray) -> Environment:
    """The coefficients of the map turned by `rotation` (3, 3): L'(d) = L(rotation^T d)."""
    return sh.rotate(np.asarray(environment, np.float64), np.asarray(rotation, np.float64))


def radiance(environment: Environment, directions: Annotated[np.ndarray, "(N, 3)"]) -> np.ndarray:
    """(N, 3) the bands' radiance towards unit `directions` (0 where negative)."""
    return np.maximum(sh.basis(directions, 2) @ environment, 0.0)


def diffuse(environment: Environment, normals: Annotated[np.ndarray, "(N, 3)"]) -> np.ndarray:
    """(N, 3) E(n) / pi, the radiance a white Lambertian surface facing `normals` (unit) sends back
    under the whole map (0 where the bands' ringing would make it negative)."""
    weights = np.array([COSINE[band] for band in BAND_OF])
    return np.maximum(sh.basis(normals, 2) @ (weights[:, None] * environment), 0.0)


def glossy(environment: Environment, directions: Annotated[np.ndarray, "(N, 3)"], alpha: np.ndarray) -> np.ndarray:
    """(N, 3) the map's radiance towards `directions` (unit mirror directions) averaged over a lobe
    of GGX width `alpha` (N,): the bands attenuated as the module notes say (0 where negative)."""
    band = np.array(BAND_OF, np.float64)
    attenuation = np.exp(-np.outer(np.asarray(alpha, np.float64) ** 2 / 4.0, band * (band + 1.0)))
    return np.maximum(np.einsum("nk,nk,kc->nc", sh.basis(directions, 2), attenuation, environment), 0.0)


def _basis_one(x, y, z, out):
    """core.sh.basis of bands 0-2 at the unit direction (x, y, z), into out (9,)."""
    out[0] = sh.C0
    out[1], out[2], out[3] = -sh.C1 * y, sh.C1 * z, -sh.C1 * x
    out[4] = sh.C2[0] * x * y
    out[5] = sh.C2[1] * y * z
    out[6] = sh.C2[2] * (2.0 * z * z - x * x - y * y)
    out[7] = sh.C2[3] * x * z
    out[8] = sh.C2[4] * (x * x - y * y)


def _radiance_one(environment, basis, filters, channel):
    """sum_k filters[band k] environment[k, channel] basis[k], at least 0: diffuse's sum with the
    cosine's bands, glossy's with a lobe's (filters (3,), per band)."""
    total = 0.0
    for k in range(COEFFICIENTS):
        band = 0 if k == 0 else (1 if k < 4 else 2)
        total += filters[band] * environment[k, channel] * basis[k]
    return max(total, 0.0)
