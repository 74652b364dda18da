"""`blender -b scene.blend --command splatwright VERB ...`: batch export, render and mesh conversion.

    export OUT [--frames A-B[:STEP]] [--format FORMAT] [--objects NAMES] [--sh-degree N]
               [--spz-version 2|3|4] [--half] [--prune-opacity T]
    render [OUT] [--frames A-B[:STEP]] [--objects NAMES] [--meshes cycles|eevee|workbench|none]
    from-mesh OUT [--objects NAMES] [--max-splats N | --target-psnr DB] [--posed] [--view-size PX]
                  [--measure-from around|camera] [--view-count N] [--view-near X] [--view-far X]
                  [--appearance base-color|rendered [--bake-views N] [--bake-samples N] [--bake-degree D]
                                                    [--bake-geometry-steps N]]
    collide A B [--frames A-B[:STEP]] [--sigma K] [--ignore-bones NAMES] [--json OUT]

Progress goes to stdout, one line per step; a failure prints "splatwright: error: ..." to stderr and
exits non-zero (1 for a failed job, 2 for a bad command line). `execute(argv)` is the handler
registered with bpy.utils.register_cli_command; it also runs in any Blender session.
"""

import argparse
import contextlib
import json
import re
import sys
import traceback
from pathlib import Path

import bpy

from ..core import sh as shmod
from ..io import DEFAULT_EXTENSIONS, FORMATS, format_of, write_splats
from ..io.common import atomic_write
from . import data
from .convert import from_mesh
from .files import animation, import_export
from .files.export_options import ExportOptions
from .render import mesh_layer
from .render.scene import MESH_ENGINE
from .rig import collide
from .ui import preferences

COMMAND = "splatwright"
FORMAT_EXTENSIONS = DEFAULT_EXTENSIONS
# render OUT's extension -> image formats that write it (the first is chosen if none is set)
IMAGE_FORMATS = {
    ".png": ("PNG",),
    ".exr": ("OPEN_EXR", "OPEN_EXR_MULTILAYER"),
    ".jpg": ("JPEG",),
    ".jpeg": ("JPEG",),
    ".tif": ("TIFF",),
    ".tiff": ("TIFF",),
}
APPEARANCES = ("base-color", "rendered")  # from-mesh --appearance: the operator's Appearance
MEASURE_FROM = ("around", "camera")  # from-mesh --measure-from: the operator's Measure From
BAKE_FLAGS = ("--bake-views", "--bake-samples", "--bake-degree", "--bake-geometry-steps")
PATH_LINE_FRAMES = 64  # from-mesh --measure-from camera: a progress line per so many frames
FRAMES = re.compile(r"^\s*(-?\d+)\s*(?:-\s*(-?\d+))?\s*(?::\s*(\d+))?\s*$")

_handle = None


class CommandError(Exception):
    """A job that cannot run as asked; the message says why."""


class _Exit(Exception):
    """argparse wanted to end the process (help, usage error): the handler returns `code` instead."""

    def __init__(self, code):
        super().__init__(code)
        self.code = code


class _Parser(argparse.ArgumentParser):
    def exit(self, status=0, message=None):  # never sys.exit inside Blender
        if message:
            print(message, file=sys.stderr, end="")
        raise _Exit(status)

    def error(self, message):
        self.print_usage(sys.stderr)
        self.exit(2, f"{self.prog}: error: {message}\n")


def _say(message):
    print(f"{COMMAND}: {message}", flush=True)


def _in_range(low, high, parse=int, expected="a whole number"):
    """An argparse type: `expected` (read by `parse`) from `low` to `high`; anything else is a usage
    error naming the option."""

    def checked(text):
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got '{text}'") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be from {low:g} to {high:g}, got {text}")
        return value

    return checked


