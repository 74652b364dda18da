"""A world no reading stands for, lit as Cycles renders it (splat_addon/render/world_panorama.py): the
SPLATWRIGHT engine's reading of Sky Texture worlds (Blender 5.3's Multiple Scattering sky with its
sun disc high and low, and the Hosek / Wilkie sky without one) against Cycles' render of a white
diffuse ball under each.

Everything Blender does runs in a child process of Blender 5.3's bpy-only Python
(bench/_world_light_child.py, as bench/blender_render.py runs its renders): it times Cycles' render
of the ball (the baseline: the picture the reading stands in for), the reading made afresh (the
child Blender's panorama and sun view; about a second) and kept (the same world again), in turns.

Error: the ball Cycles renders against albedo x (the reading's bands + its sun on a Lambertian
surface) at every ball pixel clear of the outline, as tests/test_blender_lights.py scores it: the
sum's error per channel, and the worst pixel over the brightest; the worst pixel, over the same, of
what lit relit splats before (the world's Viewport Display colour, uniform) and of the bands alone
(no sun light).
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from blender_render import run_blender, timing  # noqa: E402
from common import Row, print_rows  # noqa: E402
from environment_reference import ball_normals, lambert, sun_light  # noqa: E402

TOPIC = "world_light"
CHILD = HERE / "_world_light_child.py"
ALBEDO = 0.8
ORTHO_SCALE = 2.4  # the camera's view of the ball (radius 1)
SCATTERING = "MULTIPLE_SCATTERING"
WORLDS = {  # the node's model, its sun's elevation and rotation (degrees), its disc on
    "sun 35 degrees up (Multiple Scattering)": dict(model=SCATTERING, elevation=35.0, rotation=40.0, disc=True),
    "sun 8 degrees up (Multiple Scattering)": dict(model=SCATTERING, elevation=8.0, rotation=200.0, disc=True),
    "no disc (Hosek / Wilkie)": dict(model="HOSEK_WILKIE", elevation=35.0, rotation=40.0, disc=False),
}


def predicted(coefficients, sun, normals):
    """albedo x (the bands + the sun, a saved reading's dict or None, on a Lambertian surface) at `normals`."""
    light = None if sun is None else sun_light(sun["towards"], sun["irradiance"])
    return ALBEDO * lambert(coefficients, light, normals)


def errors(seen, ours, peak):
    """(the sum's largest relative error per channel, the worst pixel over `peak`) of `ours`."""
    return float(np.abs(seen.sum(axis=0) / ours.sum(axis=0) - 1.0).max()), float(np.abs(seen - ours).max() / peak)


def run(quick=False):
    size, samples, repeat = (32, 64, 2) if quick else (48, 256, 3)
    worlds = {k: WORLDS[k] for k in list(WORLDS)[: 1 if quick else None]}
    job = {"size": size, "samples": samples, "repeat": repeat, "albedo": ALBEDO, "ortho_scale": ORTHO_SCALE}
    job["worlds"] = {name: spec for name, spec in worlds.items()}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        results = run_blender(job, work, CHILD)
        pictures = {name: np.load(work / f"{name}.npy") for name in worlds}
    inside, normals = ball_normals(size, ORTHO_SCALE)
    rows = []
    for name in worlds:
        read = results["worlds"][name]
        seen = pictures[name][inside].astype(np.float64)
        ours = predicted(read["coefficients"], read["sun"], normals)
        plain = ALBEDO * np.broadcast_to(np.array(read["plain"][:3]), ours.shape)
        bands = predicted(read["coefficients"], None, normals)
        baseline = timing(results["runs"][f"{name}/cycles"])
        error = dict(zip(("sum_error", "worst_pixel"), errors(seen, ours, ours.max()), strict=True))
        error["worst_pixel_plain_colour"] = errors(seen, plain, ours.max())[1]  # each over the same brightest
        error["worst_pixel_bands_alone"] = errors(seen, bands, ours.max())[1]
        against = f"Cycles' render of the ball, {size}x{size}, {samples} samples"
        extra = {"baseline": against, "sun": read["sun"] is not None}
        afresh, kept = (timing(results["runs"][f"{name}/{how}"]) for how in ("rendered", "kept"))
        rows.append(Row(TOPIC, f"{name}: read afresh", afresh, baseline, error, extra))
        rows.append(Row(TOPIC, f"{name}: kept (the same world again)", kept, baseline, {}, {"baseline": against}))
    return rows


if __name__ == "__main__":
    t0 = time.perf_counter()
    print_rows(run(quick="--quick" in sys.argv))
    print(f"{time.perf_counter() - t0:.0f} s")
