"""The scene as both of the engine's pictures see it, the final render (engine.py) and the Rendered
viewport (viewport.py): its splats in one cloud, the world's colour, the engine that draws the
meshes, and the conversion of a display-sRGB picture to Blender's scene-linear."""

import dataclasses
from typing import NamedTuple

import bpy
import numpy as np
from mathutils import Euler

from ...core import environment
from ...core.color import srgb_to_linear
from .. import data

MESH_ENGINE = "splatwright_mesh_engine"  # Scene property: what renders everything but the splats


def mesh_engine(scene):
    return getattr(scene, MESH_ENGINE, "NONE")


def drawn_splats(depsgraph):
    """The data.SplatInstance of every splat object and instance the depsgraph renders: instances
    whose transform collapses them (zero scale) show nothing."""
    return [
        i
        for i in data.splat_instances(depsgraph)
        if (i.instancer is not None or not i.obj.hide_render) and abs(np.linalg.det(i.matrix[:3, :3])) > 0
    ]


def scene_splats(depsgraph, origin, prepare=None, instances=None):
    """Every splat object and instance the depsgraph renders (`instances`, drawn_splats' when given)
    as one cloud, in their order, in world space shifted by -`origin` (None if there are none);
    `prepare(obj, cloud) -> cloud` is applied to each object's splats first (see
    data.instances_cloud)."""
    shift = np.eye(4)
    shift[:3, 3] = -origin
    drawn = [(i.obj, i.matrix) for i in (drawn_splats(depsgraph) if instances is None else instances)]
    return data.instances_cloud(depsgraph, drawn, shift, prepare) if drawn else None


def linking_names(obj, instancer=None):
    """The names by which light and shadow linking may take in object `obj`: its own and, for an
    instance, its instancer's (Cycles takes an instance in where either is listed)."""
    return (obj.name,) if instancer is None else (obj.name, instancer.name)


SURFACE_TYPES = {"MESH", "CURVE", "SURFACE", "FONT", "META"}  # what to_mesh() turns into triangles


def surface_triangles(depsgraph, shadow_casters_only=False, owners=None):
    """Every visible surface that is not a splat object as world-space triangles (T,3,3) with the
    viewport colour (T,3) of each face's material (the object's colour without one); with
    `shadow_casters_only`, only objects that shadow rays see (Object > Visibility > Shadow).
    `owners`, a list if given, receives (linking_names, triangle count) for each object, in order."""
    corners, colors = [], []
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type not in SURFACE_TYPES or data.is_splat_object(obj.original):
            continue
        if shadow_casters_only and not getattr(obj, "visible_shadow", True):
            continue
        mesh = obj.to_mesh()
        try:
            if mesh is None or not len(mesh.polygons):
                continue
            mesh.calc_loop_triangles()
            n = len(mesh.loop_triangles)
            co = np.empty(len(mesh.vertices) * 3)
            mesh.vertices.foreach_get("co", co)
            tris = np.empty(n * 3, np.int64)
            mesh.loop_triangles.foreach_get("vertices", tris)
            slots = np.empty(n, np.int64)
            mesh.loop_triangles.foreach_get("material_index", slots)
            palette = [
                tuple(m.diffuse_color[:3]) if m is not None else tuple(obj.color[:3])
                for m in (obj.material_slots[i].material for i in range(len(obj.material_slots)))
            ]
            palette = np.array(palette or [tuple(obj.color[:3])], np.float64)
            matrix = np.array(inst.matrix_world, np.float64)
            world = co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
            corners.append(world[tris.reshape(-1, 3)])
            colors.append(palette[np.minimum(slots, len(palette) - 1)])
            if owners is not None:
                owners.append((linking_names(obj, data.instancer_of(inst)), n))
        finally:
            obj.to_mesh_clear()
    if not corners:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    return np.concatenate(corners), np.concatenate(colors)


def world_color(scene):
    """The world's background colour (scene-linear RGB): colour x strength of the Background node
    feeding the world output, an equirectangular Environment Texture's mean radiance standing for its
    colour (environment_map); the world's plain colour when it uses no nodes or other nodes drive
    the background; black without a world."""
    return world_background(scene)[0]


