"""The world's light for relit splats where its nodes are more than scene.world_background reads (a
Sky Texture, textures mixed, a Mapping with a location): Cycles renders the world alone in the
child Blender (mesh_layer.py; child_blender.py's "world" request) and core.environment reads the
picture as it reads an Environment Texture's image.

- A panorama, PANORAMA pixels in an Environment Texture's layout, SAMPLES samples a pixel each
  the mean over its own area: its broad light (spherical harmonics to band 2) and, where one
  stands out of it, its sun (core.environment.light_of).
- A sky's sun disc (a Sky Texture of a model with one, its disc on) is a fraction of a panorama
  pixel, whose few samples measure its light to tens of percent or miss it: the panorama is rendered
  with the discs off, and a close view of the sun, SUN_VIEW pixels a side with the discs on,
  measures it as a sun light (core.environment.sun_in_view: the view less the panorama's light
  there). The view looks where the node puts the sun (its elevation; its rotation turning it from
  +Y towards +X, measured in Cycles), AIMED disc radii wide; where nodes drive the node's Vector
  input (the disc models leave it unavailable in every Blender tested), or the view shows no sun
  there, the panorama is rendered once more with the discs on, with enough samples that SUN_HITS
  of them are expected on the disc, and the view looks at the brightest pixel of the difference.

Read as the camera sees the world: a world whose nodes show the camera something else than they
light with (Light Path's Is Camera Ray) is read as the camera sees it.
"""

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ...core import environment
from ...core.camera import Camera
from ...io.exr_plain import read_plain_exr
from .scene import Background

PANORAMA = (128, 64)  # pixels: 2.8 degrees each, ten times finer than band 2's features
SAMPLES = 16  # a pixel, in the panorama and the sun's close view
# The panorama with the discs on: samples enough that this many are expected on the smallest disc
# (none with a chance of e^-12), within what a second of Cycles renders (128 x 64 pixels, 2 cores:
# 16 samples 0.2 s, 256 0.4-0.5 s, 1024 1.2-1.5 s)
SUN_HITS = 12.0
LIT_SAMPLES = (16, 1024)
SUN_VIEW = 96  # pixels a side of the close view of a sky's sun
SUN_SKIES = {"NISHITA", "SINGLE_SCATTERING", "MULTIPLE_SCATTERING"}  # the sky models with a sun disc
# The close view's half-width: where the node puts the sun, this many disc radii and AIM_SLACK; found
# in the panorama, whose brightest pixel's centre is within its half-diagonal of the sun's edge, this
# many of those plus the disc's radius (sun_size / 2) with room to spare
AIMED = 2.0
AIM_SLACK = math.radians(0.25)
PIXEL_REACH = 1.25
DISC_REACH = 0.75


class Disc(NamedTuple):
    """A Sky Texture's sun disc: its angular diameter (radians) and the unit direction towards it
    where the node puts it, None where nodes drive its Vector input (turning the sky)."""

    size: float
    towards: np.ndarray | None


def wanted(background: Background) -> bool:
    """Whether the world's light needs rendering: nodes drive it that world_background does not read
    (it stands the world's plain colour or a map's mean in for them, with a note)."""
    return background.note is not None and background.environment is None


def sun_discs(world) -> dict[str, Disc]:
    """The world's Sky Texture nodes whose sun disc is on, by name."""
    tree = getattr(world, "node_tree", None)
    if tree is None:
        return {}
    skies = [n for n in tree.nodes if n.bl_idname == "ShaderNodeTexSky" and n.sky_type in SUN_SKIES and n.sun_disc]
    return {node.name: Disc(float(node.sun_size), None if _turned(node) else sun_direction(node)) for node in skies}


def _turned(node) -> bool:
    """Whether nodes drive the sky's Vector input (the disc models leave it unavailable, so far)."""
    vector = next((socket for socket in node.inputs if socket.identifier == "Vector"), None)
    return vector is not None and vector.enabled and vector.is_linked


def sun_direction(node) -> np.ndarray:
    """(3,) where a Sky Texture puts its sun: its elevation up, its rotation turning it from +Y
    towards +X (measured in Cycles, the same in every Blender tested: tests/test_blender_lights.py)."""
    up, around = float(node.sun_elevation), float(node.sun_rotation)
    return np.array([math.cos(up) * math.sin(around), math.cos(up) * math.cos(around), math.sin(up)])


