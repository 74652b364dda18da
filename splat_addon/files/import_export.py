"""Import / export operators, usable from Python in background mode (execute never needs a UI)."""

from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper, axis_conversion, orientation_helper

from ..core import SplatCloud, SplatValidationError
from ..io import FORMATS, SplatFileError, read_splats, write_splats
from ..io.common import nonfinite_counts
from . import data, display
from .export_options import ExportOptionProperties

FILTER_GLOB = ";".join(f"*{ext}" for ext in FORMATS)
EXTENSIONS = ";".join(FORMATS)
MENU_LABEL = "Gaussian Splats (.ply, .spz, .usd, .sog, .glb, .splat)"
DISPLAY_BUDGET = 1_000_000      # splats drawn per object before the display thins itself out

# 3DGS captures come out of COLMAP/OpenCV: the scene's up is -Y and cameras look along +Z. These
# defaults turn that upright in Blender (file x, y, z -> Blender x, z, -y, a quarter turn about X).
FILE_FORWARD, FILE_UP = "Z", "-Y"
# What a failed read or write can raise; anything else is a bug and should surface as one.
EXPECTED_ERRORS = (SplatFileError, SplatValidationError, data.SplatObjectError, OSError, ValueError)


def upright():
    """The Blender placement of a file's axes by default (file x, y, z -> Blender x, z, -y)."""
    return np.array(axis_conversion(from_forward=FILE_FORWARD, from_up=FILE_UP).to_4x4(), dtype=np.float64)


def export_conversion(forward=None, up=None):
    """The Blender -> file axis matrix: the given axes, else the default (a 3DGS capture's axes).
    The same for every format: the io layer turns the model's axes into each format's own (OpenUSD
    files come out Y-up, with Blender's Z as their Y)."""
    return axis_conversion(to_forward=forward or FILE_FORWARD, to_up=up or FILE_UP).to_4x4()


class _Progress:
    """Blender's progress API where there is a window to show it in; silent otherwise."""

    def __init__(self, context, total):
        self.wm = context.window_manager if context.window is not None else None
        if self.wm is not None:
            self.wm.progress_begin(0, max(total, 1))

    def update(self, value):
        if self.wm is not None:
            self.wm.progress_update(value)

    def end(self):
        if self.wm is not None:
            self.wm.progress_end()


def read_cloud(path, drop_invalid, report):
    """Read a splat file, passing the format's warnings on as Blender warnings. Splats with NaN/Inf
    cannot be drawn or rendered: with `drop_invalid` they are dropped (and counted in a warning),
    otherwise the file is refused."""
    with data.reported_warnings(report):
        return read_splats(path, nonfinite="drop" if drop_invalid else "raise")


def finite_for_export(path, cloud, drop_invalid, report):
    """The splats to write: those holding NaN/Inf are left out (counted in a warning) with
    `drop_invalid`, otherwise the export is refused before anything is written."""
    finite = cloud.finite_mask()
    bad = len(cloud) - int(finite.sum())
    if not bad:
        return cloud
    if not drop_invalid:
        detail = ", ".join(f"{name} in {count}" for name, count in nonfinite_counts(cloud).items())
        raise SplatFileError(path, f"{bad} of {len(cloud)} splats have non-finite values (NaN or Inf): {detail}; "
                                   "turn on Drop Invalid Splats to export the others")
    report({"WARNING"}, f"left out {bad} of {len(cloud)} splats holding NaN or infinite values")
    return cloud[finite]


