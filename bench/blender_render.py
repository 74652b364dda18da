"""One native Blender 5.3 splat cloud rendered by Cycles (CPU), EEVEE and the SPLATWRIGHT engine, each
image set against the float64 brute-force reference (tests/reference_render.py) of the same splats
through the same camera.

The scene: a PLY written by splatwright.io (SH degree 3) of a sphere's surface made of flat discs (half
of them thinner than a thousandth of their width) inside a ring of fuzzy, partly needle-like splats,
imported with Blender's own wm.ply_import, so Blender holds it as its native "3D Gaussian Splats"
point cloud (type GAUSSIAN_SPLAT), and a Blender camera. Everything Blender does runs in a child
process of Blender 5.3's bpy-only Python (bench/_blender_render_child.py; tests/blender_envs.py makes
that environment), which installs the extension zip as the tests do and renders with every renderer
in turn, run after run, so they meet the same load. World: none (black); film opaque; view transform
Standard, display sRGB, no look, exposure 0, gamma 1 (checked: the PNG Blender saves through the
view transform equals the EXR's scene-linear values under the sRGB curve).

Colour: Blender renders scene-linear (the EXR's values); the reference, like every 3DGS viewer, gives
display sRGB (SH colours are display values). Each Blender image is turned to display sRGB with the
sRGB curve (core.color.linear_to_srgb) and both sides are clipped to [0, 1], what a display shows;
PSNR and the largest absolute error are taken there. Cycles is also scored against the reference
of the same splats with every smallest scale raised to 1e-3 of the largest (the clamp users report
for Cycles), and against its own colours read as if Blender took SH values for linear ones.

Rows: Cycles at a few sample counts (denoising and adaptive sampling off, the default 1.5 px
Blackman-Harris pixel filter), Cycles with a point-like pixel filter (a 0.01 px box: every sample at
the pixel centre, as the rasteriser samples), EEVEE, the SPLATWRIGHT engine (F12 path: reading the
native cloud, the core render, writing the result) and core.render called directly through the
engine's camera conversion. Times are medians of the timed runs after one warm-up each (the
warm-up compiles EEVEE's shaders and the core's kernels); SPLATWRIGHT's baseline is Cycles at the
fewest samples, the cheapest Cycles picture.
"""

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(ROOT / "tests"))
from common import Row, Timing, print_rows

from splatwright.core import SplatCloud
from splatwright.core.camera import Camera
from splatwright.core.color import linear_to_srgb, srgb_to_linear
from splatwright.core.metrics import psnr
from splatwright.io import write_splats

TOPIC = "blender_render"
BLENDER = "5.3"
CHILD = HERE / "_blender_render_child.py"
CLAMP = 1e-3  # Cycles' reported floor on a splat's smallest scale, relative to its largest
C0 = 0.28209479177387814


# the scene -------------------------------------------------------------------------------------------


