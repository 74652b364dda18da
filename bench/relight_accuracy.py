"""Relighting accuracy: splats made from meshes, shaded by core.relight.render_lit under lights their
conversion never saw, against Blender Cycles rendering the source mesh under the same light.

Meshes: a smooth-shaded grey sphere (roughness 1; its vertex normals given to the conversion as
corner normals, Blender's smooth shading in Cycles) standing on core.mesh_corpus's grid plane (a 2 m
textured floor, converted to splats with the sphere: its shadows are splat-on-splat), Blender's Suzanne made metallic
(metallic 1, roughness 0.35: specular lobes), pybullet's textured duck (Principled defaults) and the
corpus's striped cylinder and decal box (hard-edged textures), flat-shaded. Each is converted by
mesh_to_splats(..., material=True) at default settings: the conversion sees only its own unlit views.

Lights, one at a time, placed from a fixed seed around the mesh's bounding sphere (radius R, centre
c) at 3R from c, 30 to 60 degrees above the y = 0 plane: a point light (soft radius 0.05 R), a spot
aimed at c whose cone edge crosses the mesh, a sun (3 degree disc) and a 0.6 R x 0.4 R rectangular
area light facing c, each giving about IRRADIANCE W/m^2 at c; white; world a dim uniform grey.
Cycles receives the same numbers (Blender units: watts, W/m^2, metres, radians).

Reference: Cycles (CPU, headless bpy, bench/mesh2splats.py's child with this scene) renders the
MESH with Principled BSDF materials carrying the same roughness and metallic (textures and colours as
the Mesh to Splats bench draws them), max_bounces 0 (direct light only, as render_lit models it),
no denoising, Standard view transform, film transparent, composited over black. Cycles shadows the
world's light by the mesh; render_lit at its defaults does not (World.occlusion 0), and a column
gives each light's dB with the world occluded from core.ambient's default directions. Its noise
floor is the PSNR between two renders with different seeds. Shadows off on both sides: the mesh's
object invisible to shadow rays in Cycles, the light's cast_shadow False for render_lit, so shading
error and shadow error part (Cycles' world light stays occluded: hiding the object from shadow rays
leaves it unchanged).

Views: bench/mesh2splats.py's held-out cameras (0.5x, 1x and 3x the framing distance; the floor
scene's from 2 to 50 degrees above the floor). PSNR per distance over its views together.

Rows per mesh and light: dB at 0.5x / 1x / 3x with shadows, the same without, the noise floor, and
the share of the squared error inside penumbrae (render_lit's shadow pass between 0.05 and 0.95),
inside full shadow (above 0.95), on specular highlights (the specular pass above 5% of the
pixel's diffuse + specular) and on edges (silhouettes and texture steps: the reference's gradient above 0.1 per pixel).
Time: a lit frame as the engine makes one for one light (shadow maps, shading, one render; no
passes; the world unoccluded) against the unlit render of the same splats, over the 1x views. A row
per mesh gives its conversion's unlit error against Cycles' emission render (bench/mesh2splats.py's
reference): what shading cannot beat. Another gives the world alone (WORLD_ALONE grey, no light)
against Cycles, occluded and not: what the world's occlusion is worth by itself; its time is the
occlusion's (core.ambient.world_visibility), which depends on neither the view nor the lights,
against the unlit frame. Two more, an environment map alone (an overcast sky glowing to one side,
then a sunny sky, as the world's Environment Texture; no light): its nine SH coefficients and its sun
as a light (core.environment.light_of), occluded and not, against Cycles lighting the mesh by the map.

    python bench/relight_accuracy.py [--quick]
    ./run bench relight_accuracy [--quick] [--only sphere|suzanne|duck|cylinder|box]
"""

import dataclasses
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from _cycles_reference import _cycles_main, cycles_render  # noqa: E402
from common import Row, Timing, print_rows  # noqa: E402
from environment_reference import directions, sunny_sky  # noqa: E402
from mesh2splats import (  # noqa: E402
    DISTANCES,
    blender_primitives,
    convert,
    held_out_cameras,
    psnr_by_distance,
    pybullet_meshes,
    uv_sphere,
)

from splatwright.core import ambient  # noqa: E402
from splatwright.core.lights import Light, World  # noqa: E402
from splatwright.core.mesh import Material, Mesh  # noqa: E402
from splatwright.core.mesh_corpus import decal_box, grid_plane, striped_cylinder  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.core.robot import join_meshes  # noqa: E402

