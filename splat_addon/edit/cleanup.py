"""Clean-up and grading of splat objects, kept as settings on the object and applied wherever the
splats are read (export, animation export, the render engine, collisions: data.evaluated_cloud), so
the splats themselves stay as captured: change a setting, or clear it, at any time; Blender's undo
covers every change. Settings are simpler than a geometry-nodes modifier here because grading turns
every SH band by a 3x3 map and cropping by a closed mesh needs a winding number, neither of which
geometry nodes can do on both splat forms of every Blender from 4.2. What the display modifier
draws in the Solid viewport is the unedited splats; the Rendered viewport and every export show
the edits ('baked on export').

Settings (object property "splatwright_cleanup", JSON), each applied to the splats the object shows
(posed, modified) in object space, masks first (all computed on the unedited splats, so their order
does not matter), then the grade, then the SH degree:

    crop         {"volume": object name, "invert": bool}: inside an Empty's cube (its display size)
                 or a closed mesh (winding number; the mesh's own data, modifiers not applied)
    opacity      keep splats at least this opaque
    size         [min, max]: keep splats whose largest standard deviation, in world units, lies in it
    visibility   keep splats whose largest blending weight over the scene camera's frames exceeds this;
                 the weights are measured once by splat.prune and kept in VISIBILITY (per own splat)
    grade        {"exposure", "saturation", "hue" (radians), "white": [r, g, b]}: core.cleanup
    sh_degree    keep SH bands up to this degree
"""

import json

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, StringProperty

from ...core import cleanup as core_cleanup
from ...core import economy
from .. import data
from ..data import camera as blender_camera
from ..data.errors import EXPECTED_ERRORS
from ..data.meshes import mesh_triangles

SETTINGS = "splatwright_cleanup"
REPORT = "splatwright_cleanup_report"  # the last change's report (JSON), for panels and scripts
VISIBILITY = ".splatwright_visibility"  # FLOAT point attribute: largest weight over the camera path
DEFAULT_MAX_FRAMES = 24
VISIBILITY_SIZE = 256  # pixels on the long side of the visibility renders


class CleanupError(ValueError):
    """A clean-up that cannot be set; the message names the object and the problem."""


# settings -------------------------------------------------------------------------------------------


def settings_of(obj):
    """The object's clean-up settings (a dict; empty when it has none)."""
    return json.loads(obj.get(SETTINGS, "{}") or "{}")


def store_settings(obj, settings):
    if settings:
        obj[SETTINGS] = json.dumps(settings)
    elif SETTINGS in obj:
        del obj[SETTINGS]


def _object_scale(matrix):
    """The object's size factor: the cube root of its volume scale."""
    return abs(float(np.linalg.det(matrix[:3, :3]))) ** (1.0 / 3.0)


def crop_mask(obj, depsgraph, positions, crop):
    """(N,) bool: object-space `positions` of `obj` inside (or, inverted, outside) the crop volume."""
    volume = bpy.data.objects.get(crop["volume"])
    if volume is None:
        raise data.SplatObjectError(f"'{obj.name}': its crop volume '{crop['volume']}' is gone")
    to_object = np.linalg.inv(data.world_matrix(obj, depsgraph)) @ data.world_matrix(volume, depsgraph)
    if volume.type == "EMPTY":
        inside = core_cleanup.inside_box(positions, to_object @ np.diag([volume.empty_display_size] * 3 + [1.0]))
    else:
        vertices, triangles = mesh_triangles(volume.data)
        inside = core_cleanup.inside_mesh(positions, vertices @ to_object[:3, :3].T + to_object[:3, 3], triangles)
    return ~inside if crop.get("invert") else inside