def parser():
    top = _Parser(
        prog=f"blender -b FILE.blend --command {COMMAND}",
        description="Export, render or convert splats in a .blend file, without a window.",
    )
    verbs = top.add_subparsers(dest="verb", required=True, parser_class=_Parser)
    top.verb_parsers = verbs.choices  # name -> the verb's parser, for parse()'s own checks
    frames_help = "frames A-B, A-B:STEP or A (default: the scene's frame range and step)"
    objects_help = "comma-separated object names (default: every visible splat object)"
    distances = ", ".join(f"{d:g}" for d in from_mesh.VIEW_DISTANCES)

    p = verbs.add_parser("export", help="write splat objects over a frame range (animated USD or numbered files)")
    p.add_argument("output", help="file, or sequence pattern: shot.usdc, shot_####.ply (see README)")
    p.add_argument("--frames", help=frames_help)
    p.add_argument("--format", choices=sorted(FORMAT_EXTENSIONS), help="the file format, when OUT has no extension")
    p.add_argument("--objects", help=objects_help)
    p.add_argument("--axis-forward", choices=("X", "Y", "Z", "-X", "-Y", "-Z"), help="file forward axis")
    p.add_argument("--axis-up", choices=("X", "Y", "Z", "-X", "-Y", "-Z"), help="file up axis")
    p.add_argument(
        "--sh-degree",
        type=int,
        choices=range(shmod.MAX_DEGREE + 1),
        help="reduce the SH to this degree (default: the preferences', else as the splats have it)",
    )
    p.add_argument("--spz-version", type=int, choices=(2, 3, 4), help="SPZ version (default: the preferences', 3)")
    p.add_argument(
        "--half",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="OpenUSD: half floats for orientations, scales, opacities and SH (default: the preferences')",
    )
    p.add_argument(
        "--prune-opacity",
        type=float,
        metavar="T",
        default=0.0,
        help="leave out splats whose opacity is below T at the first frame (0..1; default 0: none)",
    )

    p = verbs.add_parser("render", help="render frames with the Splatwright engine")
    p.add_argument(
        "output",
        nargs="?",
        help="output path pattern as in Output Properties (default: the scene's); "
        ".png/.exr/.jpg/.tif pick that image format",
    )
    p.add_argument("--frames", help=frames_help)
    p.add_argument("--objects", help="only these splat objects are rendered (default: all)")
    p.add_argument(
        "--meshes",
        choices=[key.lower() for key, *_ in mesh_layer.ENGINE_CHOICES],
        help="what renders the meshes, curves, volumes and world that the splats are composited "
        "with (default: the scene's Splatwright > Meshes setting)",
    )

    p = verbs.add_parser("from-mesh", help="convert mesh objects to splat objects")
    p.add_argument(
        "output",
        help="a .blend to save the scene with the new splat objects to, or a splat "
        "file (.ply, .usdc, ...) to write them to",
    )
    p.add_argument("--objects", help="comma-separated mesh objects (default: every visible mesh object)")
    p.add_argument(
        "--max-splats",
        type=int,
        help=f"splats per object (default {from_mesh.DEFAULT_BUDGET}); with --target-psnr, the most per object",
    )
    p.add_argument("--target-psnr", type=float, help="refine until renders reach this PSNR (dB)")
    p.add_argument(
        "--calibrate",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="a budget: calibrate the silhouettes against renders of the mesh and the splats (default; "
        "a few seconds per object); --no-calibrate renders nothing and keeps the splats on the surface",
    )
    p.add_argument(
        "--mode",
        choices=("classic", "antialiased"),
        default=from_mesh.DEFAULT_RENDER_MODE,
        help="the rendering the splats are made for, kept on the objects and in PLY, SPZ and OpenUSD files "
        f"(default {from_mesh.DEFAULT_RENDER_MODE}: antialiased keeps outlines right at every "
        "distance, classic is for viewers that cannot render antialiased)",
    )
    p.add_argument(
        "--posed", action="store_true", help="convert armature-deformed meshes as posed (default: in the rest position)"
    )
    p.add_argument(
        "--view-size",
        type=_in_range(*from_mesh.VIEW_SIZES),
        metavar="PX",
        default=from_mesh.VIEW_SIZE,
        help=f"pixels across each view that quality is measured in and the look baked from "
        f"({from_mesh.VIEW_SIZES[0]}-{from_mesh.VIEW_SIZES[1]}; default {from_mesh.VIEW_SIZE})",
    )
    p.add_argument(
        "--measure-from",
        choices=MEASURE_FROM,
        default="around",
        help="where quality is measured: around, views all around each mesh from --view-near to "
        "--view-far (default); camera, the scene camera at up to --view-count frames of the frame "
        "range, spread by how much the view changes (the rendered look is baked from them too)",
    )
    counts, limits = from_mesh.VIEW_COUNTS, from_mesh.VIEW_DISTANCE_LIMITS
    p.add_argument(
        "--view-count",
        type=_in_range(*counts),
        metavar="N",
        default=from_mesh.VIEWS_PER_DISTANCE,
        help=f"views at each distance (around) or frames of the camera path (camera) "
        f"({counts[0]}-{counts[1]}; default {from_mesh.VIEWS_PER_DISTANCE})",
    )
    for end, default in (("near", from_mesh.VIEW_DISTANCES[0]), ("far", from_mesh.VIEW_DISTANCES[-1])):
        p.add_argument(
            f"--view-{end}",
            type=_in_range(*limits, float, "a number"),
            metavar="X",
            default=default,
            help=f"the {'closest' if end == 'near' else 'farthest'} view distance around, and baked "
            f"from, a multiple of the one framing the mesh ({limits[0]:g}-{limits[1]:g}; "
            f"default {default:g})",
        )
    p.add_argument(
        "--appearance",
        choices=APPEARANCES,
        default="base-color",
        help="base-color: the surface's Base Color, unlit (default); rendered: the look Cycles renders "
        "in this scene (lights, world, shadows, speculars) baked into the splats' SH from Cycles "
        "views around each mesh",
    )
    p.add_argument(
        "--bake-views",
        type=_in_range(1, from_mesh.MAX_BAKE_VIEWS),
        metavar="N",
        help=f"rendered: Cycles views to bake from at each view distance ({distances} times the "
        f"one framing the mesh) (1-{from_mesh.MAX_BAKE_VIEWS}; default {from_mesh.BAKE_VIEWS})",
    )
    p.add_argument(
        "--bake-samples",
        type=_in_range(1, from_mesh.MAX_BAKE_SAMPLES),
        metavar="N",
        help=f"rendered: Cycles samples per view, denoised "
        f"(1-{from_mesh.MAX_BAKE_SAMPLES}; default {from_mesh.BAKE_SAMPLES})",
    )
    p.add_argument(
        "--bake-degree",
        type=int,
        choices=range(from_mesh.MAX_BAKE_DEGREE + 1),
        metavar="D",
        help=f"rendered: SH degree of the baked colours, 0 view-independent, higher for speculars "
        f"(0-{from_mesh.MAX_BAKE_DEGREE}; default {from_mesh.BAKE_DEGREE})",
    )
    p.add_argument(
        "--bake-geometry-steps",
        type=_in_range(0, from_mesh.MAX_BAKE_GEOMETRY_STEPS),
        metavar="N",
        help="rendered: after the colours, steps fitting the splats' positions, shapes and opacities to "
        "the Cycles views too (truer look between the views where it is shading, though close-ups "
        "of glossy facets can lose; about 0.2 s a step for 20k splats at 256 px, 0.9 s without "
        "numba; default 0, colours only)",
    )

    p = verbs.add_parser("collide", help="check two splat objects for contact over a frame range")
    p.add_argument("object_a", help="a splat object (e.g. a rigged avatar)")
    p.add_argument("object_b", help="the other splat object (e.g. the environment)")
    p.add_argument("--frames", help=frames_help)
    p.add_argument(
        "--sigma",
        type=float,
        default=collide.DEFAULT_SIGMA,
        help=f"splats touch when their ellipsoids of this many standard deviations meet "
        f"(default {collide.DEFAULT_SIGMA:g})",
    )
    p.add_argument(
        "--min-opacity",
        type=float,
        default=collide.DEFAULT_MIN_OPACITY,
        help=f"leave out splats fainter than this (default {collide.DEFAULT_MIN_OPACITY:g})",
    )
    p.add_argument("--ignore-bones", help="comma-separated bones whose splats are left out")
    p.add_argument("--json", help="write the per-frame report to this JSON file")
    return top


