"""Relit splats in the SPLATWRIGHT engine's pictures: which splats the scene's lights shade (objects
with Relight on that carry a material), the meshes that shadow them, the stand-in that lets the
meshes' engine draw their shadows in turn, and the lit picture (core.relight's shading).

Relit and unlit splats render in ONE cloud (so they blend in depth order as before): when any
object is relit, every object's splats carry the material extras, an unlit object's as NaN
albedo and normals, the rows core.relight leaves with their own colour (core.material.carried), so
that joining keeps the extras (data.instances_cloud joins only those every cloud has).
"""

import warnings
from typing import NamedTuple

import numpy as np

from ...core import material
from .. import data
from ..data import RelightWarning
from .lights import is_relit, scene_lights, takes_in
from .scene import drawn_splats, linking_names, scene_splats, surface_triangles


def wants_relight(depsgraph):
    """Whether any splat object the depsgraph draws has Relight on."""
    return any(is_relit(i.obj) for i in data.splat_instances(depsgraph))


def scene_cloud(depsgraph, origin):
    """(cloud, lit, owners) of the depsgraph's splats (world shifted by -`origin`, see scene_splats):
    lit is an (N,) bool mask of the relit splats, or None when none is relit (the cloud is then as an
    unlit render reads it, and owners None); owners, (names, (N,) int index into names) the
    scene.linking_names of the object (and instancer) each splat comes from, for light linking."""
    from ...core.material import carried

    if not wants_relight(depsgraph):
        return scene_splats(depsgraph, origin), None, None
    instances, sizes = drawn_splats(depsgraph), {}

    def prepare(obj, cloud):
        sizes[obj.name] = len(cloud)
        return _marked(obj, cloud)

    cloud = scene_splats(depsgraph, origin, prepare=prepare, instances=instances)
    if cloud is None:
        return None, None, None
    lit = carried(cloud)
    if not lit.any():
        return cloud, None, None
    # the cloud joins the instances in their order, each with its object's splats
    keys = [linking_names(i.obj, i.instancer) for i in instances]
    position = {key: k for k, key in enumerate(dict.fromkeys(keys))}  # a dict: scenes of many instances
    index = np.repeat([position[key] for key in keys], [sizes[i.obj.name] for i in instances]).astype(np.int32)
    names = list(position)
    return cloud, lit, (names, index)


def linked_lights(depsgraph, origin, owners, meshes=None):
    """(lights, receivers, blockers, mesh_blockers): the scene's lights (lights.scene_lights) and
    their light and shadow linking as core.relight takes them, {light index: (N,) bool} the splats
    (of the objects `owners`, scene_cloud's) each light lights and the splats that shadow it, and
    {light index: [Surface]} the meshes (of `meshes`, occluders()') that shadow it, for the lights
    that leave an object out."""
    from ...core.mesh import Surface

    links = []
    found = scene_lights(depsgraph, origin, links)
    receiving, blocking = zip(*links) if links else ((), ())
    mesh_blockers = {}
    if meshes is not None and meshes.owners is not None:
        (surface,) = meshes.surfaces
        for k, taken in _linked(blocking, meshes.owners).items():
            mesh_blockers[k] = [Surface(surface.vertices, surface.faces[taken])] if taken.any() else []
    return found, _linked(receiving, owners), _linked(blocking, owners), mesh_blockers


def _linked(rules, owners):
    """{light index: (N,) bool} of the splats (or triangles) each rule (lights.linking_of's) takes
    in, for the rules that leave an object out; {} without owners ((names, (N,) index into names))."""
    if owners is None:
        return {}
    names, index = owners
    taken = _taken(rules, names)
    return {k: taken[index, k] for k in range(len(rules)) if not taken[:, k].all()}


def _taken(rules, names):
    """(len(names), len(rules)) bool: whether each rule (lights.linking_of's) takes in each object."""
    return np.array([[takes_in(rule, name) for rule in rules] for name in names], bool).reshape(len(names), len(rules))


def _marked(obj, cloud):
    """`cloud` of object `obj` with its material, all four parts (NaN albedo and normals where the
    object is not relit, so core.relight keeps its colours)."""
    relit = is_relit(obj)
    if relit and not material.has_material(cloud):  # once per render: objects are read once
        missing = [part for part, keys in (("albedo", [material.ALBEDO]), ("normals", material.NORMALS)) if
                   not all(key in cloud.extras for key in keys)]  # fmt: skip
        warnings.warn(
            f"{obj.name}: Relight is on but its splats carry no {' and no '.join(missing)} (a material needs "
            "albedo and normals): rendered unlit; convert the mesh with Material for Relighting, or estimate "
            "normals",
            RelightWarning,
            stacklevel=2,
        )
        relit = False
    n = len(cloud)
    extras = {material.ROUGHNESS: material.roughness(cloud), material.METALLIC: material.metallic(cloud)}
    if not relit:
        extras.update({material.ALBEDO: np.full((n, 3), np.nan), **{k: np.full(n, np.nan) for k in material.NORMALS}})
    extras = {k: np.asarray(v, np.float32) for k, v in extras.items()}
    return cloud.replace(extras={**cloud.extras, **extras})


