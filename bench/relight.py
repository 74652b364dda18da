"""Relighting's cost against the unlit frame, and the shadow error each shadow-map size buys.

Baseline, timed in the same run (alternating with the lit renders): core.render of the same cloud
unlit (its own SH-3 colours) at 1920x1080. The lit frames (core.relight.render_lit) shade every
splat and draw it with one render call, plus each light's shadow maps; the target is a lit/unlit
time ratio of at most 2 per light. The scene is a ground plane of flat splats with spheres of
splats on it, all with a material (albedo, normals): what Mesh to Splats makes of meshes.

Shadow errors are mean and 95th-percentile |visibility - reference| over the splats facing the
light in a small scene (a sphere over a plane, 5,100 splats), the reference being the float64 ray
reference of tests/shadow_reference.py (64 samples over the light's disc).

    python bench/relight.py [--quick]
"""

import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from common import Row, machine, paired, print_rows  # noqa: E402
from shadow_reference import plane_cloud, reference_visibility, sphere_cloud  # noqa: E402

from splatwright.core import material, relight, shadows  # noqa: E402
from splatwright.core.camera import Camera  # noqa: E402
from splatwright.core.lights import Light, World  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.core.splats import SplatCloud  # noqa: E402

TOPIC = "relight"

LIGHTS = [
    Light("point", power=500.0, position=(1.0, -1.0, 3.0), radius=0.2),
    Light("sun", power=3.0, direction=(0.3, 0.2, -1.0), angle=math.radians(3)),
    Light("spot", power=800.0, position=(-1.0, -2.0, 3.0), direction=(0.3, 0.5, -1.0), radius=0.1, spot_size=1.0),
    Light("area", power=300.0, position=(0.0, 1.0, 3.0), direction=(0.0, 0.0, -1.0), size_x=1.0),
]


def scene(quick):
    """A plane of flat splats and eight spheres on it, SH-3 colours and a material."""
    rng = np.random.default_rng(0)
    side, per_sphere = (200, 8000) if quick else (500, 20000)
    parts = [plane_cloud(3.0, side)]
    for _ in range(8):
        centre = (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(0.4, 1.0))
        parts.append(sphere_cloud(centre, rng.uniform(0.2, 0.5), per_sphere))
    cloud = SplatCloud.concatenate(parts)
    n = len(cloud)
    cloud = cloud.replace(sh=rng.normal(0.0, 0.2, (n, 16, 3)).astype(np.float32))
    return material.with_material(cloud, albedo=rng.uniform(0.2, 0.9, (n, 3)))


def shadow_errors(lights, resolution=None):
    """Mean and p95 |visibility - float64 reference| over the facing splats of the small scene,
    pooled over `lights`, at `resolution` (default: relight's per kind)."""
    plane = plane_cloud(1.5, 60)
    cloud = SplatCloud.concatenate([plane, sphere_cloud((0.0, 0.0, 0.8), 0.3, 1500)])
    rng = np.random.default_rng(0)
    errors = []
    for light in lights:
        light = _small_scene_light(light)
        idx = rng.choice(len(cloud), 300, replace=False)
        p = cloud.positions[idx].astype(np.float64)
        to_light = -light.direction[None] if light.kind == "sun" else light.position - p
        idx = idx[np.einsum("ni,ni->n", material.normals(cloud)[idx], to_light) > 0]
        ref = reference_visibility(cloud, light, idx, samples=64)
        res = resolution or relight.SHADOW_RESOLUTION[light.kind]
        errors.append(np.abs(shadows.visibility(cloud, light, resolution=res)[idx] - ref))
    e = np.concatenate(errors)
    return {"shadow_mean_err": float(e.mean()), "shadow_p95_err": float(np.quantile(e, 0.95))}


def _small_scene_light(light):
    """The same kind of light placed over the small scene's sphere."""
    if light.kind == "sun":
        return light
    return Light(
        light.kind,
        position=(0.4, -0.3, 2.6),
        direction=(0.0, 0.0, -1.0),
        radius=light.radius,
        spot_size=light.spot_size,
        size_x=light.size_x,
    )


def run(quick=False):
    cloud = scene(quick)
    width, height = (960, 540) if quick else (1920, 1080)
    camera = Camera.look_at((4, -5, 3.5), (0, 0, 0.3), up=(0, 0, 1), fov_deg=50, width=width, height=height)
    world = World((0.05, 0.05, 0.06))
    repeat = 2 if quick else 7  # a noisy machine: medians of more runs
    print(f"  {len(cloud)} splats at {width}x{height}", flush=True)
    relight.render_lit(cloud, camera, LIGHTS[:1], world)  # load the kernels
    rows = []
    for count in (1, 2, 4):
        lights = LIGHTS[:count]
        base, lit = paired(
            lambda: render(cloud, camera), lambda: relight.render_lit(cloud, camera, lights, world), repeat
        )
        rows.append(
            Row(
                TOPIC,
                f"{count} light{'s' if count > 1 else ''} ({', '.join(light.kind for light in lights)})",
                lit,
                base,
                shadow_errors(lights),
                {
                    "lit_over_unlit": f"{lit.median / base.median:.2f}",
                    "per_light": f"{(lit.median / base.median - 1) / count:.2f}",
                    "splats": len(cloud),
                    "size": f"{width}x{height}",
                    "baseline": "unlit core.render, same cloud",
                },
            )
        )
    rows += kind_rows(cloud, camera, world, repeat)
    rows += resolution_sweep(cloud, camera, world, repeat)
    return rows


def kind_rows(cloud, camera, world, repeat):
    """Each kind of light alone: a point or area light's cube of maps against a sun's or spot's one."""
    rows = []
    for light in LIGHTS[1:]:
        base, lit = paired(
            lambda: render(cloud, camera), lambda: relight.render_lit(cloud, camera, [light], world), repeat
        )
        maps = len(shadows.shadow_views(cloud, light, resolution=relight.SHADOW_RESOLUTION[light.kind]))
        rows.append(
            Row(
                TOPIC,
                f"1 light ({light.kind}) alone",
                lit,
                base,
                extra={"lit_over_unlit": f"{lit.median / base.median:.2f}", "shadow maps": maps},
            )
        )
    return rows


def resolution_sweep(cloud, camera, world, repeat):
    """One point light (a cube of maps) at three map sizes: time against shadow error."""
    rows = []
    light = LIGHTS[0]
    for resolution in (256, 512, 1024):
        t0 = time.perf_counter()
        base, lit = paired(
            lambda: render(cloud, camera),
            lambda: relight.render_lit(cloud, camera, [light], world, shadow_resolution=resolution),
            repeat,
        )
        rows.append(
            Row(
                TOPIC,
                f"point light, {resolution} texels a cube face",
                lit,
                base,
                shadow_errors([light], resolution),
                {"lit_over_unlit": f"{lit.median / base.median:.2f}", "measured_s": f"{time.perf_counter() - t0:.0f}"},
            )
        )
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