TOPIC = "relight_accuracy"
TARGET_DB = 33.0
SAMPLES, QUICK_SAMPLES = 96, 32
IRRADIANCE = 2.5  # W/m^2 at the mesh's centre on a surface facing the light
WORLD = (0.03, 0.03, 0.03)  # dim uniform grey, scene-linear
WORLD_ALONE = (0.5, 0.5, 0.5)  # the world-alone rows' grey: no light, so the world's occlusion is all there is
MAP_SIZE = (128, 256)  # the environment rows' map, rows by columns
LIGHT_SEED = 11
KINDS = ("point", "spot", "sun", "area")
PENUMBRA = (0.05, 0.95)  # render_lit's shadow pass between these: a penumbra; above: full shadow
SPECULAR_SHARE = 0.05  # specular pass above this share of the pixel's radiance: a highlight
EDGE_STEP = 0.1  # reference gradient (display units per pixel) above which a pixel is on an edge


# scenes ------------------------------------------------------------------------------------------


def sphere_on_floor(segments=64, rings=32) -> tuple[Mesh, np.ndarray]:
    """A smooth grey sphere of radius 0.5 m (roughness 1) resting on the corpus's 2 m grid plane
    (y = 0), and its normals per vertex (V,3): the sphere's radial, the floor's up."""
    v, f, _ = uv_sphere(segments, rings)
    grey = Material(base_color=(0.6, 0.6, 0.6), roughness=1.0, metallic=0.0)
    sphere = Mesh(0.5 * v + np.array([0.0, 0.5, 0.0]), f, None, None, [grey])
    floor = grid_plane()
    up = np.broadcast_to([0.0, 1.0, 0.0], floor.vertices.shape)
    return join_meshes([sphere, floor]), np.concatenate([v, up])


def with_surface(mesh: Mesh, roughness: float, metallic: float) -> Mesh:
    """The mesh with every material's roughness and metallic replaced."""
    materials = [dataclasses.replace(m, roughness=roughness, metallic=metallic) for m in mesh.materials]
    return Mesh(mesh.vertices, mesh.faces, mesh.corner_uvs, mesh.face_materials, materials, mesh.corner_colors)


class Scene(NamedTuple):
    """A bench mesh: whether it stands on a floor (the held-out views then keep above it) and its
    normals per vertex where it is smooth-shaded (None: flat, as Cycles draws a mesh by default)."""

    name: str
    mesh: Mesh
    floor: bool = False
    normals: np.ndarray | None = None


def _sphere(folder):
    mesh, normals = sphere_on_floor()
    return Scene("grey sphere on the grid floor (smooth)", mesh, True, normals)


def _suzanne(folder):
    suzanne = blender_primitives(folder)["Blender Suzanne"]
    return Scene("Blender Suzanne (metallic 1, roughness 0.35)", with_surface(suzanne, 0.35, 1.0))


def _duck(folder):
    found, note = pybullet_meshes()
    return Scene("pybullet duck", found["pybullet duck"]) if found else note


# `./run bench relight_accuracy --only <part>` measures one mesh; the quick run only the first
SCENES = {
    "sphere": _sphere,
    "suzanne": _suzanne,
    "duck": _duck,
    "cylinder": lambda folder: Scene("corpus: striped cylinder", striped_cylinder()),
    "box": lambda folder: Scene("corpus: decal box", decal_box()),
}


