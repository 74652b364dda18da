"""A Blender camera object -> the core Camera: reads the numbers, core.camera does the math."""

import numpy as np

from ...core.camera import Camera


class CameraError(ValueError):
    """A camera the core renderer cannot reproduce (panoramic, not a camera, a degenerate transform)."""


def lens_settings(cam_data, render):
    """The keyword arguments of core.camera.blender_intrinsics for a Blender camera datablock."""
    if cam_data.type not in ("PERSP", "ORTHO"):
        raise CameraError(
            f"camera '{cam_data.name}' is {cam_data.type}; Splatwright renders perspective and orthographic cameras"
        )
    return {
        "lens": cam_data.lens,
        "sensor_width": cam_data.sensor_width,
        "sensor_height": cam_data.sensor_height,
        "sensor_fit": cam_data.sensor_fit,
        "shift_x": cam_data.shift_x,
        "shift_y": cam_data.shift_y,
        "type": cam_data.type,
        "ortho_scale": cam_data.ortho_scale,
        "pixel_aspect_x": render.pixel_aspect_x,
        "pixel_aspect_y": render.pixel_aspect_y,
    }


def from_object(cam_obj, scene, width, height, origin=(0.0, 0.0, 0.0)):
    """The core Camera for an (evaluated) Blender camera object at the given output size, in a world
    frame moved by -`origin`."""
    if cam_obj.type != "CAMERA":
        raise CameraError(f"the scene camera '{cam_obj.name}' is {cam_obj.type.lower()}, not a camera object")
    cam_data = cam_obj.data
    matrix = np.array(cam_obj.matrix_world, dtype=np.float64)
    if not np.isfinite(matrix).all() or np.linalg.det(matrix[:3, :3]) == 0:
        raise CameraError(f"camera '{cam_obj.name}' has a zero scale or a transform holding NaN or Inf")
    matrix[:3, 3] -= origin
    return Camera.from_blender(
        matrix,
        width,
        height,
        clip_start=cam_data.clip_start,
        clip_end=cam_data.clip_end,
        **lens_settings(cam_data, scene.render),
    )
