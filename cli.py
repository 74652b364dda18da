"""The `splatwright` command line: one sub-command per verb, each a pair of functions.

To add a verb, write `_add_<verb>(parser)` and `_run_<verb>(args)` and list them in VERBS.
"""

import argparse
import json
import math
import os
import re
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


class Progress:
    """A one-line progress indicator on stderr: `progress(done, total, label)`."""

    def __init__(self, stream=None, min_interval=0.1):
        self.stream, self.min_interval, self._last = stream or sys.stderr, min_interval, 0.0

    def __call__(self, done, total, label=""):
        now = time.monotonic()
        if done < total and now - self._last < self.min_interval:
            return
        self._last = now
        pct = 100.0 * done / total if total else 100.0
        end = "\n" if done >= total else "\r"
        self.stream.write(f"{label} {pct:5.1f}% ({done}/{total}){end}")
        self.stream.flush()


def _parse_vec(text):
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got '{text}'") from None
    return np.array(values)


class OptionError(ValueError):
    """An option whose value is out of its range or makes no camera (exit status 1, as for a bad
    file)."""


class UsageError(Exception):
    """An option the files given cannot use, e.g. --half for a PLY output (exit status 2, as
    argparse's own usage errors)."""


def _three(ok):
    return lambda v: len(v) == 3 and bool(np.isfinite(v).all()) and ok(v)


# dest: (what the value must be, test). Checked after parsing for every verb with that option; NaN
# fails every comparison, so it is refused everywhere.
RANGES = {
    "width": ("a whole number >= 1", lambda v: v >= 1),
    "height": ("a whole number >= 1", lambda v: v >= 1),
    "fov": ("a horizontal field of view in degrees, between 0 and 180 (both excluded)", lambda v: 0 < v < 180),
    "ortho_scale": ("a width in world units, finite and > 0", lambda v: 0 < v < math.inf),
    "near": ("a distance, finite and > 0", lambda v: 0 < v < math.inf),
    "camera_pos": ("3 finite numbers x,y,z", _three(lambda v: True)),
    "look_at": ("3 finite numbers x,y,z", _three(lambda v: True)),
    "up": ("3 finite numbers x,y,z, not all zero", _three(lambda v: bool(np.any(v)))),
    "background": ("3 numbers r,g,b from 0 to 1, or 'none'", _three(lambda v: bool(((0 <= v) & (v <= 1)).all()))),
    "prune_opacity": ("an opacity from 0 to 1", lambda v: 0 <= v <= 1),
    "prune_invisible": ("a blending weight from 0 up to (not including) 1", lambda v: 0 <= v < 1),
    "views": ("a whole number from 1 to 1000", lambda v: 1 <= v <= 1000),
    "view_size": ("a whole number of pixels from 1 to 4096", lambda v: 1 <= v <= 4096),
    "max_splats": ("a whole number from 1 to 2147483647", lambda v: 1 <= v <= 2**31 - 1),
    "target_psnr": ("a PSNR in dB, finite and > 0", lambda v: 0 < v < math.inf),
    "filter_width": ("a width in pixels, finite and > 0", lambda v: 0 < v < math.inf),
}


def check_ranges(args):
    """Refuse (OptionError naming the option) any numeric option outside its range."""
    for dest, (what, ok) in RANGES.items():
        value = getattr(args, dest, None)
        if value is not None and not ok(value):
            shown = ",".join(f"{x:g}" for x in value) if isinstance(value, np.ndarray) else f"{value:g}"
            raise OptionError(f"--{dest.replace('_', '-')} must be {what}, got {shown}")


def _add_allow_outside(p):
    p.add_argument(
        "--allow-outside",
        action="store_true",
        help="follow the names a file makes of other files (OpenUSD layers, glTF buffers, SOG images, "
        "URDF meshes, textures) outside its folder too; a hostile file could then read any file on this machine",
    )


# info ---------------------------------------------------------------------------------------------