# A node's settings that only change how it looks in the editor
UI_SETTINGS = {
    "rna_type", "name", "label", "location", "width", "height", "dimensions", "select", "show_options",
    "show_preview", "show_texture", "hide", "use_custom_color", "color", "parent", "inputs", "outputs",
    "internal_links", "width_hidden", "bl_width_default", "bl_width_min", "bl_width_max", "bl_height_default",
    "bl_height_min", "bl_height_max", "bl_icon", "bl_static_type", "bl_label", "bl_description", "type",
    "location_absolute", "warning_propagation", "id_data",
}  # fmt: skip
_KEPT: dict = {}  # one world's state -> its light: a still world renders once for an animation


def kept(key: str) -> Background | None:
    """The light world_light last gave for a world in the state `key` (state()), or None."""
    return _KEPT.get(key)


def keep(key: str, light: Background) -> None:
    """Keep `light` for a world in the state `key`, in place of any other."""
    _KEPT.clear()
    _KEPT[key] = light


def state(world) -> str:
    """What decides the world's picture, as text: its nodes' settings and input values (the
    values a frame's animation and drivers gave them, in an evaluated world), the images they
    show (by name, file and whether edited), node groups' own nodes, and the links."""
    return repr(_tree_state(world.node_tree, depth=0)) if getattr(world, "node_tree", None) else ""


def _tree_state(tree, depth):
    nodes = []
    for node in tree.nodes:  # a loop over nodes, not pixels
        inputs = [(socket.identifier, _value(getattr(socket, "default_value", None), depth)) for socket in node.inputs]
        nodes.append((node.bl_idname, node.name, node.mute, _settings(node, depth), inputs))
    links = [(k.from_node.name, k.from_socket.identifier, k.to_node.name, k.to_socket.identifier) for k in tree.links]
    return nodes, links


def _settings(struct, depth):
    names = [p.identifier for p in struct.bl_rna.properties if p.identifier not in UI_SETTINGS]
    return [(name, _value(getattr(struct, name, None), depth)) for name in names]


def _value(value, depth):
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "nodes") and hasattr(value, "links"):  # a node group's tree
        return _tree_state(value, depth + 1) if depth < 4 else value.name
    if hasattr(value, "filepath"):  # an image
        return (value.name, value.filepath, getattr(value, "is_dirty", False))
    if hasattr(value, "name") and hasattr(value, "users"):  # another data-block
        return value.name
    try:
        return [_value(item, depth) for item in value]  # a vector, colour or collection (a ramp's elements)
    except TypeError:
        pass
    if hasattr(value, "bl_rna") and depth < 4:  # a nested setting (a colour ramp, a texture mapping)
        return _settings(value, depth + 1)
    return repr(value)


def files(folder: Path, stamp: str) -> dict[str, Path]:
    """The EXR files of one world's pictures in `folder`."""
    return {name: folder / f"world_{name}_{stamp}.exr" for name in ("panorama", "lit", "on")}


def first_ask(discs: dict[str, Disc], paths: dict[str, Path]) -> tuple[dict, Camera | None]:
    """(the child's "world" request, the close view's core Camera or None): the panorama with the
    `discs` (sun_discs') off and, where the node puts the one sun, the close view of it."""
    ask = {"discs": sorted(discs), "samples": SAMPLES}
    ask["panorama"] = {"size": list(PANORAMA), "out": str(paths["panorama"])}
    aims = [disc for disc in discs.values() if disc.towards is not None]
    if len(discs) != 1 or len(aims) != 1:
        return ask, None
    fov = 2.0 * (AIMED * 0.5 * aims[0].size + AIM_SLACK)
    ask["view"], camera = _view(aims[0].towards, fov, paths)
    return ask, camera


