"""Mesh to Splats with the look Cycles gives the mesh in its scene (core/bake.py does the fit).

The object is rendered by Cycles on the CPU from core.bake.bake_views' cameras around it, in its
scene: the scene's lights, world and other objects light it and cast shadows on it, but the camera
sees the object alone (every other object is made invisible to camera rays, the world transparent;
splat objects, whose display points Cycles would render as spheres, are left out of the render),
over black, as splats render. Images are written as 8-bit PNG through the scene's colour management
(what a render of the scene shows) and read back as display values, the splats' colour space.

Each view is one step that leaves the scene as it was: a temporary camera made and removed, the
render settings and visibility flags it changes put back, the image read and removed. So a job
cancelled between steps leaves nothing behind, and neither does a finished one.
"""

import contextlib
import os
import tempfile

import bpy
import mathutils
import numpy as np

from ...core import geometry
from ...core import sh as shmod
from ...core.bake import (
    DEFAULT_ITERATIONS,
    VIEWS_PER_DISTANCE,
    bake_sh_steps,
    bake_splats_steps,
    bake_views,
    path_weights,
)
from ...core.camera import blender_lens, opengl_camera_to_world
from ...core.steps import mapped_steps
from .. import data

TEMPORARY = "splatwright_bake"


def bake_steps(
    scene,
    obj,
    cloud,
    vertices,
    *,
    samples=16,
    count=VIEWS_PER_DISTANCE,
    size=256,
    distances=None,
    degree=2,
    iterations=DEFAULT_ITERATIONS,
    geometry_steps=0,
    path=(),
    info=None,
):
    """A generator baking `obj`'s look into `cloud` (object space, made from the object's evaluated
    `vertices`): yields (done, total, label) per Cycles view and per fitting iteration or step and
    returns the cloud with fitted SH of `degree`. `path`: core Cameras (world space) the object will
    be seen from, baked from beside the views around it and weighted to count as much as those
    together (core.bake.path_weights: highlights come out right only near views fitted).
    `geometry_steps`: Adam steps that then fit the splats' positions, shapes and opacities too
    (core.bake.bake_splats); without them the geometry is kept. The fit runs in world space, where
    the cameras are; the SH (and fitted splats) are turned back into the object's axes."""
    world = np.array(obj.matrix_world, dtype=np.float64)
    points = np.asarray(vertices, np.float64) @ world[:3, :3].T + world[:3, 3]
    around = bake_views(points, size, count, distances)
    cameras = around + list(path)
    total = len(cameras) + iterations + 1 + geometry_steps
    images = []
    with tempfile.TemporaryDirectory(prefix="splatwright-bake-") as folder:
        for i, cam in enumerate(cameras):
            images.append(render_view(scene, obj, cam, samples, os.path.join(folder, f"view_{i}.png")))
            yield i + 1, total, f"bake: Cycles view {i + 1}/{len(cameras)}"
    weights = path_weights(len(around), len(cameras) - len(around))
    fit = bake_sh_steps(
        cloud.transformed(world), cameras, images, degree, iterations=iterations, weights=weights, info=info
    )
    fitted = yield from _relabelled(fit, len(cameras), total, "fitting colours")
    if geometry_steps:
        steps = bake_splats_steps(
            fitted,
            cameras,
            images,
            steps=geometry_steps,
            weights=weights,
            report_every=1,
            info=None if info is None else info.setdefault("geometry", {}),
        )
        fitted = yield from _relabelled(steps, total - geometry_steps, total, "fitting splats")
        return fitted.transformed(np.linalg.inv(world))
    rotation = geometry.polar_rotation(world[:3, :3])
    return cloud.replace(sh=shmod.rotate(fitted.sh, rotation.T).astype(np.float32))


def _relabelled(steps, offset, total, what):
    """Pass a core generator's (done, total, label) on as a bake's steps from `offset`; returns its value."""
    return mapped_steps(steps, lambda done, count, _: (offset + done, total, f"bake: {what} {done}/{count}"))


def render_view(scene, obj, cam, samples, path):
    """(H, W, 3) display-sRGB image of `obj` alone, lit by its scene, seen by the core Camera `cam`
    (world space), premultiplied over black; the scene is left as it was."""
    cam_data = bpy.data.cameras.new(TEMPORARY)
    cam_obj = bpy.data.objects.new(TEMPORARY, cam_data)
    image = None
    try:
        scene.collection.objects.link(cam_obj)
        lens = blender_lens(cam)
        for name in ("sensor_fit", "sensor_width", "sensor_height", "shift_x", "shift_y", "type", "lens"):
            setattr(cam_data, name, lens[name])
        if lens["ortho_scale"] is not None:
            cam_data.ortho_scale = lens["ortho_scale"]
        cam_data.clip_start = cam.near
        cam_data.clip_end = cam.far if np.isfinite(cam.far) else 1e6 * max(cam.near, 1e-6)
        cam_obj.matrix_world = mathutils.Matrix(opengl_camera_to_world(cam.world_to_camera).tolist())  # rows
        others = [o for o in scene.objects if o is not obj and o is not cam_obj]
        hidden = [(o, "hide_render", True) if data.is_splat_object(o) else (o, "visible_camera", False) for o in others]
        with _changed(_settings(scene, cam_obj, cam, lens, samples, path) + hidden):
            bpy.ops.render.render(write_still=True, scene=scene.name)
        image = bpy.data.images.load(path, check_existing=False)
        pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
        image.pixels.foreach_get(pixels)
        rgba = pixels.reshape(image.size[1], image.size[0], image.channels)[::-1]  # row 0 at the top
    finally:
        if image is not None:
            bpy.data.images.remove(image)
        bpy.data.objects.remove(cam_obj)
        bpy.data.cameras.remove(cam_data)
    if rgba.shape[2] < 4:
        return np.ascontiguousarray(rgba[..., :3])
    return np.ascontiguousarray(rgba[..., :3] * rgba[..., 3:])


def _settings(scene, cam_obj, cam, lens, samples, path):
    """(owner, attribute, value) of every setting a bake view changes (`lens`: the camera's blender_lens)."""
    render, image = scene.render, scene.render.image_settings
    return [
        (scene, "camera", cam_obj),
        (render, "engine", "CYCLES"),
        (scene.cycles, "device", "CPU"),
        (scene.cycles, "samples", int(samples)),
        (scene.cycles, "use_denoising", True),
        (render, "resolution_x", cam.width),
        (render, "resolution_y", cam.height),
        (render, "resolution_percentage", 100),
        (render, "pixel_aspect_x", lens["pixel_aspect_x"]),
        (render, "pixel_aspect_y", lens["pixel_aspect_y"]),
        (render, "use_border", False),
        (render, "film_transparent", True),
        (render, "use_compositing", False),
        (render, "use_sequencer", False),
        (render, "use_multiview", False),
        (render, "filepath", path),
        (render, "use_file_extension", False),
        (image, "file_format", "PNG"),
        (image, "color_mode", "RGBA"),
        (image, "color_depth", "8"),
    ]


@contextlib.contextmanager
def _changed(settings):
    """Set each (owner, attribute, value) for the duration, then put every old value back."""
    old = []
    try:
        for owner, name, value in settings:
            old.append((owner, name, getattr(owner, name)))
            setattr(owner, name, value)
        yield
    finally:  # in order: a file format before its colour depth
        for owner, name, value in old:
            setattr(owner, name, value)
