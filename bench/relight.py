"""Relighting's cost against the unlit frame, and the shadow error each shadow-map size buys.

Baseline, timed in the same run (alternating with the lit renders): core.render of the same cloud
unlit (its own SH-3 colours) at 1920x1080. The lit frames (core.relight.render_lit) shade every
splat and draw it with one render call, plus each light's shadow maps; the target is a lit/unlit
time ratio of at most 2 per light (lit_over_unlit: the median of each alternating pair's ratio, which
the machine's load moves less than the ratio of the two medians). The scene is a ground plane of
flat splats with spheres of splats on it, all with a material (albedo, normals): what Mesh to
Splats makes of meshes.

Shadow errors are mean and 95th-percentile |visibility - reference| over the splats facing the
light in a small scene (a sphere over a plane, 5,100 splats), the reference being the float64 ray
reference of tests/shadow_reference.py (64 samples over the light's disc).

    python bench/relight.py [--quick]
"""

import dataclasses
import itertools
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from common import Row, machine, paired_ratio, print_rows  # noqa: E402
from environment_reference import irradiance, sunny_sky  # noqa: E402
from shadow_reference import ball_surface, plane_cloud, reference_visibility, sphere_cloud  # noqa: E402

from splatwright.core import ambient, material, relight, scratch, shading, shadows  # noqa: E402
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
        base, lit, ratio = paired_ratio(
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
                    "lit_over_unlit": f"{ratio:.2f}",
                    "per_light": f"{(ratio - 1) / count:.2f}",
                    "splats": len(cloud),
                    "size": f"{width}x{height}",
                    "baseline": "unlit core.render, same cloud",
                },
            )
        )
    rows += kind_rows(cloud, camera, world, repeat)
    rows += closeup_rows(cloud, camera, world, repeat)
    rows += environment_rows(cloud, camera, repeat)
    rows += glossy_rows(cloud, camera, world, repeat)
    rows += resolution_sweep(cloud, camera, world, repeat)
    rows += world_occlusion_rows(cloud, camera, world, 2 if quick else 3)
    rows += kept_rows(cloud, camera, world, repeat)
    rows += memory_rows(cloud, camera, world, repeat)
    return rows


def memory_rows(cloud, camera, world, repeat):
    """The unlit frame and a lit one on kept working memory (core.scratch) against the same frame
    on memory fresh from the system each time (scratch handing out nothing): the images must agree
    to the bit."""
    rows = []
    frames = {
        "unlit frame": lambda: render(cloud, camera),
        "1 light (point)": lambda: relight.render_lit(cloud, camera, LIGHTS[:1], world),
    }
    for name, frame in frames.items():
        fresh = lambda: _on_fresh_memory(frame)  # noqa: E731
        base, kept, ratio = paired_ratio(fresh, frame, repeat)
        difference = float(np.abs(fresh().color - frame().color).max())
        rows.append(
            Row(
                TOPIC,
                f"{name}, working memory kept (core.scratch)",
                kept,
                base,
                {"max abs difference": difference},
                {"baseline": "the same frame on fresh memory", "kept_over_fresh": f"{ratio:.2f}"},
            )
        )
    return rows


def _on_fresh_memory(frame):
    """frame() with every request going to the allocator (scratch's buffers stay for the next kept
    frame, as they would in a loop of kept frames)."""
    saved = scratch.MIN_BYTES
    scratch.MIN_BYTES = 1 << 62
    try:
        return frame()
    finally:
        scratch.MIN_BYTES = saved


def kept_rows(cloud, camera, world, repeat):
    """Frames of a still scene from a moving camera with the shadows kept from frame to frame
    (core.relight.KeptVisibilities, as an animation render keeps them): a point light, then the
    world occluded from 24 directions as well; each against the unlit frame, and a kept frame
    against the same frame made afresh."""
    moved = Camera.look_at(
        (4.3, -4.7, 3.5), (0, 0, 0.3), up=(0, 0, 1), fov_deg=50, width=camera.width, height=camera.height
    )
    rows = []
    for name, occluded in (
        ("1 light (point)", World(world.color)),
        ("1 light (point), world occlusion (24 directions)", World(world.color, 24)),
    ):
        kept, views = relight.KeptVisibilities(), itertools.cycle([camera, moved])
        relight.render_lit(cloud, camera, LIGHTS[:1], occluded, kept=kept)  # the first frame makes them
        base, lit, ratio = paired_ratio(
            lambda: render(cloud, camera),
            lambda: relight.render_lit(cloud, next(views), LIGHTS[:1], occluded, kept=kept),
            repeat,
        )
        fresh = relight.render_lit(cloud, moved, LIGHTS[:1], occluded).color
        difference = np.abs(relight.render_lit(cloud, moved, LIGHTS[:1], occluded, kept=kept).color - fresh).max()
        rows.append(
            Row(
                TOPIC,
                f"{name}, shadows kept, the camera moving",
                lit,
                base,
                extra={
                    "lit_over_unlit": f"{ratio:.2f}",
                    "error against": "the frame made afresh",
                    "worst error": f"{difference:.1e}",
                },
            )
        )
    return rows