def _add_info(p):
    p.add_argument(
        "file",
        help="a splat file (.ply, .compressed.ply, .usd/.usda/.usdc/.usdz, .spz, .splat, "
        ".sog or meta.json, .glb/.gltf)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _add_allow_outside(p)
    _add_spz_axes(p)


SPZ_INPUT_AXES = "SPZ input: the axes its values are in (default: what its coordinate-system record says, else RUB)"


def _add_spz_axes(p, what=SPZ_INPUT_AXES):
    p.add_argument(
        "--spz-axes",
        choices=("rub", "rdf"),
        help=f"{what}; rdf for files holding PLY's axes without saying so (upside down when read as RUB)",
    )


def _spz_read_options(args, path):
    """{"spz_axes": ...} for an SPZ file when --spz-axes was given; refuses it for other files."""
    from .io import format_of

    if args.spz_axes is None:
        return {}
    if format_of(path) != "spz":
        raise UsageError(f"--spz-axes needs an SPZ file (.spz), not {path}")
    return {"spz_axes": args.spz_axes}


def summarize(cloud):
    """The statistics `info` prints, as plain Python values."""
    finite = cloud.finite_mask()
    pos = cloud.positions[finite]
    stats = lambda a: {"min": float(a.min()), "median": float(np.median(a)), "max": float(a.max())} if len(a) else None
    return {
        "count": len(cloud),
        "sh_degree": cloud.sh_degree,
        "made_for": "antialiased rendering" if cloud.antialiased else "classic rendering",
        "bbox_min": pos.min(axis=0).tolist() if len(pos) else None,
        "bbox_max": pos.max(axis=0).tolist() if len(pos) else None,
        "opacity": stats(cloud.opacities[finite]),
        "scale": stats(cloud.scales[finite].max(axis=1)),
        "non_finite_splats": int((~finite).sum()),
        "problems": cloud.problems(),
        "extras": sorted(cloud.extras),
    }


def _run_info(args):
    from .io import format_of, read_splats

    # info reports non-finite values (and any other reader warning) instead of refusing the file.
    options, facts = _spz_read_options(args, args.file), {}
    if format_of(args.file) == "spz":
        options["facts"] = facts  # the version, the axes read in and the record naming them
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloud = read_splats(args.file, nonfinite="keep", allow_outside=args.allow_outside, **options)
    spz_facts = {f"spz_{key}": facts[key] for key in ("version", "axes", "axes_record")} if facts else {}
    summary = {
        "file": args.file,
        "format": format_of(args.file),
        **spz_facts,
        **summarize(cloud),
        "warnings": [str(w.message) for w in caught],
    }
    if args.json:
        print(json.dumps(summary))
    else:
        for key, value in summary.items():
            print(f"{key:>18}: {value}")
    return 0


# convert ------------------------------------------------------------------------------------------


def _add_convert(p):
    p.add_argument("input")
    p.add_argument("output")
    _add_allow_outside(p)
    p.add_argument("--sh-degree", type=int, choices=range(5), help="truncate SH to this degree (0..4)")
    p.add_argument(
        "--spz-version",
        type=int,
        choices=(2, 3, 4),
        help="SPZ version to write (default 3, or 4 for SH degree 4, which v2/v3 cannot store)",
    )
    p.add_argument(
        "--half", action="store_true", help="OpenUSD output: orientations, scales, opacities and SH as half floats"
    )
    p.add_argument(
        "--axes",
        choices=("upright", "y-up", "as-is"),
        help="OpenUSD output: the capture's coordinates under a transform standing them upright "
        "(default), values turned Y-up with no transform, or the coordinates as they are "
        "(as NVIDIA's converter writes: upside down in Y-up viewers)",
    )
    p.add_argument(
        "--usd-input",
        choices=("capture", "stage"),
        help="OpenUSD input: take splat prims without our upright transform as capture (PLY) "
        "coordinates (default, right for NVIDIA's and OpenUSD's converters) or in the stage's axes",
    )
    _add_spz_axes(
        p,
        "with an SPZ input: the axes it is read in (default: its coordinate-system record's, else RUB); "
        "else, with an SPZ output: the axes it stores (default RUB)",
    )
    p.add_argument("--prune-opacity", type=float, metavar="T", help="drop splats whose opacity is below T (0..1)")
    p.add_argument(
        "--prune-invisible",
        type=float,
        nargs="?",
        const=0.0,
        metavar="W",
        help="drop splats that add nothing to any pixel of the views around the cloud (with W: "
        "whose blending weight T*alpha never exceeds W; 0.004 is about one 8-bit step)",
    )
    p.add_argument(
        "--views",
        type=int,
        default=12,
        help="views around the cloud that --prune-invisible keeps what they see of (default 12); "
        "the error is measured from as many others, between them",
    )
    p.add_argument("--view-size", type=int, default=128, help="pixels per side of those views (default 128)")
    p.add_argument(
        "--no-check",
        action="store_true",
        help="skip measuring the render error of the economies (quicker for huge files)",
    )


def _write_options(args):
    """Format-specific write options from the convert flags, refusing flags the output cannot use."""
    from .io import format_of

    fmt = format_of(args.output)
    options = {}
    if args.spz_version is not None:
        if fmt != "spz":
            raise UsageError(f"--spz-version needs a .spz output, not {args.output}")
        options["version"] = args.spz_version
    if args.half:
        if fmt != "usd":
            raise UsageError(f"--half needs an OpenUSD output (.usd, .usda, .usdc, .usdz), not {args.output}")
        options["half"] = True
    if args.spz_axes is not None and format_of(args.input) != "spz":
        if fmt != "spz":
            raise UsageError(f"--spz-axes needs an SPZ input or output, not {args.input} to {args.output}")
        options["spz_axes"] = args.spz_axes
    if args.axes is not None:
        if fmt != "usd":
            raise UsageError(f"--axes needs an OpenUSD output (.usd, .usda, .usdc, .usdz), not {args.output}")
        options["layout"] = args.axes
    return options


def _read_options(args):
    """Format-specific read options from the convert flags."""
    from .io import format_of

    if args.spz_axes is not None and format_of(args.input) == "spz":
        return {"spz_axes": args.spz_axes}
    if args.usd_input is None:
        return {}
    if format_of(args.input) != "usd":
        raise UsageError(f"--usd-input needs an OpenUSD input (.usd, .usda, .usdc, .usdz), not {args.input}")
    return {"unmarked": args.usd_input}


def _run_convert(args):
    from .io import read_splats, write_splats

    options = _write_options(args)
    cloud = read_splats(args.input, allow_outside=args.allow_outside, **_read_options(args))
    stages = _economy_stages(args, cloud, options)
    if stages:
        _write_stages(args, cloud, stages)
        cloud = stages[-1][1]
    else:
        write_splats(args.output, cloud, **options)
    print(f"wrote {len(cloud)} splats (SH degree {cloud.sh_degree}) to {args.output}")
    return 0


def _economy_stages(args, cloud, options):
    """[(label, cloud, write options)]: the input as the output format writes it, then one stage per
    economy asked for, each applied to the one before; [] when none is asked for."""
    from .core import economy

    plain = {k: v for k, v in options.items() if k != "half"}
    stages = [(f"as {Path(args.output).suffix}", cloud, plain)]
    try:
        if args.prune_opacity is not None:
            cloud = cloud[economy.opacity_mask(cloud, args.prune_opacity)]
            stages.append((f"prune opacity < {args.prune_opacity:g}", cloud, plain))
        if args.prune_invisible is not None:
            views = economy.orbit_views(economy.cloud_points(stages[0][1]), args.views, args.view_size)
            print(f"finding splats that {len(views)} views of {args.view_size} px see ...", file=sys.stderr)
            cloud = cloud[economy.visible_mask(cloud, views, min_weight=args.prune_invisible)]
            weight = f" (weight <= {args.prune_invisible:g})" if args.prune_invisible else ""
            stages.append((f"prune invisible{weight}", cloud, plain))
    except ValueError as exc:
        raise OptionError(str(exc)) from None
    if args.sh_degree is not None and args.sh_degree != cloud.sh_degree:
        stages.append((f"SH degree {cloud.sh_degree} -> {args.sh_degree}", cloud.with_sh_degree(args.sh_degree), plain))
    if args.half:
        stages.append(("half floats", stages[-1][1], options))
    return stages if len(stages) > 1 else []


def _write_stages(args, original, stages):
    """Write every stage (the last one to the output, the others to a temporary folder) and print
    what each saves against the stage before and, unless --no-check, the render error of the file
    written (read back, so format losses count) against the input from views around it. Warnings
    about the files written only to be measured are left out: the output's own are shown."""
    from .core import economy
    from .io import read_splats, write_splats

    views = reference = None
    if not args.no_check:
        views = economy.orbit_views(economy.cloud_points(original), args.views, args.view_size, phase=0.5)
        reference = economy.render_views(original, views)
    errors = "" if views is None else f"{'PSNR dB':>10}{'max abs':>10}"
    print(f"{'economy':<34}{'splats':>10}{'':>9}{'bytes':>14}{'':>9}{errors}")
    print(f"{Path(args.input).name[:33]:<34}{len(original):>10}{'':>9}{os.path.getsize(args.input):>14}")
    previous = None
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, cloud, options) in enumerate(stages):
            final = i == len(stages) - 1
            path = args.output if final else Path(tmp) / f"stage{i}{Path(args.output).suffix}"
            with warnings.catch_warnings():
                if not final:
                    warnings.simplefilter("ignore")
                write_splats(path, cloud, **options)
            size = os.path.getsize(path)
            row = (
                f"{label[:33]:<34}{len(cloud):>10}{_change(len(cloud), previous and previous[0]):>9}"
                f"{size:>14}{_change(size, previous and previous[1]):>9}"
            )
            if views is not None:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    written = read_splats(path)
                error = economy.image_error(reference, written, views)
                row += f"{error.psnr:>10.2f}{error.max_abs:>10.4f}"
            print(row, flush=True)
            previous = (len(cloud), size)
    if views is not None:
        print(
            f"error: RGBA renders of each file written against the input, {len(views)} views of "
            f"{args.view_size} px around it (colour premultiplied, clipped to [0, 1])"
        )


