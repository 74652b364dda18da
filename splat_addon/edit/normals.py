"""Estimate Normals: each splat's surface normal from its shape (core.normals), stored as the splat
object's material normals (the extras nx, ny, nz) for relighting, oriented towards the scene's
cameras (those that saw each splat) or away from the splats' centre."""

import json

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty

from ...core import geometry, material
from ...core import normals as core_normals
from ...core.camera import spread_along
from .. import data
from ..data import camera as cameras
from ..data.errors import EXPECTED_ERRORS

ORIENT_ITEMS = (
    ("CAMERAS", "Cameras", "Face the scene's cameras that see each splat (away from the centre without cameras)"),
    ("CENTRE", "Away from Centre", "Point away from the splats' centre (right for closed, convex shapes)"),
)
# Object property: JSON of the last estimate (splats, too_round, cameras, orient), for the panel and tests.
REPORT_KEY = "splatwright_normals_report"


class SPLAT_OT_estimate_normals(bpy.types.Operator):
    """Estimate each splat's surface normal from its shape (its shortest axis) for relighting,
    facing the scene's cameras or pointing away from the splats' centre"""

    bl_idname = "splat.estimate_normals"
    bl_label = "Estimate Normals"
    bl_options = {"REGISTER", "UNDO"}

    orient: EnumProperty(name="Orient", items=ORIENT_ITEMS, default="CAMERAS")
    # Each camera costs a render of the splats (about 1 s per 200k splats without compiled kernels):
    # a capture's hundreds of cameras are thinned to this many, spread along their order by name.
    max_cameras: IntProperty(
        name="Cameras at Most",
        description="Use at most this many of the scene's cameras, spread evenly along them by name",
        default=32,
        min=1,
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT" and data.is_splat_object(context.active_object)

    def execute(self, context):
        obj = context.active_object
        if obj.data.users > 1:
            self.report({"ERROR"}, f"splat data shared by several objects: {obj.name}")
            return {"CANCELLED"}
        scene = context.scene
        try:
            matrix = np.array(obj.matrix_world, dtype=np.float64)
            world = data.object_to_cloud(obj, matrix)  # the cameras live in world space
            views, unusable = scene_cameras(scene) if self.orient == "CAMERAS" else ([], [])
            if len(views) > self.max_cameras:
                centre = core_normals.robust_centre(world.positions)
                views = [views[i] for i in spread_along(views, self.max_cameras, centre)]
            found = core_normals.estimate_normals(world, cameras=views or None)
            own = geometry.transform_normals(np.linalg.inv(matrix[:3, :3]), found)  # world -> object: A^T n
            stored = material.with_material(data.object_cloud(obj), normals=own)
            skipped = data.set_extras(obj, {k: stored.extras[k] for k in material.NORMALS})
        except EXPECTED_ERRORS as exc:  # camera errors are ValueErrors too
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if skipped:
            self.report({"ERROR"}, f"'{obj.name}' cannot hold normals as attributes: {', '.join(skipped)}")
            return {"CANCELLED"}
        too_round = int(core_normals.too_round(world).sum())
        obj[REPORT_KEY] = json.dumps(
            {"splats": len(world), "too_round": too_round, "cameras": len(views), "orient": self.orient}
        )
        self.report({"INFO"}, summary(len(world), too_round, len(views), self.orient))
        if unusable:
            self.report({"WARNING"}, f"cameras not used: {'; '.join(unusable)}")
        return {"FINISHED"}


def scene_cameras(scene):
    """The scene's camera objects as core Cameras at its output size (world space), and a note for
    each that cannot be one (panoramic, degenerate transform)."""
    render = scene.render
    scale = render.resolution_percentage / 100.0
    width, height = max(1, round(render.resolution_x * scale)), max(1, round(render.resolution_y * scale))
    views, unusable = [], []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        if obj.type != "CAMERA":
            continue
        try:
            views.append(cameras.from_object(obj, scene, width, height))
        except ValueError as exc:  # CameraError, or a matrix Camera refuses
            unusable.append(str(exc))
    return views, unusable


def summary(count, round_count, camera_count, orient):
    """The operator's report: how many normals, how oriented, how many too round to trust."""
    if camera_count:
        how = f"facing {camera_count} camera{'s' if camera_count != 1 else ''}"
    else:
        how = "away from the centre" + (" (the scene has no cameras)" if orient == "CAMERAS" else "")
    return (
        f"Estimated normals of {count} splats, {how}; {round_count} too round to trust "
        f"({100.0 * round_count / max(count, 1):.1f}%)"
    )


CLASSES = (SPLAT_OT_estimate_normals,)