@orientation_helper(axis_forward=FILE_FORWARD, axis_up=FILE_UP)
class SPLAT_OT_import_file(bpy.types.Operator, ImportHelper):
    """Import Gaussian splats (PLY, OpenUSD, SPZ, .splat) as splat objects"""

    bl_idname = "splat.import_file"
    bl_label = "Import Splats"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default=FILTER_GLOB, options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    drop_invalid: BoolProperty(name="Drop Invalid Splats", default=True,
                               description="Drop splats holding NaN or Inf values (with a warning) "
                                           "instead of refusing the file")

    def _paths(self):
        names = [f.name for f in self.files if f.name]
        if names and self.directory:
            return [Path(self.directory) / name for name in names]
        return [Path(bpy.path.abspath(self.filepath))] if self.filepath else []

    def execute(self, context):
        paths = self._paths()
        if not paths:
            self.report({"ERROR"}, "no file to import: give a filepath (or a directory and files)")
            return {"CANCELLED"}
        progress = _Progress(context, 2 * len(paths))
        try:
            clouds = []
            for i, path in enumerate(paths):     # read everything first: a bad file changes nothing
                clouds.append(read_cloud(path, self.drop_invalid, self.report))
                progress.update(i + 1)
            objects = self._create(context, paths, clouds, progress)
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        finally:
            progress.end()
        for obj in context.view_layer.objects:
            obj.select_set(False)
        for obj in objects:
            obj.select_set(True)
        context.view_layer.objects.active = objects[-1]
        total = sum(len(c) for c in clouds)
        self.report({"INFO"}, f"imported {total} splats from {len(paths)} file(s)")
        return {"FINISHED"}

    def _create(self, context, paths, clouds, progress):
        collection = context.collection or context.scene.collection
        created = []
        try:
            for i, (path, cloud) in enumerate(zip(paths, clouds)):
                forward, up = self.axis_forward, self.axis_up
                matrix = axis_conversion(from_forward=forward, from_up=up).to_4x4()
                obj, skipped = data.new_splat_object(cloud, path.stem, collection, matrix)
                created.append(obj)
                display.add_display(obj, min(1.0, DISPLAY_BUDGET / max(len(cloud), 1)))    # mesh form only
                if skipped:
                    self.report({"WARNING"}, f"{path}: extras not kept (no matching attribute type): "
                                             f"{', '.join(skipped)}")
                progress.update(len(paths) + i + 1)
        except BaseException:
            for obj in created:          # leave the scene as it was
                data.remove_splat_object(obj)
            raise
        return created


def export_objects(context, selected_only):
    """The objects an export writes: splat objects, and objects that instance them (an Empty
    instancing a collection of splat objects, say); SplatObjectError saying why there are none."""
    if selected_only:
        candidates = list(context.selected_objects)
        if not candidates:
            raise data.SplatObjectError("nothing is selected")
    else:
        candidates = [obj for obj in context.view_layer.objects if obj.visible_get()]
    makers = {(i.instancer or i.obj).name for i in data.splat_instances(context.evaluated_depsgraph_get())}
    chosen = [obj for obj in candidates if data.is_splat_object(obj) or obj.name in makers]
    if not chosen:
        others = ", ".join(f"'{o.name}' ({o.type})" for o in candidates[:5])
        where = "selected" if selected_only else "visible"
        why = f"; {others} are not splat clouds" if others else ""
        raise data.SplatObjectError(f"no splat objects {where}{why}")
    return chosen


def scene_instances(depsgraph, objects):
    """(splat object, world matrix) pairs `objects` put in the scene at the depsgraph's frame: each
    splat object itself (drawn or not), and every splat instance an object of `objects` makes."""
    names = {obj.name for obj in objects}
    found = data.splat_instances(depsgraph)
    generated = {i.obj.name for i in found if i.instancer is None and not data.is_splat_object(i.obj)}
    own = [(obj, data.world_matrix(obj, depsgraph)) for obj in objects
           if data.is_splat_object(obj) or obj.name in generated]
    return own + [(i.obj, i.matrix) for i in found if i.instancer is not None and i.instancer.name in names]


def scene_cloud(context, objects, conversion, keep_source=False):
    """One cloud in file space: the splats of `objects` and their instances (see scene_instances) as the
    scene shows them, each instance's world matrix, then `conversion`, applied. The extras a file carried
    are kept; the from-mesh bookkeeping (data.SOURCE_EXTRAS) only when `keep_source` (the output of a
    conversion, which a pipeline may bind later)."""
    depsgraph = context.evaluated_depsgraph_get()
    # Splats that landed in a file's own axes (data.landed_raw) stand as if imported upright: written
    # with the default axes, their world coordinates are the file's, and the file comes back as it was.
    instances = scene_instances(depsgraph, objects)
    raw = {obj.name for obj in {obj for obj, _ in instances} if data.landed_raw(obj)}
    instances = [(obj, upright() @ matrix if obj.name in raw else matrix) for obj, matrix in instances]
    if not instances:
        return SplatCloud.empty()
    cloud = data.instances_cloud(depsgraph, instances, np.array(conversion, dtype=np.float64))
    if keep_source:
        return cloud
    return cloud.replace(extras={k: v for k, v in cloud.extras.items() if k not in data.SOURCE_EXTRAS})