def _turn_z_to(normals):
    """(w, x, y, z) quaternions turning +z onto each unit normal."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, normals)
    w = 1.0 + normals @ z
    q = np.concatenate([w[:, None], axis], axis=1)
    flip = w < 1e-9  # the normal is -z: half a turn about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def make_scene(n=4000, seed=7):
    """A sphere of radius 1 tiled by 3/4 of the splats as flat discs tangent to it (thickness 1e-2 of
    the width for half of them, 1e-4 for the others), coloured in bands of longitude, inside a ring of
    radius 1.6 of the other quarter: fuzzy, anisotropic, translucent. SH degree 3 throughout, the
    higher bands small and random (view-dependent colour)."""
    rng = np.random.default_rng(seed)
    n_disc = 3 * n // 4
    n_ring = n - n_disc
    normals = rng.normal(size=(n_disc, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    width = rng.uniform(0.04, 0.08, n_disc)
    thin = np.where(np.arange(n_disc) % 2 == 0, 1e-2, 1e-4)
    disc_scales = np.stack([width, width * rng.uniform(0.6, 1.0, n_disc), width * thin], axis=1)
    longitude = np.arctan2(normals[:, 1], normals[:, 0])
    band = (np.floor((longitude + np.pi) / (2 * np.pi) * 8) % 3).astype(int)
    palette = np.array([[0.85, 0.3, 0.15], [0.2, 0.6, 0.35], [0.25, 0.35, 0.85]])
    disc_rgb = palette[band] * (0.75 + 0.25 * (normals[:, 2:3] + 1) / 2)

    angle = rng.uniform(0, 2 * np.pi, n_ring)
    ring = np.stack([1.6 * np.cos(angle), 1.6 * np.sin(angle), np.zeros(n_ring)], axis=1)
    ring += rng.normal(0, 0.08, (n_ring, 3))
    ring_scales = np.exp(rng.uniform(np.log(0.01), np.log(0.08), (n_ring, 3)))
    ring_rgb = rng.uniform(0.3, 1.0, (n_ring, 3))

    positions = np.concatenate([normals, ring])
    rotations = np.concatenate([_turn_z_to(normals), rng.normal(size=(n_ring, 4))])
    log_scales = np.log(np.concatenate([disc_scales, ring_scales]))
    logits = np.concatenate([rng.uniform(1.0, 4.0, n_disc), rng.normal(-0.5, 1.0, n_ring)])
    sh = rng.normal(0, 0.06, (n, 16, 3))
    sh[:, 0] = (np.concatenate([disc_rgb, ring_rgb]) - 0.5) / C0
    return SplatCloud(positions, rotations, log_scales, logits, sh)


def linear_blend_reference(cloud, camera):
    """The reference image composited in scene-linear light, as a path tracer blends: the same
    splats, weights and order, each splat's display-sRGB colour taken to linear before it is
    blended, the sum shown through the sRGB curve. (The reference itself, like the 3DGS rasteriser,
    blends the display values.)"""
    import reference_render

    plain = reference_render.sh_colors
    reference_render.sh_colors = lambda coeffs, directions: srgb_to_linear(plain(coeffs, directions))
    try:
        return display(reference_render.reference_render(cloud, camera)["color"])
    finally:
        reference_render.sh_colors = plain


def clamped(cloud, ratio=CLAMP):
    """The cloud with each splat's smallest scale raised to `ratio` of its largest."""
    scales = np.exp(cloud.log_scales.astype(np.float64))
    floor = ratio * scales.max(axis=1, keepdims=True)
    return SplatCloud(
        cloud.positions, cloud.rotations, np.log(np.maximum(scales, floor)), cloud.opacity_logits, cloud.sh
    )


# Blender's side --------------------------------------------------------------------------------------


def blender_python():
    """Blender 5.3's bpy-only interpreter (tests/blender_envs.py), or a RuntimeError saying what is missing."""
    import blender_envs

    try:
        return blender_envs.python_of(BLENDER)
    except blender_envs.Unavailable as exc:
        raise RuntimeError(
            f"bench {TOPIC} renders in Blender {BLENDER} ({blender_envs.VERSIONS[BLENDER][1][0]} "
            f"on Python {blender_envs.VERSIONS[BLENDER][0]}) and cannot run here: {exc}. Install "
            f"Python {blender_envs.VERSIONS[BLENDER][0]}, then `python tests/blender_envs.py` makes "
            f"the environment in {blender_envs.CACHE / BLENDER}"
        ) from None


def run_blender(job, work, child=CHILD):
    """Run the `child` script on `job` (written into `work`) in Blender BLENDER's bpy-only Python,
    the extension zip built for it; its results.json."""
    python = blender_python()
    from helpers import build_extension_zip

    job = {**job, "work": str(work), "zip": str(build_extension_zip(work))}
    (work / "job.json").write_text(json.dumps(job))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["BLENDER_USER_RESOURCES"] = str(work / "user")
    proc = subprocess.run(
        [python, str(child), str(work / "job.json")],
        check=False,
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=7200,
    )
    shutil.rmtree(work / "user", ignore_errors=True)  # the installed extension: ~300 MB
    log = f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-3000:]}\n--- stderr\n{proc.stderr[-3000:]}"
    results_file = work / "results.json"
    if not results_file.exists():
        raise RuntimeError(f"the Blender {BLENDER} child wrote no results:\n{log}")
    results = json.loads(results_file.read_text())
    if "error" in results:
        raise RuntimeError(f"the Blender {BLENDER} child failed:\n{results['error']}\n{log}")
    return results


def core_camera(fields):
    return Camera(
        **{
            **fields,
            "world_to_camera": np.array(fields["world_to_camera"]),
            "far": np.inf if fields["far"] is None else fields["far"],
        }
    )


# scoring ---------------------------------------------------------------------------------------------


def display(linear_rgb):
    """Scene-linear RGB -> display sRGB as the Standard view transform shows it, clipped to [0, 1]."""
    return np.clip(linear_to_srgb(np.maximum(linear_rgb, 0.0)), 0.0, 1.0)


def scores(image, reference):
    """PSNR (dB) and largest absolute error of two display-sRGB images."""
    return psnr(image, reference), float(np.abs(image - reference).max())


