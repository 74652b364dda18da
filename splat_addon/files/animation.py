"""A frame range of splat objects exported as one animated OpenUSD file (time samples on one prim,
time code = frame number, played at the scene's frame rate) or as a numbered sequence of files, one per frame.

Sequence names follow Blender's output paths: the last run of '#' in the file name becomes the
frame number zero-padded to that many digits (shot_####.ply -> shot_0007.ply); without '#',
"_" and four digits go before the extension (shot.ply -> shot_0007.ply). A frame's file name never
depends on the range exported, so render-farm jobs can split a range and write the same files.
Every frame goes through the same evaluated-cloud path as a single export (import_export.scene_cloud).
"""

import re
from pathlib import Path

import bpy
from bpy.props import BoolProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, orientation_helper

from ...io import SplatFileError, format_of, write_splats
from ...io.common import publish_together
from .. import data
from ..data.errors import EXPECTED_ERRORS
from ..data.progress import Progress
from ..data.scene import frame_range
from . import import_export
from .export_options import ExportOptionProperties, ExportOptions

HASHES = re.compile(r"#+")
DEFAULT_PADDING = 4  # Blender's own default, ####


def frame_path(pattern, frame):
    """The file for `frame` in a sequence named by `pattern` (see the module notes)."""
    pattern = Path(pattern)
    name = pattern.name
    runs = list(HASHES.finditer(name))
    if runs:
        last = runs[-1]
        name = f"{name[: last.start()]}{frame:0{len(last.group())}d}{name[last.end() :]}"
    else:
        name = f"{pattern.stem}_{frame:0{DEFAULT_PADDING}d}{pattern.suffix}"
    return pattern.with_name(name)


def is_single_file(path):
    """OpenUSD holds every frame in one file; other formats are written one file per frame."""
    return format_of(path) == "usd"


def export_animation(context, objects, path, frames, conversion=None, progress=None, options=None):
    """Write `objects` (splat objects) at each of `frames` to `path`; returns the files written.
    All or nothing: a frame that fails leaves every file of the sequence as it was.

    conversion: the Blender -> file axis matrix (default: import_export.export_conversion()).
    progress(done, total, message) is called after each frame. The scene's frame is restored.
    options: an ExportOptions (SH degree, SPZ version, half floats, pruning); pruning keeps the same
    splats in every frame: those at least that opaque at the first frame.
    """
    options = ExportOptions() if options is None else options
    path = Path(path)
    frames = list(frames)
    if not frames:
        raise ValueError("no frames to export")
    single = is_single_file(path)  # raises SplatFileError for an unknown extension
    if not path.parent.is_dir():
        raise SplatFileError(path, f"folder {path.parent} does not exist")
    conversion = import_export.export_conversion() if conversion is None else conversion
    scene = context.scene
    current, subframe = scene.frame_current, scene.frame_subframe

    def clouds():
        """Each frame's cloud, evaluated when the writer asks for it: one frame in memory at a time."""
        kept = None
        for i, frame in enumerate(frames):
            scene.frame_set(frame)
            try:
                cloud = import_export.scene_cloud(context, objects, conversion)
            except data.SplatObjectError as exc:
                raise data.SplatObjectError(f"frame {frame}: {exc}") from None
            kept = options.kept(cloud) if i == 0 else kept
            if kept is not None and len(kept) != len(cloud):
                raise SplatFileError(
                    path,
                    f"frame {frame} has {len(cloud)} splats, the first frame {len(kept)}: "
                    "pruning keeps the first frame's splats in every frame",
                )
            cloud = options.reduce(cloud, kept)
            count = len(cloud)
            yield cloud
            del cloud  # before the next frame is evaluated
            if progress:
                where = "" if single else f" -> {frame_path(path, frame)}"
                progress(i + 1, len(frames), f"frame {frame}: {count} splats{where}")

    try:
        if single:
            from ...io import usd

            usd.write_frames(
                path,
                clouds(),
                times=frames,
                fps=scene.render.fps / scene.render.fps_base,
                **options.writer_options(path),
            )
            return [path]
        written = [frame_path(path, frame) for frame in frames]
        blocked = next((out for out in written if out.is_dir()), None)
        if blocked is not None:  # found before any frame is written, not when renaming
            raise SplatFileError(blocked, "a folder of that name is in the way")
        with publish_together():  # each frame lands on its name once all are written
            for out, cloud in zip(written, clouds()):
                write_splats(out, cloud, **options.writer_options(out, cloud))
        return written
    finally:
        scene.frame_set(current, subframe=subframe)


@orientation_helper(axis_forward=import_export.FILE_FORWARD, axis_up=import_export.FILE_UP)
class SPLAT_OT_export_animation(ExportOptionProperties, bpy.types.Operator, ExportHelper):
    """Export splat objects over a frame range: one animated OpenUSD file, or one file per frame
    (name_####.ply) for other formats"""

    bl_idname = "splat.export_animation"
    bl_label = "Export Splat Animation"
    bl_options = {"REGISTER", "PRESET"}

    filename_ext = ".usd"  # binary with OpenUSD's module, text where Blender lacks it (4.2)
    check_extension = None
    filter_glob: StringProperty(default=import_export.FILTER_GLOB, options={"HIDDEN"})
    selected_only: BoolProperty(name="Selected Only", description="Export only selected splat objects", default=False)
    use_scene_range: BoolProperty(
        name="Scene Frame Range", default=True, description="Export the scene's frame range and step"
    )
    frame_start: IntProperty(name="Start", default=1, description="First frame (without the scene range)")
    frame_end: IntProperty(name="End", default=250, description="Last frame (without the scene range)")
    frame_step: IntProperty(name="Step", default=1, min=1, description="Frames between exported frames")

    def frames(self, scene):
        if self.use_scene_range:
            return frame_range(scene.frame_start, scene.frame_end, scene.frame_step)
        return frame_range(self.frame_start, self.frame_end, self.frame_step)

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        try:
            frames = self.frames(context.scene)
            objects = import_export.export_objects(context, self.selected_only)
            progress = Progress(context, len(frames))
            try:
                written = export_animation(
                    context,
                    objects,
                    path,
                    frames,
                    import_export.export_conversion(self.axis_forward, self.axis_up),
                    progress=lambda done, total, message: progress.update(done),
                    options=self.export_options(context),
                )
            finally:
                progress.end()
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        where = written[0] if len(written) == 1 else f"{written[0]} ... {written[-1].name}"
        self.report({"INFO"}, f"wrote {len(frames)} frame(s) of {len(objects)} object(s) to {where}")
        return {"FINISHED"}


CLASSES = (SPLAT_OT_export_animation,)  # listed in File > Export by import_export.menu_export
