"""The Blender half of bench/world_light.py, run by Blender 5.3's bpy-only Python as a child process.

    python _world_light_child.py JOB.json

The child installs the extension zip (bench/_blender_render_child.py's main and install), builds a white
diffuse ball (radius 1, smooth) seen along +Y by an orthographic camera, and for each Sky Texture
world of the job: renders the ball with Cycles (the reference, and the baseline's time), then reads
the world's light as the SPLATWRIGHT engine does (splat_addon/render/mesh_layer.render with `world`:
the child Blender's panorama and sun view), afresh (its kept reading dropped) and kept, run after
run. It writes into the job's folder results.json (seconds per run, each reading's coefficients and
sun) and <world>.npy (the reference picture, scene-linear RGB, row 0 at the top).
"""

import importlib
import math
import sys
import time

import numpy as np
from _blender_render_child import MODULE, install, main


def _run(job, work, results):
    import bpy

    install(bpy, job)
    results["worlds"] = {}
    mesh_layer = importlib.import_module(f"{MODULE}.splat_addon.render.mesh_layer")
    world_panorama = importlib.import_module(f"{MODULE}.splat_addon.render.world_panorama")
    scene, sky = _scene(bpy, job)
    size = job["size"]

    def read():
        depsgraph = bpy.context.evaluated_depsgraph_get()
        return mesh_layer.render(depsgraph, "CYCLES", size, size, layer=False, world=True)[1]

    for name, world in job["worlds"].items():
        sky.sky_type = world["model"]
        sky.sun_elevation, sky.sun_rotation = math.radians(world["elevation"]), math.radians(world["rotation"])
        sky.sun_disc = world["disc"]
        read()  # warm-up: the child started, Cycles' kernels loaded
        for _ in range(job["repeat"]):  # in turns, so all three meet the same load
            start = time.perf_counter()
            bpy.ops.render.render()
            results["runs"].setdefault(f"{name}/cycles", []).append(time.perf_counter() - start)
            world_panorama._KEPT.clear()
            start = time.perf_counter()
            light = read()
            results["runs"].setdefault(f"{name}/rendered", []).append(time.perf_counter() - start)
            start = time.perf_counter()
            read()
            results["runs"].setdefault(f"{name}/kept", []).append(time.perf_counter() - start)
        sun = light.sun
        results["worlds"][name] = {
            "coefficients": np.asarray(light.environment).tolist(),
            "sun": None if sun is None else _sun(sun),
            "plain": list(scene.world.color),
            "sun_size": sky.sun_size,
        }
        np.save(work / f"{name}.npy", _pixels(bpy, work, name, size))


def _sun(sun):
    return {"towards": (-sun.direction).tolist(), "irradiance": (sun.power * sun.color).tolist(), "angle": sun.angle}


def _scene(bpy, job):
    """The ball, the camera, Cycles' settings and the world's Sky Texture node."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_uv_sphere_add(segments=192, ring_count=96, radius=1.0, location=(0.0, 0.0, 0.0))
    bpy.ops.object.shade_smooth()
    material = bpy.data.materials.new("White")
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.clear()
    bsdf = nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Color"].default_value = (job["albedo"],) * 3 + (1.0,)
    output = nodes.new("ShaderNodeOutputMaterial")
    material.node_tree.links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
    bpy.context.active_object.data.materials.append(material)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    camera.location, camera.rotation_euler = (0.0, -10.0, 0.0), (math.pi / 2, 0.0, 0.0)
    camera.data.type, camera.data.ortho_scale = "ORTHO", job["ortho_scale"]
    world = bpy.data.worlds.new("World")
    scene.world = world
    tree = world.node_tree
    background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
    sky = tree.nodes.new("ShaderNodeTexSky")
    tree.links.new(sky.outputs["Color"], background.inputs["Color"])
    render = scene.render
    render.engine = "CYCLES"
    render.resolution_x = render.resolution_y = job["size"]
    render.resolution_percentage = 100
    render.film_transparent = True
    render.dither_intensity = 0.0
    render.image_settings.file_format = "OPEN_EXR"  # scene-linear, unclipped
    render.image_settings.color_depth = "32"
    scene.view_settings.view_transform = "Standard"
    scene.cycles.device = "CPU"
    scene.cycles.samples = job["samples"]
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.filter_width = 0.01
    return scene, sky


def _pixels(bpy, work, name, size):
    path = work / f"{name}.exr"
    bpy.data.images["Render Result"].save_render(str(path))
    loaded = bpy.data.images.load(str(path))
    pixels = np.empty(len(loaded.pixels), np.float32)
    loaded.pixels.foreach_get(pixels)
    bpy.data.images.remove(loaded)
    return pixels.reshape(size, size, 4)[::-1, :, :3]


if __name__ == "__main__":
    main(sys.argv[1], _run)