def visibility_weights(obj, count):
    """The stored visibility weights of `obj`, repeated for copies its modifiers make (count a
    multiple of its own splats)."""
    attr = obj.data.attributes.get(VISIBILITY)
    own = data.splat_count(obj.data)
    if attr is None or len(attr.data) != own or own == 0 or count % own:
        raise data.SplatObjectError(
            f"'{obj.name}': its visibility was measured for other splats; prune by visibility again"
        )
    weights = np.empty(own, np.float32)
    attr.data.foreach_get("value", weights)
    return np.tile(weights, count // own)


def keep_mask(obj, depsgraph, cloud, settings):
    """(N,) bool of the splats of `cloud` the settings keep, or None when no setting drops any."""
    keep = None

    def both(mask):
        return mask if keep is None else keep & mask

    if "crop" in settings:
        keep = both(crop_mask(obj, depsgraph, cloud.positions, settings["crop"]))
    if "opacity" in settings:
        keep = both(economy.opacity_mask(cloud, settings["opacity"]))
    if "size" in settings:
        low, high = settings["size"]
        scale = _object_scale(data.world_matrix(obj, depsgraph))
        keep = both(core_cleanup.size_mask(cloud, low, np.inf if high is None else high, scale))
    if "visibility" in settings:
        keep = both(visibility_weights(obj, len(cloud)) > settings["visibility"])
    return keep


def apply_settings(obj, depsgraph, cloud):
    """`cloud` (what `obj` shows, object space) with the object's clean-up and grade applied: a
    data.EDITS hook."""
    settings = settings_of(obj)
    if not settings:
        return cloud
    try:
        keep = keep_mask(obj, depsgraph, cloud, settings)
        if keep is not None:
            cloud = cloud[keep]
        if "grade" in settings:
            cloud = core_cleanup.graded(cloud, core_cleanup.grade_matrix(**settings["grade"]))
    except core_cleanup.CleanupError as exc:
        raise data.SplatObjectError(f"'{obj.name}': {exc}") from None
    degree = settings.get("sh_degree")
    if degree is not None and degree < cloud.sh_degree:
        cloud = cloud.with_sh_degree(degree)
    return cloud


# measuring ------------------------------------------------------------------------------------------


def change_report(context, obj, measure=True):
    """What `obj`'s edits save and cost against its unedited splats (world space, the current frame):
    core.economy.change_report, stored on the object as REPORT and returned."""
    depsgraph = context.evaluated_depsgraph_get()
    before = data.evaluated_cloud(obj, depsgraph, edits=False)
    after = data.evaluated_cloud(obj, depsgraph)
    report = economy.change_report(before, after, views=None if measure else [])
    obj[REPORT] = json.dumps(report)  # an unchanged image's PSNR is written Infinity
    return report


def camera_path_weights(context, obj, max_frames=DEFAULT_MAX_FRAMES):
    """(own splats,) float32: each splat's largest blending weight T alpha over the scene camera's
    frames (at most `max_frames`, spread over the frame range), posed as each frame shows it, by
    the renderer's own rules (core.economy.contributions)."""
    scene = context.scene
    if scene.camera is None:
        raise CleanupError("the scene has no camera: visibility is measured along the scene camera's path")
    frames = np.unique(
        np.linspace(scene.frame_start, scene.frame_end, min(max_frames, scene.frame_end - scene.frame_start + 1))
        .round()
        .astype(int)
    )
    width, height = _visibility_size(scene)
    own = data.splat_count(obj.data)
    best = np.zeros(own, np.float32)
    current = scene.frame_current
    try:
        for frame in frames:
            scene.frame_set(int(frame))
            depsgraph = context.evaluated_depsgraph_get()
            cloud = data.evaluated_cloud(obj, depsgraph, edits=False)
            if own == 0 or len(cloud) % own:
                raise CleanupError(
                    f"'{obj.name}': its modifiers change its splat count, so its splats' visibility cannot be kept"
                )
            cam = blender_camera.from_object(scene.camera.evaluated_get(depsgraph), scene, width, height)
            weight = economy.contributions(cloud, [cam]).reshape(-1, own).max(axis=0)
            np.maximum(best, weight, out=best)
    finally:
        scene.frame_set(current)
    return best, len(frames)


def _visibility_size(scene):
    """The render's aspect at VISIBILITY_SIZE pixels on its long side (or its own size, if smaller)."""
    pct = scene.render.resolution_percentage
    width, height = scene.render.resolution_x * pct / 100, scene.render.resolution_y * pct / 100
    factor = min(1.0, VISIBILITY_SIZE / max(width, height))
    return max(1, round(width * factor)), max(1, round(height * factor))


# operators ------------------------------------------------------------------------------------------


def splat_targets(context, exclude=()):
    """The selected splat objects (not those in `exclude`), or CleanupError naming what was selected."""
    chosen = [o for o in context.selected_objects if data.is_splat_object(o) and o not in exclude]
    if not chosen:
        others = ", ".join(f"'{o.name}' ({o.type.lower()})" for o in context.selected_objects if o not in exclude)
        raise CleanupError("no splat objects selected" + (f": {others} are not splat objects" if others else ""))
    return chosen


class _CleanupOperator:
    """Sets one setting on every selected splat object, then reports what it saves and costs."""

    bl_options = {"REGISTER", "UNDO"}

    measure: BoolProperty(
        name="Measure",
        default=True,
        description="Report the render error of the change (PSNR over a few views around "
        "the splats); off is quicker for huge clouds",
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def execute(self, context):
        try:
            targets = self.targets(context)
            changes = [(obj, self.change(context, obj)) for obj in targets]  # everything checked first
        except (CleanupError, core_cleanup.CleanupError, *EXPECTED_ERRORS) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        olds = {obj.name: settings_of(obj) for obj in targets}
        try:
            for obj, (key, value) in changes:
                settings = settings_of(obj)
                if value is None:
                    settings.pop(key, None)
                else:
                    settings[key] = value
                store_settings(obj, settings)
                self.stored(obj)
            reports = [(obj, change_report(context, obj, self.measure)) for obj in targets]
        except EXPECTED_ERRORS as exc:  # a setting that cannot be applied: put the old back
            for obj in targets:
                store_settings(obj, olds[obj.name])
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for obj, report in reports:
            self.report({"INFO"}, f"'{obj.name}' {self.bl_label.lower()}: {economy.describe_change(report)}")
        return {"FINISHED"}

    def targets(self, context):
        return splat_targets(context)

    def stored(self, obj):
        """After the setting is stored on `obj` (what else it needs)."""


class SPLAT_OT_crop(_CleanupOperator, bpy.types.Operator):
    """Keep only the splats inside a box (an Empty's cube) or a closed mesh (the active object unless
    named), applied on export and render; the splats themselves stay"""

    bl_idname = "splat.crop"
    bl_label = "Crop Splats"
    bl_options = {"REGISTER", "UNDO"}

    volume: StringProperty(
        name="Volume", default="", description="Empty (its cube) or closed mesh to crop to (empty: the active object)"
    )
    invert: BoolProperty(name="Invert", default=False, description="Keep the splats outside the volume instead")
    clear: BoolProperty(name="Clear", default=False, description="Remove the crop")

    def targets(self, context):
        self._volume = None if self.clear else self.find_volume(context)
        return splat_targets(context, exclude=(self._volume,))

    def find_volume(self, context):
        volume = bpy.data.objects.get(self.volume) if self.volume else context.view_layer.objects.active
        if volume is None:
            raise CleanupError(
                f"no object named '{self.volume}'"
                if self.volume
                else "no crop volume: make an Empty or a closed mesh the active object, or name it"
            )
        if volume.type not in ("EMPTY", "MESH") or data.is_splat_object(volume):
            raise CleanupError(
                f"'{volume.name}' ({volume.type.lower()}) cannot be a crop volume: use an Empty "
                "(its cube) or a closed mesh"
            )
        if volume.type == "MESH" and not len(volume.data.polygons):
            raise CleanupError(f"the crop mesh '{volume.name}' has no faces: it encloses no volume")
        return volume

    def change(self, context, obj):
        return "crop", None if self.clear else {"volume": self._volume.name, "invert": self.invert}


class SPLAT_OT_prune(_CleanupOperator, bpy.types.Operator):
    """Remove splats by opacity, by size, or by visibility along the scene camera's path (splats that
    never add a visible amount to any pixel of its frames), applied on export and render"""

    bl_idname = "splat.prune"
    bl_label = "Prune Splats"
    bl_options = {"REGISTER", "UNDO"}

    by: EnumProperty(
        name="By",
        default="OPACITY",
        items=(
            ("OPACITY", "Opacity", "Remove splats fainter than the threshold"),
            (
                "SIZE",
                "Size",
                "Remove splats smaller or larger than the sizes (largest standard deviation, world units)",
            ),
            ("VISIBILITY", "Camera Visibility", "Remove splats the scene camera never sees over the frame range"),
        ),
    )
    threshold: FloatProperty(name="Min Opacity", default=0.05, min=0.0, max=1.0)
    min_size: FloatProperty(name="Min Size", default=0.0, min=0.0, unit="LENGTH")
    max_size: FloatProperty(
        name="Max Size", default=0.0, min=0.0, unit="LENGTH", description="Remove splats larger than this (0: no limit)"
    )
    min_weight: FloatProperty(
        name="Min Weight",
        default=1.0 / 255.0,
        min=0.0,
        max=1.0,
        description="Remove splats whose largest blending weight (T alpha) over the camera's frames is not above this",
    )
    max_frames: IntProperty(
        name="Frames",
        default=DEFAULT_MAX_FRAMES,
        min=1,
        max=1000,
        description="Camera frames to look from, spread over the frame range",
    )
    clear: BoolProperty(name="Clear", default=False, description="Remove this kind of pruning")

    KEYS = {"OPACITY": "opacity", "SIZE": "size", "VISIBILITY": "visibility"}

    def change(self, context, obj):
        key = self.KEYS[self.by]
        if self.clear:
            return key, None
        if self.by == "OPACITY":
            return key, self.threshold
        if self.by == "SIZE":
            if self.max_size and self.max_size < self.min_size:
                raise CleanupError(f"max size {self.max_size:g} is below min size {self.min_size:g}")
            return key, [self.min_size, self.max_size or None]
        weights, _ = camera_path_weights(context, obj, self.max_frames)
        self._pending = getattr(self, "_pending", {})  # written once every object is checked
        self._pending[obj.name] = weights
        return key, self.min_weight

    def stored(self, obj):
        weights = getattr(self, "_pending", {}).get(obj.name)
        if weights is not None:
            data.set_attribute(obj.data, VISIBILITY, "FLOAT", weights)


class SPLAT_OT_grade(_CleanupOperator, bpy.types.Operator):
    """Grade the splats' colours (exposure, saturation, hue, white balance) on every SH band alike, so
    view-dependent colour is graded too; applied on export and render"""

    bl_idname = "splat.grade"
    bl_label = "Grade Splats"
    bl_options = {"REGISTER", "UNDO"}

    exposure: FloatProperty(
        name="Exposure", default=0.0, min=-10.0, max=10.0, description="Stops: colours times 2^exposure"
    )
    saturation: FloatProperty(name="Saturation", default=1.0, min=0.0, max=4.0)
    hue: FloatProperty(
        name="Hue",
        default=0.0,
        min=-np.pi,
        max=np.pi,
        subtype="ANGLE",
        description="Turn of the hues about the grey axis",
    )
    white: FloatVectorProperty(
        name="White",
        default=(1.0, 1.0, 1.0),
        min=1e-3,
        max=1.0,
        size=3,
        subtype="COLOR",
        description="The colour that becomes neutral grey (white balance)",
    )
    clear: BoolProperty(name="Clear", default=False, description="Remove the grade")

    def change(self, context, obj):
        if self.clear:
            return "grade", None
        grade = {"exposure": self.exposure, "saturation": self.saturation, "hue": self.hue, "white": list(self.white)}
        core_cleanup.grade_matrix(**grade)  # refused here, not at export
        return "grade", grade


class SPLAT_OT_reduce_sh(_CleanupOperator, bpy.types.Operator):
    """Keep spherical-harmonic bands up to a degree (less view-dependent colour, fewer bytes), applied
    on export and render"""

    bl_idname = "splat.reduce_sh"
    bl_label = "Reduce SH Degree"
    bl_options = {"REGISTER", "UNDO"}

    degree: IntProperty(name="Degree", default=1, min=0, max=3)
    clear: BoolProperty(name="Clear", default=False, description="Keep every band again")

    def change(self, context, obj):
        return "sh_degree", None if self.clear else self.degree


class SPLAT_OT_clear_cleanup(bpy.types.Operator):
    """Remove every clean-up and grade setting of the selected splat objects"""

    bl_idname = "splat.clear_cleanup"
    bl_label = "Clear Splat Clean-up"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            targets = splat_targets(context)
        except CleanupError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for obj in targets:
            store_settings(obj, {})
            if REPORT in obj:
                del obj[REPORT]
            if VISIBILITY in obj.data.attributes:
                obj.data.attributes.remove(obj.data.attributes[VISIBILITY])
        return {"FINISHED"}


CLASSES = (SPLAT_OT_crop, SPLAT_OT_prune, SPLAT_OT_grade, SPLAT_OT_reduce_sh, SPLAT_OT_clear_cleanup)


def register():
    if apply_settings not in data.EDITS:
        data.EDITS.append(apply_settings)


def unregister():
    if apply_settings in data.EDITS:
        data.EDITS.remove(apply_settings)