def search_ask(discs: dict[str, Disc], paths: dict[str, Path]) -> dict:
    """The child's "world" request for the panorama with the `discs` on, samples enough that
    SUN_HITS are expected on the smallest."""
    # a disc of diameter s takes s^2 / 16 of the sphere (its solid angle pi s^2 / 4 over 4 pi)
    smallest = max(min((disc.size for disc in discs.values()), default=1.0), 1e-6)
    samples = SUN_HITS * 16.0 / (PANORAMA[0] * PANORAMA[1] * smallest**2)
    lit_samples = int(np.clip(math.ceil(samples), *LIT_SAMPLES))
    pano = {"size": list(PANORAMA), "lit": str(paths["lit"]), "lit_samples": lit_samples}
    return {"discs": sorted(discs), "samples": SAMPLES, "panorama": pano}


def found_ask(discs: dict[str, Disc], paths: dict[str, Path]) -> tuple[dict, Camera]:
    """(the child's "world" request for the close view of the sun, its core Camera), the sun found
    in the panoramas with the `discs` on and off."""
    towards = environment.peak_direction(_panorama(paths["lit"]) - _panorama(paths["panorama"]))
    half_diagonal = math.sqrt(0.5) * 2.0 * math.pi / PANORAMA[0]
    largest = max((disc.size for disc in discs.values()), default=0.0)
    fov = 2.0 * (PIXEL_REACH * half_diagonal + DISC_REACH * 0.5 * largest)
    view, camera = _view(towards, fov, paths)
    return {"discs": sorted(discs), "samples": SAMPLES, "view": view}, camera


def _view(towards, fov, paths):
    """(the "view" of a request looking along `towards` `fov` radians wide, its core Camera)."""
    camera = Camera.look_at(np.zeros(3), towards, up=(0.0, 0.0, 1.0), fov_deg=math.degrees(fov), width=SUN_VIEW,
                            height=SUN_VIEW)  # fmt: skip
    rows = camera.rotation  # right, down, forward; a Blender camera's axes: right, up, backward
    to_world = np.column_stack([rows[0], -rows[1], -rows[2]])
    view = {"size": SUN_VIEW, "fov": fov, "rotation": to_world.tolist(), "on": str(paths["on"])}
    return view, camera


def shows_sun(sun, camera: Camera | None) -> bool:
    """Whether `sun` (view_sun's, or None) lies in the close view through `camera` clear of its edges."""
    if sun is None:
        return False
    half = math.atan(0.5 * camera.width / camera.fx)
    return math.acos(min(float(-sun.direction @ camera.forward), 1.0)) + 0.5 * sun.angle < half


def view_sun(paths: dict[str, Path], camera: Camera):
    """The sun of the close view through `camera` (core.environment.sun_in_view): the view less the
    panorama's light there, or None."""
    directions, solid_angles = camera.pixel_rays()
    sky = environment.radiance(environment.from_equirect(_panorama(paths["panorama"])), directions.reshape(-1, 3))
    return environment.sun_in_view(_rgb(paths["on"]) - sky.reshape(directions.shape), directions, solid_angles)


def world_light(paths: dict[str, Path], disc=None) -> Background:
    """The world's Background as the panorama in `paths` shows it (its bands and sun), the close
    view's sun `disc` (view_sun's) in place of the panorama's where there is one."""
    coefficients, sun = environment.light_of(_panorama(paths["panorama"]))
    if disc is not None:
        if sun is not None:  # the sky's own brightest part stays in its light
            coefficients = environment.with_sun(coefficients, sun)
        sun = disc
    return Background(environment.mean(coefficients), _note(sun), coefficients, sun)


def _panorama(path: Path) -> np.ndarray:
    """(H, W, 3) a panorama the child wrote, rows from the bottom as an Environment Texture's."""
    return _rgb(path)[::-1]


def _rgb(path: Path) -> np.ndarray:
    """(H, W, 3) float64 scene-linear RGB of a one-layer EXR the child wrote, rows top first."""
    channels = read_plain_exr(path)
    return np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float64)


def _note(sun) -> str:
    what = "its broad light (spherical harmonics to band 2)"
    if sun is not None:
        what += " and its sun, a sun light of its own with shadows and highlights"
    return (
        f"the world's nodes light relit splats as Cycles renders the world: {what}, read from a "
        f"{PANORAMA[0]} x {PANORAMA[1]} panorama; its other sharp features cast no shadows and make no sharp highlights"
    )