class Occluders(NamedTuple):
    """The scene's surfaces that shadow the relit splats (occluders()): `surfaces`, one
    core.mesh.Surface in the engine's frame in a list (empty when there are none), and `owners`,
    (names, (T,) int index into them) the scene.linking_names of each triangle's object, for shadow
    linking."""

    surfaces: list
    owners: tuple | None = None


def occluders(depsgraph, origin):
    """The scene's surfaces that shadow rays see (not splats), as Occluders in the frame shifted by
    -`origin`: what shadows the relit splats."""
    from ...core.mesh import Surface

    owners = []
    corners, _ = surface_triangles(depsgraph, shadow_casters_only=True, owners=owners)
    if not len(corners):
        return Occluders([])
    vertices = corners.reshape(-1, 3) - np.asarray(origin, np.float64)
    names = [name for name, _ in owners]
    index = np.repeat(np.arange(len(owners)), [count for _, count in owners])
    return Occluders([Surface(vertices, np.arange(len(vertices)).reshape(-1, 3))], (names, index))


class StandIn(NamedTuple):
    """The relit splats' shadow stand-in for the meshes' engine (shadow_casters()): `vertices` (V,3)
    float32 world space, `faces` (F,3) int32, `groups` (F,) int32 the part each face belongs to, and
    `links`, [(blocker collection name, [state per part])] how each part enters each light's shadow
    linking: "INCLUDE" or "EXCLUDE", None where it is left out of the collection (it then blocks as
    the collection's other unlisted objects do)."""

    vertices: np.ndarray
    faces: np.ndarray
    groups: np.ndarray
    links: list


def shadow_casters(cloud, lit, origin, owners=None, collections=(), budget=None):
    """The relit splats' shadow stand-in (core.shadow_casters) as a StandIn, None when nothing is
    relit. With `owners` (scene_cloud's) and `collections` (lights.blocker_collections'), the splats
    fall into parts by the blocker collections that take them in, so that each light's shadow
    linking holds for them as for their objects. Its memory in the meshes' Blender is held to
    `budget` bytes (default: core.memory.default_budget()): past the finest shape's, each splat gets
    the plain octahedron, and past that the meshes get no shadow from the splats (warned)."""
    from ...core.memory import default_budget, human_bytes
    from ...core.shadow_casters import BYTES_PER_TRIANGLE, SHAPES, casting, ellipsoids, shape_within

    if cloud is None or lit is None:
        return None
    part = cloud[lit]
    casts = casting(part)
    count = int(casts.sum())
    budget = default_budget() if budget is None else budget
    shape = shape_within(count, budget)
    if shape is not SHAPES[0]:
        need = count * len(SHAPES[0][1]) * BYTES_PER_TRIANGLE
        warnings.warn(
            f"the shadow stand-in of {count} relit splats would take {human_bytes(need)}, past the memory "
            f"budget ({human_bytes(budget)}): "
            + ("coarser ellipsoids cast their shadows" if shape is not None else "meshes get no shadow from them"),
            RelightWarning,
            stacklevel=2,
        )
    if shape is None:
        return None
    vertices, faces = ellipsoids(part, shape=shape)
    parts, links = _stand_in_parts(owners, lit, collections)
    groups = np.repeat(parts[casts], len(shape[1])).astype(np.int32)  # ellipsoids' faces: a run per splat
    return StandIn(vertices + np.asarray(origin, np.float32), faces, groups, links)


def _stand_in_parts(owners, lit, collections):
    """((M,) int the part of each relit splat, [(collection name, [state per part])]): splats whose
    objects the blocker collections take in alike share a part (one part without collections)."""
    count = int(lit.sum())
    if owners is None or not collections:
        return np.zeros(count, np.int64), []
    names, index = owners
    taken = _taken([rule for _, rule in collections], names)
    kinds, per_object = np.unique(taken, axis=0, return_inverse=True)
    links = []
    for k, (collection, (included, _)) in enumerate(collections):
        # Set INCLUDE only where the collection includes objects already: one included object makes
        # Blender leave out every object not included. A part taken in by a collection of
        # exclusions only blocks unlisted, as the objects it stands for.
        states = [("INCLUDE" if included else None) if kind[k] else "EXCLUDE" for kind in kinds]
        links.append((collection, states))
    return per_object.reshape(-1)[index[lit]], links


# the lit render ------------------------------------------------------------------------------------

# the passes a relit render adds (with the view layer's Splats and Meshes Passes on): name, channels,
# channel letters, kind, as RenderEngine.register_pass takes them
PASSES = (("Diffuse", 3, "RGB", "COLOR"), ("Specular", 3, "RGB", "COLOR"), ("Shadow", 1, "X", "VALUE"))


def any_relit(scene):
    """Whether any splat object of `scene` has Relight on (then the render registers PASSES)."""
    return any(is_relit(obj) for obj in scene.objects if data.is_splat_object(obj))


def lit_passes(result):
    """{pass name: (H,W,C) image} of a core.relight.LitRender made with passes (see PASSES)."""
    return {"Diffuse": result.diffuse, "Specular": result.specular, "Shadow": result.shadow}
