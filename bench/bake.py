"""Appearance baking: Mesh to Splats with the look Cycles gives the mesh in a lit scene, against
Base Color only, at held-out views.

The scene: bench/mesh2splats.py's meshes with Principled BSDF materials (their base colours and
textures, Blender's default roughness 0.5), a sun and an area light, a dim world and two bounces,
rendered by Blender Cycles on the CPU (headless bpy in a subprocess, 'Standard' view transform,
denoised, the world transparent to the camera so images come over black). References: 64 samples
at mesh2splats' nine held-out views (three each at 0.5x, 1x, 3x the framing distance). Bake inputs:
16 samples at core.bake.bake_views' 96 views (32 per distance), none of them held out. Splats: a
calibrated budget conversion made for classic rendering; baking fits SH of degree 3 (geometry and
opacity kept) by core.bake.bake_sh.

Rows: Base Color only (the converter's colours), and baked, with the seconds of the Cycles
reference renders and of the fit; baked again on splats made for antialiased rendering (and
rendered so), from the same Cycles views, and those splats fitted further (positions, shapes,
opacities and SH) by GEOMETRY_STEPS Adam steps through core.render_grad's backward pass
(core.bake.bake_splats); the same two from DENSER times as many Cycles views; and once more with
the held-out views (rendered as the bake inputs are) added as a camera path the user renders from,
weighted by core.bake.path_weights: not held out there, the row says what a bake along the user's
own views gives at them. Each fitted row also gives its worst fitted view, the lowest PSNR among
the views it was fitted to: where that is low, the look is beyond what the splats can hold even
where they were shown it.

The same meshes with Diffuse BSDF materials (no specular: the look SH of degree 3 can hold from
every direction), baked on the antialiased splats from the views around (`--only diffuse`).

For the sphere, a camera path: still at a 1x held-out view for 50 frames, then turning 90 degrees
around the mesh over 50, baked from four of its frames spread evenly, four spread by how much the
view changes (core.camera.spread_along) and as many as the add-on's bake spacing takes, measured at
13 frames along the turn.

    python bench/bake.py [--quick]
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _cycles_reference import cycles_render  # noqa: E402
from common import Row, Timing, print_rows  # noqa: E402
from mesh2splats import (  # noqa: E402
    blender_primitives,
    by_distance,
    convert,
    held_out_cameras,
    sphere_texture,
    uv_sphere,
    versus,
    worst_distance,
    write_obj,
)

from splatwright.core.bake import VIEWS_PER_DISTANCE, bake_sh, bake_splats, bake_views, path_weights  # noqa: E402
from splatwright.core.camera import Camera, spread_along  # noqa: E402
from splatwright.core.kinematics import axis_angle_matrices  # noqa: E402
from splatwright.core.metrics import psnr_from_mse  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.io.mesh import read_mesh  # noqa: E402

TOPIC = "bake"
REFERENCE_SAMPLES = 64
BAKE_SAMPLES = 16
DEGREE = 3
GEOMETRY_STEPS = 1000
DENSER = 2


def bench_meshes(folder, quick):
    sphere = uv_sphere(48, 24) if quick else uv_sphere(96, 48)
    meshes = {"textured sphere": read_mesh(write_obj(folder, "sphere", *sphere, sphere_texture()))}
    primitives = blender_primitives(folder)
    meshes.update({k: v for k, v in primitives.items() if "Suzanne" in k} if quick else primitives)
    return meshes


def mesh_rows(name, mesh, size, budget, folder, iterations):
    held = held_out_cameras(mesh, size)
    held_cameras = [cam for _, cam in held]
    references, _ = cycles_render(mesh, held_cameras, folder, samples=REFERENCE_SAMPLES, lit=True)
    # The whole budget, as the add-on keeps it for baking: fewer splats render the Base Color better, not the lit look.
    cloud = convert(mesh, max_splats=budget, view_size=size, render_mode="classic", try_fewer=False)
    views = bake_views(mesh.vertices, size)
    images, render_s = cycles_render(mesh, views, folder, samples=BAKE_SAMPLES, lit=True)
    base = by_distance(cloud, held, references)
    common = {"splats": len(cloud), "faces": len(mesh.faces)}
    rows = [
        Row(
            TOPIC,
            f"{name}: Base Color only",
            Timing(0.0, 0.0, 1),
            error={**base, "worst dB": worst_distance(base)},
            extra=common,
        )
    ]
    antialiased = convert(mesh, max_splats=budget, view_size=size, render_mode="antialiased", try_fewer=False)
    path, path_s = cycles_render(mesh, held_cameras, folder, samples=BAKE_SAMPLES, lit=True)
    runs = (
        (views, images, None, "", cloud, render_s),
        (views, images, None, ", made for antialiased rendering", antialiased, render_s),
        (
            views + held_cameras,
            images + path,
            path_weights(len(views), len(held)),
            ", antialiased, the held-out views baked from too as a camera path",
            antialiased,
            render_s + path_s,
        ),
    )
    for views_used, images_used, weights, made_for, splats, cycles_s in runs:
        baked, row = sh_row(
            name, made_for, splats, views_used, images_used, weights, held, references, cycles_s, iterations, common
        )
        rows.append(row)
        if made_for == ", made for antialiased rendering":
            rows.append(geometry_row(name, baked, views, images, held, references, row.timing.median, common))
    rows += denser_rows(name, mesh, size, antialiased, held, references, folder, iterations, common)
    if name == "textured sphere":
        rows += turn_rows(
            name,
            mesh,
            [cam for d, cam in held if d == 1.0][1],
            antialiased,
            views,
            images,
            render_s,
            folder,
            iterations,
        )
    return rows


def diffuse_rows(name, mesh, size, budget, folder, iterations):
    """The mesh with Diffuse BSDF materials (no specular, the same colours, textures and lights),
    baked (SH 3) on splats made for antialiased rendering from the views around, as the add-on
    bakes: the look without highlights, at the held-out views."""
    held = held_out_cameras(mesh, size)
    references, _ = cycles_render(mesh, [cam for _, cam in held], folder, samples=REFERENCE_SAMPLES, lit="diffuse")
    splats = convert(mesh, max_splats=budget, view_size=size, render_mode="antialiased", try_fewer=False)
    views = bake_views(mesh.vertices, size)
    images, cycles_s = cycles_render(mesh, views, folder, samples=BAKE_SAMPLES, lit="diffuse")
    common = {"splats": len(splats), "faces": len(mesh.faces)}
    label = ", antialiased, diffuse materials (no specular)"
    _, row = sh_row(name, label, splats, views, images, None, held, references, cycles_s, iterations, common)
    return [row]


def sh_row(name, made_for, splats, views, images, weights, held, references, cycles_s, iterations, common):
    """`splats` with SH fitted to the Cycles `images` (core.bake.bake_sh), and its row; the row's
    seconds are the Cycles views' and the fit's."""
    info = {}
    start = time.perf_counter()
    baked = bake_sh(splats, views, images, degree=DEGREE, iterations=iterations, weights=weights, info=info)
    bake_s = time.perf_counter() - start
    after = by_distance(baked, held, references)  # rendered in the mode it was made for
    return baked, Row(
        TOPIC,
        f"{name}: baked from Cycles (SH {DEGREE}){made_for}",
        Timing(cycles_s + bake_s, 0.0, 1),
        error={**after, "worst dB": worst_distance(after)},
        extra={
            **common,
            "views": len(views),
            "Cycles s": f"{cycles_s:.1f}",
            "fit s": f"{bake_s:.1f}",
            "iterations": info["iterations"],
            "fit dB": f"{info['psnr'][0]:.1f} -> {info['psnr'][-1]:.1f}",
            "worst fitted view dB": worst_fitted(baked, views, images),
        },
    )


def denser_rows(name, mesh, size, splats, held, references, folder, iterations, common):
    """The antialiased splats baked from DENSER times the default views per distance (the add-on's
    Bake Views), then fitted by GEOMETRY_STEPS steps (its Bake Geometry Steps)."""
    views = bake_views(mesh.vertices, size, count=DENSER * VIEWS_PER_DISTANCE)
    images, cycles_s = cycles_render(mesh, views, folder, samples=BAKE_SAMPLES, lit=True)
    label = f", antialiased, from {len(views)} views"
    baked, row = sh_row(name, label, splats, views, images, None, held, references, cycles_s, iterations, common)
    return [
        row,
        geometry_row(
            name, baked, views, images, held, references, row.timing.median, common, f", from {len(views)} views"
        ),
    ]


def geometry_row(name, baked, views, images, held, references, before_s, common, label=""):
    """The SH bake's splats fitted further by GEOMETRY_STEPS Adam steps (core.bake.bake_splats):
    positions, shapes, opacities and SH, from the same Cycles views."""
    info = {}
    start = time.perf_counter()
    fitted = bake_splats(baked, views, images, steps=GEOMETRY_STEPS, info=info)
    fit_s = time.perf_counter() - start
    after = by_distance(fitted, held, references)
    return Row(
        TOPIC,
        f"{name}: baked (SH {DEGREE}), antialiased{label}, then {GEOMETRY_STEPS} steps fitting the splats",
        Timing(before_s + fit_s, 0.0, 1),
        error={**after, "worst dB": worst_distance(after)},
        extra={
            **common,
            "views": len(views),
            "fit s": f"{fit_s:.1f}",
            "fit dB": f"{info['psnr'][0]:.1f} -> {info['psnr'][-1]:.1f}",
            "worst fitted view dB": worst_fitted(fitted, views, images),
        },
    )


def worst_fitted(cloud, views, images):
    """The lowest PSNR among the views the splats were fitted to."""
    return round(
        min(psnr_from_mse(np.mean((render(cloud, cam).color - image) ** 2)) for cam, image in zip(views, images)), 1
    )


def turning_path(mesh, start):
    """100 cameras: `start` for 50 frames, then turning 90 degrees around the mesh's centre."""
    v = mesh.vertices
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    eye = start.center - centre
    axis = np.cross(eye, [0.0, 0.0, 1.0])
    turns = axis_angle_matrices(axis / np.linalg.norm(axis), [0.0] * 50 + list(np.linspace(0.0, np.pi / 2, 51)[1:]))
    return centre, [
        Camera.look_at(
            centre + turn @ eye, centre, fov_deg=40.0, width=start.width, height=start.height, near=start.near
        )
        for turn in turns
    ]