def _change(value, before):
    """'-12.5%' for a change from `before`; '' without one."""
    return f"{100.0 * (value - before) / before:+.1f}%" if before else ""


# render -------------------------------------------------------------------------------------------


def _add_render(p):
    p.add_argument("input", help="a splat file")
    _add_allow_outside(p)
    p.add_argument("-o", "--output", required=True, help="image to write: .png (8-bit) or .exr (R,G,B,A,Z)")
    p.add_argument("--width", type=int, default=512)
    p.add_argument("--height", type=int, default=512)
    p.add_argument("--fov", type=float, default=60.0, help="horizontal field of view in degrees")
    p.add_argument("--camera-pos", type=_parse_vec, help="x,y,z (default: frame the cloud)")
    p.add_argument("--look-at", type=_parse_vec, help="x,y,z (default: the centre of the cloud)")
    p.add_argument("--up", type=_parse_vec, default=np.array([0.0, 1.0, 0.0]), help="x,y,z world up")
    p.add_argument(
        "--background",
        type=lambda t: None if t.lower() == "none" else _parse_vec(t),
        default=np.zeros(3),
        help="r,g,b display sRGB in [0,1]; 'none' for a transparent image",
    )
    p.add_argument("--ortho-scale", type=float, help="orthographic camera showing this width in world units")
    p.add_argument(
        "--mode",
        choices=("classic", "antialiased"),
        default=None,
        help="render mode (default: the one the splats were made for: antialiased where the file "
        "says so, classic otherwise)",
    )
    p.add_argument(
        "--near",
        type=float,
        default=0.2,
        help="near clip distance (default 0.2, as the 3DGS reference; the same wherever the camera looks)",
    )
    _add_spz_axes(p)


