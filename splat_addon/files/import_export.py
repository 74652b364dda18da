"""Import / export operators, usable from Python in background mode (execute never needs a UI)."""

from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper, axis_conversion, orientation_helper

from ...core import SplatCloud
from ...io import FORMATS, READ_ONLY, SplatFileError, format_of, read_splats, write_splats
from ...io.common import nonfinite_counts
from .. import data
from ..data.display import DISPLAY_BUDGET, add_display
from ..data.errors import EXPECTED_ERRORS
from ..data.progress import Progress
from .export_options import ExportOptionProperties

FILTER_GLOB = ";".join(f"*{ext}" for ext in FORMATS)  # .ksplat, lod-meta.json, .lcc2 and .lcc among them
EXPORT_FILTER_GLOB = ";".join(f"*{ext}" for ext, fmt in FORMATS.items() if fmt not in READ_ONLY)
EXTENSIONS = ";".join(FORMATS)
MENU_LABEL = "Gaussian Splats (.ply, .spz, .usd, .sog, .glb, .splat)"
IMPORT_MENU_LABEL = "Gaussian Splats (.ply, .spz, .usd, .sog, .glb, .splat, .ksplat, .lcc2, .lcc)"

# 3DGS captures come out of COLMAP/OpenCV: the scene's up is -Y and cameras look along +Z. These
# defaults turn that upright in Blender (file x, y, z -> Blender x, z, -y, a quarter turn about X).
FILE_FORWARD, FILE_UP = "Z", "-Y"


def upright():
    """The Blender placement of a file's axes by default (file x, y, z -> Blender x, z, -y)."""
    return np.array(axis_conversion(from_forward=FILE_FORWARD, from_up=FILE_UP).to_4x4(), dtype=np.float64)


def export_conversion(forward=None, up=None):
    """The Blender -> file axis matrix: the given axes, else the default (a 3DGS capture's axes).
    The same for every format: the io layer turns the model's axes into each format's own (OpenUSD
    files come out Y-up, with Blender's Z as their Y)."""
    return axis_conversion(to_forward=forward or FILE_FORWARD, to_up=up or FILE_UP).to_4x4()


def read_cloud(path, drop_invalid, report, allow_outside=False, spz_axes=None):
    """Read a splat file, passing the format's warnings on as Blender warnings. Splats with NaN/Inf
    cannot be drawn or rendered: with `drop_invalid` they are dropped (and counted in a warning),
    otherwise the file is refused. allow_outside: follow the names of other files the file makes
    (OpenUSD layers, glTF buffers, SOG images) outside its folder too (io.policy). spz_axes: the axes
    an SPZ file's values are in ("rub", "rdf"; None: its coordinate-system record's, else RUB)."""
    options = {"spz_axes": spz_axes} if spz_axes and format_of(path) == "spz" else {}
    with data.reported_warnings(report):
        return read_splats(path, nonfinite="drop" if drop_invalid else "raise", allow_outside=allow_outside, **options)


SPZ_AXES_ITEMS = (
    ("AUTO", "Auto", "What the file's coordinate-system record says, else RUB (SPZ's documented axes)"),
    ("RUB", "RUB", "SPZ's documented axes: x right, y up, z back"),
    ("RDF", "RDF", "PLY's axes, as many SPZ files without a record hold them (read as RUB they stand upside down)"),
)


PLACEMENT_ITEMS = (
    ("UPRIGHT", "Upright (Splatwright)", "The file's values as they are, stood upright by the object's transform"),
    (
        "BLENDER",
        "As Blender's Importer",
        "Where Blender 5.3's own importers put a file: an SPZ turned upright in its values, a PLY in the "
        "file's axes (on its side), both with no transform; other formats upright",
    ),
)


def spz_axes_option(value):
    """The io layer's spz_axes for an SPZ Axes property value (None: auto)."""
    return None if value == "AUTO" else value.lower()


def placed(cloud, path, conversion, as_blender):
    """(values, object matrix, whether the values are the file's axes as they are) for a file's cloud.
    Splatwright keeps the values and stands them upright by the object's matrix (`conversion`, from
    the Forward/Up settings); as Blender 5.3's own importers do (which have no such settings), an
    SPZ's values are turned upright instead and a PLY's left in the file's axes (a capture on its
    side), both at the identity, so clouds imported either way share a scene. Formats Blender imports
    no splats from are placed by `conversion`."""
    if as_blender and format_of(path) == "spz":
        return data.transform_cloud(cloud, upright()), np.eye(4), False
    if as_blender and format_of(path) == "ply":
        return cloud, np.eye(4), True
    return cloud, conversion, False


def finite_for_export(path, cloud, drop_invalid, report):
    """The splats to write: those holding NaN/Inf are left out (counted in a warning) with
    `drop_invalid`, otherwise the export is refused before anything is written."""
    finite = cloud.finite_mask()
    bad = len(cloud) - int(finite.sum())
    if not bad:
        return cloud
    if not drop_invalid:
        detail = ", ".join(f"{name} in {count}" for name, count in nonfinite_counts(cloud).items())
        raise SplatFileError(
            path,
            f"{bad} of {len(cloud)} splats have non-finite values (NaN or Inf): {detail}; "
            "turn on Drop Invalid Splats to export the others",
        )
    report({"WARNING"}, f"left out {bad} of {len(cloud)} splats holding NaN or infinite values")
    return cloud[finite]