def turn_rows(name, mesh, start, splats, views, images, views_s, folder, iterations):
    """Baked from a still-then-turning camera path's frames picked three ways, at frames along the
    turn; seconds as the other bake rows', the Cycles views around (`views_s`) included."""
    from splatwright.splat_addon.convert.from_mesh import BAKE_PATH_SPACING, VIEW_COUNTS

    centre, path = turning_path(mesh, start)
    along = list(range(50, 100, 4))
    references, _ = cycles_render(mesh, [path[i] for i in along], folder, samples=REFERENCE_SAMPLES, lit=True)
    picks = {
        "4 frames spread evenly": np.unique(np.round(np.linspace(0, len(path) - 1, 4)).astype(int)),
        "4 frames spread by view change": spread_along(path, 4, centre),
        f"frames at most {BAKE_PATH_SPACING} apart by view change (the add-on's bake)": spread_along(
            path, 4, centre, BAKE_PATH_SPACING, VIEW_COUNTS[1]
        ),
    }
    rows = []
    for label, pick in picks.items():
        cams = [path[i] for i in pick]
        shots, cycles_s = cycles_render(mesh, cams, folder, samples=BAKE_SAMPLES, lit=True)
        start_s = time.perf_counter()
        baked = bake_sh(
            splats,
            views + cams,
            images + shots,
            degree=DEGREE,
            iterations=iterations,
            weights=path_weights(len(views), len(cams)),
        )
        bake_s = time.perf_counter() - start_s
        seen = [render(baked, path[i]).color for i in along]
        each = [versus([image], [ref])["psnr_db"] for image, ref in zip(seen, references)]
        whole = versus(seen, references)["psnr_db"]
        rows.append(
            Row(
                TOPIC,
                f"{name}: a camera still, then turning 90 degrees; baked from {label}",
                Timing(views_s + cycles_s + bake_s, 0.0, 1),
                error={"dB along the turn": whole, "worst dB": min(each)},
                extra={
                    "views": len(views) + len(cams),
                    "path views": len(cams),
                    "Cycles s": f"{views_s + cycles_s:.1f}",
                    "fit s": f"{bake_s:.1f}",
                },
            )
        )
    return rows


def sizes(quick):
    """(view size, splat budget, iterations)."""
    return (128, 20_000, 20) if quick else (256, 60_000, 20)


def run(quick=False, parts=(mesh_rows, diffuse_rows)):
    size, budget, iterations = sizes(quick)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name, mesh in bench_meshes(folder, quick).items():
            for rows_of in parts:
                part = rows_of(name, mesh, size, budget, folder, iterations)
                print_rows(part)
                rows += part
    return rows


# Parts that `./run bench bake --only <part>` runs alone, their rows merged into the report's.
PARTS = {"diffuse": lambda quick: run(quick, parts=(diffuse_rows,))}


if __name__ == "__main__":
    print_rows(run(quick="--quick" in sys.argv))
