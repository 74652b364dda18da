"""Blender's lights (point, spot, sun, area) and the world (uniform, or an environment map's bands:
core.environment), in Blender's units, for relighting.

A Light lives in the world frame of the cloud it lights. Its units are those Cycles renders with
(tests/test_blender_lights.py checks every factor against Cycles renders of a white diffuse plane):

- point: power P watts, radiant intensity P / (4 pi) W/sr in every direction; `radius` (Blender's
  soft size) is a sphere of that intensity, which only softens shadows here (seen from outside, a
  uniformly bright sphere lights a surface facing it exactly as a point at its centre does);
- spot: a point light times Blender's cone: smoothstep((cos t - cos(size/2)) / ((1 - cos(size/2)) *
  blend)) of the angle t between the spot's axis and the ray to the lit point (no cosine falloff
  inside the cone; the cone does not concentrate the power);
- sun: `power` is the irradiance ("Strength", W/m^2) on a surface facing it; `angle` (its disc's
  diameter, radians) only softens shadows;
- area: a one-sided rectangle or ellipse of `size_x` by `size_y` metres emitting radiance
  P / (pi * area) towards its -Z side (`direction`; so P / area W/m^2 leave its surface), sampled
  at a stratified grid of points, each a small cosine-weighted (Lambertian) emitter (see
  area_points), the grid as fine as the lit point's distance needs (area_grids). Blender's Spread
  narrows it (spread_factor): radiance times (tan(s/2) - tan a) / (tan(s/2) - s/2) at an angle a from
  its axis, none past s/2, the same power in all (Cycles' soft-box grid); a point close to it then
  samples only the disc of it that reaches it (spread_samples).

Irradiance is the power per square metre arriving on a surface, colour included; a diffuse surface of
albedo a then reflects radiance a * E / pi. Lights are evaluated per splat, vectorised (`incident`
and `irradiance`), with the light's direction and distance per point.
"""

import math
from dataclasses import dataclass, field
from typing import Annotated, NamedTuple

import numpy as np

from . import sh

KINDS = ("point", "spot", "sun", "area")
AREA_SHAPES = ("SQUARE", "RECTANGLE", "DISK", "ELLIPSE")
# Area lights are sampled on a g x g stratified pattern (cell centres, mapped to the disc by an
# area-preserving map for DISK/ELLIPSE). The midpoint rule's error falls as (side / (g distance))^2,
# so a point gets g = ceil(AREA_REACH side / distance) clipped to 1..AREA_GRID (side: the longer one;
# distance: to the centre): 16 points nearer than two sides, one point (the light as a single
# patch) from AREA_REACH sides on. The largest error is then that of the full grid
# at about one side length, a little over 1% (tests/test_lights.py states the measured errors).
AREA_GRID = 4
AREA_SAMPLES = AREA_GRID * AREA_GRID  # the most a point gets
AREA_REACH = 6.0
AREA_GLOSS = 1.5  # samples across a glossy lobe's width (area_grids' lobes; docs/DESIGN.md's figures)
# A light narrowed by its Spread reaches a point from a disc of radius t tan(spread/2) on it (t: the
# point's height over its plane): g at least AREA_SPREAD side / (t tan(spread/2)), within AREA_GRID.
AREA_SPREAD = 3.0
# Where that disc is smaller than the light (a narrow Spread close up, where a grid over the whole
# light puts few or no samples in it), a point samples the disc itself instead: SPREAD_RINGS rings
# at Gauss-Legendre radii (the spread factor is linear in the radius), SPREAD_ANGLES samples on each
# spread evenly over the ring's arcs inside the light, cut where the ring crosses the light's rim:
# exactly at a rectangle's edges or a disc's rim, an ellipse's by bisection (ELLIPSE_SCAN steps
# around the ring find where it crosses, ELLIPSE_BISECTIONS halvings place each crossing).
# docs/DESIGN.md has the measured errors.
SPREAD_RINGS = 6
SPREAD_ANGLES = 4
SPREAD_SAMPLES = SPREAD_RINGS * SPREAD_ANGLES
ELLIPSE_SCAN = 32
ELLIPSE_BISECTIONS = 24
# Radiance of an area light per watt per square metre of its surface: 1/pi, so that its radiant
# exitance (pi * radiance) is power / area. Measured: Cycles' renders agree within 0.1%
# (tests/test_blender_lights.py); its kernel's 0.25 / area comes with a 4/pi from Blender's side.
AREA_RADIANCE = 1.0 / math.pi
MIN_SPREAD = math.radians(1.0)  # narrower spreads are taken as this, as Cycles takes them