class Background(NamedTuple):
    """The world's light as world_background reads it: its colour (scene-linear RGB), a note or
    None, and an environment map's SH coefficients (core.environment) and sun (a core.lights sun
    Light), or None."""

    color: np.ndarray
    note: str | None = None
    environment: np.ndarray | None = None
    sun: object = None


def world_background(scene):
    """The world's Background (see Background): its colour x strength; an equirectangular
    Environment Texture on its Color gives the map's coefficients and sun (environment_map) times
    the Strength, turned as its Vector input turns the lookup (map_lookup), the colour then its
    mean; the note says how the world's light is read where nodes drive the Background (the map's
    bands and sun, its mean where nodes remap its directions otherwise, or the world's plain colour
    where the nodes are not read), for the engine to report; None where the colour is the
    Background's own."""
    world = scene.world
    if world is None:
        return Background(np.zeros(3))
    uses_nodes = world.node_tree is not None and (bpy.app.version >= (5, 0, 0) or world.use_nodes)
    node = _background_node(world.node_tree) if uses_nodes else None
    plain = np.array(world.color[:3], dtype=np.float64)
    if node is None:
        return Background(plain)
    color, strength = node.inputs["Color"], node.inputs["Strength"]
    if strength.is_linked:
        return Background(plain, _unread(strength.links[0].from_node.name))
    if color.is_linked:
        source = color.links[0].from_node
        found = environment_map(source)
        if found is None:
            return Background(plain, _unread(source.name))
        (coefficients, sun), scale = found, strength.default_value
        coefficients = coefficients * scale
        sun = None if sun is None else dataclasses.replace(sun, power=sun.power * scale)
        lookup = map_lookup(source)
        if lookup is None:  # remapped by nodes not read: its directions are not, its mean is (the sun's too)
            whole = coefficients if sun is None else environment.with_sun(coefficients, sun)
            return Background(environment.mean(whole), _remapped(source.name))
        coefficients = environment.rotated(coefficients, lookup.T)  # its light at d: the map's at lookup d
        if sun is not None:  # the map's sun seen in direction d where lookup d is its own
            sun = dataclasses.replace(sun, direction=lookup.T @ sun.direction)
        return Background(environment.mean(coefficients), _bands(source.name, sun), coefficients, sun)
    return Background(np.array(color.default_value[:3], dtype=np.float64) * strength.default_value)


def _bands(name, sun):
    if sun is not None:
        return (
            f"the world's Environment Texture '{name}' lights relit splats by its broad light (its spherical "
            "harmonics to band 2) and its sun, a sun light of its own with shadows and highlights: the map's other "
            "sharp features cast no shadows and make no sharp highlights"
        )
    return (
        f"the world's Environment Texture '{name}' lights relit splats by its broad light (its spherical "
        "harmonics to band 2): the map's sharp features cast no shadows and make no sharp highlights"
    )


def _remapped(name):
    return (
        f"the world's Environment Texture '{name}' lights relit splats by its mean radiance, uniform from every "
        "direction (the nodes on its Vector input are not read: a Mapping node's rotation of the Generated "
        "coordinates is)"
    )


def _unread(name):
    return (
        f"the world's Background is driven by the node '{name}', which relighting does not read: relit "
        "splats are lit by the world's Viewport Display colour instead, uniform from every direction"
    )


LINEAR_SPACES = {"Linear", "Linear Rec.709", "Linear CIE-XYZ E", "Non-Color", "Raw"}


def map_lookup(texture):
    """(3, 3) M: the Environment Texture `texture` shows in direction d its map's radiance at M d: the
    identity where its Vector input is the world's own direction (unlinked, or the Texture
    Coordinate's Generated), a Mapping node's rotation of that direction (Point and Vector types: M
    = R; Texture: M = R^T; its scale uniform, no location on a Point or Texture), else None (other
    nodes, or inputs they drive, are not read)."""
    vector = texture.inputs["Vector"]
    if not vector.is_linked or _generated(vector):
        return np.eye(3)
    node = vector.links[0].from_node
    if node.bl_idname != "ShaderNodeMapping" or node.vector_type not in ("POINT", "TEXTURE", "VECTOR"):
        return None
    inputs = [node.inputs[name] for name in ("Location", "Rotation", "Scale")]
    if not _generated(node.inputs["Vector"]) or any(socket.is_linked for socket in inputs):
        return None
    location, rotation, scale = (np.array(socket.default_value[:3], np.float64) for socket in inputs)
    moved = node.vector_type != "VECTOR" and location.any()  # a Vector mapping leaves location out
    if moved or not (scale[0] > 0 and (scale == scale[0]).all()):
        return None
    turn = np.array(Euler(rotation, "XYZ").to_matrix(), np.float64)
    return turn.T if node.vector_type == "TEXTURE" else turn


