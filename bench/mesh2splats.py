"""Mesh to splats: PSNR and SSIM at close-up, whole and distant views against Blender Cycles, by
splat count and conversion time, per mesh.

Meshes: our own (a textured UV sphere, a thin-walled cup with different colours outside and
inside, a large textured plane seen down to floor level), Blender primitives (Suzanne, a torus;
made by bpy in a subprocess) and pybullet's data meshes (duck.obj with its texture, bunny.obj, the
Franka Panda's hand with five materials; pybullet is installed once in bench/.oracles, see
_oracles.py). The independent reference is Cycles (headless bpy in a subprocess): emission-only
materials so the image is unlit, the 'Standard' view transform so pixels are sRGB-encoded
emission, CPU, black world. Held-out views: three per distance, at 0.5x, 1x and 3x the distance
that frames the mesh, from random directions (fixed seed; the plane's from 2 to 50 degrees above
it), none among the converter's own. Our splats are rendered by core.render in the mode they were
made for (the converter's default, classic, unless the row says otherwise). Errors: PSNR over the
views of each distance together, and the mean SSIM of all nine.

Rows per mesh: the default conversion (target 36 dB), the same made for antialiased rendering,
budgets with their calibration, the same budgets without it (as budgets were converted before:
more splats rendered worse) and made for antialiased rendering. Speed: a 100k-triangle textured sphere to 1M splats
(uncalibrated budget) against a per-triangle Python loop, and for the sphere and Suzanne the
classic conversion's CPU seconds against the converter as of SPEED_BEFORE (alternating runs), with
the PSNR each reaches.
Ceiling rows (`--only ceiling`): what no conversion can beat at the held-out views, no conversion
made (ceiling_rows).

    python bench/mesh2splats.py [--quick]
"""

import math
import pickle
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _cycles_reference import cycles_render  # noqa: E402
from _oracles import pybullet_data  # noqa: E402
from common import Row, Timing, _combine, paired, print_rows, timeit  # noqa: E402

from splatwright.core import (
    SplatCloud,  # noqa: E402
    metrics,  # noqa: E402
)
from splatwright.core.camera import Camera  # noqa: E402
from splatwright.core.mesh import Material, Mesh  # noqa: E402
from splatwright.core.mesh_refine import KNEE_GAIN_DB, VIEW_DISTANCES, VIEWS_PER_DISTANCE, conversion_bytes  # noqa: E402
from splatwright.core.mesh_render import render_mesh  # noqa: E402
from splatwright.core.mesh_to_splats import DEFAULT_RENDER_MODE, DEFAULT_TARGET_PSNR, mesh_to_splats  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.core.render_constants import LOW_PASS  # noqa: E402
from splatwright.core.scenes import thin_walled_cup  # noqa: E402
from splatwright.io.mesh import read_mesh  # noqa: E402

TOPIC = "mesh2splats"
DISTANCES = (0.5, 1.0, 3.0)
# The PSNR-against-splats curve: budgets doubling (the knee is where a doubling buys under
# KNEE_GAIN_DB at the worst held-out distance), and the Blender operator's default budget beside them.
CURVE_BUDGETS = (8_000, 16_000, 32_000, 64_000, 128_000, 256_000)
QUICK_CURVE_BUDGETS = (4_000, 16_000, 64_000)
SPEED_REPEAT = 3  # default conversions of textured meshes, each in a fresh process
LARGE_SEGMENTS, LARGE_RINGS = 176, 86  # a textured sphere of 29,920 triangles
MEMORY_BOUND = 4 << 30  # the most a default conversion of a mesh under 100k triangles may take
ROOT = HERE.parent
LARGE_NAME = "textured sphere, 30k triangles (checker patch)"


# bench meshes ------------------------------------------------------------------------------------


