"""Relit splats in the SPLATWRIGHT engine's pictures: which splats the scene's lights shade (objects
with Relight on that carry a material), the meshes that shadow them, and the stand-in that lets the
meshes' engine draw their shadows in turn.

Relit and unlit splats render in ONE cloud (so they blend in depth order as before): when any
object is relit, every object's splats get the material extras (unlit ones a placeholder) and the
extra LIT, 1 where a splat is shaded, so that joining keeps them (data.instances_cloud joins only
the extras every cloud has).
"""

import warnings
from typing import NamedTuple

import numpy as np

from ...core import material
from .. import data
from .lights import is_relit
from .scene import scene_splats, surface_triangles

LIT = "splatwright_lit"  # extra: 1 where the splat is shaded with the scene's lights, else 0


class RelightWarning(UserWarning):
    """A relit object that cannot be shaded (the engine reports it)."""


def wants_relight(depsgraph):
    """Whether any splat object the depsgraph draws has Relight on."""
    return any(is_relit(i.obj) for i in data.splat_instances(depsgraph))


def scene_cloud(depsgraph, origin):
    """(cloud, lit) of the depsgraph's splats (world shifted by -`origin`, see scene_splats): lit is an
    (N,) bool mask of the relit splats, or None when none is relit (the cloud is then as an unlit
    render reads it)."""
    if not wants_relight(depsgraph):
        return scene_splats(depsgraph, origin), None
    cloud = scene_splats(depsgraph, origin, prepare=_marked)
    if cloud is None:
        return None, None
    lit = cloud.extras.get(LIT, np.zeros(len(cloud))).astype(bool)
    return cloud, (lit if lit.any() else None)


def _marked(obj, cloud):
    """`cloud` of object `obj` with its material (a placeholder where it is not relit) and LIT."""
    relit = is_relit(obj)
    if relit and not material.has_material(cloud):  # once per render: objects are read once
        warnings.warn(
            f"{obj.name}: Relight is on but its splats carry no material (albedo and normals): rendered "
            "unlit; convert the mesh with Material for Relighting, or estimate normals",
            RelightWarning,
            stacklevel=2,
        )
        relit = False
    n = len(cloud)
    if relit:
        extras = {material.ROUGHNESS: material.roughness(cloud), material.METALLIC: material.metallic(cloud)}
    else:
        extras = {
            material.ALBEDO: np.zeros((n, 3)),
            **{k: np.zeros(n) for k in material.NORMALS[:2]},
            material.NORMALS[2]: np.ones(n),
            material.ROUGHNESS: np.full(n, material.DEFAULT_ROUGHNESS),
            material.METALLIC: np.full(n, material.DEFAULT_METALLIC),
        }
    extras = {k: np.asarray(v, np.float32) for k, v in extras.items()}
    return cloud.replace(extras={**cloud.extras, **extras, LIT: np.full(n, relit, np.uint8)})


def occluders(depsgraph, origin):
    """The scene's surfaces that shadow rays see (not splats), as one core.mesh.Surface in the frame
    shifted by -`origin`, in a list (empty when there are none): what shadows the relit splats."""
    from ...core.mesh import Surface

    corners, _ = surface_triangles(depsgraph, shadow_casters_only=True)
    if not len(corners):
        return []
    vertices = corners.reshape(-1, 3) - np.asarray(origin, np.float64)
    return [Surface(vertices, np.arange(len(vertices)).reshape(-1, 3))]


def shadow_casters(cloud, lit, origin):
    """(vertices, faces) in world space of the relit splats' shadow stand-in (core.shadow_casters),
    for the meshes' engine; None when nothing is relit."""
    from ...core.shadow_casters import ellipsoids

    if cloud is None or lit is None:
        return None
    vertices, faces = ellipsoids(cloud[lit])
    return vertices + np.asarray(origin, np.float32), faces


# the lit render ------------------------------------------------------------------------------------

# the passes a relit render adds (with the view layer's Splats and Meshes Passes on): name, channels,
# channel letters, kind, as RenderEngine.register_pass takes them
PASSES = (("Diffuse", 3, "RGB", "COLOR"), ("Specular", 3, "RGB", "COLOR"), ("Shadow", 1, "X", "VALUE"))