@orientation_helper(axis_forward=FILE_FORWARD, axis_up=FILE_UP)
class SPLAT_OT_import_file(bpy.types.Operator, ImportHelper):
    """Import Gaussian splats (PLY, OpenUSD, SPZ, SOG, glTF, .splat, .ksplat, LCC2) as splat objects"""

    bl_idname = "splat.import_file"
    bl_label = "Import Splats"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default=FILTER_GLOB, options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    drop_invalid: BoolProperty(
        name="Drop Invalid Splats",
        default=True,
        description="Drop splats holding NaN or Inf values (with a warning) instead of refusing the file",
    )
    allow_outside: BoolProperty(
        name="Allow Files Outside",
        default=False,
        description="Also read the files a splat file names (OpenUSD layers, glTF buffers, SOG images) from "
        "outside its folder. Only for files you trust: a hostile file could then read any file on this machine",
    )
    spz_axes: EnumProperty(
        name="SPZ Axes", items=SPZ_AXES_ITEMS, default="AUTO", description="The axes an SPZ file's values are in"
    )
    placement: EnumProperty(
        name="Placement",
        items=PLACEMENT_ITEMS,
        default="UPRIGHT",
        description="Where the splats stand: one scene stays in one place when importers are mixed",
    )

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
        progress = Progress(context, 2 * len(paths))
        try:
            clouds = []
            for i, path in enumerate(paths):  # read everything first: a bad file changes nothing
                spz_axes = spz_axes_option(self.spz_axes)
                clouds.append(read_cloud(path, self.drop_invalid, self.report, self.allow_outside, spz_axes))
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
                conversion = axis_conversion(from_forward=forward, from_up=up).to_4x4()
                cloud, matrix, raw = placed(cloud, path, conversion, self.placement == "BLENDER")
                obj, skipped = data.new_splat_object(cloud, path.stem, collection, matrix)
                created.append(obj)
                data.stamp_landing(obj, raw)
                add_display(obj, min(1.0, DISPLAY_BUDGET / max(len(cloud), 1)))  # mesh form only
                if skipped:
                    self.report(
                        {"WARNING"}, f"{path}: extras not kept (no matching attribute type): {', '.join(skipped)}"
                    )
                progress.update(len(paths) + i + 1)
        except BaseException:
            for obj in created:  # leave the scene as it was
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
    own = [
        (obj, data.world_matrix(obj, depsgraph))
        for obj in objects
        if data.is_splat_object(obj) or obj.name in generated
    ]
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
    objects_shown = {obj.name: obj for obj, _ in instances}
    raw = {name for name, obj in objects_shown.items() if data.landed_raw(obj)}
    stand_up = upright()
    instances = [(obj, stand_up @ matrix if obj.name in raw else matrix) for obj, matrix in instances]
    if not instances:
        return SplatCloud.empty()
    cloud = data.instances_cloud(depsgraph, instances, np.array(conversion, dtype=np.float64))
    if keep_source:
        return cloud
    return cloud.replace(extras={k: v for k, v in cloud.extras.items() if k not in data.SOURCE_EXTRAS})


@orientation_helper(axis_forward=FILE_FORWARD, axis_up=FILE_UP)
class SPLAT_OT_export_file(ExportOptionProperties, bpy.types.Operator, ExportHelper):
    """Export splat objects (with their transforms applied) to PLY, compressed PLY, OpenUSD, SPZ, SOG, glTF or .splat"""

    bl_idname = "splat.export_file"
    bl_label = "Export Splats"
    bl_options = {"REGISTER", "PRESET"}

    filename_ext = ".ply"
    check_extension = None  # the extension picks the format: keep what the user typed
    filter_glob: StringProperty(default=EXPORT_FILTER_GLOB, options={"HIDDEN"})
    selected_only: BoolProperty(name="Selected Only", description="Export only selected splat objects", default=False)
    drop_invalid: BoolProperty(
        name="Drop Invalid Splats",
        default=False,
        description="Leave out splats holding NaN or infinite values (counted in a "
        "warning) instead of refusing to export",
    )

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        progress = Progress(context, 2)
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
        pruned = (
            f" ({len(cloud) - len(written)} fainter than {options.prune_opacity:g} left out)"
            if len(written) < len(cloud)
            else ""
        )
        self.report({"INFO"}, f"wrote {len(written)} splats{pruned} from {len(objects)} object(s) to {path}")
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
    self.layout.operator(SPLAT_OT_import_file.bl_idname, text=IMPORT_MENU_LABEL)


def menu_export(self, context):
    self.layout.operator(SPLAT_OT_export_file.bl_idname, text=MENU_LABEL)
    self.layout.operator("splat.export_animation", text="Gaussian Splat Animation (.usd, .ply ####)")


CLASSES = (SPLAT_OT_import_file, SPLAT_OT_export_file, SPLAT_FH_files)
MENUS = ((bpy.types.TOPBAR_MT_file_import, menu_import), (bpy.types.TOPBAR_MT_file_export, menu_export))