def parse(argv):
    """The parsed command line; a malformed one prints the usage and an error and raises _Exit(2)."""
    top = parser()
    args = top.parse_args(list(argv))
    if args.verb == "from-mesh" and args.appearance != "rendered":
        unused = [flag for flag in BAKE_FLAGS if getattr(args, flag[2:].replace("-", "_")) is not None]
        if unused:
            top.verb_parsers[args.verb].error(
                f"{', '.join(unused)}: only with --appearance rendered (base-color bakes nothing)"
            )
    return args


def execute(argv):
    """The command handler: run one verb; returns the exit code."""
    try:
        args = parse(argv)
    except _Exit as done:
        return done.code
    runs = {"export": run_export, "render": run_render, "from-mesh": run_from_mesh, "collide": run_collide}
    try:
        runs[args.verb](args, bpy.context)
    except (CommandError, from_mesh.MeshConversionError, *data.EXPECTED_ERRORS, RuntimeError) as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr, flush=True)
        return 1
    except Exception:
        traceback.print_exc()
        print(f"{COMMAND}: error: internal error in '{args.verb}' (traceback above)", file=sys.stderr, flush=True)
        return 1
    return 0


# arguments ------------------------------------------------------------------------------------------


def parse_frames(text, scene):
    """Frames from "A-B", "A-B:STEP" or "A"; the scene's range and step when `text` is None."""
    if text is None:
        return data.frame_range(scene.frame_start, scene.frame_end, scene.frame_step)
    match = FRAMES.match(text)
    if match is None:
        raise CommandError(f"--frames '{text}': expected A-B, A-B:STEP or A (whole frame numbers)")
    start = int(match.group(1))
    end = int(match.group(2)) if match.group(2) is not None else start
    step = int(match.group(3)) if match.group(3) is not None else 1
    try:
        return data.frame_range(start, end, step)
    except ValueError as exc:
        raise CommandError(f"--frames '{text}': {exc}") from None


