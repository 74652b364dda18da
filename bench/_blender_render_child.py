"""The Blender half of bench/blender_render.py, run by Blender 5.3's bpy-only Python as a child process.

    python _blender_render_child.py JOB.json

JOB.json names the PLY, the extension zip, the camera, the image size, the renderers and how many
timed runs each gets. The child installs the zip into the user repository that BLENDER_USER_RESOURCES
names (as a user's Install from Disk does), imports the PLY with Blender's own wm.ply_import (a native
"3D Gaussian Splats" point cloud), renders it with every renderer of the job, the renderers taking
turns run after run so they meet the same load, and writes into the job's folder:

    results.json     seconds of every timed run per renderer, the scene's colour management, the
                     point cloud's type, the core Camera the engine's conversion makes, notes
    <renderer>.npy   the first timed render as scene-linear RGBA float32, row 0 at the top
    check.npy        the first renderer's picture saved as a 16-bit PNG through the view transform

Only the standard library, NumPy, bpy and the installed extension are used: this Python has nothing
else.
"""

import importlib
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

MODULE = "bl_ext.user_default.splatwright"  # the extension's package once installed


def main(job_path, run=None):
    """Run the job of `job_path` (by `run`, default this bench's) into its folder's results.json,
    the error's traceback there if it fails."""
    job = json.loads(Path(job_path).read_text())
    work = Path(job["work"])
    results = {"runs": {}, "notes": {}}
    try:
        (run or _run)(job, work, results)
    except Exception:  # noqa: BLE001 - handed to the bench, which raises it with the log
        results["error"] = traceback.format_exc()
    (work / "results.json").write_text(json.dumps(results, indent=1))


def install(bpy, job):
    """Install and enable the job's extension zip, as Install from Disk does."""
    bpy.ops.extensions.package_install_files(filepath=job["zip"], repo="user_default", enable_on_install=True)


def _run(job, work, results):
    import bpy

    install(bpy, job)
    camera = importlib.import_module(f"{MODULE}.splat_addon.data.camera")
    scene = _scene(bpy, job, results)
    results["core_camera"] = _core_camera(bpy, camera, scene)
    direct = _direct(bpy, camera, scene, job)

    renderers = job["renderers"]
    for r in renderers:  # warm-up: kernels, shaders, compiled code, caches
        if r.get("warmup", True):
            direct(r) if r["engine"] == "CORE" else _render(bpy, scene, r, job)
    saved = set()
    for _ in range(job["repeat"]):
        for r in renderers:
            seconds, error = direct(r) if r["engine"] == "CORE" else _render(bpy, scene, r, job)
            results["runs"].setdefault(r["name"], []).append(seconds)
            if error:
                results["notes"][r["name"]] = error
            if r["name"] not in saved:
                saved.add(r["name"])
                if r["engine"] == "CORE":
                    np.save(work / f"{r['name']}.npy", direct.image)
                    continue
                np.save(work / f"{r['name']}.npy", _pixels(bpy, scene, work, r["name"]))
                if len(saved) == 1:
                    np.save(work / "check.npy", _view_png(bpy, scene, work))
    results["colour_management"] = {
        "view_transform": scene.view_settings.view_transform,
        "look": scene.view_settings.look,
        "exposure": scene.view_settings.exposure,
        "gamma": scene.view_settings.gamma,
        "display_device": scene.display_settings.display_device,
    }


def _scene(bpy, job, results):
    """The default scene with only its camera, placed as the job says, and the imported PLY."""
    import mathutils

    scene = bpy.context.scene
    for obj in list(bpy.data.objects):
        if obj.type != "CAMERA":
            bpy.data.objects.remove(obj)
    cam = scene.camera
    cam.location = job["camera"]["location"]
    cam.rotation_mode = "QUATERNION"
    look = mathutils.Vector(job["camera"]["target"]) - mathutils.Vector(job["camera"]["location"])
    cam.rotation_quaternion = look.to_track_quat("-Z", "Y")
    cam.data.type = "PERSP"
    cam.data.lens = job["camera"]["lens"]
    cam.data.sensor_fit = "AUTO"
    cam.data.clip_start, cam.data.clip_end = job["camera"]["clip"]
    bpy.ops.wm.ply_import(filepath=job["ply"])
    cloud = bpy.context.active_object
    results["pointcloud_type"] = getattr(cloud.data, "type", None)
    results["points"] = len(cloud.data.points)
    results["object_matrix"] = [list(row) for row in cloud.matrix_world]
    scene.world = None  # black behind the splats, in every renderer
    render = scene.render
    render.resolution_x, render.resolution_y = job["size"]
    render.resolution_percentage = 100
    render.pixel_aspect_x = render.pixel_aspect_y = 1.0
    render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    scene.display_settings.display_device = "sRGB"
    settings = render.image_settings
    if hasattr(settings, "media_type"):
        settings.media_type = "IMAGE"
    settings.file_format, settings.color_depth, settings.exr_codec = "OPEN_EXR", "32", "NONE"
    return scene


