"""Mesh to splats: flat Gaussians lying in the surface, spent where the mesh needs them
(core/mesh_sampling.py places them for a density per face).

Sizing: a budget (`max_splats`) spreads one density over the whole surface; a target PSNR lets
core/mesh_refine.py choose the density per face from the render error against the mesh.
"""

import numpy as np

from . import sh as shmod
from .bake import bake_sh
from .memory import check_budget
from .mesh import Surface
from .mesh_material import corner_normals_of, with_surface_material
from .mesh_refine import VIEW_DISTANCES, VIEWS_PER_DISTANCE, refine_rounds, splats_within
from .mesh_render import CYCLES_FILTER_WIDTH, DEFAULT_PIXEL_FILTER, filter_taps
from .mesh_sampling import (
    OPAQUE,
    SAME_WALL_SIGMAS,
    SOLID_OPACITY,
    WALL_SIGMAS,
    budget_density,
    build_splats,
    face_opacities,
    thin_wall_density,
    wall_thickness,
)
from .splats import SplatCloud
from .steps import drain

# The entry points, and the sampling names callers of mesh_to_splats reach for.
__all__ = [
    "DEFAULT_RENDER_MODE",
    "DEFAULT_TARGET_PSNR",
    "OPAQUE",
    "SAME_WALL_SIGMAS",
    "SOLID_OPACITY",
    "WALL_SIGMAS",
    "build_splats",
    "face_opacities",
    "mesh_to_splats",
    "mesh_to_splats_steps",
    "thin_wall_density",
    "wall_thickness",
]

DEFAULT_TARGET_PSNR = 36.0
# The rendering splats are made for by default: antialiased, whose outlines hold at every distance
# (classic outlines fatten by pixels, so no one cloud suits near and far views); "classic" for
# viewers that cannot render antialiased (see the design notes).
DEFAULT_RENDER_MODE = "antialiased"
# Conjugate-gradient steps of the colour fit to the views (the grid plane: 5 as good as 10, in half the time),
FIT_ITERATIONS = 6
# ... its damping towards the sampled colours (core.bake.bake_sh's), and how far (display) a fit may
# move a colour. Held-out 0.5x / 1x / 3x dB of the striped cylinder (363k splats): unfitted 29.1 /
# 27.6 / 31.9; damping 0.1: 25.3 / 28.5 / 33.0 (the fitted close-ups' pixels over-fitted); 1.0: 28.4 /
# 28.7 / 32.9; 0.3 and changes within 0.05: 30.2 / 28.4 / 32.4 (0.2: 28.7 / 28.7 / 32.8).
FIT_DAMPING = 0.3
FIT_CHANGE = 0.05


def mesh_to_splats(vertices, faces, *, progress=None, **options):
    """Convert a triangle mesh to a SplatCloud of flat Gaussians: mesh_to_splats_steps run to its
    end, each step passed to `progress(done, total, label)`. The options are mesh_to_splats_steps'."""
    return drain(mesh_to_splats_steps(vertices, faces, **options), progress)