@orientation_helper(axis_forward=FILE_FORWARD, axis_up=FILE_UP)
class SPLAT_OT_export_file(ExportOptionProperties, bpy.types.Operator, ExportHelper):
    """Export splat objects (with their transforms applied) to PLY, OpenUSD, SPZ or .splat"""

    bl_idname = "splat.export_file"
    bl_label = "Export Splats"
    bl_options = {"REGISTER", "PRESET"}

    filename_ext = ".ply"
    check_extension = None          # the extension picks the format: keep what the user typed
    filter_glob: StringProperty(default=FILTER_GLOB, options={"HIDDEN"})
    selected_only: BoolProperty(name="Selected Only", description="Export only selected splat objects",
                                default=False)
    drop_invalid: BoolProperty(name="Drop Invalid Splats", default=False,
                               description="Leave out splats holding NaN or infinite values (counted in a "
                                           "warning) instead of refusing to export")

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        progress = _Progress(context, 2)
        try:
            objects = export_objects(context, self.selected_only)
            with data.reported_warnings(self.report):
                cloud = scene_cloud(context, objects, export_conversion(self.axis_forward, self.axis_up))
                progress.update(1)
                cloud = finite_for_export(path, cloud, self.drop_invalid, self.report)
                options = self.export_options(context)
                written = options.reduce(cloud)
                write_splats(path, written, **options.writer_options(path, written))
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        finally:
            progress.end()
        pruned = f" ({len(cloud) - len(written)} fainter than {options.prune_opacity:g} left out)" \
            if len(written) < len(cloud) else ""
        self.report({"INFO"}, f"wrote {len(written)} splats{pruned} from {len(objects)} object(s) to {path}")
        return {"FINISHED"}


class SPLAT_OT_apply_transform(bpy.types.Operator):
    """Bake the whole object transform into the splats (centres, orientations, sizes and SH), leaving
    an identity transform; use this instead of Apply > Rotation/Scale, which moves centres only"""

    bl_idname = "splat.apply_transform"
    bl_label = "Apply Splat Transform"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT" and data.is_splat_object(context.active_object)

    def execute(self, context):
        targets = [o for o in context.selected_objects if data.is_splat_object(o)] or [context.active_object]
        shared = [o.name for o in targets if o.data.users > 1]
        if shared:
            self.report({"ERROR"}, f"splat data shared by several objects: {', '.join(shared)}")
            return {"CANCELLED"}
        try:
            baked = [data.object_to_cloud(o, np.array(o.matrix_basis, dtype=np.float64)) for o in targets]
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for obj, cloud in zip(targets, baked):
            data.update_splats(obj, cloud)
            obj.matrix_basis.identity()
            data.remember_frame(obj)
        return {"FINISHED"}