def closeup_rows(cloud, camera, world, repeat):
    """A close-up of one sphere (a third of the splats in the frame), one light of each cube kind:
    the lit frame testing and shading the splats the picture may show (render_lit) against the
    same frame testing and shading every splat (lit_colors, then render: what render_lit did before),
    each also against the unlit frame; the two pictures must agree."""
    centre = np.array(_first_sphere_centre())
    close = Camera.look_at(
        centre + (1.2, -1.5, 0.8), centre, up=(0, 0, 1), fov_deg=40, width=camera.width, height=camera.height
    )
    shown = float(relight.may_show(cloud, close).mean())
    rows = []
    for light in (LIGHTS[0], LIGHTS[3]):

        def everywhere():
            rows_, shading = relight.lit_colors(cloud, close, [light], world)
            return render(relight.lit_cloud(cloud, rows_, shading), close)

        picture = lambda: relight.render_lit(cloud, close, [light], world)  # noqa: E731
        base, lit, ratio = paired_ratio(everywhere, picture, repeat)
        unlit = paired_ratio(lambda: render(cloud, close), picture, repeat)[2]
        unlit_everywhere = paired_ratio(lambda: render(cloud, close), everywhere, repeat)[2]
        difference = float(np.abs(picture().color - everywhere().color).max())
        rows.append(
            Row(
                TOPIC,
                f"1 light ({light.kind}), a close-up: the splats the picture may show tested and shaded",
                lit,
                base,
                {"max abs difference": difference},
                {
                    "baseline": "every splat tested and shaded",
                    "lit_over_unlit": f"{unlit:.2f} (every splat: {unlit_everywhere:.2f})",
                    "shown": f"{shown:.2f}",
                },
            )
        )
    return rows


def _first_sphere_centre():
    """The centre of scene()'s first sphere (its generator's first draws)."""
    rng = np.random.default_rng(0)
    return (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(0.4, 1.0))


