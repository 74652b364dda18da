"""A light's diffuse and GGX specular, integrated over the light rather than sampled.

An area light is a polygon: a square or rectangle its four corners, a disc or ellipse ROUND_SIDES
sides of the same area. A sphere light (a point or spot light with a radius) or the sun's disc is
seen from a point as a disc across the direction to it, that polygon too (disc_shares): only its
highlight is integrated, its diffuse being a point's. An area light's diffuse is then exact (for a
round light, up to that polygon): a uniform Lambertian polygon's irradiance is the integral of the
clamped cosine over the spherical polygon it spans (Lambert's contour formula: per edge, the angle
it subtends times the normal's component along the edge plane's normal, summed and divided by
2 pi), the polygon first clipped to the surface's upper hemisphere.

The specular uses linearly transformed cosines (Heitz, Dupuy, Hill and Neubelt 2016): the GGX lobe
towards one view, normalised, is close to a clamped cosine seen through a 3x3 matrix, so its integral
over a polygon is the cosine's integral over the polygon taken back through the inverse matrix, the
same contour formula. The inverse matrices, fitted per view angle and roughness by tools/fit_ltc.py
(core.ltc_table), are looked up bilinearly; the lobe's own albedo (core.shading's Fresnel split) scales
the share. In the splat's frame the normal is +z and the view lies in the xz plane (x >= 0).

Only smooth lobes are integrated (roughness up to ROUGHNESS): there the sampled grid of core.lights,
at most 16 samples, leaves a highlight the shape of its samples (28% of its peak off at roughness
0.1), the fitted cosines within 2%; rougher lobes at grazing views are no transformed cosine (their
tail towards the normal), 7-14% off at roughness 0.45-1, where the samples keep within 1%
(tests/test_ltc.py). A smooth splat's cost is then two polygons whatever its distance, where the
grid needed 16 samples. Rougher splats and lights narrowed by a Spread are sampled
(core.lights.incident); a round light's rougher highlight is its widened lobe (core.shading), which
left a smooth one's 16-36% off, the polygon 0.2-1.5% (up to 15% at a near mirror's rim).

Each function has a scalar twin (`_..._one`) for the compiled shading kernel, written the same way.
"""

import math
from typing import Annotated

import numpy as np

from .lights import Light, spread_terms, y_axis
from .ltc_table import INVERSE, ROUGHNESS, SIZE

CORNERS = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))  # a rectangle's corners in its half extents
# A disc or ellipse is a polygon of this many sides and the same area: its rim within 1.3% of the
# round one's radius, a mirror image's corners finer than a pixel's worth of most highlights.
ROUND_SIDES = 16
MAX_VERTICES = ROUND_SIDES + 1  # a convex polygon cut by a plane keeps at most one vertex more
EDGE_DEGREE = 10  # of the compiled contour formula's polynomial (_edge_polynomial): 6e-9 relative
KERNEL = (
    "_lookup_one", "_angle_over_sine_one", "_edge_one", "_clipped_share_one", "_tangent_one", "_frame_one",
    "_lobe_share_one", "_light_one", "_disc_one",
)  # fmt: skip


def integrated(light: Light) -> bool:
    """Whether the light's shading is integrated here for smooth splats (roughness up to ROUGHNESS):
    an area light without a Spread narrowing it."""
    return light.kind == "area" and spread_terms(light)[0] <= 0.0


def _unit_round() -> np.ndarray:
    """(ROUND_SIDES, 2) the polygon standing for a unit disc: its vertices at the radius that keeps
    the disc's area, in order around it."""
    angle = 2.0 * math.pi * np.arange(ROUND_SIDES) / ROUND_SIDES
    same_area = math.sqrt(2.0 * math.pi / (ROUND_SIDES * math.sin(2.0 * math.pi / ROUND_SIDES)))
    return np.c_[np.cos(angle), np.sin(angle)] * same_area


ROUND = _unit_round()