def timing(seconds):
    return Timing(statistics.median(seconds), (max(seconds) - min(seconds)) / 2, len(seconds))


# run -------------------------------------------------------------------------------------------------


def renderers(quick):
    samples = (16, 64) if quick else (16, 64, 256)
    out = [
        {
            "name": f"cycles_{s}",
            "engine": "CYCLES",
            "samples": s,
            "label": f"Cycles CPU, {s} samples",
            "warmup": s == samples[0],
        }
        for s in samples
    ]
    out.append(
        {
            "name": f"cycles_{samples[-1]}_point",
            "engine": "CYCLES",
            "samples": samples[-1],
            "warmup": False,
            "filter": ["BOX", 0.01],
            "label": f"Cycles CPU, {samples[-1]} samples, 0.01 px box filter",
        }
    )
    eevee = 16 if quick else 64
    out.append({"name": "eevee", "engine": "BLENDER_EEVEE", "samples": eevee, "label": f"EEVEE, {eevee} samples"})
    out.append({"name": "splatwright", "engine": "SPLATWRIGHT", "label": "SPLATWRIGHT engine (F12)"})
    out.append({"name": "core", "engine": "CORE", "label": "core.render through the engine's camera conversion"})
    return out


def run(quick=False):
    size = (160, 120) if quick else (320, 240)
    repeat = 3
    cloud = make_scene(2000 if quick else 4000)
    job = {
        "size": size,
        "repeat": repeat,
        "renderers": renderers(quick),
        "camera": {"location": [3.4, -3.0, 1.9], "target": [0.0, 0.0, 0.0], "lens": 40.0, "clip": [0.1, 100.0]},
    }
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        job["ply"] = str(work / "scene.ply")
        write_splats(job["ply"], cloud)
        results = run_blender(job, work)
        images = {r["name"]: np.load(work / f"{r['name']}.npy") for r in job["renderers"]}
        check = np.load(work / "check.npy")
    if results["pointcloud_type"] != "GAUSSIAN_SPLAT" or results["points"] != len(cloud):
        raise RuntimeError(f"wm.ply_import made a {results['pointcloud_type']} cloud of {results['points']} points")
    if not np.allclose(results["object_matrix"], np.eye(4)):
        raise RuntimeError("wm.ply_import placed the cloud with a transform; the reference assumes none")
    camera = core_camera(results["core_camera"])
    from reference_render import reference_render

    reference = np.clip(reference_render(cloud, camera)["color"], 0.0, 1.0)
    reference_linear = linear_blend_reference(cloud, camera)
    reference_clamped = linear_blend_reference(clamped(cloud), camera)
    first = job["renderers"][0]["name"]
    view_check = float(np.abs(check[..., :3] - display(images[first][..., :3].astype(np.float64))).max())

    cycles_base = timing(results["runs"][first])
    note = {
        "splats": len(cloud),
        "sh_degree": 3,
        "pixels": f"{size[0]}x{size[1]}",
        "colour": f"view {results['colour_management']['view_transform']}, display "
        f"{results['colour_management']['display_device']}",
    }
    rows = []
    for r in job["renderers"]:
        linear = images[r["name"]][..., :3].astype(np.float64)
        shown = display(linear)
        p, m = scores(shown, reference)
        error = {"psnr_srgb_db": p, "max_abs_srgb": m}
        extra = dict(note)
        baseline = None
        if r["engine"] in ("CYCLES", "BLENDER_EEVEE"):
            error["psnr_linear_blend_db"], error["max_abs_linear_blend"] = scores(shown, reference_linear)
            error["psnr_linear_blend_clamped_db"] = scores(shown, reference_clamped)[0]
            error["psnr_sh_as_linear_db"] = scores(np.clip(linear, 0, 1), reference)[0]
        if r["engine"] in ("SPLATWRIGHT", "CORE"):
            baseline = cycles_base
            extra["baseline"] = job["renderers"][0]["label"]
        if r["name"] in results["notes"]:
            extra["engine_report"] = results["notes"][r["name"]]
        rows.append(Row(TOPIC, r["label"], timing(results["runs"][r["name"]]), baseline, error, extra))
    rows[0].extra["png_vs_srgb_of_exr"] = view_check
    rows[0].extra["clamp_changes_ref_db"] = scores(reference_clamped, reference_linear)[0]
    rows[0].extra["linear_vs_srgb_blend_ref_db"] = scores(reference_linear, reference)[0]
    return rows


if __name__ == "__main__":
    t0 = time.perf_counter()
    print_rows(run(quick="--quick" in sys.argv))
    print(f"{time.perf_counter() - t0:.0f} s")