def bounds(mesh: Mesh) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of the mesh's bounding box's sphere."""
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)


def _above(rng) -> np.ndarray:
    """A unit direction 30 to 60 degrees above the y = 0 plane, random azimuth."""
    azimuth, elevation = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(30, 60))
    return np.array(
        [math.cos(elevation) * math.cos(azimuth), math.sin(elevation), math.cos(elevation) * math.sin(azimuth)]
    )


def scene_lights(mesh: Mesh, seed: int = LIGHT_SEED) -> dict[str, Light]:
    """One light of each kind (see the module notes), each about IRRADIANCE W/m^2 at the centre."""
    centre, radius = bounds(mesh)
    rng = np.random.default_rng(seed)
    d = 3.0 * radius
    at = {kind: _above(rng) for kind in KINDS}
    side = np.cross(at["area"], [0.0, 1.0, 0.0])
    return {
        "point": Light(
            "point", power=IRRADIANCE * 4 * math.pi * d * d, position=centre + d * at["point"], radius=0.05 * radius
        ),
        "spot": Light(
            "spot",
            power=IRRADIANCE * 4 * math.pi * d * d,
            position=centre + d * at["spot"],
            direction=-at["spot"],
            radius=0.05 * radius,
            spot_size=2 * math.atan(0.6 / 3.0),  # the cone's edge crosses the mesh
            spot_blend=0.3,
        ),
        "sun": Light("sun", power=IRRADIANCE, direction=-at["sun"], angle=math.radians(3.0)),
        "area": Light(
            "area",
            power=IRRADIANCE * math.pi * d * d,  # radiance P / (pi A), seen from d: E ~ P / (pi d^2)
            position=centre + d * at["area"],
            direction=-at["area"],
            size_x=0.6 * radius,
            size_y=0.4 * radius,
            shape="RECTANGLE",
            x_axis=side,
        ),
    }


def light_spec(light: Light) -> dict:
    """The light's numbers for the Cycles child (JSON)."""
    keys = ("power", "radius", "angle", "spot_size", "spot_blend", "size_x", "size_y", "shape")
    out = {k: getattr(light, k) for k in keys}
    vectors = {k: getattr(light, k).tolist() for k in ("color", "position", "direction", "x_axis")}
    return {"kind": light.kind, **out, **vectors}


# Cycles ------------------------------------------------------------------------------------------


def cycles_lit(mesh, cameras, folder, light, samples, shadows=True, seed=0, smooth=False, world=WORLD, sky=None):
    """Cycles' images of the mesh under `light` and `world` (see the module notes), or the map `sky`
    (H, W, 3) rows from the bottom as an Environment Texture, smooth-shaded (Blender's vertex
    normals) or flat."""
    sky_path = None
    if sky is not None:
        sky_path = str(folder / "sky.npy")
        np.save(sky_path, np.asarray(sky, np.float32))
    spec = {
        "smooth": smooth,
        "light": light_spec(light),
        "world": list(world),
        "sky": sky_path,
        "shadows": shadows,
        "seed": seed,
        "surfaces": [(m.roughness, m.metallic) for m in mesh.materials or [Material()]],
    }
    images, _ = cycles_render(mesh, cameras, folder, samples, lit=True, script=__file__, relight=json.dumps(spec))
    return images