def outline(light: Light) -> Annotated[np.ndarray, "(V, 2)"]:
    """The light's polygon (V,2) in its own x and y (metres), in order around it: a rectangle's
    corners, or ROUND_SIDES vertices on the disc or ellipse scaled to keep its area."""
    half = np.array(light.extent) / 2.0
    return ROUND * half if light.round else np.array(CORNERS) * half


def vertices(light: Light) -> Annotated[np.ndarray, "(V, 3)"]:
    """The light's polygon (outline) in world space (V,3)."""
    local = outline(light)
    return light.position + local[:, :1] * light.x_axis + local[:, 1:] * y_axis(light)


def inverse_params(cos_v: np.ndarray, roughness: np.ndarray) -> Annotated[np.ndarray, "(N, 4)"]:
    """(N,4) the inverse matrix's (a, b, c, d) (core.ltc_table) at each view's n.v (N,) and
    roughness (N,, up to ROUGHNESS), bilinear in sqrt(1 - n.v) and roughness."""
    x = np.sqrt(np.clip(1.0 - np.clip(cos_v, 0.0, 1.0), 0.0, 1.0)) * (SIZE - 1)
    y = np.clip(roughness / ROUGHNESS, 0.0, 1.0) * (SIZE - 1)
    i, j = np.minimum(x.astype(np.int64), SIZE - 2), np.minimum(y.astype(np.int64), SIZE - 2)
    fx, fy = (x - i)[:, None], (y - j)[:, None]
    low = INVERSE[i, j] * (1 - fx) + INVERSE[i + 1, j] * fx
    high = INVERSE[i, j + 1] * (1 - fx) + INVERSE[i + 1, j + 1] * fx
    return low * (1 - fy) + high * fy


def clipped_share(polygons: Annotated[np.ndarray, "(N, V, 3)"]) -> Annotated[np.ndarray, "(N,)"]:
    """(N,) the integral of the clamped cosine max(z, 0) / pi over the spherical polygon each row's
    V vertices (directions from the origin, any length; a convex polygon) span: the polygon clipped
    to z >= 0 (Sutherland-Hodgman), then Lambert's contour formula. Rows wholly above the plane (most)
    skip the clipping."""
    n, v = polygons.shape[:2]
    out = np.empty(n)
    cut = (polygons[..., 2] < 0.0).any(axis=1)
    out[~cut] = _contour(polygons[~cut], np.full(int((~cut).sum()), v))
    polygons = polygons[cut]
    nxt = np.roll(polygons, -1, axis=1)
    z, z_next = polygons[..., 2], nxt[..., 2]
    up, up_next = z >= 0.0, z_next >= 0.0
    t = np.where(up != up_next, z / np.where(z != z_next, z - z_next, 1.0), 0.0)
    crossing = polygons + t[..., None] * (nxt - polygons)
    crossing[..., 2] = 0.0
    # each edge gives its start (if above) then its crossing (if it crosses): 2 V slots, in order
    slots = np.stack([polygons, crossing], axis=2).reshape(-1, 2 * v, 3)
    kept = np.stack([up, up != up_next], axis=2).reshape(-1, 2 * v)
    order = np.argsort(~kept, axis=1, kind="stable")  # the kept slots first, in their order
    out[cut] = _contour(np.take_along_axis(slots, order[..., None], axis=1)[:, : v + 1], kept.sum(axis=1))
    return out