class SPLAT_OT_join(bpy.types.Operator):
    """Join the selected splat objects into the active one, turning each one's splats (orientations,
    sizes and SH too) into the active object's space; Blender's own Join moves centres only"""

    bl_idname = "splat.join"
    bl_label = "Join Splats"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT" and data.is_splat_object(context.active_object)

    def execute(self, context):
        target = context.active_object
        others = [o for o in context.selected_objects if o is not target]
        problem = _join_problem(target, others)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        to_target = np.linalg.inv(np.array(target.matrix_world, dtype=np.float64))
        try:
            # Read everything before changing anything, so an error leaves the scene as it was; the
            # target too, or Join would fill its missing attributes with made-up defaults.
            own = data.object_cloud(target)
            moved = [data.object_to_cloud(o, to_target @ np.array(o.matrix_world, dtype=np.float64))
                     for o in others]
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if all(data.splat_form(o) == data.MESH_FORM for o in (target, *others)):
            return self._join_meshes(context, target, others, moved)
        return self._join_clouds(context, target, others, [own, *moved])

    def _join_meshes(self, context, target, others, moved):
        """Blender's own Join, after each splat object is turned into the target's space: vertex
        groups and materials join as Blender joins them."""
        for obj, cloud in zip(others, moved):
            data.update_splats(obj, cloud)
            obj.matrix_world = target.matrix_world
            data.remember_frame(obj)
        with context.temp_override(active_object=target, selected_editable_objects=[target, *others],
                                   selected_objects=[target, *others]):
            done = bpy.ops.object.join()
        if done != {"FINISHED"}:
            self.report({"ERROR"}, f"Blender's Join did not join the splat objects into '{target.name}'")
        return done

    def _join_clouds(self, context, target, others, clouds):
        """Native splats (Blender joins no point clouds): the target gets new data, in its own form,
        holding every cloud; the others are removed."""
        try:
            joined = SplatCloud.concatenate(clouds)
            made, skipped = data.new_splat_object(joined, target.name, context.scene.collection,
                                                  form=data.splat_form(target))
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        old = target.data
        data.stamp_landing(made, data.landed_raw(target))
        target.data = made.data
        bpy.data.objects.remove(made)
        data.remove_geometry(old)
        for obj in others:
            data.remove_splat_object(obj)
        if skipped:
            self.report({"WARNING"}, f"extras not kept: {', '.join(skipped)}")
        return {"FINISHED"}


def _join_problem(target, others):
    """Why `others` cannot be joined into the splat object `target`, or None."""
    wrong = [o.name for o in others if not data.is_splat_object(o)]
    if wrong:
        return f"not splat objects: {', '.join(wrong)}"
    shared = [o.name for o in others if o.data.users > 1 or o.data is target.data]
    if shared:
        return f"splat data shared by several objects: {', '.join(shared)}"
    if not others:
        return "select the splat objects to join into the active one"
    if not any(data.splat_count(o.data) for o in others):      # Blender's Join would cancel
        return f"nothing to join: the selected splat objects hold no splats ({', '.join(o.name for o in others)})"
    antialiased = data.made_antialiased(target.data)
    other_mode = [o.name for o in others if data.made_antialiased(o.data) != antialiased]
    if other_mode:
        return (f"{', '.join(other_mode)}: made for {'classic' if antialiased else 'antialiased'} rendering, "
                f"'{target.name}' for {'antialiased' if antialiased else 'classic'}; one object renders one way")
    matrix = np.array(target.matrix_world, dtype=np.float64)
    if not np.isfinite(matrix).all():
        return f"'{target.name}' has a transform holding NaN or Inf: splats cannot be joined into it"
    if np.linalg.det(matrix[:3, :3]) == 0:
        return f"'{target.name}' has a zero scale: splats cannot be joined into it"
    return None


def convert_form(context, obj, form):
    """Replace splat object `obj` by one of the other form (data.MESH_FORM or data.NATIVE_FORM) holding
    the same splats, name, transform, parent, collections and armature binding; returns the new
    object. Modifiers other than Splatwright's own are not carried over (a warning names them)."""
    from . import rigging
    cloud = data.object_cloud(obj)
    rig = rigging.rig_of(obj)
    bones = rigging.weight_names(obj)
    weights = rigging.group_weights(obj, bones)[1].T if rig is not None else None
    name, collections = obj.name, list(obj.users_collection)
    made, skipped = data.new_splat_object(cloud, name + ".converting", collections[0], form=form)
    try:
        for collection in collections[1:]:
            collection.objects.link(made)
        made.parent, made.matrix_parent_inverse = obj.parent, obj.matrix_parent_inverse.copy()
        made.matrix_world = obj.matrix_world.copy()
        data.stamp_landing(made, data.landed_raw(obj))
        data.remember_frame(made)
        if form == data.MESH_FORM:
            display.add_display(made, min(1.0, DISPLAY_BUDGET / max(len(cloud), 1)))
        if rig is not None:
            rigging.write_weights(made, bones, weights)
            rigging.attach(made, rig[0], rig[1])
    except BaseException:
        data.remove_splat_object(made)
        raise
    dropped = [m.name for m in obj.modifiers if m.name not in data.OWN_MODIFIERS and m.type != "ARMATURE"]
    selected, active = obj.select_get(), context.view_layer.objects.active == obj
    data.remove_splat_object(obj)
    made.name = name
    made.select_set(selected)
    if active:
        context.view_layer.objects.active = made
    return made, skipped, dropped