def _light_matrix(light: dict) -> np.ndarray:
    """The Blender light object's world matrix (4,4): -Z along the direction, +X the x_axis (made
    perpendicular; any perpendicular where it is parallel)."""
    z = -np.asarray(light["direction"], float)
    x = np.asarray(light["x_axis"], float)
    x = x - z * (x @ z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, light["position"]
    return m


def _relit_scene(spec_path, scene, obj, world):
    """Runs inside the Cycles child: the light, world, surfaces and settings of the spec's "relight"."""
    import bpy
    import mathutils

    spec = json.loads(str(np.load(spec_path)["relight"]))
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*spec["world"], 1.0)
    if spec["sky"] is not None:  # an equirectangular map on the Background's Color
        rows = np.load(spec["sky"])
        image = bpy.data.images.new("sky", rows.shape[1], rows.shape[0], float_buffer=True)
        pixels = np.ones((*rows.shape[:2], 4), np.float32)
        pixels[..., :3] = rows
        image.pixels.foreach_set(pixels.ravel())
        texture = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
        texture.image = image
        world.node_tree.links.new(texture.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    light = spec["light"]
    data = bpy.data.lights.new("light", light["kind"].upper())
    data.color, data.energy = light["color"], light["power"]
    if light["kind"] in ("point", "spot"):
        data.shadow_soft_size = light["radius"]
    if light["kind"] == "spot":
        data.spot_size, data.spot_blend = light["spot_size"], light["spot_blend"]
    if light["kind"] == "sun":
        data.angle = light["angle"]
    if light["kind"] == "area":
        data.shape, data.size, data.size_y = light["shape"], light["size_x"], light["size_y"]
    lamp = bpy.data.objects.new("light", data)
    lamp.matrix_world = mathutils.Matrix(_light_matrix(light).tolist())
    scene.collection.objects.link(lamp)
    if spec["smooth"]:
        obj.data.shade_smooth()
    obj.visible_shadow = bool(spec["shadows"])  # off: the mesh shadows neither the light nor the world
    for material, (roughness, metallic) in zip(obj.data.materials, spec["surfaces"]):
        node = next(n for n in material.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
        node.inputs["Roughness"].default_value = roughness
        node.inputs["Metallic"].default_value = metallic
    scene.cycles.max_bounces = 0  # direct light only, as render_lit shades
    scene.cycles.seed = int(spec["seed"])
    scene.cycles.use_denoising = False
    scene.render.film_transparent = True
    scene.render.image_settings.color_mode = "RGBA"


# splats ------------------------------------------------------------------------------------------


def lit_frames(
    cloud, cameras, lights, shadows=True, passes=True, occluded=True, timed=False, world=WORLD, environment=None
):
    """render_lit frames of the cloud under `lights` and `world` (or the SH coefficients
    `environment`; occluded from core.ambient's default directions, as Cycles occludes it, or not),
    and the seconds of each. Timed frames make their shadow maps each, as the engine does; the
    others share the lights' and the world's (they do not depend on the camera)."""
    from splatwright.core.relight import render_lit, visibilities

    lights = [light if shadows else dataclasses.replace(light, cast_shadow=False) for light in lights]
    world = World(world, ambient.DIRECTIONS if occluded else 0, environment)
    visible = None if timed else visibilities(cloud, lights, world)
    frames, seconds = [], []
    for camera in cameras:
        start = time.perf_counter()
        frames.append(render_lit(cloud, camera, lights, world, passes=passes, visible=visible))
        seconds.append(time.perf_counter() - start)
    return frames, seconds


def display(image) -> np.ndarray:
    """A frame's colour as a display shows it: clipped to [0, 1], as Cycles' Standard view transform
    and its 8-bit output clip (render_lit's highlights go past 1)."""
    return np.clip(np.asarray(image, np.float64), 0.0, 1.0)


def _luminance(image) -> np.ndarray:
    return np.asarray(image, np.float64)[..., :3] @ np.array([0.2126, 0.7152, 0.0722])


def error_shares(frames, references) -> dict[str, float]:
    """The share of the squared error (all views together) inside penumbrae, full shadow, highlights
    and edges (see the module notes; a pixel may be in several)."""
    total, parts = 0.0, dict.fromkeys(("penumbra", "full shadow", "highlight", "edge"), 0.0)
    for frame, ref in zip(frames, references, strict=True):
        err = np.sum((display(frame.color) - ref) ** 2, axis=-1)
        shadow = np.asarray(frame.shadow, np.float64).reshape(err.shape)
        specular, diffuse = _luminance(frame.specular), _luminance(frame.diffuse)
        gy, gx = np.gradient(_luminance(ref))
        masks = {
            "penumbra": (shadow > PENUMBRA[0]) & (shadow < PENUMBRA[1]),
            "full shadow": shadow >= PENUMBRA[1],
            "highlight": specular > SPECULAR_SHARE * (specular + diffuse + 1e-12),
            "edge": np.hypot(gx, gy) > EDGE_STEP,
        }
        total += float(err.sum())
        for key, mask in masks.items():
            parts[key] += float(err[mask].sum())
    return {key: value / max(total, 1e-30) for key, value in parts.items()}


def _triple(error) -> str:
    return " / ".join(f"{error[f'dB {d:g}x']:.1f}" for d in DISTANCES if f"dB {d:g}x" in error)


def _timing(seconds) -> Timing:
    return Timing(statistics.median(seconds), (max(seconds) - min(seconds)) / 2, len(seconds))


def light_row(scene, kind, light, cloud, cams, folder, samples, unlit_seconds):
    """One row: a mesh under one light, with and without shadows, the world unoccluded (the
    engine's default) and occluded, against Cycles."""
    cameras = [cam for _, cam in cams]
    smooth = scene.normals is not None
    ref = cycles_lit(scene.mesh, cameras, folder, light, samples, smooth=smooth)
    second = cycles_lit(scene.mesh, cameras, folder, light, samples, seed=1, smooth=smooth)
    ref_flat = cycles_lit(scene.mesh, cameras, folder, light, samples, shadows=False, smooth=smooth)
    # at the engine's defaults: the world unoccluded (World.occlusion 0)
    frames, _ = lit_frames(cloud, cameras, [light], occluded=False)
    flat, _ = lit_frames(cloud, cameras, [light], shadows=False, occluded=False)
    occluded_world, _ = lit_frames(cloud, cameras, [light], passes=False)
    # the time of a frame as the engine makes one for one light (shadow maps, shading, one render;
    # no passes), over the 1x views, against the unlit render of the same views
    timed = [cam for d, cam in cams if d == 1.0]
    _, seconds = lit_frames(cloud, timed, [light], passes=False, occluded=False, timed=True)
    error = psnr_by_distance([display(f.color) for f in frames], cams, ref)
    occluded = psnr_by_distance([display(f.color) for f in occluded_world], cams, ref)
    error["worst dB"] = min(error.values())
    no_shadow = psnr_by_distance([display(f.color) for f in flat], cams, ref_flat)
    noise = psnr_by_distance(second, cams, ref)
    shares = error_shares(frames, ref)
    return Row(
        TOPIC,
        f"{scene.name}: {kind} light",
        _timing(seconds),
        _timing(unlit_seconds),
        error=error,
        extra={
            "no shadows dB 0.5x / 1x / 3x": _triple(no_shadow),
            f"world occluded ({ambient.DIRECTIONS} directions) dB 0.5x / 1x / 3x": _triple(occluded),
            "no shadows worst dB": f"{min(no_shadow.values()):.1f}",
            "Cycles noise floor dB (worst)": f"{min(noise.values()):.1f}",
            "error share penumbra": f"{shares['penumbra']:.2f}",
            "error share full shadow": f"{shares['full shadow']:.2f}",
            "error share highlight": f"{shares['highlight']:.2f}",
            "error share edge": f"{shares['edge']:.2f}",
            f"meets {TARGET_DB:g} dB": error["worst dB"] >= TARGET_DB,
            f"meets {TARGET_DB:g} dB, world occluded": min(occluded.values()) >= TARGET_DB,
        },
    )


def world_row(scene, cloud, cams, folder, samples, unlit_seconds):
    """The world alone (WORLD_ALONE, no light): render_lit with the world occluded from
    core.ambient's default directions and unoccluded, against Cycles; its time is the occlusion's
    (core.ambient.world_visibility, median of 3) against the unlit frame."""
    cameras = [cam for _, cam in cams]
    dark = dataclasses.replace(scene_lights(scene.mesh)["sun"], power=0.0)
    smooth = scene.normals is not None
    ref = cycles_lit(scene.mesh, cameras, folder, dark, samples, smooth=smooth, world=WORLD_ALONE)
    occluded, _ = lit_frames(cloud, cameras, [], passes=False, world=WORLD_ALONE)
    open_world, _ = lit_frames(cloud, cameras, [], passes=False, occluded=False, world=WORLD_ALONE)
    seconds = []
    for _ in range(3):
        start = time.perf_counter()
        ambient.world_visibility(cloud)
        seconds.append(time.perf_counter() - start)
    case = f"{scene.name}: the world alone (grey {WORLD_ALONE[0]:g}, no light)"
    return _world_row(case, "world", seconds, unlit_seconds, cams, ref, occluded, open_world)


def _world_row(case, light, seconds, unlit_seconds, cams, ref, occluded, open_world):
    """A row of the world's light alone: `case`, occluded from core.ambient's default directions
    (its dB by distance), the `light`'s unoccluded dB and both mean errors against Cycles' `ref`."""
    error = psnr_by_distance([display(f.color) for f in occluded], cams, ref)
    error["worst dB"] = min(error.values())
    unoccluded = psnr_by_distance([display(f.color) for f in open_world], cams, ref)
    return Row(
        TOPIC,
        f"{case}, occluded from {ambient.DIRECTIONS} directions",
        _timing(seconds),
        _timing(unlit_seconds),
        error=error,
        extra={
            f"{light} unoccluded dB 0.5x / 1x / 3x": _triple(unoccluded),
            "mean error, occluded / unoccluded": " / ".join(
                f"{_mean_error(frames, ref):+.4f}" for frames in (occluded, open_world)
            ),
        },
    )


def glow_sky(height, width):
    """(H, W, 3) an overcast sky brighter towards a low glow 30 degrees to the side of +X, over a dim
    brown ground: broad light from one side (no sun: what nine SH coefficients hold)."""
    d, _ = directions(height, width)
    glow = np.array([math.cos(math.radians(15)) * math.cos(0.5), math.cos(math.radians(15)) * math.sin(0.5), 0.26])
    toward = np.maximum(d @ glow, 0.0)[..., None]
    sky = np.array([0.35, 0.4, 0.5]) + toward**3 * np.array([1.6, 1.1, 0.6])
    return np.where(d[..., 2:] > 0.0, sky, np.array([0.12, 0.09, 0.06]))


MAPS = {
    "a glowing overcast sky": lambda: glow_sky(*MAP_SIZE),
    # fine enough for its 4-degree sun, which gives IRRADIANCE as the light rows' lights do
    "a sunny sky": lambda: sunny_sky(2 * MAP_SIZE[0], 2 * MAP_SIZE[1]) * (IRRADIANCE / (3.0 * math.pi)),
}


def environment_row(scene, cloud, cams, folder, samples, unlit_seconds, name):
    """An environment map alone (MAPS[name] as the world's Environment Texture, no light): render_lit
    with its SH coefficients and its sun (core.environment.light_of), the world occluded from
    core.ambient's default directions and unoccluded, against Cycles lighting the mesh by the map
    itself; the time of a frame (the occlusion and the sun's shadows shared by the views, as for a
    still scene) against the unlit frame."""
    from splatwright.core import environment

    cameras = [cam for _, cam in cams]
    dark = dataclasses.replace(scene_lights(scene.mesh)["sun"], power=0.0)
    sky = MAPS[name]()
    coefficients, sun = environment.light_of(sky)
    suns = [] if sun is None else [sun]
    ref = cycles_lit(scene.mesh, cameras, folder, dark, samples, smooth=scene.normals is not None, sky=sky)
    occluded, _ = lit_frames(cloud, cameras, suns, passes=False, environment=coefficients)
    open_world, _ = lit_frames(cloud, cameras, suns, passes=False, occluded=False, environment=coefficients)
    timed = [cam for d, cam in cams if d == 1.0]
    _, seconds = lit_frames(cloud, timed, suns, passes=False, environment=coefficients)
    case = f"{scene.name}: an environment map ({name}{', its sun a light' if sun else ''}, no light)"
    return _world_row(case, "environment", seconds, unlit_seconds, cams, ref, occluded, open_world)


def _mean_error(frames, references) -> float:
    """The mean of our display colour minus Cycles' over every pixel of every view."""
    return float(np.mean([np.mean(display(f.color) - r) for f, r in zip(frames, references, strict=True)]))


def scene_rows(scene, folder, size, per_distance, samples) -> list[Row]:
    """The conversion's row (its unlit error against Cycles' emission render: what the lit error
    cannot beat) and one row per light."""
    cams = held_out_cameras(scene.mesh, size, per_distance=per_distance, floor=scene.floor)
    cameras = [cam for _, cam in cams]
    start = time.perf_counter()
    cloud = convert(scene.mesh, material=True, corner_normals=scene.normals)
    seconds = time.perf_counter() - start
    unlit_refs, _ = cycles_render(scene.mesh, cameras, folder, samples)
    unlit, unlit_seconds = [], []
    for d, camera in cams:
        t0 = time.perf_counter()
        unlit.append(display(render(cloud, camera).color))
        if d == 1.0:
            unlit_seconds.append(time.perf_counter() - t0)
    unlit_error = psnr_by_distance(unlit, cams, unlit_refs)
    rows = [
        Row(
            TOPIC,
            f"{scene.name}: conversion (material=True, defaults), unlit",
            Timing(seconds, 0.0, 1),
            error={**unlit_error, "worst dB": min(unlit_error.values())},
            extra={"splats": len(cloud), "faces": len(scene.mesh.faces)},
        ),
        world_row(scene, cloud, cams, folder, samples, unlit_seconds),
        *(environment_row(scene, cloud, cams, folder, samples, unlit_seconds, name) for name in MAPS),
    ]
    print_rows(rows)
    for kind, light in scene_lights(scene.mesh).items():
        rows.append(light_row(scene, kind, light, cloud, cams, folder, samples, unlit_seconds))
        print_rows(rows[-1:])
    return rows


def run(quick=False, parts=None):
    """Every scene of SCENES (or the keys in `parts`; quick: the first only, smaller and noisier)."""
    size, per_distance, samples = (96, 1, QUICK_SAMPLES) if quick else (128, 2, SAMPLES)
    keys = parts or (list(SCENES)[:1] if quick else list(SCENES))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for key in keys:
            scene = SCENES[key](folder)
            if isinstance(scene, str):  # a note: the mesh could not be had
                rows.append(Row(TOPIC, scene, Timing(0.0, 0.0, 0)))
                continue
            rows += scene_rows(scene, folder, size, per_distance, samples)
    return rows


PARTS = {key: (lambda quick, key=key: run(quick, [key])) for key in SCENES}


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--cycles":
        spec_path = sys.argv[2]
        _cycles_main(spec_path, lambda scene, obj, world: _relit_scene(spec_path, scene, obj, world))
    else:
        print_rows(run(quick="--quick" in sys.argv))