def _vector(value, name: str, problems: list[str], unit: bool = False) -> np.ndarray:
    """`value` as a float64 (3,) vector; unit vectors normalised; problems noted, not raised."""
    v = np.array(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        problems.append(f"{name} must be 3 finite numbers, got {value!r}")
        return np.zeros(3)
    if unit:
        norm = float(np.linalg.norm(v))
        if norm < 1e-12:
            problems.append(f"{name} must be a non-zero vector, got {value!r}")
            return np.zeros(3)
        v = v / norm
    return v


@dataclass(frozen=True, eq=False)
class Light:
    """One light in the cloud's world frame, Blender's units (see the module docstring).

    color: (3,) scene-linear, >= 0. power: watts (point, spot, area; Blender's Power times
    2**exposure where the light has an exposure, and times its area for an area light with Normalize
    off) or W/m^2 (sun's Strength). position: (3,) metres
    (unused by the sun). direction: (3,) where the light points, Blender's light -Z axis (normalised
    here). radius: point/spot soft size (m). angle: sun disc diameter (rad). spot_size: full cone angle
    (rad, in (0, pi]); spot_blend in [0, 1]. size_x, size_y: area extent (m; SQUARE and DISK use
    size_x for both); shape: one of AREA_SHAPES; x_axis: (3,) the area light's local +X in world
    (made orthogonal to direction here). cast_shadow: whether it casts shadows. diffuse, specular:
    >= 0, the light's weight in diffuse and in specular reflection (0: none, as a Blender light whose
    Diffuse or Glossy ray visibility is off, which Cycles reads so). spread: an area light's Spread
    (rad, in (0, pi]; pi: a plain Lambertian emitter; see spread_factor).
    """

    kind: str
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    power: float = 1000.0
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    radius: float = 0.1
    angle: float = 0.0
    spot_size: float = math.radians(45.0)
    spot_blend: float = 0.15
    size_x: float = 1.0
    size_y: float = 1.0
    shape: str = "SQUARE"
    x_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    cast_shadow: bool = True
    diffuse: float = 1.0
    specular: float = 1.0
    spread: float = math.pi

    def __post_init__(self):
        problems: list[str] = []
        if self.kind not in KINDS:
            problems.append(f"kind must be one of {KINDS}, got {self.kind!r}")
        color = _vector(self.color, "color", problems)
        if (color < 0).any():
            problems.append(f"color must be >= 0, got {self.color!r}")
        position = _vector(self.position, "position", problems)
        direction = _vector(self.direction, "direction", problems, unit=True)
        x_axis = _vector(self.x_axis, "x_axis", problems, unit=True)
        if not problems and self.kind == "area":
            # Gram-Schmidt: a light's matrix may carry round-off; a parallel axis is an error.
            x_axis = x_axis - direction * float(x_axis @ direction)
            if np.linalg.norm(x_axis) < 1e-6:
                problems.append("x_axis must not be parallel to direction")
            else:
                x_axis = x_axis / np.linalg.norm(x_axis)
        values = {
            "power": (self.power, 0.0, math.inf, True),
            "radius": (self.radius, 0.0, math.inf, True),
            "angle": (self.angle, 0.0, math.pi, True),
            "spot_size": (self.spot_size, 0.0, math.pi, False),
            "spot_blend": (self.spot_blend, 0.0, 1.0, True),
            "size_x": (self.size_x, 0.0, math.inf, False),
            "size_y": (self.size_y, 0.0, math.inf, False),
            "diffuse": (self.diffuse, 0.0, math.inf, True),
            "specular": (self.specular, 0.0, math.inf, True),
            "spread": (self.spread, 0.0, math.pi * (1.0 + 1e-6), False),  # Blender's float32 pi passes
        }
        for name, (value, low, high, closed_low) in values.items():
            ok = isinstance(value, int | float | np.floating | np.integer) and math.isfinite(value)
            ok = ok and (value >= low if closed_low else value > low) and value <= high
            if not ok:
                bound = ">=" if closed_low else ">"
                problems.append(f"{name} must be finite, {bound} {low} and <= {high}, got {value!r}")
        if self.shape not in AREA_SHAPES:
            problems.append(f"shape must be one of {AREA_SHAPES}, got {self.shape!r}")
        if problems:
            raise ValueError("invalid light: " + "; ".join(problems))
        object.__setattr__(self, "color", color)
        object.__setattr__(self, "direction", direction)
        object.__setattr__(self, "x_axis", x_axis)
        object.__setattr__(self, "position", position)
        object.__setattr__(self, "cast_shadow", bool(self.cast_shadow))
        object.__setattr__(self, "spread", min(float(self.spread), math.pi))

    @property
    def extent(self) -> tuple[float, float]:
        """The area light's (x, y) size in metres: SQUARE and DISK are size_x both ways."""
        square = self.shape in ("SQUARE", "DISK")
        return self.size_x, self.size_x if square else self.size_y

    @property
    def round(self) -> bool:
        return self.shape in ("DISK", "ELLIPSE")

    @property
    def area(self) -> float:
        """The emitting area in m^2 (area lights)."""
        sx, sy = self.extent
        return sx * sy * (math.pi / 4.0 if self.round else 1.0)


@dataclass(frozen=True, eq=False)
class World:
    """The world's light: scene-linear radiance `color` (3,) from every direction (Blender's world
    Background colour times its strength), or with `environment` the (9, 3) SH coefficients of an
    environment map's radiance (core.environment; Blender's Environment Texture), `color` then its
    mean; `sun`, the sun taken out of that map (core.environment.light_of), a sun Light that the
    callers light with beside their own (lights()). occlusion: the directions (sphere_directions)
    sampled for what the splats and meshes hide of it (core.ambient); 0 leaves it unoccluded."""

    color: np.ndarray = field(default_factory=lambda: np.zeros(3))
    occlusion: int = 0
    environment: np.ndarray | None = None
    sun: Light | None = None

    def __post_init__(self):
        problems: list[str] = []
        if self.sun is not None and not (isinstance(self.sun, Light) and self.sun.kind == "sun"):
            raise ValueError(f"invalid world: its sun must be a sun Light, got {self.sun!r}")
        if self.environment is not None:
            environment = np.array(self.environment, np.float64)
            if environment.shape != (9, 3) or not np.isfinite(environment).all():
                raise ValueError("invalid world: environment must be (9, 3) finite SH coefficients (core.environment)")
            object.__setattr__(self, "environment", environment)
            object.__setattr__(self, "color", np.maximum(environment[0] * sh.C0, 0.0))  # its mean
        color = _vector(self.color, "color", problems)
        if problems or (color < 0).any():
            raise ValueError(f"invalid world: color must be 3 finite numbers >= 0, got {self.color!r}")
        if not isinstance(self.occlusion, int | np.integer) or self.occlusion < 0:
            raise ValueError(f"invalid world: occlusion must be a whole number >= 0, got {self.occlusion!r}")
        object.__setattr__(self, "color", color)
        object.__setattr__(self, "occlusion", int(self.occlusion))

    def lights(self, lights: list[Light]) -> list[Light]:
        """`lights` and the world's sun after them (light linking's indices stay theirs)."""
        return list(lights) if self.sun is None else [*lights, self.sun]

    @property
    def occluded(self) -> bool:
        """Whether relighting tests what of the world the splats and meshes hide: some directions
        asked for, and some light to hide."""
        return self.occlusion > 0 and bool(self.color.any())


def sphere_directions(count: int) -> Annotated[np.ndarray, "(K, 3)"]:
    """(count, 3) float64 unit vectors spread evenly over the sphere (a Fibonacci spiral): each has
    an equal share of the sphere, 4 pi / count steradians."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    ring = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    turn = k * math.pi * (3.0 - math.sqrt(5.0))  # the golden angle
    return np.stack([ring * np.cos(turn), ring * np.sin(turn), z], axis=1)


def cone_angle(count: int) -> float:
    """The full angle (rad) of a cone holding 1/count of the sphere, 2 pi (1 - cos half) = 4 pi / count;
    at most pi (a hemisphere: a sun is no wider)."""
    return 2.0 * math.acos(min(max(1.0 - 2.0 / count, 0.0), 1.0))


class Incident(NamedTuple):
    """Light arriving at N points from one emitter (a whole point/spot/sun light, or one sample of an
    area light): unit `direction` (N,3) from each point towards the emitter, `distance` (N,) to it
    (inf for the sun), `strength` (N,), the irradiance on a surface facing it before the light's
    colour and the receiver's cosine (times Light.color: W/m^2 per channel), and `radius`, the
    emitter's size in metres as a sphere or disc (a point or spot light's radius, (N,) for an area
    sample's patch; the sun's is its angle)."""

    direction: np.ndarray
    distance: np.ndarray
    strength: np.ndarray
    radius: np.ndarray | float = 0.0


def spot_cone(light: Light, cos_angle: np.ndarray) -> np.ndarray:
    """Blender's spot cone factor (N,) for rays leaving the light at cos_angle (N,) to its axis:
    smoothstep((cos_angle - cos(size/2)) / ((1 - cos(size/2)) * blend)), a hard edge at blend 0."""
    cos_half = math.cos(0.5 * light.spot_size)
    width = (1.0 - cos_half) * light.spot_blend
    if width <= 0.0:
        return (cos_angle > cos_half).astype(np.float64)
    x = np.clip((cos_angle - cos_half) / width, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def spread_terms(light: Light) -> tuple[float, float]:
    """(tan(s/2), 1 / (tan(s/2) - s/2)) of an area light's spread s (at least MIN_SPREAD), from which
    spread_factor follows; (0, 1) for a full spread of pi (no narrowing)."""
    if light.spread >= math.pi:
        return 0.0, 1.0
    half = 0.5 * max(light.spread, MIN_SPREAD)
    tan_half = math.tan(half)
    # tan h - h loses digits for small h: its series h^3/3 + 2h^5/15 + 17h^7/315 there
    gap = tan_half - half if half > 0.05 else half**3 / 3 + 2 * half**5 / 15 + 17 * half**7 / 315
    return tan_half, 1.0 / gap


def spread_factor(light: Light, cos_emit: np.ndarray) -> np.ndarray:
    """(N,) what an area light's Spread leaves of its radiance towards directions at cos_emit (N,) to
    its axis: (tan(s/2) - tan a) / (tan(s/2) - s/2), 0 past s/2. The divisor keeps the light's power:
    the integral of cos a sin a over the cone times it is 1/2, a Lambertian hemisphere's; 1 for a
    spread of pi."""
    tan_half, scale = spread_terms(light)
    cos_emit = np.asarray(cos_emit, np.float64)
    if tan_half == 0.0:
        return np.ones_like(cos_emit)
    with np.errstate(divide="ignore", invalid="ignore"):
        tan_a = np.sqrt(np.maximum(1.0 - cos_emit * cos_emit, 0.0)) / cos_emit
    return np.where(cos_emit > 0.0, np.maximum(tan_half - tan_a, 0.0) * scale, 0.0)


def area_points(light: Light, grid: int = AREA_GRID) -> tuple[np.ndarray, np.ndarray]:
    """The area light's sample points (grid*grid, 3) in world and each one's share of its area (m^2):
    cell centres of a grid x grid split of the rectangle, or of the unit square mapped to the disc by
    Shirley and Chiu's concentric map (area-preserving, so every point holds area / grid^2)."""
    centres = (np.arange(grid) + 0.5) / grid * 2.0 - 1.0  # in (-1, 1)
    a, b = (m.ravel() for m in np.meshgrid(centres, centres, indexing="ij"))
    if light.round:
        # concentric map: squares of the grid to rings, wedges to sectors, area kept
        first = np.abs(a) > np.abs(b)
        r = np.where(first, a, b)
        r = np.sign(r) * np.sqrt(r * r + 1.0 / grid**2)  # the ring cell's area-median radius
        safe_a = np.where(a == 0.0, 1.0, a)
        safe_b = np.where(b == 0.0, 1.0, b)
        phi = np.where(first, (math.pi / 4.0) * b / safe_a, math.pi / 2.0 - (math.pi / 4.0) * a / safe_b)
        a, b = r * np.cos(phi), r * np.sin(phi)
    sx, sy = light.extent
    points = light.position + np.outer(0.5 * sx * a, light.x_axis) + np.outer(0.5 * sy * b, y_axis(light))
    return points, np.full(len(points), light.area / len(points))