def uv_sphere(segments, rings):
    """A closed UV sphere: shared poles and seam positions, per-corner UVs with the seam split."""
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.cos(t), -np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    uv = np.stack([p / (2 * np.pi), 1 - t / np.pi], -1).reshape(-1, 2)
    r, s = (a.ravel() for a in np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij"))
    i = lambda r_, s_: r_ * (segments + 1) + s_
    a, b, c, d = i(r, s), i(r + 1, s), i(r + 1, s + 1), i(r, s + 1)
    f = np.concatenate([np.stack([a, b, c], 1)[r < rings - 1], np.stack([a, c, d], 1)[r > 0]])
    return v, f, uv[f]


def sphere_texture(w=1024, h=512, checker=False):
    """Smooth colour fields and soft stripes; `checker` adds a patch of sharp-edged squares."""
    y, x = np.mgrid[:h, :w] / np.array([h, w])[:, None, None]
    r = 0.55 + 0.3 * np.sin(2 * np.pi * 3 * x) * np.cos(2 * np.pi * 2 * y)
    g = 0.5 + 0.3 * np.cos(2 * np.pi * (2 * x + y)) + 0.1 * np.sin(2 * np.pi * 9 * x)
    b = 0.35 + 0.3 * y + 0.15 * np.tanh(3 * np.sin(2 * np.pi * 6 * x))
    img = np.stack([r, g, b], -1)
    if checker:
        patch = (x > 0.55) & (x < 0.8) & (y > 0.3) & (y < 0.6)
        squares = ((np.floor(x * 48) + np.floor(y * 24)) % 2)[..., None]
        img = np.where(patch[..., None], 0.15 + 0.7 * squares * np.array([1.0, 0.9, 0.3]), img)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def write_obj(folder, name, v, f, uv, texture, face_materials=None, flat_kd=(0.6, 0.25, 0.05)):
    """OBJ + MTL + PNG; material 'painted' (texture) and, where face_materials is 1, 'flat'."""
    from PIL import Image

    Image.fromarray(texture).save(folder / f"{name}.png")
    (folder / f"{name}.mtl").write_text(
        f"newmtl painted\nKd 0.8 0.8 0.8\nmap_Kd {name}.png\nnewmtl flat\nKd {flat_kd[0]} {flat_kd[1]} {flat_kd[2]}\n"
    )
    fm = np.zeros(len(f), int) if face_materials is None else face_materials
    lines = [f"mtllib {name}.mtl"]
    lines += [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v]
    lines += [f"vt {a:.9g} {b:.9g}" for a, b in uv.reshape(-1, 2)]
    for m, material in enumerate(("painted", "flat")):
        lines.append(f"usemtl {material}")
        for k in np.flatnonzero(fm == m):
            a, b, c = f[k] + 1
            t = 3 * k + 1
            lines.append(f"f {a}/{t} {b}/{t + 1} {c}/{t + 2}")
    path = folder / f"{name}.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def large_plane(size=10.0, n=40):
    """A 10 m square floor, textured, n x n quads."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    x, z = np.meshgrid(xs, xs)
    v = np.column_stack([x.ravel(), np.zeros(x.size), z.ravel()])
    i = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + n + 2, i + 1], 1), np.stack([i, i + n + 1, i + n + 2], 1)])
    uv = np.column_stack([(x.ravel() + size / 2) / size, (z.ravel() + size / 2) / size])[f]
    return Mesh(v, f, uv, None, [Material(texture=sphere_texture(512, 512))])


def blender_primitives(folder):
    """Suzanne and a torus as Blender makes them, one flat colour each."""
    out = folder / "primitives.npz"
    subprocess.run(
        [sys.executable, __file__, "--primitives", str(out)],
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    d = np.load(out)
    return {
        "Blender Suzanne": Mesh(
            d["suzanne_vertices"], d["suzanne_faces"], None, None, [Material(base_color=(0.7, 0.35, 0.1))]
        ),
        "Blender torus": Mesh(
            d["torus_vertices"], d["torus_faces"], None, None, [Material(base_color=(0.2, 0.45, 0.7))]
        ),
    }


def pybullet_meshes():
    """pybullet_data's duck (textured), bunny and Franka hand (multi-material), or a note saying why
    there are none."""
    try:
        root = pybullet_data()
    except (OSError, subprocess.CalledProcessError) as exc:
        return {}, f"pybullet's data could not be installed ({exc}): its meshes were not measured"
    return {
        "pybullet duck": read_mesh(root / "duck.obj"),
        "pybullet bunny": read_mesh(root / "bunny.obj"),
        "pybullet robot hand (5 materials)": read_mesh(root / "franka_panda/meshes/visual/hand.obj"),
    }, ""


def corpus_meshes():
    """The textured mesh corpus that core may carry (a public function of core.scenes, or of a core
    module named for textures or a corpus, whose name says corpus): name -> Mesh, empty without one."""
    import importlib
    import pkgutil

    import splatwright.core as core

    names = ["scenes"] + [m.name for m in pkgutil.iter_modules(core.__path__) if re.search("corpus|textur", m.name)]
    for module_name in names:
        module = importlib.import_module(f"splatwright.core.{module_name}")
        for attr in sorted(dir(module)):
            if "corpus" in attr and not attr.startswith("_") and callable(getattr(module, attr)):
                found = getattr(module, attr)()
                items = found.items() if isinstance(found, dict) else found
                return {f"corpus: {name}": mesh for name, mesh in items if isinstance(mesh, Mesh)}
    return {}


def bench_meshes(folder, quick):
    """name -> Mesh, and a note about meshes that could not be had."""
    sphere = uv_sphere(48, 24) if quick else uv_sphere(96, 48)
    large = uv_sphere(LARGE_SEGMENTS, LARGE_RINGS)
    meshes = {
        "textured sphere": read_mesh(write_obj(folder, "sphere", *sphere, sphere_texture())),
        "textured sphere, checker patch": read_mesh(
            write_obj(folder, "checker", *sphere, sphere_texture(checker=True))
        ),
        LARGE_NAME: read_mesh(write_obj(folder, "large", *large, sphere_texture(checker=True))),
        "thin-walled cup (5 mm)": thin_walled_cup(),
        "large plane (10 m)": large_plane(),
    }
    meshes.update(blender_primitives(folder))
    found, note = pybullet_meshes()
    meshes.update(found)
    meshes.update(corpus_meshes())
    return meshes, note


def textured(mesh):
    """Whether the mesh's colour varies within faces: a texture, or colours per corner."""
    return mesh.corner_colors is not None or any(m.texture is not None for m in mesh.materials or [])


def held_out_cameras(mesh, size, per_distance=3, distances=DISTANCES, seed=5, floor=False):
    """`per_distance` views at each of `distances` (multiples of the distance that frames the mesh,
    as the converter's own views) from random directions (fixed seed); with `floor`, from 2 to 50
    degrees above the y = 0 plane."""
    v = mesh.vertices
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    framing = 1.1 * np.linalg.norm(v - centre, axis=1).max() / math.sin(math.radians(20.0))
    rng = np.random.default_rng(seed)
    cams = []
    for d in distances:
        dirs = rng.normal(size=(per_distance, 3))
        if floor:
            azimuth = rng.uniform(0, 2 * np.pi, per_distance)
            elevation = np.radians([2.0, 15.0, 50.0][:per_distance])
            dirs = np.column_stack(
                [np.cos(elevation) * np.cos(azimuth), np.sin(elevation), np.cos(elevation) * np.sin(azimuth)]
            )
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        cams += [
            (
                d,
                Camera.look_at(
                    centre + framing * d * u, centre, fov_deg=40.0, width=size, height=size, near=1e-3 * framing
                ),
            )
            for u in dirs
        ]
    return cams


def _primitives_main(out_path):
    """Runs inside a subprocess: Blender's own primitives as triangles."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    arrays = {}
    for name, add in (("suzanne", bpy.ops.mesh.primitive_monkey_add), ("torus", bpy.ops.mesh.primitive_torus_add)):
        add()
        obj = bpy.context.active_object
        obj.data.calc_loop_triangles()
        arrays[f"{name}_vertices"] = np.array([v.co[:] for v in obj.data.vertices], np.float64)
        arrays[f"{name}_faces"] = np.array([t.vertices[:] for t in obj.data.loop_triangles], np.int64)
        bpy.data.objects.remove(obj)
    np.savez(out_path, **arrays)


# comparisons -----------------------------------------------------------------------------------


def versus(images, references):
    """PSNR over all images together and mean SSIM."""
    mse = np.mean([np.mean((np.asarray(a, np.float64) - b) ** 2) for a, b in zip(images, references)])
    ssim = np.mean([metrics.ssim(a, b) for a, b in zip(images, references)])
    return {"psnr_db": float(10 * np.log10(1 / mse)), "ssim": float(ssim)}


def splat_error(cloud, cameras, references, mode=None):
    return versus([render(cloud, cam, mode=mode).color for cam in cameras], references)


def convert(mesh, **options):
    return mesh_to_splats(mesh.vertices, mesh.faces, **mesh.appearance(), **options)


# the baseline: one Python iteration per triangle -------------------------------------------------


def baseline_convert(mesh, max_splats, seed=0):
    """A straightforward per-triangle converter: per face, round(N * area share) random points
    (at least one), isotropic discs of the face's spacing, colour by nearest-texel lookup."""
    rng = np.random.default_rng(seed)
    v, f = mesh.vertices, mesh.faces
    areas = [0.5 * np.linalg.norm(np.cross(v[b] - v[a], v[c] - v[a])) for a, b, c in f]
    total = sum(areas)
    material = mesh.materials[0]
    texture = material.texture.astype(np.float64) / 255.0
    h, w = texture.shape[:2]
    out = {"p": [], "q": [], "s": [], "c": []}
    for k, (a, b, c) in enumerate(f):
        if areas[k] <= 0:
            continue
        n = max(1, round(max_splats * areas[k] / total))
        r1, r2 = np.sqrt(rng.uniform(size=n)), rng.uniform(size=n)
        bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)
        out["p"].append(bary @ v[[a, b, c]])
        normal = np.cross(v[b] - v[a], v[c] - v[a])
        normal /= np.linalg.norm(normal)
        t1 = (v[b] - v[a]) / np.linalg.norm(v[b] - v[a])
        frame = np.stack([t1, np.cross(normal, t1), normal], 1)
        w_ = math.sqrt(max(0.0, 1 + frame[0, 0] + frame[1, 1] + frame[2, 2])) / 2
        quat = [
            w_,
            (frame[2, 1] - frame[1, 2]) / (4 * w_ + 1e-12),
            (frame[0, 2] - frame[2, 0]) / (4 * w_ + 1e-12),
            (frame[1, 0] - frame[0, 1]) / (4 * w_ + 1e-12),
        ]
        out["q"].append(np.tile(quat, (n, 1)))
        sigma = math.sqrt(areas[k] / n)
        out["s"].append(np.tile([sigma, sigma, 0.01 * sigma], (n, 1)))
        uv = bary @ mesh.corner_uvs[k]
        px = (uv[:, 0] % 1 * w).astype(int).clip(0, w - 1)
        py = ((1 - uv[:, 1] % 1) * h).astype(int).clip(0, h - 1)
        out["c"].append(texture[py, px])
    return SplatCloud.from_activated(
        np.concatenate(out["p"]),
        np.concatenate(out["q"]),
        np.concatenate(out["s"]),
        np.full(sum(len(p) for p in out["p"]), 0.99),
        colors=np.concatenate(out["c"]),
    )


