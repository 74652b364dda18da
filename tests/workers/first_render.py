"""A user's first renders after installing the extension, in a fresh Blender (a bpy-only Python):

    python first_render.py JOB.json

JOB.json names the extension zip, a PLY, the image size, how many F12 renders to run and the work
folder. BLENDER_USER_RESOURCES (a fresh user folder) and SPLATWRIGHT_CACHE_DIR (the kernel cache:
empty for a first render) are set by the caller. The child installs the zip as Install from Disk
does, imports the PLY with the extension's importer, renders the scene with the Splatwright engine
`renders` times (bpy.ops.render.render, the F12 path) and writes into the work folder:

    results.json   seconds of the install and of each render, the kernels' status (render.backend_status)
    render.npy     the first render's pixels (RGBA float32, scene-linear, row 0 at the bottom)

Only the standard library, NumPy, bpy and the installed extension are used.
"""

import importlib
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

MODULE = "bl_ext.user_default.splatwright"


def run(job, work, results):
    import bpy

    start = time.perf_counter()
    bpy.ops.extensions.package_install_files(filepath=job["zip"], repo="user_default", enable_on_install=True)
    results["install_s"] = time.perf_counter() - start
    for obj in list(bpy.data.objects):
        if obj.type != "CAMERA":
            bpy.data.objects.remove(obj)
    bpy.ops.splat.import_file(filepath=job["ply"])
    scene = bpy.context.scene
    camera = scene.camera
    camera.location, camera.rotation_euler = (0.0, -4.0, 0.0), (np.pi / 2, 0.0, 0.0)
    scene.render.engine = "SPLATWRIGHT"
    scene.render.resolution_x, scene.render.resolution_y = job["size"]
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    results["render_s"] = []
    for i in range(job["renders"]):
        start = time.perf_counter()
        bpy.ops.render.render()
        results["render_s"].append(time.perf_counter() - start)
        if i == 0:
            path = work / "render.exr"
            image = scene.render.image_settings
            if hasattr(image, "media_type"):
                image.media_type = "IMAGE"
            image.file_format, image.color_depth = "OPEN_EXR", "32"
            bpy.data.images["Render Result"].save_render(str(path))
            loaded = bpy.data.images.load(str(path))
            pixels = np.empty(len(loaded.pixels), np.float32)
            loaded.pixels.foreach_get(pixels)
            np.save(work / "render.npy", pixels.reshape(job["size"][1], job["size"][0], 4))
    results["backend"] = importlib.import_module(f"{MODULE}.core.render").backend_status()
    results["numba"] = getattr(sys.modules.get("numba"), "__file__", None)


def main(job_path):
    job = json.loads(Path(job_path).read_text())
    work = Path(job["work"])
    results = {}
    try:
        run(job, work, results)
    except Exception:  # noqa: BLE001 - handed to the caller, which raises it with the log
        results["error"] = traceback.format_exc()
    (work / "results.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main(sys.argv[1])