def area_table(light: Light) -> np.ndarray:
    """(AREA_GRID + 1, AREA_SAMPLES, 3) float64: [g, k] is sample k of the area light's g x g grid
    (area_points; each holds area / g^2), zeros past g * g and for g = 0."""
    table = np.zeros((AREA_GRID + 1, AREA_SAMPLES, 3))
    for g in range(1, AREA_GRID + 1):  # a loop over grids
        table[g, : g * g] = area_points(light, g)[0]
    return table


def area_grids(light: Light, points: np.ndarray, lobes: np.ndarray | None = None) -> np.ndarray:
    """(N,) int: the sampling grid (g of g x g, 1..AREA_GRID) of the area light at each point (N,3),
    from its distance to the light's centre (see AREA_REACH) and, for a light narrowed by its
    Spread, its height over the light's plane (AREA_SPREAD); the finest where it is undefined.
    lobes: (N,) angular widths (radians) of glossy reflections to be lit: the samples' spacing, the
    side over g distance, stays within a lobe's width, or a glossy highlight takes the shape of
    too few samples."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    distance = towards(light.position, points)[1]
    side = max(light.extent)
    tan_half = spread_terms(light)[0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        grids = np.ceil(AREA_REACH * side / distance)
        if lobes is not None:
            grids = np.maximum(grids, np.ceil(AREA_GLOSS * side / (distance * lobes)))
        if tan_half > 0.0:  # a Spread: the part of the light that reaches the point
            height = np.abs((points - light.position) @ light.direction)
            grids = np.maximum(grids, np.ceil(AREA_SPREAD * side / (height * tan_half)))
    return np.clip(np.nan_to_num(grids, nan=AREA_GRID), 1, AREA_GRID).astype(np.int64)


def y_axis(light: Light) -> np.ndarray:
    """(3,) an area light's local +Y in world: x, y, -direction right-handed."""
    return np.cross(light.x_axis, light.direction)