def _run_render(args):
    from .core import economy
    from .core.camera import Camera, frame_points
    from .core.render import check_image_memory, render
    from .io import read_splats
    from .io.image import write_image

    try:  # before the file is read and anything allocated
        check_image_memory(Camera(args.width, args.height, 1.0, 1.0, 0.0, 0.0))
    except ValueError as exc:
        raise OptionError(f"--width, --height: {exc}") from None
    cloud = read_splats(args.input, allow_outside=args.allow_outside, **_spz_read_options(args, args.input))
    try:
        camera = frame_points(
            economy.cloud_points(cloud),
            args.width,
            args.height,
            args.fov,
            ortho_scale=args.ortho_scale,
            eye=args.camera_pos,
            target=args.look_at,
            up=args.up,
            near=args.near,
        )
    except ValueError as exc:
        raise OptionError(f"--camera-pos, --look-at: {exc}") from None
    up = args.up / np.linalg.norm(args.up)
    if np.linalg.norm(np.cross(camera.forward, up)) < 1e-6:
        raise OptionError(
            f"--up ({','.join(f'{x:g}' for x in args.up)}) is parallel to the view direction; give an up that is not"
        )
    start = time.perf_counter()
    try:
        result = render(cloud, camera, background=args.background, mode=args.mode, progress=Progress())
    except ValueError as exc:  # its memory check again, for the kernels it will use
        raise OptionError(str(exc)) from None
    write_image(args.output, result)
    skipped = result.stats["skipped_nonfinite"]
    print(
        f"rendered {result.stats['visible']} of {len(cloud)} splats at {args.width}x{args.height} in "
        f"{time.perf_counter() - start:.2f} s to {args.output}"
        + (f" ({skipped} splats with non-finite values skipped)" if skipped else "")
    )
    return 0