def any_relit(scene):
    """Whether any splat object of `scene` has Relight on (then the render registers PASSES)."""
    return any(is_relit(obj) for obj in scene.objects if data.is_splat_object(obj))


SHADOW_RESOLUTION = 512  # texels a side of each shadow-map view (core.shadows)


def visibilities(cloud, lights, occluders=(), resolution=SHADOW_RESOLUTION, threads=None):
    """{light index: (N,) visibility} of every light that casts shadows: what reaches each splat past
    the whole cloud (relit or not) and the `occluders` meshes (core.shadows.visibility)."""
    from ...core.shadows import visibility

    return {
        i: visibility(cloud, light, occluders=list(occluders), resolution=resolution, threads=threads)
        for i, light in enumerate(lights)
        if light.cast_shadow
    }


def shaded(cloud, lit, eye, lights, world, visible=None):
    """(cloud, shading): `cloud` with its `lit` splats' colour replaced by the radiance the lights and
    world send towards `eye` (a position or core Camera), as display sRGB in the DC coefficient (the
    higher SH bands of those splats zeroed), and the core.shading.Shading of the lit splats.
    `visible` is visibilities()'s result (None: no shadows)."""
    from ...core.color import linear_to_srgb
    from ...core.sh import rgb_to_dc
    from ...core.shading import shade

    part = cloud[lit]
    shading = shade(part, eye, lights, world, {i: v[lit] for i, v in (visible or {}).items()})
    sh = cloud.sh.copy()
    sh[lit] = 0.0
    radiance = np.maximum(shading.diffuse.astype(np.float64) + shading.specular, 0.0)
    sh[lit, 0] = rgb_to_dc(linear_to_srgb(radiance))
    return cloud.replace(sh=sh), shading


class LitScene(NamedTuple):
    """A relit render: image, the core RenderResult (display sRGB, as core.render gives it); diffuse,
    specular (H,W,3) and shadow (H,W,1) scene-linear premultiplied passes, or None."""

    image: object
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None
    shadow: np.ndarray | None = None


def render_scene(cloud, lit, camera, lights, world, *, occluders, background, layer, passes, progress=None):
    """`cloud` with its `lit` splats shaded by `lights` and `world` (the others keep their own colour),
    shadowed by the whole cloud and by `occluders`, rendered once by core.render with `background`
    and `layer`; with `passes`, also the lit splats' Diffuse, Specular and Shadow seen through the same
    blending (one more render each, the layer's colour black so only the splats add)."""
    from ...core.render import Layer, render

    visible = visibilities(cloud, lights, occluders)
    coloured, shading = shaded(cloud, lit, camera, lights, world, visible)
    image = render(coloured, camera, background=background, layer=layer, progress=progress)
    if not passes:
        return LitScene(image)
    dark = None if layer is None else Layer(np.zeros_like(layer.color), layer.alpha, layer.depth)
    values = {
        "diffuse": shading.diffuse,
        "specular": shading.specular,
        "shadow": np.repeat(shading.shadow[:, None], 3, 1),
    }
    out = {}
    for name, value in values.items():
        out[name] = _splat_image(cloud, lit, value, camera, dark)
    out["shadow"] = out["shadow"][..., :1]
    return LitScene(image, **out)


def _splat_image(cloud, lit, value, camera, layer):
    """(H,W,3) per-splat `value` (M,3) of the lit splats (0 for the others) blended as their colour."""
    from ...core.render import render
    from ...core.sh import rgb_to_dc

    sh = np.zeros((len(cloud), 1, 3))
    sh[:, 0] = rgb_to_dc(0.0)
    sh[lit, 0] = rgb_to_dc(np.asarray(value, np.float64))
    return render(cloud.replace(sh=sh), camera, background=None, layer=layer).color


def lit_passes(result):
    """{pass name: (H,W,C) image} of a LitRender made with passes (see PASSES)."""
    return {"Diffuse": result.diffuse, "Specular": result.specular, "Shadow": result.shadow}