def reachable_discs(light: Light, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The discs of a light narrowed by its Spread that reach points (N,3) (a point at height t
    over its plane sees the light within t tan(spread/2) of its foot): (N,) bool where the disc is
    smaller than the light and is sampled itself, the foot (N,2) in the light's local x, y and the
    disc's radius (N,)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    tan_half = spread_terms(light)[0]
    offset = points - light.position
    height = offset @ light.direction
    foot = np.stack([offset @ light.x_axis, offset @ y_axis(light)], axis=1)
    radius = np.maximum(height, 0.0) * tan_half
    sampled = (tan_half > 0.0) & (height > 0.0)
    return sampled & (math.pi * radius * radius < light.area), foot, radius


def ring_arcs(light: Light, centre: np.ndarray, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The arcs inside the light of circles about centre (N,2, the light's local x, y) of radius
    (N,) > 0: (N,8) start angles and (N,8) lengths (0 for the pieces outside), between the angles
    where the circle crosses the light's rim."""
    a, b = 0.5 * light.extent[0], 0.5 * light.extent[1]
    x0, y0 = centre[:, 0], centre[:, 1]
    cuts = np.full((len(radius), 9), np.nan)
    cuts[:, 0] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        if light.round and a != b:
            cuts[:, 1:5] = ellipse_crossings(x0, y0, radius, a, b)
        elif light.round:  # |centre + r e(phi)| = a: cos(phi - psi) = (a^2 - |centre|^2 - r^2) / (2 r |centre|)
            reach = np.hypot(x0, y0)
            c = (a * a - reach * reach - radius * radius) / (2.0 * radius * reach)
            crosses = np.abs(c) < 1.0
            psi, turn = np.arctan2(y0, x0), np.arccos(np.clip(c, -1.0, 1.0))
            cuts[:, 1] = np.where(crosses, psi + turn, np.nan)
            cuts[:, 2] = np.where(crosses, psi - turn, np.nan)
        else:  # x = +-a: cos phi = (+-a - x0) / r; y = +-b: sin phi = (+-b - y0) / r
            for k, (edge, along) in enumerate(((a, x0), (-a, x0), (b, y0), (-b, y0))):
                q = (edge - along) / radius
                crosses = np.abs(q) < 1.0
                angle = np.arccos(np.clip(q, -1.0, 1.0)) if k < 2 else np.arcsin(np.clip(q, -1.0, 1.0))
                other = -angle if k < 2 else math.pi - angle
                cuts[:, 1 + 2 * k] = np.where(crosses, angle, np.nan)
                cuts[:, 2 + 2 * k] = np.where(crosses, other, np.nan)
    cuts = np.sort(np.mod(cuts, 2.0 * math.pi), axis=1)  # NaN last
    cuts = np.where(np.isnan(cuts), 2.0 * math.pi, cuts)  # a full turn closes the last piece
    start, length = cuts[:, :-1], np.diff(cuts, axis=1)
    middle = start + 0.5 * length
    x, y = x0[:, None] + radius[:, None] * np.cos(middle), y0[:, None] + radius[:, None] * np.sin(middle)
    inside = (x * x / (a * a) + y * y / (b * b) <= 1.0) if light.round else (np.abs(x) <= a) & (np.abs(y) <= b)
    return start, np.where(inside, length, 0.0)


def ellipse_rim(x0, y0, radius, a, b, angle):
    """Where a circle about (x0, y0) of `radius` is at `angle`, relative to an ellipse of half axes
    a, b about the origin: (x/a)^2 + (y/b)^2 - 1 there (< 0 inside), as its Fourier series,
    A0 + A1 cos t + B1 sin t + A2 cos 2t."""
    ia2, ib2 = 1.0 / (a * a), 1.0 / (b * b)
    c, s = np.cos(angle), np.sin(angle)
    constant = x0 * x0 * ia2 + y0 * y0 * ib2 + 0.5 * radius * radius * (ia2 + ib2) - 1.0
    twice = 0.5 * radius * radius * (ia2 - ib2) * (2.0 * c * c - 1.0)
    return constant + 2.0 * radius * (x0 * ia2 * c + y0 * ib2 * s) + twice


def ellipse_crossings(x0, y0, radius, a, b) -> np.ndarray:
    """(N,4) the angles where circles about (x0, y0) (N,) of radius (N,) cross the rim of an
    ellipse of half axes a, b, NaN past the last (at most four): found as sign changes of
    ellipse_rim at ELLIPSE_SCAN steps around the circle, each halved ELLIPSE_BISECTIONS times (a
    circle that only touches the rim between two steps is taken as not crossing it)."""
    steps = np.linspace(0.0, 2.0 * math.pi, ELLIPSE_SCAN + 1)
    rim = ellipse_rim(x0[:, None], y0[:, None], radius[:, None], a, b, steps[None, :])
    row, step = np.nonzero((rim[:, :-1] < 0.0) != (rim[:, 1:] < 0.0))
    low, high = steps[step], steps[step + 1]
    below = rim[row, step] < 0.0
    for _ in range(ELLIPSE_BISECTIONS):  # a loop over halvings, every crossing at once
        middle = 0.5 * (low + high)
        same = (ellipse_rim(x0[row], y0[row], radius[row], a, b, middle) < 0.0) == below
        low, high = np.where(same, middle, low), np.where(same, high, middle)
    out = np.full((len(radius), 4), np.nan)
    rank = np.arange(len(row)) - np.searchsorted(row, row)  # the crossing's place in its row
    keep = rank < 4
    out[row[keep], rank[keep]] = 0.5 * (low + high)[keep]
    return out


def disc_rings() -> np.ndarray:
    """(SPREAD_RINGS, 2): the reachable disc's ring radii, as fractions of its radius, and their
    weights (Gauss-Legendre on [0, 1])."""
    nodes, weights = np.polynomial.legendre.leggauss(SPREAD_RINGS)
    return np.stack([0.5 * (nodes + 1.0), 0.5 * weights], axis=1)


def spread_samples(light: Light, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples of each point's reachable disc (reachable_discs): (N,) bool where it is sampled,
    positions (SPREAD_SAMPLES, N, 3) in world and each one's area (SPREAD_SAMPLES, N) m^2 (0 where
    the point does not sample its disc, and for the samples of a ring wholly outside the light)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(points)
    sampled, foot, radius = reachable_discs(light, points)
    positions, areas = np.zeros((SPREAD_SAMPLES, n, 3)), np.zeros((SPREAD_SAMPLES, n))
    rows = np.flatnonzero(sampled)
    if not len(rows):
        return sampled, positions, areas
    foot, radius = foot[rows], radius[rows]
    for ring, (node, weight) in enumerate(disc_rings()):  # a loop over rings
        start, length = ring_arcs(light, foot, node * radius)
        total, ends = length.sum(axis=1), np.cumsum(length, axis=1)
        for k in range(SPREAD_ANGLES):  # a loop over a ring's samples: midpoints of equal shares of its arcs
            along = (k + 0.5) / SPREAD_ANGLES * total
            piece = np.minimum((ends <= along[:, None]).sum(axis=1), length.shape[1] - 1)[:, None]
            angle = np.take_along_axis(start + length - ends, piece, 1)[:, 0] + along
            local = foot + (node * radius)[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
            slot = ring * SPREAD_ANGLES + k
            positions[slot, rows] = light.position + local @ np.stack([light.x_axis, y_axis(light)])
            areas[slot, rows] = weight * node * radius * radius * total / SPREAD_ANGLES
    return sampled, positions, areas


def area_radiance(light: Light) -> float:
    """The radiance (W / (sr m^2), before its colour) an area light's surface sends forwards:
    AREA_RADIANCE times its power per square metre (a Spread's scale not included)."""
    return AREA_RADIANCE * light.power / light.area


def towards(source: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (N,3) from points to `source` ((3,) or one per point (N,3)) and the distances
    (N,), float64."""
    offset = source - points
    distance = np.sqrt(np.einsum("ij,ij->i", offset, offset))
    return offset / np.maximum(distance, 1e-300)[:, None], distance


def incident(light: Light, points: np.ndarray, lobes: np.ndarray | None = None) -> list[Incident]:
    """The light arriving at points (N,3): one Incident per emitter, in float64. An area light gives
    one per sample slot, up to AREA_SAMPLES: slot k holds sample k of each point's grid (area_grids),
    no light where that grid has fewer (`lobes` as area_grids'). A point closer than 1e-300 to an
    emitter gets no light from it."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    if light.kind == "sun":
        to_sun = np.broadcast_to(-light.direction, (n, 3))
        return [Incident(to_sun, np.full(n, np.inf), np.full(n, light.power))]
    if light.kind in ("point", "spot"):
        direction, distance = towards(light.position, points)
        intensity = np.full(n, light.power / (4.0 * math.pi))
        if light.kind == "spot":
            intensity = intensity * spot_cone(light, -(direction @ light.direction))
        scalar = np.where(distance > 1e-300, intensity / np.maximum(distance, 1e-300) ** 2, 0.0)
        return [Incident(direction, distance, scalar, light.radius)]
    grids = area_grids(light, points, lobes)
    table = area_table(light)
    disc, disc_points, disc_areas = spread_samples(light, points)
    radiance = area_radiance(light)
    slots = max(int(grids.max(initial=1)) ** 2, SPREAD_SAMPLES if disc.any() else 0)
    out = []
    for k in range(slots):  # a loop over sample slots, not points
        on_grid = np.where(k < grids * grids, light.area / (grids * grids), 0.0)
        on_disc = disc_points[min(k, SPREAD_SAMPLES - 1)]
        sample = np.where(disc[:, None], on_disc, table[grids, min(k, AREA_SAMPLES - 1)])
        share = np.where(disc, disc_areas[k] if k < SPREAD_SAMPLES else 0.0, on_grid)
        direction, distance = towards(sample, points)
        # one-sided Lambertian patch: its cosine towards each point, 0 behind it
        cos_emit = np.maximum(-(direction @ light.direction), 0.0)
        scalar = radiance * share * cos_emit * spread_factor(light, cos_emit) / np.maximum(distance, 1e-300) ** 2
        scalar = np.where(distance > 1e-300, scalar, 0.0)
        out.append(Incident(direction, distance, scalar, np.sqrt(share / math.pi)))
    return out


def irradiance(light: Light, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (N,3) float64 W/m^2 (colour included) from `light` on surfaces at points (N,3) with
    unit normals (N,3): the sum over the light's emitters of their strength times max(0, n . l)."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    total = np.zeros(len(normals))
    for inc in incident(light, points):
        total += inc.strength * np.maximum(np.einsum("ij,ij->i", inc.direction, normals), 0.0)
    return total[:, None] * light.color


def direction_and_distance(light: Light, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction (N,3) from each point towards the light (its centre; for the sun, -direction)
    and the distance (N,) to it (inf for the sun): what shadow lookups need."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if light.kind == "sun":
        return np.broadcast_to(-light.direction, points.shape).copy(), np.full(len(points), np.inf)
    return towards(light.position, points)