def mesh_to_splats_steps(
    vertices,
    faces,
    *,
    corner_uvs=None,
    face_materials=None,
    materials=None,
    corner_colors=None,
    max_splats=None,
    target_psnr=None,
    overlap=0.8,
    opacity=None,
    thickness=0.01,
    seed=0,
    views=None,
    view_size=256,
    view_distances=None,
    view_count=None,
    render_mode=DEFAULT_RENDER_MODE,
    calibrate=True,
    try_fewer=True,
    pixel_filter=DEFAULT_PIXEL_FILTER,
    filter_width=CYCLES_FILTER_WIDTH,
    memory_budget=None,
    texture_aware=True,
    material=False,
    corner_normals=None,
    info=None,
):
    """A generator converting a triangle mesh to a SplatCloud of flat Gaussians (SH in display sRGB).

    vertices (V,3), faces (F,3) int; corner_uvs (F,3,2); face_materials (F,) indices into
    `materials` (a list of core.mesh.Material); corner_colors (F,3,3) or (V,3), scene-linear.
    core/mesh.py states the colour space of every input.

    Size: `max_splats` alone is a budget (splats spread by area), with the silhouettes of solid
    parts calibrated for the views, and fewer splats (2000, 4000, 8000, ... below it: one ladder
    for all budgets, core.mesh_refine.budget_ladder) when they render better there
    (`try_fewer=False` keeps `max_splats`, for splats whose colours a later step such as baking
    the lit look refits; `calibrate=False` skips renders altogether).
    `target_psnr` (dB) refines until the splats rendered by core.render in `render_mode` match
    the mesh rendered by core.mesh_render in every one of the views, with `max_splats` as a cap.
    `render_mode` is also the mode the cloud is made for (its `antialiased` flag): "antialiased"
    (the default) gives right silhouettes at every distance, "classic" is for viewers that cannot
    render antialiased.
    With neither, the target is DEFAULT_TARGET_PSNR.
    Views (where quality is measured): `views`, a list of core Cameras (a scene camera along its
    path, say), or by default `view_count` cameras (4) at each of `view_distances` (0.5, 1, 3:
    multiples of the distance that frames the whole mesh) around it, `view_size` pixels square,
    black background; see core/mesh_refine.py. The mesh is rendered there with the pixel filter
    Cycles would use (`pixel_filter`, `filter_width`: Cycles' Film settings, its default by default;
    see core.mesh_render.filter_taps).
    Texture: with `texture_aware` (the default) each splat's colour is the surface colour averaged
    over its own Gaussian (an elliptical footprint in the texture), splats near hard colour edges
    (a texture's steps, material and vertex-colour boundaries) are narrowed across them, and, in
    target mode, the colours are then fitted to the mesh's renders from the views (linear least
    squares through the renderer's adjoint, core.bake.bake_sh, damped towards the sampled
    colours); False converts as before (colours averaged over a square mip footprint, no fit).
    Look: `overlap` (in-plane sigma times the square root of the density; 0.8 closes the
    surface), `opacity`, `thickness` (normal sigma / in-plane sigma), `seed` (the sampling offset).
    It yields (done, total, label) as work proceeds (with renders: after each count a budget
    tries, or the calibration and each refinement round, so a caller may stop between them) and
    returns the cloud; `info`, if a dict, receives "splats", "repaired" (what was skipped or
    repaired, with counts) and, with views, "psnr" (the worst view), "psnr_views", "worst_view",
    "worst_view_distance", "psnr_all_views", "inset_pixels", "views", "budget" (budgets:
    `max_splats`) and (target mode) "reached" and "limit" (why not).

    Memory: the conversion predicts its peak memory (core.mesh_refine.conversion_bytes) and holds
    no more splats than `memory_budget` bytes allow (default: core.memory.default_budget(), half the
    memory free when it starts); a conversion stopped there keeps the best splats it reached, and
    `info` says so ("memory_budget", "memory_cap": the splats it allowed, None when it did not bind;
    "limit" names it). A budget too small for the mesh and views alone is a ValueError, raised before
    anything is allocated.

    Material: with `material`, the splats also carry what relighting shades them with
    (core.material's extras, core.mesh_material): the Base Color in scene-linear light averaged over
    each splat's footprint as its colour is, the normal (`corner_normals`, (F,3,3) per corner or
    (V,3) per vertex, interpolated where given: smooth shading; else the face's winding normal), and
    the face material's roughness and metallic. The splat's own colour stays the unlit look.

    Extras: "source_triangle" (N,) int32 index into `faces`, "barycentric" (N,3) float32 and
    "normal_offset" (N,) float32, with position = sum_k barycentric[k] * vertices[faces[
    source_triangle, k]] + normal_offset * (unit normal of the face's winding). The offset is 0
    without calibration; with it, solid parts are pulled in by about a pixel of the views.
    Degenerate faces (zero area, non-finite vertices) get no splats; ValueError for malformed
    arrays or a mesh without any face of positive area.
    """
    surface = Surface(vertices, faces, corner_uvs, face_materials, materials, corner_colors)
    corner_normals = corner_normals_of(surface, corner_normals) if material else None  # checked before any work
    if not surface.valid.any():
        raise ValueError(
            f"mesh has no face with positive area ({len(surface.faces)} faces, {len(surface.vertices)} vertices)"
        )
    if max_splats is not None and int(max_splats) < 1:
        raise ValueError(f"max_splats must be at least 1, got {max_splats}")
    filter_taps(pixel_filter, filter_width, 1)  # a ValueError for an unknown filter
    budget = check_budget(memory_budget)
    style = dict(
        overlap=overlap,
        opacity=face_opacities(surface, opacity, render_mode == "antialiased"),
        thickness=thickness,
        seed=seed,
        texture_aware=texture_aware,
    )
    if target_psnr is None and max_splats is not None and not calibrate:
        count = min(int(max_splats), splats_within(budget, len(surface.faces), 0))
        density = _uniform_density(surface, count)
        cloud = build_splats(
            surface,
            budget_density(density, thin_wall_density(surface, density, overlap)[0], surface.area, count),
            **style,
        )
        if isinstance(info, dict):
            info.update(memory_budget=budget, memory_cap=count if count < int(max_splats) else None)
        yield 1, 1, "mesh2splats"
    else:
        budget_only = target_psnr is None and max_splats is not None
        target = DEFAULT_TARGET_PSNR if target_psnr is None else float(target_psnr)
        cloud = yield from refine_rounds(
            surface,
            np.inf if budget_only else target,
            max_splats,
            views,
            view_size,
            render_mode,
            info,
            style,
            uniform=budget_only,
            view_distances=VIEW_DISTANCES if view_distances is None else tuple(view_distances),
            view_count=VIEWS_PER_DISTANCE if view_count is None else int(view_count),
            pixel_filter=(pixel_filter, filter_width),
            try_fewer=try_fewer,
            memory_budget=budget,
            fit_colours=fit_colours_to_views if texture_aware and not budget_only else None,
        )
    if material:
        cloud = with_surface_material(
            cloud, surface, overlap=overlap, texture_aware=texture_aware, corner_normals=corner_normals
        )
    if isinstance(info, dict):
        info.update(splats=len(cloud), repaired=dict(surface.report))
    return cloud.replace(antialiased=render_mode == "antialiased")