def speed_rows(quick, sphere_mesh, cameras, references):
    """100k triangles -> 1M splats, ours against the per-triangle loop, with the PSNR each buys."""
    segments, rings = (100, 50) if quick else (318, 158)
    v, f, uv = uv_sphere(segments, rings)
    big = Mesh(v, f, uv, None, [Material(texture=sphere_texture())])
    splats = 10 * len(f)
    big.materials[0].linear_texture()  # decode once, outside the timing
    ours = timeit(lambda: convert(big, max_splats=splats, calibrate=False), repeat=3 if quick else 5)
    subset = 1000 if quick else 2000
    part = Mesh(v, f[:subset], uv[:subset], None, big.materials)
    loop = timeit(lambda: baseline_convert(part, splats * subset // len(f)), repeat=3, warmup=0)
    scale = len(f) / subset
    baseline = Timing(loop.median * scale, loop.spread * scale, loop.runs)
    per_100k = 1e5 / len(f)
    equal = 60_000 if quick else 150_000
    err_ours = splat_error(convert(sphere_mesh, max_splats=equal, calibrate=False), cameras, references)
    err_base = splat_error(baseline_convert(sphere_mesh, equal), cameras, references)
    return [
        Row(
            TOPIC,
            f"{len(f) // 1000}k triangles -> {splats // 1000}k splats (budget)",
            ours,
            baseline,
            error={
                "psnr_db": err_ours["psnr_db"],
                "baseline_psnr_db": err_base["psnr_db"],
                "ssim": err_ours["ssim"],
                "baseline_ssim": err_base["ssim"],
            },
            extra={
                "s per 100k tris": f"{ours.median * per_100k:.2f}",
                "baseline s per 100k tris": f"{baseline.median * per_100k:.1f} (timed on {subset} faces)",
                "error at": f"{equal // 1000}k splats on the bench sphere",
            },
        )
    ]


# the benchmark -----------------------------------------------------------------------------------


def psnr_by_distance(images, cams, references):
    """{"dB 0.5x": ...}: the PSNR of `images` against `references` per held-out distance, over the
    views of each distance (`cams`: (distance, Camera) pairs) together; distances without views left
    out."""
    out = {}
    for d in DISTANCES:
        pick = [i for i, (dd, _) in enumerate(cams) if dd == d]
        if pick:
            out[f"dB {d:g}x"] = versus([images[i] for i in pick], [references[i] for i in pick])["psnr_db"]
    return out


def by_distance(cloud, cams, references):
    """PSNR per held-out distance (over its views together) and the mean SSIM of all views."""
    images = [render(cloud, cam).color for _, cam in cams]
    out = psnr_by_distance(images, cams, references)
    out["ssim"] = float(np.mean([metrics.ssim(a, b) for a, b in zip(images, references)]))
    return out


def thin_splat_limit(mesh, cams, references):
    """by_distance's PSNR of the image infinitely many, infinitely thin splats would draw: the mesh's
    own samples blended in display colour under the renderer's low-pass (core.mesh_render, mix
    "display"). A splat renderer blends display colours where Cycles mixes linear light, so hard
    colour edges lose this much before the splats' own size; calibrated outlines can do better."""
    width = 4 * math.sqrt(LOW_PASS)  # Cycles' Gaussian filter has sigma width / 4
    images = [
        render_mesh(mesh, cam, pixel_filter="gaussian", filter_width=width, mix="display").color for _, cam in cams
    ]
    return psnr_by_distance(images, cams, references)


def ceiling_rows(quick=False):
    """What no splats drawn by a 3DGS renderer can beat on the textured bench meshes, no conversion
    made: against Cycles at the held-out views, the image of infinitely many, infinitely thin splats
    (the mesh's own samples under the renderer's 0.3 px^2 Gaussian) blended in display colour as every
    3DGS renderer blends (thin_splat_limit), the same blended in linear light (as Cycles mixes a
    pixel: what a linear-light splat renderer could reach), and core.mesh_render's own reference (the
    Blackman-Harris filter Cycles uses, linear light: how far the reference itself is from Cycles)."""
    size = 128 if quick else 256
    width = 4 * math.sqrt(LOW_PASS)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        meshes, _ = bench_meshes(folder, quick)
        names = [n for n, m in meshes.items() if textured(m)]
        for name in names[:2] if quick else names:
            mesh = meshes[name]
            cams = held_out_cameras(mesh, size, floor="plane" in name)
            references, _ = cycles_render(mesh, [cam for _, cam in cams], folder)
            t0 = time.perf_counter()
            display = thin_splat_limit(mesh, cams, references)
            timing = Timing(time.perf_counter() - t0, 0.0, 1)
            linear = [render_mesh(mesh, cam, pixel_filter="gaussian", filter_width=width).color for _, cam in cams]
            own = [render_mesh(mesh, cam).color for _, cam in cams]
            columns = lambda e: " / ".join(f"{e[f'dB {d:g}x']:.1f}" for d in DISTANCES)  # noqa: E731
            row = Row(
                TOPIC,
                f"{name}: ceiling of thin splats (display blending) against Cycles",
                timing,
                error=display,
                extra={
                    "linear-light thin splats dB 0.5x / 1x / 3x": columns(psnr_by_distance(linear, cams, references)),
                    "mesh reference dB 0.5x / 1x / 3x": columns(psnr_by_distance(own, cams, references)),
                },
            )
            rows.append(row)
            print_rows([row])
    return rows


def worst_distance(error):
    """The lowest of by_distance's per-distance dB."""
    return min(error[f"dB {d:g}x"] for d in DISTANCES)


# the default conversion against the converter before its speed-up ----------------------------------

OTHER_MODE = "antialiased" if DEFAULT_RENDER_MODE == "classic" else "classic"
SPEED_BEFORE = "b588814"  # the last commit before the default conversion was made faster
SPEED_MESHES = ("textured sphere", LARGE_NAME)


def converter_before():
    """mesh_to_splats as of SPEED_BEFORE (with its refinement and mesh rasteriser), beside today's."""
    from _before import module_before

    old = dict(commit=SPEED_BEFORE, suffix="speed_before")
    module_before("core/mesh_render.py", **old)
    steps = module_before(
        "core/mesh_to_splats.py", {"from .mesh_refine import": "from ._mesh_refine_speed_before import"}, **old
    )
    module_before(
        "core/mesh_refine.py",
        {
            "from .mesh_render import": "from ._mesh_render_speed_before import",
            "from .mesh_to_splats import": "from ._mesh_to_splats_speed_before import",
        },
        **old,
    )
    return steps.mesh_to_splats


def speed_before_row(name, mesh, size, cams, references, quick):
    """CPU seconds of the default target conversion made for classic rendering (SPEED_BEFORE's only
    mode), today's against SPEED_BEFORE's in alternating runs, with the worst own-view and held-out
    PSNR each reaches."""
    before = converter_before()
    runs = {}

    def conversion(fn, key, **mode):
        def run():
            info = {}
            cloud = fn(mesh.vertices, mesh.faces, **mesh.appearance(), view_size=size, info=info, **mode)
            runs[key] = (cloud, info)

        return run

    base, ours = paired(
        conversion(before, "before"),
        conversion(mesh_to_splats, "ours", render_mode="classic"),
        1,  # each run of the converter before takes minutes on the larger meshes
        time.process_time,
        warmup=False,
    )
    error = {}
    for key, prefix in (("ours", ""), ("before", "before ")):
        cloud, info = runs[key]
        held = by_distance(cloud, cams, references)
        error[f"{prefix}own worst dB"] = info["psnr"]
        error[f"{prefix}held-out worst dB"] = worst_distance(held)
    return Row(
        TOPIC,
        f"{name}: classic conversion, CPU s, against {SPEED_BEFORE} (before the speed-up)",
        ours,
        base,
        error=error,
        extra={"faces": len(mesh.faces), "splats": len(runs["ours"][0]), "splats before": len(runs["before"][0])},
    )


def operator_budget():
    """The Blender operator's default splat budget (splat_addon/convert/from_mesh.py DEFAULT_BUDGET,
    read from the file: importing it needs bpy)."""
    text = (ROOT / "splat_addon" / "convert" / "from_mesh.py").read_text()
    return int(re.search(r"^DEFAULT_BUDGET = ([\d_]+)", text, re.M).group(1).replace("_", ""))


def default_view_pixels(size):
    return VIEWS_PER_DISTANCE * len(VIEW_DISTANCES) * size * size


def convert_in_child(mesh, folder, repeat=1, **options):
    """The conversion run `repeat` times, each in a fresh process (so its peak resident memory is
    its own): (cloud, info, Timing of the conversions, memory of the run with the highest peak)."""
    src, dst = folder / "convert_in.pkl", folder / "convert_out.pkl"
    with open(src, "wb") as f:
        pickle.dump((mesh, options), f)
    seconds, memory = [], None
    for _ in range(repeat):
        subprocess.run([sys.executable, __file__, "--convert", str(src), str(dst)], check=True)
        with open(dst, "rb") as f:
            cloud, info, took, used = pickle.load(f)
        seconds.append(took)
        memory = used if memory is None or used["peak"] > memory["peak"] else memory
    spread = (max(seconds) - min(seconds)) / 2
    return cloud, info, Timing(statistics.median(seconds), spread, repeat), memory


def _status_bytes(field):
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    return None


def _reset_peak():
    """Start the peak resident memory (VmHWM) again from the current (Linux 4.0+); False where it
    cannot be."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _convert_main(src, dst):
    """Runs in the child: a small conversion to load the compiled kernels, then the one measured."""
    import resource

    with open(src, "rb") as f:
        mesh, options = pickle.load(f)
    small = uv_sphere(12, 6)
    convert(Mesh(*small[:2], small[2], None, [Material(texture=sphere_texture(64, 32))]), view_size=32)
    rss_before = _status_bytes("VmRSS")
    fresh_peak = _reset_peak()
    info = {}
    start, cpu = time.perf_counter(), time.process_time()
    cloud = convert(mesh, info=info, **options)
    seconds = time.perf_counter() - start
    info["cpu_seconds"] = time.process_time() - cpu
    peak = _status_bytes("VmHWM") if fresh_peak else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    memory = {"rss_before": rss_before, "peak": peak, "peak_is_conversion": fresh_peak}
    info = {k: v for k, v in info.items() if isinstance(v, (int, float, str, bool, list, dict, type(None)))}
    with open(dst, "wb") as f:
        pickle.dump((cloud, info, seconds, memory), f)


def default_row(name, mesh, size, cams, references, folder, quick):
    """The default conversion (target DEFAULT_TARGET_PSNR) in fresh processes (SPEED_REPEAT runs for
    textured meshes): its held-out error, seconds and peak resident memory beside the prediction."""
    repeat = SPEED_REPEAT if textured(mesh) and not quick else 1
    cloud, info, timing, memory = convert_in_child(mesh, folder, repeat, view_size=size)
    predicted = conversion_bytes(len(cloud), len(mesh.faces), default_view_pixels(size))
    grown = memory["peak"] - memory["rss_before"]
    row = Row(
        TOPIC,
        f"{name}: default (target {DEFAULT_TARGET_PSNR:g} dB, {DEFAULT_RENDER_MODE})",
        timing,
        error=by_distance(cloud, cams, references),
        extra={
            "faces": len(mesh.faces),
            "splats": len(cloud),
            "own worst dB": f"{info['psnr']:.1f}",
            "reached": info["reached"],
            "worst own view": f"{info['worst_view_distance']:g}x, {info['worst_view_edge_share']:.0%} on silhouettes",
            "textured": textured(mesh),
            "CPU s": f"{info.get('cpu_seconds', float('nan')):.1f}",
            "peak RSS MiB": round(memory["peak"] / 2**20),
            "RSS growth MiB": round(grown / 2**20),
            "predicted MiB": round(predicted / 2**20),
            "memory budget GiB": f"{info['memory_budget'] / 2**30:.1f}",
            "memory cap": info.get("memory_cap"),
        },
    )
    memory.update(predicted=predicted, budget=info["memory_budget"], cap=info.get("memory_cap"), faces=len(mesh.faces))
    return row, cloud, memory


def classic_row(name, mesh, size, cams, references):
    info = {}
    start = time.perf_counter()
    cloud = convert(mesh, view_size=size, info=info, render_mode=OTHER_MODE)
    seconds = time.perf_counter() - start
    return Row(
        TOPIC,
        f"{name}: default, made for {OTHER_MODE} rendering",
        Timing(seconds, 0.0, 1),
        error=by_distance(cloud, cams, references),  # rendered in its own mode
        extra={
            "faces": len(mesh.faces),
            "splats": len(cloud),
            "own worst dB": f"{info['psnr']:.1f}",
            "reached": info["reached"],
            "worst own view": f"{info['worst_view_distance']:g}x, {info['worst_view_edge_share']:.0%} on silhouettes",
        },
    )


def knee(points):
    """(budget, worst dB) of the smallest budget from which every further step buys under KNEE_GAIN_DB
    per doubling at the worst held-out distance (a plateau that more splats climb out of again is no
    knee: a budget whose calibration kept a smaller rung), or None when the last step still buys more."""
    pts = sorted(points)
    at = None
    for (n, worst), (more, better) in reversed(list(zip(pts, pts[1:]))):
        if (better - worst) / math.log2(more / n) >= KNEE_GAIN_DB:
            break
        at = (n, worst)
    return at


def knee_row(name, curve, operator):
    """Where the defaults land against the knee of the mesh's curve."""
    doubling = [(n, worst_distance(e)) for n, _, e, _ in curve["budgets"] if n != operator]
    at = knee(doubling)
    seconds = {n: s for n, _, _, s in curve["budgets"]}
    splats, error = curve["default"]
    extra = {
        "default splats": splats,
        "default worst dB": f"{worst_distance(error):.1f}",
        "knee budget": at[0] if at else f"past {max(n for n, _ in doubling)}",
        "knee worst dB": f"{at[1]:.1f}" if at else "",
    }
    if at:
        extra["default / knee splats"] = f"{splats / at[0]:.2f}"
        extra["knee budget s"] = f"{seconds[at[0]]:.1f}"
    for n, kept, e, s in curve["budgets"]:
        if n == operator:
            extra["operator budget worst dB"] = f"{worst_distance(e):.1f}"
            extra["operator budget kept"] = kept
            extra["operator budget s"] = f"{s:.1f}"
            if at:
                extra["operator budget over knee dB"] = f"{worst_distance(e) - at[1]:+.1f}"
    return Row(
        TOPIC,
        f"{name}: knee (from it each doubling buys < {KNEE_GAIN_DB:g} dB) and the defaults",
        Timing(0.0, 0.0, 0),
        extra=extra,
    )


def curve_rows(name, mesh, size, budgets, cams, references):
    """A calibrated budget conversion per budget: rows and the curve's points (budget, kept, error)."""
    rows, points = [], []
    for n in budgets:
        info = {}
        start = time.perf_counter()
        cloud = convert(mesh, max_splats=n, view_size=size, info=info)
        seconds = time.perf_counter() - start
        error = by_distance(cloud, cams, references)
        points.append((n, len(cloud), error, seconds))
        rows.append(
            Row(
                TOPIC,
                f"{name}: budget {n}",
                Timing(seconds, 0.0, 1),
                error=error,
                extra={"splats": len(cloud), "inset px": f"{info['inset_pixels']:.2f}"},
            )
        )
    return rows, points


def mesh_rows(name, mesh, size, budgets, folder, quick=False):
    cams = held_out_cameras(mesh, size, floor="plane" in name)
    references, cycles_s = cycles_render(mesh, [cam for _, cam in cams], folder)
    row, cloud, memory = default_row(name, mesh, size, cams, references, folder, quick)
    rows = [row, classic_row(name, mesh, size, cams, references)]
    if name in SPEED_MESHES and not (quick and name == LARGE_NAME):
        rows.append(speed_before_row(name, mesh, size, cams, references, quick))
    budget_rows, points = curve_rows(name, mesh, size, budgets, cams, references)
    rows += budget_rows
    curve = {"budgets": points, "default": (len(cloud), row.error)}
    rows.append(knee_row(name, curve, operator_budget()))
    return rows, curve, memory, (cams, references, cycles_s)


def memory_row(store):
    """Whether any default conversion exceeded its memory budget (its resident memory grew past it,
    or its splats reached what the budget holds), and the bound for meshes under 100k triangles."""
    memories = list(store["memories"].values())
    splats = {name: store["curves"][name]["default"][0] for name in store["memories"]}
    capped = [n for n, m in store["memories"].items() if m["cap"] is not None and splats[n] >= m["cap"]]
    grown = [n for n, m in store["memories"].items() if m["peak"] - m["rss_before"] > m["budget"]]
    under_100k = [m for m in memories if m["faces"] < 100_000]
    within = sum(m["peak"] <= MEMORY_BOUND for m in under_100k)
    ratio = max((m["peak"] - m["rss_before"]) / m["predicted"] for m in memories)
    return Row(
        TOPIC,
        "memory: every default conversion, each in a fresh process",
        Timing(0.0, 0.0, 0),
        extra={
            "conversions": len(memories),
            "over their memory budget": len(set(capped + grown)),
            "highest peak RSS MiB": round(max(m["peak"] for m in memories) / 2**20),
            "under 100k faces within 4 GiB": f"{within} of {len(under_100k)}",
            "highest growth / predicted": f"{ratio:.2f}",
            "memory budget GiB": f"{min(m['budget'] for m in memories) / 2**30:.1f}",
        },
    )


CURVES_FILE = HERE / "mesh2splats_curves.json"  # every mesh's curve and memory, for the plot
# Parts that `./run bench mesh2splats --only <part>` runs alone (on two cores, two at once), their rows
# merged into the report's: the meshes up to and including the first group's last, the rest, and
# core's textured corpus; the plot and the memory row are made from every mesh measured so far.
FIRST_PART_LAST = "thin-walled cup (5 mm)"


def in_part(part, names):
    """The bench meshes' names in `part` (None: all)."""
    names = list(names)
    split = names.index(FIRST_PART_LAST) + 1
    return {
        None: names,
        "first": names[:split],
        "second": [n for n in names[split:] if not n.startswith("corpus")],
        "corpus": [n for n in names if n.startswith("corpus")],
    }[part]


def run(quick=False, part=None):
    size = 128 if quick else 256
    operator = operator_budget()
    budgets = sorted(set(QUICK_CURVE_BUDGETS if quick else CURVE_BUDGETS) | {operator})
    rows = []
    if part is None:
        CURVES_FILE.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        meshes, note = bench_meshes(folder, quick)
        names = in_part(part, meshes)
        if quick:
            names = names[:3]
        first = None
        for name in names:
            mesh = meshes[name]
            mesh_rows_, curve, memory, held = mesh_rows(name, mesh, size, budgets, folder, quick)
            rows += mesh_rows_
            first = first or (name, mesh, held)
            _save_curve(name, curve, memory)
            print_rows(mesh_rows_)
        if note and part != "corpus":
            rows.append(Row(TOPIC, note, Timing(0.0, 0.0, 0)))
        store = _load_curves()
        rows.append(memory_row(store))
        if first is not None and first[0] == "textured sphere":
            _, mesh, (cams, references, _) = first
            rows += speed_rows(quick, mesh, [cam for _, cam in cams], references)
    _plot(store["curves"], operator, HERE / "mesh2splats_curve.png")
    return rows


def texture_rows(name, mesh, size, folder, quick):
    """The default conversion texture-aware (the converter's default) against texture_aware=False
    (the converter before it), in alternating fresh processes: held-out error, seconds and memory."""
    cams = held_out_cameras(mesh, size, floor="plane" in name)
    references, _ = cycles_render(mesh, [cam for _, cam in cams], folder)
    repeat = 1  # one pair: a pair takes minutes on the 30k-triangle sphere
    runs = {True: [], False: []}
    for _ in range(repeat):
        for aware in (False, True):
            runs[aware].append(convert_in_child(mesh, folder, 1, view_size=size, texture_aware=aware))
    (cloud, info, _, memory), (old_cloud, _, _, _) = runs[True][-1], runs[False][-1]
    timing, baseline = (_combine([r[2] for r in runs[aware]]) for aware in (True, False))
    error, before = by_distance(cloud, cams, references), by_distance(old_cloud, cams, references)
    limit = thin_splat_limit(mesh, cams, references)
    row = Row(
        TOPIC,
        f"{name}: default, texture-aware, against texture_aware=False",
        timing,
        baseline,
        error=error,
        extra={
            "faces": len(mesh.faces),
            "splats": len(cloud),
            "splats before": len(old_cloud),
            "reached": info["reached"],
            "CPU s": f"{info.get('cpu_seconds', float('nan')):.1f}",
            "before dB 0.5x / 1x / 3x": " / ".join(f"{before[f'dB {d:g}x']:.1f}" for d in DISTANCES),
            "thin-splat image dB 0.5x / 1x / 3x": " / ".join(f"{limit[f'dB {d:g}x']:.1f}" for d in DISTANCES),
            "peak RSS MiB": round(memory["peak"] / 2**20),
            "RSS growth MiB": round((memory["peak"] - memory["rss_before"]) / 2**20),
            "predicted MiB": round(conversion_bytes(len(cloud), len(mesh.faces), default_view_pixels(size)) / 2**20),
        },
    )
    return row, (len(cloud), error)


def run_textured(quick=False):
    """texture_rows for every textured bench mesh; the texture-aware defaults join the curves' plot."""
    size = 128 if quick else 256
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        meshes, _ = bench_meshes(folder, quick)
        # texture edges first (where texture awareness matters), the corpus next, the rest last
        first = ("checker", "duck", "hand", "corpus")
        rank = lambda n: next((k for k, word in enumerate(first) if word in n), len(first))  # noqa: E731
        names = sorted((n for n, m in meshes.items() if textured(m)), key=rank)
        for name in names[:2] if quick else names:
            row, default = texture_rows(name, meshes[name], size, folder, quick)
            rows.append(row)
            print_rows([row])
            store = _load_curves()
            if name in store["curves"]:
                store["curves"][name]["texture_aware_default"] = default
            store.setdefault("texture_rows", {})[name] = _row_data(row)
            CURVES_FILE.write_text(__import__("json").dumps(store, indent=1))
    store = _load_curves()
    _plot(store["curves"], operator_budget(), HERE / "mesh2splats_curve.png")
    return rows


def run_summary(quick=False):
    """No measuring: the knee rows, the memory row and the plot again from CURVES_FILE (after the rule
    or the plot changed, or parts ran apart)."""
    store, operator = _load_curves(), operator_budget()
    rows = [knee_row(name, curve, operator) for name, curve in store["curves"].items()]
    rows += [_row_from(data) for data in store.get("texture_rows", {}).values()]
    report = (HERE / "REPORT.md").read_text() if (HERE / "REPORT.md").exists() else ""
    rows += [row for row in _curve_rows_from(store) if f"| {row.case} |" not in report]
    rows.append(memory_row(store))
    _plot(store["curves"], operator, HERE / "mesh2splats_curve.png")
    return rows


PARTS = {part: (lambda quick, part=part: run(quick, part)) for part in ("first", "second", "corpus")}
PARTS["textured"] = run_textured
PARTS["summary"] = run_summary
PARTS["ceiling"] = ceiling_rows


def _save_curve(name, curve, memory):
    """Add a mesh's curve and memory to CURVES_FILE (read again first: parts may run at once)."""
    import json

    store = _load_curves()
    store["curves"][name], store["memories"][name] = curve, memory
    CURVES_FILE.write_text(json.dumps(store, indent=1))


def _curve_rows_from(store):
    """The default and budget rows of every stored curve (for a part stopped before it reported)."""
    for name, curve in store["curves"].items():
        splats, error = curve["default"]
        memory = store["memories"][name]
        yield Row(
            TOPIC,
            f"{name}: default (target {DEFAULT_TARGET_PSNR:g} dB, {DEFAULT_RENDER_MODE})",
            Timing(float("nan"), 0.0, 0),
            error=error,
            extra={
                "faces": memory["faces"],
                "splats": splats,
                "peak RSS MiB": round(memory["peak"] / 2**20),
                "RSS growth MiB": round((memory["peak"] - memory["rss_before"]) / 2**20),
                "predicted MiB": round(memory["predicted"] / 2**20),
            },
        )
        for n, kept, error, seconds in curve["budgets"]:
            yield Row(TOPIC, f"{name}: budget {n}", Timing(seconds, 0.0, 1), error=error, extra={"splats": kept})


def _row_data(row):
    timings = {k: vars(getattr(row, k)) for k in ("timing", "baseline") if getattr(row, k) is not None}
    return {"case": row.case, **timings, "error": row.error, "extra": row.extra}


def _row_from(data):
    baseline = Timing(**data["baseline"]) if "baseline" in data else None
    return Row(TOPIC, data["case"], Timing(**data["timing"]), baseline, data["error"], data["extra"])


def _load_curves():
    import json

    if not CURVES_FILE.exists():
        return {"curves": {}, "memories": {}}
    store = json.loads(CURVES_FILE.read_text())
    for curve in store["curves"].values():
        curve["budgets"] = [tuple(point) for point in curve["budgets"]]
    return store


def _plot(curves, operator, path):
    """One panel per mesh: PSNR at each held-out distance against the budget, the default target's
    conversion as stars, the operator's default budget and the knee as vertical lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 4
    rows = math.ceil(len(curves) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False, sharey=True)
    for ax, (name, curve) in zip(axes.ravel(), curves.items()):
        pts = sorted(curve["budgets"])
        budgets = [n for n, _, _, _ in pts]
        splats, default = curve["default"]
        for k, d in enumerate(DISTANCES):
            key = f"dB {d:g}x"
            ax.plot(budgets, [e[key] for _, _, e, _ in pts], "o-", ms=3, color=f"C{k}", label=f"{d:g}x")
            ax.plot([splats], [default[key]], "*", ms=11, color=f"C{k}", mec="k", mew=0.5)
            if "texture_aware_default" in curve:
                aware_splats, aware = curve["texture_aware_default"]
                ax.plot([aware_splats], [aware[key]], "D", ms=6, color=f"C{k}", mec="k", mew=0.5)
        doubling = [(n, worst_distance(e)) for n, _, e, _ in pts if n != operator]
        at = knee(doubling)
        if at:
            ax.axvline(at[0], color="k", ls=":", lw=1)
        ax.axvline(operator, color="gray", ls="--", lw=1)
        ax.axhline(DEFAULT_TARGET_PSNR, color="gray", lw=0.6)
        ax.set_xscale("log")
        ax.set_title(name, fontsize=8)
        ax.grid(True, alpha=0.3)
    for ax in axes.ravel()[len(curves) :]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("PSNR vs Cycles (dB)")
    for ax in axes[-1]:
        ax.set_xlabel("splat budget")
    axes[0, 0].legend(fontsize=7, title="held-out", title_fontsize=7)
    fig.suptitle(
        f"mesh2splats: PSNR against splat budget (stars: default target {DEFAULT_TARGET_PSNR:g} dB at its splats, "
        "diamonds: the same texture-aware; "
        f"dashed: operator default {operator:,}; dotted: knee, from it each doubling < {KNEE_GAIN_DB:g} dB)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--primitives":
        _primitives_main(sys.argv[2])
    elif len(sys.argv) == 4 and sys.argv[1] == "--convert":
        _convert_main(sys.argv[2], sys.argv[3])
    else:
        print_rows(run(quick="--quick" in sys.argv))