def _generated(socket):
    """Whether `socket` is fed the Texture Coordinate node's Generated output: in a world, the
    direction looked along."""
    if not socket.is_linked:
        return False
    link = socket.links[0]
    return link.from_node.bl_idname == "ShaderNodeTexCoord" and link.from_socket.identifier == "Generated"


def environment_map(node):
    """(coefficients (9, 3), sun or None) of the scene-linear radiance of an equirectangular
    Environment Texture node's image (core.environment.light_of: a sun that stands out of the map
    becomes a sun light), or None for another node, another projection, no image, colours in a
    space other than sRGB or linear ones (LINEAR_SPACES), or pixels past the memory budget
    (core.memory.default_budget)."""
    image = getattr(node, "image", None)
    if node.bl_idname != "ShaderNodeTexEnvironment" or node.projection != "EQUIRECTANGULAR" or image is None:
        return None
    space = image.colorspace_settings.name
    width, height = image.size
    if (space != "sRGB" and space not in LINEAR_SPACES) or not width or not height:
        return None
    # An image file's light is kept: the viewport asks on every scene update, and reading a 4k map
    # takes 0.2-0.4 s
    key = (image.name, image.filepath_raw, width, height, space) if image.filepath_raw and not image.is_dirty else None
    if key is not None and key in _MAPS:
        return _MAPS[key]
    found = _equirect_map(image, width, height, space)
    if key is not None:
        _MAPS.clear()  # one environment at a time
        _MAPS[key] = found
    return found


_MAPS: dict = {}


def _equirect_map(image, width, height, space):
    """environment_map of `image`'s pixels, or None where they would not fit the memory budget."""
    from ...core.memory import default_budget

    if width * height * image.channels * 4 > default_budget():
        return None
    pixels = np.empty(width * height * image.channels, np.float32)
    image.pixels.foreach_get(pixels)  # rows from the bottom (latitude -90 degrees) up
    rows = pixels.reshape(height, width, image.channels)[..., :3]
    if space == "sRGB":  # decoded in place, band by band: no second copy of the map
        for lo in range(0, height, environment.ROWS):
            rows[lo : lo + environment.ROWS] = srgb_to_linear(rows[lo : lo + environment.ROWS], np.float32)
    return environment.light_of(rows)


def _background_node(tree):
    output = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputWorld" and n.is_active_output), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return None
    node = output.inputs["Surface"].links[0].from_node
    return node if node.bl_idname == "ShaderNodeBackground" else None


def to_scene_linear(color, alpha):
    """Display-sRGB colour premultiplied by `alpha` -> premultiplied scene-linear RGBA (float32). The
    curve is applied to the straight colour, so a transparent film saves exactly the core image's
    colours."""
    alpha = np.asarray(alpha, dtype=np.float32)[..., None]
    straight = np.asarray(color, dtype=np.float32) / np.where(alpha > 0, alpha, np.float32(1))
    rgba = np.empty(alpha.shape[:-1] + (4,), dtype=np.float32)
    rgba[..., :3] = srgb_to_linear(straight, np.float32) * alpha
    rgba[..., 3] = alpha[..., 0]
    return rgba


def textured_world(scene):
    """Whether the world's background is more than one colour (a texture or nodes drive it): then
    the mesh layer renders it, else world_color() stands for it."""
    world = scene.world
    if world is None or world.node_tree is None or (bpy.app.version < (5, 0, 0) and not world.use_nodes):
        return False
    node = _background_node(world.node_tree)
    return node is None or node.inputs["Color"].is_linked or node.inputs["Strength"].is_linked