# mesh2splats --------------------------------------------------------------------------------------


def _float_list(text):
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None
    if not values or min(values) <= 0:
        raise argparse.ArgumentTypeError(f"expected positive numbers, got {text!r}")
    return values


def _memory_size(text):
    """'4G', '512M', '1.5GiB', '2e9' -> bytes (K, M, G, T are powers of 1024)."""
    match = re.fullmatch(r"\s*([0-9.]+(?:e[0-9]+)?)\s*([kmgt]?)(?:i?b)?\s*", text.lower())
    if not match:
        raise argparse.ArgumentTypeError(f"expected a size such as 4G or 512M, got {text!r}")
    return int(float(match.group(1)) * 1024 ** " kmgt".index(match.group(2) or " "))


def _add_mesh2splats(p):
    from .core.mesh_render import CYCLES_FILTER_WIDTH, DEFAULT_PIXEL_FILTER, PIXEL_FILTERS
    from .core.mesh_to_splats import DEFAULT_RENDER_MODE, DEFAULT_TARGET_PSNR

    p.add_argument(
        "mesh", help="a triangle mesh (.obj with its .mtl and textures; .stl, .dae, .glb, ... through trimesh)"
    )
    p.add_argument("output", help="the splat file to write (.ply, .usd/.usda/.usdc/.usdz, .spz, .splat)")
    _add_allow_outside(p)
    size = p.add_mutually_exclusive_group()
    size.add_argument("--max-splats", type=int, metavar="N", help="a splat budget, spread by area")
    size.add_argument(
        "--target-psnr",
        type=float,
        metavar="DB",
        help=f"refine until renders from every view reach this PSNR against the mesh's "
        f"(default {DEFAULT_TARGET_PSNR:g})",
    )
    p.add_argument("--view-size", type=int, default=256, help="pixels per side of the views PSNR is measured in")
    p.add_argument(
        "--memory-budget",
        type=_memory_size,
        metavar="SIZE",
        help="the most memory the conversion may take, e.g. 4G or 512M (default: half the memory free "
        "when it starts); it holds the splats to what fits and says so",
    )
    p.add_argument(
        "--view-distances",
        type=_float_list,
        default=None,
        metavar="D,D,...",
        help="distances of the views, multiples of the one that frames the whole mesh "
        "(default 0.5,1,3: close-up, whole, distant)",
    )
    p.add_argument("--view-count", type=int, default=None, metavar="N", help="views at each distance (default 4)")
    p.add_argument(
        "--mode",
        choices=("classic", "antialiased"),
        default=DEFAULT_RENDER_MODE,
        help="the render mode the splats are made for, which the file records (SPZ's flag, a PLY "
        f"header comment, an OpenUSD attribute); default {DEFAULT_RENDER_MODE}: antialiased keeps "
        "silhouettes right at every distance, classic is for viewers that cannot render antialiased",
    )
    p.add_argument(
        "--calibrate",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="with --max-splats: calibrate the silhouettes against renders of the mesh and the splats "
        "from the views (default; seconds per 100k splats); --no-calibrate renders nothing and "
        "keeps the splats on the surface",
    )
    p.add_argument(
        "--pixel-filter",
        choices=PIXEL_FILTERS,
        default=DEFAULT_PIXEL_FILTER,
        help="the pixel filter of the renders the splats should match, as Cycles' Film settings name it "
        f"(default {DEFAULT_PIXEL_FILTER}, Cycles' default)",
    )
    p.add_argument(
        "--filter-width",
        type=float,
        default=CYCLES_FILTER_WIDTH,
        metavar="PX",
        help=f"the filter's width in pixels, as Cycles' Film settings give it (default "
        f"{CYCLES_FILTER_WIDTH:g}; the box filter is one pixel whatever the width)",
    )
    p.add_argument(
        "--material",
        action="store_true",
        help="the splats also carry the surface's material for relighting: albedo (the Base Color, "
        "linear), normal, roughness and metallic, kept by PLY and OpenUSD (other formats drop them)",
    )