def environment_rows(cloud, camera, repeat):
    """The world as an environment map (core.environment): the shading of every splat under a sunny
    sky's nine coefficients against the same shading under its mean (a uniform world), with the
    bands' irradiance error against the brute-force integral of the map (300 normals); and the
    projection of a 4096 x 2048 map."""
    from splatwright.core import environment

    sky = sunny_sky(256, 512)
    coefficients = environment.from_equirect(sky)
    mapped, uniform = World(environment=coefficients), World(environment.mean(coefficients))
    base, mapped_time, _ = paired_ratio(
        lambda: shading.shade(cloud, camera, [], uniform), lambda: shading.shade(cloud, camera, [], mapped), repeat
    )
    error = irradiance_error(sky, coefficients)
    big = np.tile(sunny_sky(256, 512).astype(np.float32), (8, 8, 1))
    projection = paired_ratio(lambda: None, lambda: environment.from_equirect(big), max(repeat // 2, 2))[1]
    return [
        Row(TOPIC, "shading under an environment map (a sunny sky, bands 0-2)", mapped_time, base, error,
            {"baseline": "the same shading under its mean (a uniform world)", "splats": len(cloud)}),
        Row(TOPIC, "an environment map's coefficients from 4096 x 2048 pixels", projection),
    ]  # fmt: skip


def irradiance_error(sky, coefficients):
    """Max and mean |bands' irradiance - the map's| over 300 normals, over the brightest."""
    from splatwright.core import environment

    normals = np.random.default_rng(4).normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    brute = irradiance(sky, normals)
    error = np.abs(environment.diffuse(coefficients, normals) - brute) / brute.max(axis=0)
    return {"irradiance_max_err": float(error.max()), "irradiance_mean_err": float(error.mean())}


def kind_rows(cloud, camera, world, repeat):
    """Each kind of light alone: a point or area light's cube of maps against a sun's or spot's one."""
    rows = []
    for light in LIGHTS[1:]:
        base, lit, ratio = paired_ratio(
            lambda: render(cloud, camera), lambda: relight.render_lit(cloud, camera, [light], world), repeat
        )
        maps = len(shadows.shadow_views(cloud, light, resolution=relight.SHADOW_RESOLUTION[light.kind]))
        rows.append(
            Row(
                TOPIC,
                f"1 light ({light.kind}) alone",
                lit,
                base,
                extra={"lit_over_unlit": f"{ratio:.2f}", "shadow maps": maps},
            )
        )
    return rows


def glossy_rows(cloud, camera, world, repeat):
    """Glossy splats under the area light (square, then a disc) and the point light (a sphere): their
    smooth highlights integrated (core.ltc) against the same light sampled (16 samples a splat for
    such lobes) or, for the sphere, its widened lobe; the shading alone, each with its highlight's
    error against the BRDF over the light (tests/test_ltc.py's metal point and eyes, the worst over
    them relative to the brightest)."""
    rows = []
    cases = [
        (dataclasses.replace(LIGHTS[3], shape="SQUARE"), 0.1),
        (dataclasses.replace(LIGHTS[3], shape="SQUARE"), 0.2),
        (dataclasses.replace(LIGHTS[3], shape="DISK"), 0.1),
        (LIGHTS[0], 0.1),
    ]
    for light, roughness in cases:
        glossy = material.with_material(cloud, roughness=np.full(len(cloud), roughness, np.float32))
        sampled, integrated, _ = paired_ratio(
            lambda: shading.shade(glossy, camera, [light], world, integrate=False),
            lambda: shading.shade(glossy, camera, [light], world),
            repeat,
        )
        error, baseline_error = highlight_error(light, roughness)
        name = f"{light.shape.lower()} area light" if light.kind == "area" else "point light (a sphere)"
        rows.append(
            Row(
                TOPIC,
                f"shading glossy splats (roughness {roughness}) under the {name}, integrated",
                integrated,
                sampled,
                {"highlight_err": error, "baseline_err": baseline_error},
                {
                    "baseline": "the same light sampled (a sphere: its widened lobe)",
                    "error against": "GGX over the light",
                    "splats": len(cloud),
                },
            )
        )
    return rows


def highlight_error(light, roughness):
    """(integrated, sampled): the worst highlight error of tests/test_ltc.py's metal point under a 1 m
    area light of `light`'s shape 1.5 m up (six eyes), or under a point light of `light`'s radius
    (eyes at its mirror image and off it), against the BRDF over the light."""
    from test_ltc import EYES, METAL, UP, highlight_errors, light_quadrature, mirror_eyes, round_light_reference

    if light.kind == "area":
        small = Light("area", power=40.0, shape=light.shape, size_x=1.0, position=(0.3, 0.0, 1.5))
        reference = lambda view: light_quadrature(small, np.zeros(3), UP, view, roughness, METAL, 1200)[1]  # noqa: E731
        return highlight_errors(small, roughness, EYES, reference)
    position = np.array([0.3, 0.0, 1.5])
    small = Light("point", power=100.0, position=position, radius=light.radius)
    towards, half = position / np.linalg.norm(position), math.asin(light.radius / np.linalg.norm(position))
    radiance = 100.0 / (4.0 * math.pi**2 * light.radius**2)
    reference = lambda view: round_light_reference(towards, half, view, roughness, METAL, radiance)  # noqa: E731
    return highlight_errors(small, roughness, mirror_eyes(towards, half), reference)


def resolution_sweep(cloud, camera, world, repeat):
    """One point light (a cube of maps) at three map sizes: time against shadow error."""
    rows = []
    light = LIGHTS[0]
    for resolution in (256, 512, 1024):
        t0 = time.perf_counter()
        base, lit, ratio = paired_ratio(
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
                {"lit_over_unlit": f"{ratio:.2f}", "measured_s": f"{time.perf_counter() - t0:.0f}"},
            )
        )
    return rows


def world_occlusion_rows(cloud, camera, world, repeat):
    """The world's occlusion alone (no lights) from 8 to 32 directions: its frame against the unlit
    one, and its error against the closed form of a mesh ball (radius 0.5, centre 0.9 m up) over a
    splat floor: 1 - (r / D)^2 h / D at a floor splat D from the centre and h below it."""
    floor = material.with_material(plane_cloud(2.0, 100), albedo=np.full((10000, 3), 0.5))
    centre, radius = np.array([0.0, 0.0, 0.9]), 0.5
    offset = centre - floor.positions
    distance = np.linalg.norm(offset, axis=1)
    closed_form = 1 - (radius / distance) ** 2 * offset[:, 2] / distance
    ball = [ball_surface(centre, radius)]
    rows = []
    for directions in (8, 16, 24, 32):
        error = ambient.world_visibility(floor, occluders=ball, directions=directions)[:, 0] - closed_form
        occluded = World(world.color, directions)
        base, lit, ratio = paired_ratio(
            lambda: render(cloud, camera), lambda: relight.render_lit(cloud, camera, [], occluded), repeat
        )
        rows.append(
            Row(
                TOPIC,
                f"world occlusion, {directions} directions, no lights"
                + (" (core.ambient's default)" if directions == ambient.DIRECTIONS else ""),
                lit,
                base,
                {
                    "occlusion_mean_err": float(np.abs(error).mean()),
                    "occlusion_p95_err": float(np.quantile(np.abs(error), 0.95)),
                },
                {
                    "lit_over_unlit": f"{ratio:.2f}",
                    "worst error": f"{np.abs(error).max():.3f}",
                    "mean signed error": f"{error.mean():+.4f}",
                    "error against": "closed form, mesh ball over a splat floor",
                },
            )
        )
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
