"""Splats as a mesh that casts their shadow in a ray tracer (Cycles renders the meshes of a SPLATWRIGHT
render, and a mesh floor gets the splats' shadow from this stand-in, visible to shadow rays only).

Each splat becomes a closed ellipsoid, a subdivided octahedron turned and stretched by the splat's
rotation and scales, out to where its Gaussian's alpha falls to ALPHA: o exp(-r^2 / 2) = ALPHA at
r = sqrt(2 ln(o / ALPHA)) standard deviations. A ray tracer's surface is all or nothing, so a splat
blocks light where a compositor would call it at least that opaque (Cycles' own alpha threshold for
the Depth pass is 0.5, the same rule); splats fainter than ALPHA everywhere cast nothing. A surface
made of flat splats becomes a shell of flat overlapping ellipsoids, as thick as the splats are.
"""

import numpy as np

from .geometry import quaternions_to_matrices
from .splats import SplatCloud

ALPHA = 0.5  # the alpha a splat's stand-in surface sits at

# A unit octahedron subdivided once: 18 vertices, 32 triangles wound outwards (a rounder shell than
# the octahedron's 8 faces at 4x the triangles; shadows of splats a few texels wide need no more).
_OCTAHEDRON = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
_OCTAHEDRON_FACES = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int64
)


def _subdivided():
    """The octahedron with every edge split at its midpoint (pushed onto the unit sphere)."""
    vertices, faces, midpoint = list(_OCTAHEDRON), [], {}

    def middle(a, b):
        key = (min(a, b), max(a, b))
        if key not in midpoint:
            v = vertices[a] + vertices[b]
            midpoint[key] = len(vertices)
            vertices.append(v / np.linalg.norm(v))
        return midpoint[key]

    for a, b, c in _OCTAHEDRON_FACES:
        ab, bc, ca = middle(a, b), middle(b, c), middle(c, a)
        faces += [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
    return np.array(vertices), np.array(faces, np.int64)


UNIT_VERTICES, UNIT_FACES = _subdivided()
# The stand-in's shapes, finest first: the subdivided octahedron, then the octahedron itself.
SHAPES = ((UNIT_VERTICES, UNIT_FACES), (_OCTAHEDRON, _OCTAHEDRON_FACES))
# Memory a stand-in triangle takes: Blender 5.3's mesh of 6.4M such triangles and Cycles' render of it
# grew the child's peak by 239 bytes a triangle; these arrays and their file add about 20.
BYTES_PER_TRIANGLE = 260


def shape_within(count: int, budget: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The finest of SHAPES whose stand-in of `count` splats takes at most `budget` bytes
    (BYTES_PER_TRIANGLE each triangle), or None when not even the coarsest does."""
    return next((shape for shape in SHAPES if count * len(shape[1]) * BYTES_PER_TRIANGLE <= budget), None)


def reach(opacities: np.ndarray, alpha: float = ALPHA) -> np.ndarray:
    """(N,) the radius in standard deviations where each splat's alpha falls to `alpha`; 0 where the
    splat never reaches it."""
    opacities = np.asarray(opacities, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = 2.0 * np.log(np.maximum(opacities, 1e-300) / alpha)
    return np.sqrt(np.clip(r2, 0.0, None))


def casting(cloud: SplatCloud, alpha: float = ALPHA) -> np.ndarray:
    """(N,) bool: the splats with a stand-in (finite, and somewhere at least `alpha` opaque)."""
    return (reach(cloud.opacities, alpha) > 0) & cloud.finite_mask()


def ellipsoids(cloud: SplatCloud, alpha: float = ALPHA, shape=None) -> tuple[np.ndarray, np.ndarray]:
    """The stand-in mesh of `cloud`: vertices (V,3) float32 in the cloud's frame and triangles (F,3)
    int32, one closed ellipsoid per splat whose opacity exceeds `alpha` (the others are left out),
    each the unit `shape` (vertices, faces; default the finest of SHAPES) stretched and turned."""
    unit_vertices, unit_faces = SHAPES[0] if shape is None else shape
    radius = reach(cloud.opacities, alpha)
    keep = np.flatnonzero(casting(cloud, alpha))
    if not len(keep):
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    part = cloud[keep]
    rotations = quaternions_to_matrices(part.unit_rotations)  # (K,3,3)
    axes = rotations * (part.scales * radius[keep][:, None])[:, None, :]  # columns scaled by the reach
    vertices = np.einsum("kij,vj->kvi", axes, unit_vertices) + part.positions.astype(np.float64)[:, None, :]
    faces = unit_faces[None] + (np.arange(len(keep)) * len(unit_vertices))[:, None, None]
    return vertices.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3).astype(np.int32)