def _run_mesh2splats(args):
    from .core.mesh_refine import summary
    from .core.mesh_to_splats import mesh_to_splats
    from .io import SplatFileError, write_splats
    from .io.meshes import read_mesh_file

    if not args.calibrate and args.max_splats is None:
        raise OptionError("--no-calibrate applies to a --max-splats budget; a target PSNR always calibrates")
    start = time.perf_counter()
    mesh = read_mesh_file(args.mesh, allow_outside=args.allow_outside)
    info = {}
    try:
        cloud = mesh_to_splats(
            mesh.vertices,
            mesh.faces,
            **mesh.appearance(),
            max_splats=args.max_splats,
            target_psnr=args.target_psnr,
            view_size=args.view_size,
            view_distances=args.view_distances,
            view_count=args.view_count,
            render_mode=args.mode,
            calibrate=args.calibrate,
            pixel_filter=args.pixel_filter,
            filter_width=args.filter_width,
            memory_budget=args.memory_budget,
            material=args.material,
            progress=Progress(),
            info=info,
        )
    except ValueError as exc:
        raise SplatFileError(args.mesh, str(exc)) from None
    print(f"writing {len(cloud)} splats ({_file_size(args.output, cloud)}) to {args.output}", flush=True)
    write_splats(args.output, cloud)
    skipped = info.get("repaired")
    quality = summary(info)
    quality = f", {quality}" if quality else ""
    print(
        f"wrote {len(cloud)} splats from {len(mesh.faces)} faces{quality} to {args.output} in "
        f"{time.perf_counter() - start:.1f} s" + (f" (skipped or repaired: {skipped})" if skipped else "")
    )
    return 0


def _file_size(path, cloud):
    """About how large `cloud` will be written to `path`, for people ("about 12.3 MiB")."""
    from .core.memory import human_bytes
    from .io import format_of, written_size

    size = written_size(cloud, format_of(path))
    return "size unknown" if size is None else f"about {human_bytes(size)}"


# urdf2splats --------------------------------------------------------------------------------------


def _add_urdf2splats(p):
    p.add_argument("urdf", help="a robot description (.urdf) with its meshes (.obj, .stl, .dae, ...)")
    p.add_argument(
        "output",
        help="the splat file to write (.ply, .usd/.usda/.usdc/.usdz, .spz, .splat); "
        "the splats keep the URDF's frame (z up) and, in .ply, each one's link index",
    )
    p.add_argument(
        "--package-path",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder to look for package:// meshes in (repeat for more; ROS_PACKAGE_PATH is also used); "
        "meshes are read only from these and the URDF's folder",
    )
    _add_allow_outside(p)
    size = p.add_mutually_exclusive_group()
    size.add_argument(
        "--max-splats", type=int, metavar="N", help="a splat budget for the whole robot, spread by area (default 60000)"
    )
    size.add_argument(
        "--target-psnr",
        type=float,
        metavar="DB",
        help="refine until renders of the robot from every view reach this PSNR against its meshes",
    )
    p.add_argument(
        "--joint",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="pose the robot: a joint value (radians or metres; comma-separated for multi-value joints)",
    )


