"""The world light's occlusion: how much of a uniform world each splat sees (ambient occlusion).

A uniform world of radiance W gives a diffuse surface W times the cosine-weighted share of the sky
it sees. That share is estimated from `directions` sun shadow maps (core.shadows) in directions
spread evenly over the sphere (a Fibonacci spiral), each sun three quarters as wide as its share
of the sphere so that its soft shadow (core.shadows' PCSS) blurs what one ray would see
(CONE_SHARE):

    V(n) = sum_k max(n.d_k, 0) vis_k / sum_k max(n.d_k, 0)

Unoccluded, V is 1 whatever the count, so a white furnace stays white. Splats are shaded two-sided
(core.shading flips a normal towards the eye), so both sides are kept: V of the splat's normal and
of its opposite. Like the lights' shadows they do not depend on the camera.

A glossy surface reflects the world from around its mirror direction, which depends on the eye: the
result keeps each direction's visibility too, from which core.shading weighs the specular lobe's
own share (shading.lobe_sky); the cosine-weighted V would light a metal's concave parts with the
world they reflect themselves in (Suzanne's eye sockets in Cycles are dark, the metal's reflection
of the head itself, while V lit them at 0.7 of the open sky).

Light that the surroundings reflect back (the floor's bounce under a sphere) is not modelled: an
occluded direction counts as black.
"""

from collections.abc import Callable
from typing import Annotated

import numpy as np

from . import material, shadows
from .lights import Light, cone_angle, sphere_directions
from .render import Shapes
from .splats import SplatCloud
from .steps import part_progress

DIRECTIONS = 24  # sun maps over the sphere, each standing for a cone of 24 degrees' half angle
# Each sun is three quarters as wide as its cone, and each tap of its soft shadow is tested against
# the receiver's own tangent plane (core.shadows' receiver_plane): without that the filter's wide
# disc of taps on a surface tilted to the sun finds the surface itself in front of the receiver
# (the decal box's faces saw 0.95 of the world, 0.88 at the full width). Against the closed form
# of a mesh ball over a splat floor with 24 directions (mean |error|, worst, mean error): 0.011,
# 0.061, +0.001 at three quarters; 0.011, 0.080, +0.008 at the full width (the cones blur too
# much); 0.017, 0.087, -0.005 at a half (each direction's shadow shows as a blob); 16 directions
# at three quarters 0.016, 0.108, +0.008. An open plane sees 0.99 of the world, the convex box 0.994.
CONE_SHARE = 0.75
RESOLUTION = 256  # texels a side of each map: the cones' soft shadows need no finer ones


def world_visibility(
    cloud: SplatCloud,
    *,
    occluders=None,
    directions: int = DIRECTIONS,
    resolution: int = RESOLUTION,
    threads: int | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    shapes: Shapes | None = None,
) -> Annotated[np.ndarray, "(N, 2 + K)"]:
    """(N, 2 + K) float32 in [0, 1], K = `directions`: the share of a uniform world each splat sees on
    the side its normal points to (column 0) and on the other side (column 1), past the whole cloud
    and `occluders` (core.mesh.Surface meshes), then its visibility towards each of the K directions
    of core.lights.sphere_directions(K) (columns 2..); 1 for splats without a normal.
    progress(done, total, "world occlusion") follows the maps; shapes as core.shadows.visibility's."""
    if directions < 1:
        raise ValueError(f"the world's occlusion needs at least 1 direction, got {directions}")
    n = len(cloud)
    rows = material.carried(cloud)
    if not rows.any():
        return np.ones((n, 2 + directions), np.float32)
    if shapes is None:
        shapes = Shapes(cloud, threads)  # once for every map
    normals = material.normals(cloud)[rows]
    seen, weight = np.zeros((len(normals), 2)), np.zeros((len(normals), 2))
    out = np.ones((n, 2 + directions), np.float32)
    angle = cone_angle(directions) * CONE_SHARE
    for k, towards in enumerate(sphere_directions(directions)):  # a loop over directions
        sun = Light("sun", direction=-towards, angle=angle)
        vis = shadows.visibility(
            cloud,
            sun,
            occluders=occluders,
            resolution=resolution,
            receiver_plane=True,
            threads=threads,
            progress=part_progress(progress, k, directions, "world occlusion"),
            shapes=shapes,
        )[rows]
        cos = normals @ towards
        sides = np.stack([np.maximum(cos, 0.0), np.maximum(-cos, 0.0)], axis=1)
        seen += sides * vis[:, None]
        out[rows, 2 + k] = vis
        weight += sides
        if progress is not None:
            progress(k + 1, directions, "world occlusion")  # a map that drew nothing reports no end
    out[rows, :2] = np.where(weight > 0.0, seen / np.where(weight > 0.0, weight, 1.0), 1.0)
    return out