class SPLAT_OT_convert_form(bpy.types.Operator):
    """Turn splat objects into Blender's own Gaussian-splat point clouds (drawn by Blender 5.3's viewport,
    EEVEE and Cycles) or into Splatwright's splat meshes, keeping their splats, transform and binding"""

    bl_idname = "splat.convert_form"
    bl_label = "Convert Splat Form"
    bl_options = {"REGISTER", "UNDO"}

    form: EnumProperty(name="Form", default="NATIVE", items=(
        ("NATIVE", "Point Cloud (Blender's Gaussian splats)", "Blender 5.3's own splat point clouds"),
        ("MESH", "Splat Mesh", "Splatwright's mesh form, drawn by its display modifier")))

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def execute(self, context):
        targets = [o for o in context.selected_objects if data.is_splat_object(o) and data.splat_form(o) != self.form]
        if not targets:
            self.report({"ERROR"}, f"no selected splat objects to convert to the {self.form.lower()} form")
            return {"CANCELLED"}
        shared = [o.name for o in targets if o.data.users > 1]
        if shared:
            self.report({"ERROR"}, f"splat data shared by several objects: {', '.join(shared)}")
            return {"CANCELLED"}
        try:
            for obj in targets:              # every object readable before any is replaced
                data.object_cloud(obj)
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if self.form == data.NATIVE_FORM and not data.native_supported():
            self.report({"ERROR"}, f"Blender {bpy.app.version_string} cannot make point clouds from Python "
                                   "(Blender 4.5 and later can)")
            return {"CANCELLED"}
        for obj in targets:
            try:
                made, skipped, dropped = convert_form(context, obj, self.form)
            except EXPECTED_ERRORS as exc:
                self.report({"ERROR"}, str(exc))
                return {"CANCELLED"}
            if skipped:
                self.report({"WARNING"}, f"'{made.name}': extras not kept: {', '.join(skipped)}")
            if dropped:
                self.report({"WARNING"}, f"'{made.name}': modifiers not carried over: {', '.join(dropped)}")
        return {"FINISHED"}


class SPLAT_FH_files(bpy.types.FileHandler):
    bl_idname = "SPLAT_FH_files"
    bl_label = "Gaussian splats"
    bl_import_operator = "splat.import_file"
    bl_export_operator = "splat.export_file"
    bl_file_extensions = EXTENSIONS

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


def menu_import(self, context):
    self.layout.operator(SPLAT_OT_import_file.bl_idname, text=MENU_LABEL)


def menu_export(self, context):
    self.layout.operator(SPLAT_OT_export_file.bl_idname, text=MENU_LABEL)
    self.layout.operator("splat.export_animation", text="Gaussian Splat Animation (.usd, .ply ####)")


def menu_apply(self, context):
    self.layout.operator(SPLAT_OT_apply_transform.bl_idname)


def menu_join(self, context):
    if data.is_splat_object(context.active_object):
        self.layout.operator(SPLAT_OT_join.bl_idname)
        self.layout.operator_menu_enum(SPLAT_OT_convert_form.bl_idname, "form")


CLASSES = (SPLAT_OT_import_file, SPLAT_OT_export_file, SPLAT_OT_apply_transform, SPLAT_OT_join, SPLAT_OT_convert_form,
           SPLAT_FH_files)
MENUS = ((bpy.types.TOPBAR_MT_file_import, menu_import), (bpy.types.TOPBAR_MT_file_export, menu_export),
         (bpy.types.VIEW3D_MT_object_apply, menu_apply), (bpy.types.VIEW3D_MT_object, menu_join))