def _run_urdf2splats(args):
    from .core.kinematics import KinematicsError
    from .io import SplatFileError, write_splats
    from .io.urdf import read_robot

    start = time.perf_counter()
    values = {}
    for item in args.joint:
        name, sep, text = item.partition("=")
        try:
            values[name] = _parse_vec(text)
        except argparse.ArgumentTypeError:
            values[name] = None
        if not sep or values[name] is None or not np.isfinite(values[name]).all():
            raise OptionError(
                f"--joint expects NAME=VALUE with finite numbers (comma-separated for several), got '{item}'"
            )
    info = {}
    robot = read_robot(
        args.urdf,
        args.package_path,
        max_splats=args.max_splats,
        target_psnr=args.target_psnr,
        progress=Progress(),
        info=info,
        allow_outside=args.allow_outside,
    )
    try:
        cloud = robot.pose(robot.tree.pack(values))
    except KinematicsError as exc:
        raise SplatFileError(args.urdf, str(exc)) from None
    write_splats(args.output, cloud)
    quality = f", {info['psnr']:.1f} dB PSNR in the worst of {info['views']} views" if "psnr" in info else ""
    print(
        f"wrote {len(cloud)} splats on {len(np.unique(robot.links))} of {len(robot.tree)} links of "
        f"'{robot.name}' ({robot.tree.dof} degrees of freedom{quality}) to {args.output} in "
        f"{time.perf_counter() - start:.1f} s"
    )
    return 0


# demo (the main job) ------------------------------------------------------------------------------


def _add_demo(p):
    p.add_argument("--out", default="out/demo", help="folder for everything the demo writes")


def _run_demo(args):
    from .demo import run_demo

    return run_demo(args.out, progress=Progress())


VERBS = {
    "info": (_add_info, _run_info, "summarise a splat file"),
    "convert": (_add_convert, _run_convert, "convert between splat formats"),
    "render": (_add_render, _run_render, "render a splat file to a PNG or EXR image"),
    "mesh2splats": (_add_mesh2splats, _run_mesh2splats, "convert a triangle mesh to splats"),
    "urdf2splats": (_add_urdf2splats, _run_urdf2splats, "convert a robot (URDF and its meshes) to splats, posed"),
    "demo": (_add_demo, _run_demo, "run the built-in demo scene end to end"),
}


def build_parser():
    parser = argparse.ArgumentParser(
        prog="splatwright", description="3D Gaussian splats: inspect, convert, render, make from meshes, and a demo."
    )
    sub = parser.add_subparsers(dest="verb", required=True)
    for name, (add, run, help_text) in VERBS.items():
        p = sub.add_parser(name, help=help_text)
        add(p)
        p.set_defaults(run=run)
    return parser


def main(argv=None):
    """Run one verb. Exit status: 0 done; 1 a file or value error (a file that cannot be read or
    written, an option out of range); 2 a usage error (argparse's: an unknown option, a missing
    argument, text where a number belongs; ours: an option the files given cannot use). The
    message names the file or option either way. A file the system cannot read (OSError) or that
    needs more memory than there is is a bad file too: one line, status 1; any other exception is
    a defect and keeps its traceback."""
    args = build_parser().parse_args(argv)
    from .core import SplatValidationError
    from .core.memory import numpy_huge_pages
    from .io import SplatFileError

    numpy_huge_pages(False)  # fresh large arrays fault without waiting for compaction (core.memory)

    try:
        check_ranges(args)
        return args.run(args)
    except (SplatFileError, SplatValidationError, OptionError) as exc:
        print(f"splatwright {args.verb}: error: {exc}", file=sys.stderr)
        return 1
    except UsageError as exc:
        print(f"splatwright {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"splatwright {args.verb}: error: {exc.filename or _input(args)}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"splatwright {args.verb}: error: {_input(args)}: not enough memory for it", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C: outputs are written whole at the end (temporary file, rename), or not at all
        print(f"\nsplatwright {args.verb}: stopped (Ctrl-C); no output was written or changed", file=sys.stderr)
        return 130


def _input(args):
    """The file a verb reads, to name in a message."""
    return next((getattr(args, k) for k in ("file", "input", "mesh", "urdf") if getattr(args, k, None)), "input")


if __name__ == "__main__":
    sys.exit(main())