def fit_colours_to_views(
    cloud: SplatCloud,
    cameras: list,
    images: list,
    render_mode: str,
    iterations: int = FIT_ITERATIONS,
    damping: float = FIT_DAMPING,
) -> SplatCloud:
    """`cloud` with its colours fitted to the mesh's renders `images` from `cameras`: core.bake's
    linear least squares through the renderer's adjoint, started from and damped towards the
    colours sampled from the surface, so splats that few views see keep those."""
    fitted = bake_sh(
        cloud,
        cameras,
        images,
        prior="cloud",
        damping=damping,
        iterations=iterations,
        background=(0.0, 0.0, 0.0),
        mode=render_mode,
    )
    # Colours the display cannot show, and large changes, served only the views fitted (overshoot
    # at their edges, splats few of them see).
    if fitted.sh.shape[1] > 1:  # view-dependent colours: their DC alone is no colour seen
        return fitted
    before = shmod.dc_to_rgb(cloud.sh.astype(np.float64))
    change = np.clip(shmod.dc_to_rgb(fitted.sh.astype(np.float64)), 0.0, 1.0) - before
    return fitted.replace(sh=shmod.rgb_to_dc(before + np.clip(change, -FIT_CHANGE, FIT_CHANGE)).astype(np.float32))


def _uniform_density(surface, count):
    return np.where(surface.valid, count / surface.area.sum(), 0.0)