def _core_camera(bpy, camera, scene):
    """The core Camera that splat_addon/data/camera.py makes of the scene camera (what the engine renders
    through), as plain numbers."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    cam = camera.from_object(
        scene.camera.evaluated_get(depsgraph), scene, scene.render.resolution_x, scene.render.resolution_y
    )
    return {
        "width": cam.width,
        "height": cam.height,
        "fx": cam.fx,
        "fy": cam.fy,
        "cx": cam.cx,
        "cy": cam.cy,
        "world_to_camera": cam.world_to_camera.tolist(),
        "near": cam.near,
        "far": None if not np.isfinite(cam.far) else cam.far,
        "projection": cam.projection,
    }


def _direct(bpy, camera, scene, job):
    """A renderer calling the installed extension's core.render on the PLY's splats through the camera
    conversion the engine uses (splat_addon/data/camera.py), without Blender's render pipeline; its image
    is kept as scene-linear RGBA like the others (the core's display sRGB turned linear)."""
    render = importlib.import_module(f"{MODULE}.core.render")
    color = importlib.import_module(f"{MODULE}.core.color")
    cloud = importlib.import_module(f"{MODULE}.io").read_splats(job["ply"])
    depsgraph = bpy.context.evaluated_depsgraph_get()
    cam = camera.from_object(
        scene.camera.evaluated_get(depsgraph), scene, scene.render.resolution_x, scene.render.resolution_y
    )

    def run(r):
        start = time.perf_counter()
        image = render.render(cloud, cam, background=(0.0, 0.0, 0.0)).color
        seconds = time.perf_counter() - start
        run.image = np.concatenate(
            [color.srgb_to_linear(image, np.float32), np.ones(image.shape[:2] + (1,), np.float32)], axis=-1
        )
        return seconds, None

    return run


def _render(bpy, scene, r, job):
    """One render of renderer `r`; (seconds, an error the engine reported or None)."""
    scene.render.engine = r["engine"]
    if r["engine"] == "CYCLES":
        cycles = scene.cycles
        cycles.device = "CPU"
        cycles.samples = r["samples"]
        cycles.use_adaptive_sampling = False  # exactly `samples` per pixel
        cycles.use_denoising = False  # the noise is what the sample count buys
        cycles.seed = 0
        cycles.pixel_filter_type, cycles.filter_width = r.get("filter", ("BLACKMAN_HARRIS", 1.5))  # default: 1.5 px
    elif r["engine"] == "BLENDER_EEVEE":
        scene.eevee.taa_render_samples = r["samples"]
    start = time.perf_counter()
    try:
        bpy.ops.render.render()
    except RuntimeError as exc:  # an engine's ERROR report, in background mode
        return time.perf_counter() - start, str(exc)
    return time.perf_counter() - start, None


def _pixels(bpy, scene, work, name):
    """The last render as scene-linear RGBA (EXR keeps the render's values; no view transform)."""
    path = work / f"{name}.exr"
    bpy.data.images["Render Result"].save_render(filepath=str(path), scene=scene)
    image = bpy.data.images.load(str(path))
    try:
        width, height = image.size
        pixels = np.empty(width * height * 4, np.float32)
        image.pixels.foreach_get(pixels)
    finally:
        bpy.data.images.remove(image)
    return pixels.reshape(height, width, 4)[::-1].copy()  # Blender's rows start at the bottom


def _view_png(bpy, scene, work):
    """The last render saved as a 16-bit PNG (view transform applied) and read back as its raw
    values: the display picture, to check the display conversion the bench applies to the EXR."""
    settings = scene.render.image_settings
    old = settings.file_format, settings.color_depth
    settings.file_format, settings.color_depth = "PNG", "16"
    path = work / "check.png"
    try:
        bpy.data.images["Render Result"].save_render(filepath=str(path), scene=scene)
    finally:
        settings.file_format = old[0]
        settings.color_depth, settings.exr_codec = old[1], "NONE"
    image = bpy.data.images.load(str(path))
    try:
        image.colorspace_settings.name = "Non-Color"  # the file's numbers, not decoded
        width, height = image.size
        pixels = np.empty(width * height * 4, np.float32)
        image.pixels.foreach_get(pixels)
    finally:
        bpy.data.images.remove(image)
    return pixels.reshape(height, width, 4)[::-1].copy()


if __name__ == "__main__":
    main(sys.argv[1])