def _contour(points: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(M,) Lambert's contour formula over the first count (M,) of each row's points (M, V, 3), a
    polygon above the plane z = 0; 0 for fewer than three."""
    length = np.linalg.norm(points, axis=2, keepdims=True)
    unit = points / np.where(length > 0.0, length, 1.0)
    index = np.arange(points.shape[1])
    if (count == points.shape[1]).all():  # whole polygons (unclipped): each vertex's next is the row's next
        ahead = np.roll(unit, -1, axis=1)
    else:
        following = np.where(index[None] + 1 < count[:, None], index[None] + 1, 0)
        ahead = np.take_along_axis(unit, following[..., None], axis=1)
    cross_z = unit[..., 0] * ahead[..., 1] - unit[..., 1] * ahead[..., 0]
    cosine = np.clip(np.einsum("nvi,nvi->nv", unit, ahead), -1.0, 1.0)
    sine = np.sqrt(np.maximum(1.0 - cosine * cosine, 1e-300))
    angle_over_sine = np.where(cosine < 1.0 - 1e-12, np.arccos(cosine) / sine, 1.0)  # 1 in the limit
    terms = np.where(index[None] < count[:, None], angle_over_sine * cross_z, 0.0)
    return np.where(count >= 3, np.abs(terms.sum(axis=1)) / (2.0 * math.pi), 0.0)


def frames(normal: np.ndarray, view: np.ndarray) -> Annotated[np.ndarray, "(N, 3, 3)"]:
    """(N,3,3) rows x, y, z of each splat's frame: z its normal (N,3, facing the eye), x along the
    view's (N,3) part in the tangent plane (any tangent where the view is the normal)."""
    along = view - normal * np.einsum("ij,ij->i", normal, view)[:, None]
    size = np.linalg.norm(along, axis=1)
    along = np.where((size > 1e-9)[:, None], along, tangents(normal))
    x = along / np.linalg.norm(along, axis=1, keepdims=True)
    return np.stack([x, np.cross(normal, x), normal], axis=1)


def tangents(normal: np.ndarray) -> Annotated[np.ndarray, "(N, 3)"]:
    """(N,3) a unit vector across each unit `normal` (N,3): x or, near it, y with the normal's part
    taken out."""
    other = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    other = other - normal * np.einsum("ij,ij->i", normal, other)[:, None]
    return other / np.linalg.norm(other, axis=1, keepdims=True)


def light_shares(
    light: Light,
    points: Annotated[np.ndarray, "(N, 3)"],
    normal: Annotated[np.ndarray, "(N, 3)"],
    view: Annotated[np.ndarray, "(N, 3)"],
    roughness: Annotated[np.ndarray, "(N,)"],
) -> tuple[np.ndarray, np.ndarray]:
    """(form factor (N,), lobe share (N,)) of an area light (its polygon) at each point: the share of
    the clamped cosine about `normal` (facing the eye) and of the normalised GGX lobe towards `view`
    (roughness up to ROUGHNESS) that the light covers (0 behind it: it emits forwards only).
    Irradiance is pi L times the first, the specular radiance L times the second times the lobe's
    albedo (L the light's radiance)."""
    frame = frames(normal, view)
    # the light's centre (from each point) and axes in the point's frame: the vertices are sums of them
    centre = np.einsum("nij,nj->ni", frame, light.position - points)
    x_axis, y_axis_ = (frame @ axis for axis in (light.x_axis, y_axis(light)))
    shape = outline(light)
    local = centre[:, None] + shape[None, :, :1] * x_axis[:, None] + shape[None, :, 1:] * y_axis_[:, None]
    ahead = (points - light.position) @ light.direction > 0.0
    diffuse = np.where(ahead, clipped_share(local), 0.0)
    return diffuse, np.where(ahead, _lobe_share(local, normal, view, roughness), 0.0)


def disc_shares(
    direction: Annotated[np.ndarray, "(N, 3)"],
    half_angle: Annotated[np.ndarray, "(N,)"],
    normal: Annotated[np.ndarray, "(N, 3)"],
    view: Annotated[np.ndarray, "(N, 3)"],
    roughness: Annotated[np.ndarray, "(N,)"],
) -> Annotated[np.ndarray, "(N,)"]:
    """(N,) the share of the normalised GGX lobe towards `view` (roughness up to ROUGHNESS) that a
    round light covers: a sphere light or the sun's disc, seen from each point as a disc of
    `half_angle` (N,) about the unit `direction` (N,3) towards its centre (the disc across that
    direction at distance 1, radius tan(half_angle), as ROUND's polygon). Its specular radiance is L
    times this times the lobe's albedo, L = E / (pi sin^2(half_angle)) for the irradiance E it gives
    a surface facing it."""
    across = tangents(direction)
    other = np.cross(direction, across)
    # the centre and the disc's axes in each point's frame: the vertices are then sums of them
    frame = frames(normal, view)
    centre, across, other = (np.einsum("nij,nj->ni", frame, vector) for vector in (direction, across, other))
    radius = np.tan(half_angle)[:, None, None]
    ring = centre[:, None] + radius * (ROUND[None, :, :1] * across[:, None] + ROUND[None, :, 1:] * other[:, None])
    return _lobe_share(ring, normal, view, roughness)


def _lobe_share(local, normal, view, roughness):
    """(N,) clipped_share of the polygons `local` (N,V,3, in each point's frame) taken through the
    point's fitted inverse matrix."""
    cos_v = np.einsum("ij,ij->i", normal, view)
    a, b, c, d = inverse_params(cos_v, roughness).T
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    return clipped_share(np.stack([a[:, None] * x + b[:, None] * z, c[:, None] * y, d[:, None] * x + z], axis=2))


# the compiled kernel's scalar twins ----------------------------------------------------------------


def _lookup_one(table, cos_v, roughness):
    """inverse_params of one view and roughness: (a, b, c, d)."""
    x = math.sqrt(min(max(1.0 - min(max(cos_v, 0.0), 1.0), 0.0), 1.0)) * (SIZE - 1)
    y = min(max(roughness / ROUGHNESS, 0.0), 1.0) * (SIZE - 1)
    i, j = min(int(x), SIZE - 2), min(int(y), SIZE - 2)
    fx, fy = x - i, y - j
    w00, w10, w01, w11 = (1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy
    return (
        w00 * table[i, j, 0] + w10 * table[i + 1, j, 0] + w01 * table[i, j + 1, 0] + w11 * table[i + 1, j + 1, 0],
        w00 * table[i, j, 1] + w10 * table[i + 1, j, 1] + w01 * table[i, j + 1, 1] + w11 * table[i + 1, j + 1, 1],
        w00 * table[i, j, 2] + w10 * table[i + 1, j, 2] + w01 * table[i, j + 1, 2] + w11 * table[i + 1, j + 1, 2],
        w00 * table[i, j, 3] + w10 * table[i + 1, j, 3] + w01 * table[i, j + 1, 3] + w11 * table[i + 1, j + 1, 3],
    )


def _edge_polynomial(degree: int = EDGE_DEGREE) -> np.ndarray:
    """Coefficients (lowest first) of a polynomial in c = cos(angle) on [0, 1] for angle / sin(angle) =
    acos(c) / sqrt(1 - c^2), which is smooth there (1 at c = 1, pi / 2 at 0): a Chebyshev
    least-squares fit, within 6e-9 relative at degree 10 (tests/test_ltc.py): points beside a light's
    plane, where the edges' terms nearly cancel, carry its error a thousandfold (at degree 5, 4e-5
    left such a point 0.3% off; at 8, 2e-7, 1e-4)."""
    c = np.linspace(0.0, 1.0, 4001)
    value = np.ones_like(c)
    inside = c < 1.0
    value[inside] = np.arccos(c[inside]) / np.sqrt(1.0 - c[inside] ** 2)
    fit = np.polynomial.Chebyshev.fit(c, value, degree, domain=[0.0, 1.0])
    return fit.convert(kind=np.polynomial.Polynomial, domain=[0.0, 1.0], window=[0.0, 1.0]).coef


EDGE = _edge_polynomial()


def _angle_over_sine_one(c):
    """angle / sin(angle) of two unit directions at cosine c: EDGE's polynomial for c >= 0, and
    through acos(c) = pi - acos(-c) below (a library atan2 per edge was most of a rectangle's cost)."""
    x = abs(c)
    value = EDGE[EDGE.shape[0] - 1]
    for k in range(EDGE.shape[0] - 2, -1, -1):
        value = value * x + EDGE[k]
    if c >= 0.0:
        return value
    return math.pi / math.sqrt(max(1.0 - c * c, 1e-24)) - value


def _edge_one(x0, y0, z0, x1, y1, z1):
    """One edge's term of the contour formula between unit directions: angle / sine times the z of
    their cross product."""
    return _angle_over_sine_one(x0 * x1 + y0 * y1 + z0 * z1) * (x0 * y1 - y0 * x1)


def _clipped_share_one(shape, count, poly):
    """clipped_share of one polygon, the first `count` rows of shape (V,3); poly (MAX_VERTICES, 3)
    scratch. (Whole arrays and indices, no slices: a slice made per splat cost more than the formula.)"""
    m = 0
    for i in range(count):
        j = i + 1 if i + 1 < count else 0
        if shape[i, 2] >= 0.0:
            poly[m, 0], poly[m, 1], poly[m, 2] = shape[i, 0], shape[i, 1], shape[i, 2]
            m += 1
        if (shape[i, 2] >= 0.0) != (shape[j, 2] >= 0.0):
            t = shape[i, 2] / (shape[i, 2] - shape[j, 2])
            poly[m, 0] = shape[i, 0] + t * (shape[j, 0] - shape[i, 0])
            poly[m, 1] = shape[i, 1] + t * (shape[j, 1] - shape[i, 1])
            poly[m, 2] = 0.0
            m += 1
    if m < 3:
        return 0.0
    for k in range(m):
        length = math.sqrt(poly[k, 0] * poly[k, 0] + poly[k, 1] * poly[k, 1] + poly[k, 2] * poly[k, 2])
        inverse = 1.0 / length if length > 0.0 else 1.0
        poly[k, 0], poly[k, 1], poly[k, 2] = poly[k, 0] * inverse, poly[k, 1] * inverse, poly[k, 2] * inverse
    total = 0.0
    for k in range(m):
        n = k + 1 if k + 1 < m else 0
        total += _edge_one(poly[k, 0], poly[k, 1], poly[k, 2], poly[n, 0], poly[n, 1], poly[n, 2])
    return abs(total) / (2.0 * math.pi)


def _frame_one(m0, m1, m2, v0, v1, v2, cos_v):
    """frames() of one point: its x axis (the view's tangent part) and y = m x x."""
    t0, t1, t2 = v0 - m0 * cos_v, v1 - m1 * cos_v, v2 - m2 * cos_v
    size = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if size <= 1e-9:
        t0, t1, t2 = _tangent_one(m0, m1, m2)
    else:
        t0, t1, t2 = t0 / size, t1 / size, t2 / size
    return t0, t1, t2, m1 * t2 - m2 * t1, m2 * t0 - m0 * t2, m0 * t1 - m1 * t0


def _tangent_one(m0, m1, m2):
    """tangents() of one unit normal m."""
    t0, t1, t2 = (1.0, 0.0, 0.0) if abs(m0) < 0.9 else (0.0, 1.0, 0.0)
    along = t0 * m0 + t1 * m1 + t2 * m2
    t0, t1, t2 = t0 - m0 * along, t1 - m1 * along, t2 - m2 * along
    size = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    return t0 / size, t1 / size, t2 / size


def _lobe_share_one(shape, count, poly, table, cos_v, roughness):
    """_lobe_share of one polygon, the first `count` rows of shape (V,3) (overwritten)."""
    a, b, c, d = _lookup_one(table, cos_v, roughness)
    for k in range(count):
        x, z = shape[k, 0], shape[k, 2]
        shape[k, 0], shape[k, 1], shape[k, 2] = a * x + b * z, c * shape[k, 1], d * x + z
    return _clipped_share_one(shape, count, poly)


def _light_one(terms, row, outlines, p0, p1, p2, m0, m1, m2, v0, v1, v2, cos_v, roughness, table, shape, poly):
    """light_shares of one point p (facing-the-eye normal m, view v) for the light whose area terms
    are row `row` of core.shading's `terms` (its vertex count in column 21) and whose outline is
    outlines[row] (ROUND_SIDES, 2); shape (ROUND_SIDES, 3) and poly (MAX_VERTICES, 3) scratch.
    Returns the form factor and the lobe share."""
    c0, c1, c2 = terms[row, 0], terms[row, 1], terms[row, 2]
    if (p0 - c0) * terms[row, 5] + (p1 - c1) * terms[row, 6] + (p2 - c2) * terms[row, 7] <= 0.0:
        return 0.0, 0.0  # behind the light
    t0, t1, t2, b0, b1, b2 = _frame_one(m0, m1, m2, v0, v1, v2, cos_v)
    # the centre (from the point) and the light's axes in the point's frame: each vertex is then a sum
    r0, r1, r2 = c0 - p0, c1 - p1, c2 - p2
    cx, cy, cz = r0 * t0 + r1 * t1 + r2 * t2, r0 * b0 + r1 * b1 + r2 * b2, r0 * m0 + r1 * m1 + r2 * m2
    x0, x1, x2 = terms[row, 9], terms[row, 10], terms[row, 11]
    xx, xy, xz = x0 * t0 + x1 * t1 + x2 * t2, x0 * b0 + x1 * b1 + x2 * b2, x0 * m0 + x1 * m1 + x2 * m2
    y0, y1, y2 = terms[row, 12], terms[row, 13], terms[row, 14]
    yx, yy, yz = y0 * t0 + y1 * t1 + y2 * t2, y0 * b0 + y1 * b1 + y2 * b2, y0 * m0 + y1 * m1 + y2 * m2
    count = int(terms[row, 21])
    for k in range(count):  # the light's vertices, from the point, in the point's frame
        x, y = outlines[row, k, 0], outlines[row, k, 1]
        shape[k, 0], shape[k, 1], shape[k, 2] = cx + x * xx + y * yx, cy + x * xy + y * yy, cz + x * xz + y * yz
    diffuse = _clipped_share_one(shape, count, poly)
    return diffuse, _lobe_share_one(shape, count, poly, table, cos_v, roughness)


def _disc_one(l0, l1, l2, tan_half, m0, m1, m2, v0, v1, v2, cos_v, roughness, table, shape, poly):
    """disc_shares of one point for a round light about the unit direction l with tan(half angle)."""
    a0, a1, a2 = _tangent_one(l0, l1, l2)
    o0, o1, o2 = l1 * a2 - l2 * a1, l2 * a0 - l0 * a2, l0 * a1 - l1 * a0
    t0, t1, t2, b0, b1, b2 = _frame_one(m0, m1, m2, v0, v1, v2, cos_v)
    a, b, c, d = _lookup_one(table, cos_v, roughness)
    # the disc's centre and axes in the point's frame and through the inverse matrix (both linear):
    # each vertex is then a sum
    lx, ly, lz = l0 * t0 + l1 * t1 + l2 * t2, l0 * b0 + l1 * b1 + l2 * b2, l0 * m0 + l1 * m1 + l2 * m2
    ax, ay, az = a0 * t0 + a1 * t1 + a2 * t2, a0 * b0 + a1 * b1 + a2 * b2, a0 * m0 + a1 * m1 + a2 * m2
    ox, oy, oz = o0 * t0 + o1 * t1 + o2 * t2, o0 * b0 + o1 * b1 + o2 * b2, o0 * m0 + o1 * m1 + o2 * m2
    lx, ly, lz = a * lx + b * lz, c * ly, d * lx + lz
    ax, ay, az = tan_half * (a * ax + b * az), tan_half * c * ay, tan_half * (d * ax + az)
    ox, oy, oz = tan_half * (a * ox + b * oz), tan_half * c * oy, tan_half * (d * ox + oz)
    for k in range(ROUND_SIDES):
        x, y = ROUND[k, 0], ROUND[k, 1]
        shape[k, 0], shape[k, 1], shape[k, 2] = lx + x * ax + y * ox, ly + x * ay + y * oy, lz + x * az + y * oz
    return _clipped_share_one(shape, ROUND_SIDES, poly)