def named_objects(text, scene):
    """Scene objects named in a comma-separated list, or CommandError naming the unknown ones."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise CommandError("--objects names no objects")
    missing = [n for n in names if scene.objects.get(n) is None]
    if missing:
        known = ", ".join(sorted(o.name for o in scene.objects)[:20])
        raise CommandError(
            f"no object named {', '.join(repr(n) for n in missing)} in scene '{scene.name}' (it has: {known})"
        )
    return [scene.objects[n] for n in names]


def splat_objects(text, context):
    if text is None:
        return import_export.export_objects(context, selected_only=False)
    objects = named_objects(text, context.scene)
    wrong = [f"'{o.name}' ({o.type})" for o in objects if not data.is_splat_object(o)]
    if wrong:
        raise CommandError(f"not splat objects: {', '.join(wrong)}")
    return objects


def output_path(text, fmt):
    """OUT as an absolute path ('//' is the .blend's folder) whose extension names the format; OUT
    without an extension gets that of `fmt`, or of the preferences' export format."""
    path = Path(bpy.path.abspath(text))
    known = FORMATS.get(path.suffix.lower())
    if fmt is None and known is None and not path.suffix:
        fmt = preferences.current().export_format
    if fmt is None:
        format_of(path)  # SplatFileError naming an unknown extension
        return path
    if known is None:
        return path.with_name(path.name + FORMAT_EXTENSIONS[fmt])
    if known != fmt:
        raise CommandError(f"{text} has the extension {path.suffix} but --format is {fmt}")
    return path


# verbs ---------------------------------------------------------------------------------------------


def run_export(args, context):
    scene = context.scene
    path = output_path(args.output, args.format)
    frames = parse_frames(args.frames, scene)
    objects = splat_objects(args.objects, context)
    conversion = import_export.export_conversion(args.axis_forward, args.axis_up)
    options = export_options(args, path)
    _say(f"export {len(objects)} object(s), frames {frames[0]}-{frames[-1]} ({len(frames)}) to {path}")
    written = animation.export_animation(
        context,
        objects,
        path,
        frames,
        conversion,
        progress=lambda done, total, message: _say(f"[{done}/{total}] {message}"),
        options=options,
    )
    _say(f"done: {len(written)} file(s) written")


def export_options(args, path):
    """ExportOptions from the export flags, the preferences' where a flag is not given; a flag the
    output's format cannot use is refused."""
    fmt = format_of(path)
    if args.spz_version is not None and fmt != "spz":
        raise CommandError(f"--spz-version needs an SPZ output, not {path.name}")
    if args.half and fmt != "usd":
        raise CommandError(f"--half needs an OpenUSD output, not {path.name}")
    prefs = preferences.current()
    try:
        return ExportOptions(
            args.sh_degree
            if args.sh_degree is not None
            else (None if prefs.sh_degree == "KEEP" else int(prefs.sh_degree)),
            args.spz_version if args.spz_version is not None else int(prefs.spz_version),
            prefs.use_half if args.half is None else args.half,
            args.prune_opacity,
        )
    except ValueError as exc:
        raise CommandError(str(exc)) from None


@contextlib.contextmanager
def _restored(*settings):
    """Set (owner, attribute, value) triples for the duration, then put the old values back, in the
    same order (an image's media type goes back before the file format that needs it). Each
    attribute is named once."""
    old = [(owner, name, getattr(owner, name)) for owner, name, _ in settings]
    try:
        for owner, name, value in settings:
            setattr(owner, name, value)
        yield
    finally:
        for owner, name, value in old:
            setattr(owner, name, value)


def _render_settings(scene, output, only, meshes=None):
    """The temporary settings a render job needs: our engine and what renders the meshes, OUT and its
    image format, and the splat objects left out of the render."""
    render = scene.render
    settings = [(render, "engine", "SPLATWRIGHT")]
    if meshes is not None:
        settings.append((scene, MESH_ENGINE, meshes.upper()))
    if output is not None:
        settings.append((render, "filepath", output))
        formats = IMAGE_FORMATS.get(Path(output).suffix.lower())
        image = render.image_settings
        if formats and image.file_format not in formats:
            if hasattr(image, "media_type"):  # Blender 5: pick the media type first
                settings.append((image, "media_type", "IMAGE"))
            settings.append((image, "file_format", formats[0]))
    if only is not None:
        settings += [(obj, "hide_render", obj not in only) for obj in scene.objects if data.is_splat_object(obj)]
    return settings


def run_render(args, context):
    scene = context.scene
    frames = parse_frames(args.frames, scene)
    only = splat_objects(args.objects, context) if args.objects else None
    if scene.camera is None:
        raise CommandError(f"scene '{scene.name}' has no camera")
    current = scene.frame_current
    with _restored(*_render_settings(scene, args.output, only, args.meshes)):
        paths = [Path(scene.render.frame_path(frame=f)) for f in frames]
        _say(f"render frames {frames[0]}-{frames[-1]} ({len(frames)}) to {paths[0].parent}")
        try:
            for i, (frame, path) in enumerate(zip(frames, paths)):
                scene.frame_set(frame)
                _render_still(scene, path, frame)
                _say(f"[{i + 1}/{len(frames)}] frame {frame} -> {path}")
        finally:
            scene.frame_set(current)
    _say(f"done: {len(frames)} frame(s) rendered")


def _render_still(scene, path, frame):
    if not path.parent.is_dir():
        raise CommandError(f"frame {frame}: folder {path.parent} does not exist")
    before = path.stat().st_mtime_ns if path.exists() else None
    with _restored((scene.render, "filepath", str(path))):
        bpy.ops.render.render(write_still=True)  # an engine error raises RuntimeError here
    if not path.is_file() or path.stat().st_mtime_ns == before:
        raise CommandError(f"frame {frame}: no image was written to {path}")


def run_from_mesh(args, context):
    scene = context.scene
    out = Path(bpy.path.abspath(args.output))
    is_blend = out.suffix.lower() == ".blend"
    if not is_blend:
        format_of(out)
    if not out.parent.is_dir():
        raise CommandError(f"folder {out.parent} does not exist")
    if out.is_dir():  # Blender 4.2 would save a .blend over it
        raise CommandError(f"{out} is a folder")
    if args.objects:
        objects = named_objects(args.objects, scene)
        wrong = [f"'{o.name}' ({o.type})" for o in objects if o.type != "MESH" or data.is_splat_object(o)]
        if wrong:
            raise CommandError(f"not mesh objects: {', '.join(wrong)}")
    else:
        objects = [
            o
            for o in context.view_layer.objects
            if o.visible_get() and o.type == "MESH" and not data.is_splat_object(o)
        ]
        if not objects:
            raise CommandError(f"scene '{scene.name}' has no visible mesh objects to convert")
    budget = args.max_splats
    if budget is None and args.target_psnr is None:
        budget = from_mesh.DEFAULT_BUDGET
    if args.target_psnr is not None and not 0 < args.target_psnr < float("inf"):
        raise CommandError(f"--target-psnr must be a positive number of dB, got {args.target_psnr}")
    if not args.calibrate and args.target_psnr is not None:
        raise CommandError("--no-calibrate applies to a splat budget; --target-psnr always calibrates")
    _say(
        f"from-mesh: {len(objects)} object(s): {', '.join(o.name for o in objects)}"
        + (", baking the look Cycles renders" if args.appearance == "rendered" else "")
    )
    infos = []
    source = args.measure_from.upper()
    baked = args.appearance == "rendered"
    views, paths = from_mesh.measured_views(
        scene,
        objects,
        source,
        args.view_count,
        args.view_size,
        args.view_near,
        args.view_far,
        bake=baked,
        progress=_path_progress,
    )
    results = from_mesh.convert_objects(
        context,
        objects,
        max_splats=budget,
        target_psnr=args.target_psnr,
        calibrate=args.calibrate,
        use_rest_pose=not args.posed,
        render_mode=args.mode,
        bake=bake_options(args, paths) if baked else None,
        infos=infos,
        progress=lambda done, total, label: _say(f"[{done:.2f}/{total}] {label}"),
        warn=lambda m: _say(f"warning: {m}"),
        **views,
    )
    created = from_mesh.create_splat_objects(context, results)
    for obj, info in zip(created, infos):
        _say(f"{obj.name}: {from_mesh.conversion_report(data.splat_count(obj.data), info)}")
    try:
        if is_blend:
            bpy.ops.wm.save_as_mainfile(filepath=str(out), copy=True)
        else:
            write_splats(
                out, import_export.scene_cloud(context, created, import_export.export_conversion(), keep_source=True)
            )
    except BaseException:
        from_mesh.remove_objects(created)  # a session that goes on keeps the scene it had
        raise
    _say(f"done: wrote {out}")


def _path_progress(done, total, label):
    """A progress line every PATH_LINE_FRAMES frames of a camera path stepped through, and at its end."""
    if done == total or done % PATH_LINE_FRAMES == 0:
        _say(f"[{done}/{total}] {label}")


def bake_options(args, paths):
    """from_mesh.bake_options from the from-mesh flags (the operator's defaults where one is not given)
    and the scene camera's `paths` (measured_views')."""
    given = {
        key: value
        for key, value in (
            ("views", args.bake_views),
            ("samples", args.bake_samples),
            ("degree", args.bake_degree),
            ("geometry_steps", args.bake_geometry_steps),
        )
        if value is not None
    }
    return from_mesh.bake_options(
        size=args.view_size, distances=from_mesh.view_distances(args.view_near, args.view_far), paths=paths, **given
    )


def run_collide(args, context):
    scene = context.scene
    frames = parse_frames(args.frames, scene)
    obj_a, obj_b = collide.splat_objects_pair(scene, args.object_a, args.object_b)
    out = Path(bpy.path.abspath(args.json)) if args.json else None
    if out is not None and not out.parent.is_dir():
        raise CommandError(f"folder {out.parent} does not exist")
    ignore = [n.strip() for n in (args.ignore_bones or "").split(",") if n.strip()]
    _say(f"collide '{obj_a.name}' with '{obj_b.name}', frames {frames[0]}-{frames[-1]} ({len(frames)})")

    def progress(done, total, found):
        bones = ", ".join(f"{name} {count}" for name, count in found.bones_a.items())
        _say(
            f"[{done}/{total}] frame {found.frame}: {found.pairs} splat pairs in contact"
            + (f" (bones: {bones})" if bones else "")
        )

    report = collide.check_collisions(
        context, obj_a, obj_b, frames, args.sigma, args.min_opacity, ignore, progress=progress
    )
    if out is not None:
        with atomic_write(out, "w") as f:
            json.dump(report.as_dict(), f, indent=1)
    _say(f"done: {report.summary()}")


# registration -------------------------------------------------------------------------------------


def register():
    """Register the command where Blender has command-line commands (4.2 and later)."""
    global _handle
    if _handle is None and hasattr(bpy.utils, "register_cli_command"):
        _handle = bpy.utils.register_cli_command(COMMAND, execute)


def unregister():
    global _handle
    if _handle is not None:
        bpy.utils.unregister_cli_command(_handle)
        _handle = None
