"""The lit render: splats shaded by lights (core.shading) with shadows (core.shadows), drawn by one
core.render call.

Per splat, the radiance towards the camera is computed from its material under the lights and the
world, each light's share scaled by its visibility from the shadow maps; that radiance becomes the
splat's display-sRGB colour (a degree-0 SH coefficient) in a shallow copy of the cloud, which core.render
draws as it draws any cloud. A lit frame is thus one frame plus the lights' shadow maps; made for
one picture, it tests the shadows and shades the splats that picture may show alone (may_show; of
those, a light's shadows only where the seen side faces it), the others never drawn. Splats
without a material (a cloud with none, or rows whose albedo or normal is NaN, e.g. captured splats
joined with converted ones) keep their own colours, view dependence included, and still cast
shadows. The passes (diffuse, specular, shadow) are extra renders of the same splats, made only
when asked for.
"""

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from . import ambient, color, jit, material, scratch, shadow_cameras, shadows
from . import sh as shmod
from .arrays import Image
from .camera import Camera
from .lights import Light, World
from .parallel import in_chunks
from .render import Layer, RenderResult, Shapes, render
from .shading import linked_masks, shade
from .splats import SplatCloud
from .steps import part_progress

# Shadow-map texels a side per light kind (per cube face for point and area lights). The maps' cost
# is mostly per splat drawn, not per texel: by bench/relight.py, a 410k-splat 1080p frame lit by a
# point light costs 1.9-2.1, 2.0-2.2 and 2.5-2.9 unlit frames with its cube at 256, 512 and 1024
# (ranges over three runs), for shadow errors of 0.0095, 0.0032 and 0.0020 (mean |visibility -
# float64 reference|); 512 is the knee. A
# spot's cone (up to 120 degrees) spans less than a cube face, so its 512 texels are finer than a
# face's (error 0.0017). The sun's one map over the whole scene keeps the least error of all at 512
# (0.0010; 0.0004 at 1024 for 20% more of its visibility's time, and 0.3 dB of the accuracy bench at
# 0.5x framing on two of five meshes, nothing elsewhere: bench/relight_accuracy.py).
SHADOW_RESOLUTION = {"point": 512, "area": 512, "spot": 512, "sun": 512}


@dataclass
class LitRender:
    """result: core.render's RenderResult of the lit cloud (its color (H,W,3) display sRGB, alpha
    and depth are this render's too, and a layer's transmittance); with passes, diffuse and specular
    (H,W,3) float32 scene-linear radiance (premultiplied by the splats' coverage, no background) and
    shadow (H,W) float32, the blended fraction of the lights' light that shadows took away; otherwise
    None. stats: the render's, and the shading's time (shadow maps included)."""

    result: RenderResult
    diffuse: Image | None = None
    specular: Image | None = None
    shadow: Annotated[np.ndarray, "(H, W)"] | None = None
    stats: dict = field(default_factory=dict)

    @property
    def color(self) -> Image:
        return self.result.color

    @property
    def alpha(self) -> Annotated[np.ndarray, "(H, W)"]:
        return self.result.alpha

    @property
    def depth(self) -> Annotated[np.ndarray, "(H, W)"]:
        return self.result.depth


def visibilities(
    cloud: SplatCloud,
    lights: list[Light],
    world: World | None = None,
    *,
    meshes=None,
    shadow_resolution: dict | int | None = None,
    threads: int | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    shapes: Shapes | None = None,
    blockers: dict[int, np.ndarray] | None = None,
    mesh_blockers: dict[int, list] | None = None,
    camera: Camera | None = None,
    shown: np.ndarray | None = None,
) -> dict[int | str, np.ndarray]:
    """{light index: (N,) visibility} of every light that casts shadows (and gives some light to
    reflect): what reaches each splat past the whole cloud and `meshes` (core.shadows.visibility),
    at SHADOW_RESOLUTION unless told; and
    under "world" the (N,2) share of `world` each splat sees (core.ambient.world_visibility) when
    the world is occluded (World.occlusion directions) and not black. They do not depend on the
    camera: a viewport makes them once for many views. progress(done, total, label) follows all the
    maps together; shapes, core.render.Shapes of the cloud, are made here unless given. blockers:
    shadow linking, a light's index to the (N,) bool splats that may shadow its light (absent: all);
    mesh_blockers: the same for meshes, a light's index to the meshes (a list as `meshes`) that
    shadow it in place of `meshes` (absent: `meshes`; the world's occlusion always takes `meshes`).
    camera and shown: for one picture through `camera` that may show the splats `shown` (N,) bool
    (may_show): a light's visibility is tested only at those whose seen side faces it (core.shadows'
    receiving and eye), the others hold 1 (good for that picture alone: not for KeptVisibilities)."""
    _check_linking(lights, blockers, mesh_blockers)
    # a light that casts no shadow, or gives no light to reflect, needs no maps
    casting = [i for i, light in enumerate(lights) if light.cast_shadow and (light.diffuse > 0 or light.specular > 0)]
    occluded = world is not None and world.occluded
    parts = len(casting) + occluded
    if parts and shapes is None:
        shapes = Shapes(cloud, threads)  # once for every map
    visible: dict[int | str, np.ndarray] = {
        index: shadows.visibility(
            cloud,
            lights[index],
            occluders=(mesh_blockers or {}).get(index, meshes),
            resolution=_resolution(shadow_resolution, lights[index]),
            blocking=(blockers or {}).get(index),
            receiving=shown,
            eye=camera,
            threads=threads,
            progress=part_progress(progress, step, parts),
            shapes=shapes,
        )
        for step, index in enumerate(casting)  # a loop over lights
    }
    if occluded:
        visible["world"] = ambient.world_visibility(
            cloud,
            occluders=meshes,
            directions=world.occlusion,
            threads=threads,
            progress=part_progress(progress, len(casting), parts),
            shapes=shapes,
        )
    return visible


class KeptVisibilities:
    """visibilities() kept from one call to the next. While the splats' centres, shapes, opacities
    and normals, the meshes (Surface.occluding_arrays) and the shadow linking are those of the last
    call, a light keeps its visibility as long as it and its map resolution are unchanged, and the
    world its occlusion as long as its directions are: only what changed is made again. For frames
    of a still scene under a moving camera or a moving light (a `blender -b` animation, the
    viewport's updates), where the maps are most of a lit frame and the world's occlusion many
    frames. Holds a copy of the splats' geometry (about 56 bytes a splat) to compare with."""

    def __init__(self):
        self._scene: list[np.ndarray] = []
        self._kept: dict = {}  # a light's or the world's inputs -> its visibility (None: casts none)

    def __call__(
        self,
        cloud: SplatCloud,
        lights: list[Light],
        world: World | None = None,
        *,
        meshes=None,
        shadow_resolution: dict | int | None = None,
        blockers: dict[int, np.ndarray] | None = None,
        mesh_blockers: dict[int, list] | None = None,
        **options,
    ) -> dict[int | str, np.ndarray]:
        """visibilities()'s result for these inputs (its keywords, `options` threads, progress and
        shapes too), made only for the lights and world not kept."""
        _check_linking(lights, blockers, mesh_blockers)
        blockers = blockers or {}
        meshes, linked = list(meshes or []), {i: list(m) for i, m in (mesh_blockers or {}).items()}
        surfaces = list({id(m): m for m in meshes + [m for ms in linked.values() for m in ms]}.values())
        self._hold(_scene_arrays(cloud, surfaces))
        place = {id(m): k for k, m in enumerate(surfaces)}
        keys = {
            index: (
                _light_values(light),
                _resolution(shadow_resolution, light),
                None if index not in blockers else np.packbits(np.asarray(blockers[index], bool)).tobytes(),
                tuple(place[id(m)] for m in linked.get(index, meshes)),
            )
            for index, light in enumerate(lights)  # a loop over lights
        }
        world_key = ("world", world.occlusion) if world is not None and world.occluded else None
        missing = [index for index, key in keys.items() if key not in self._kept]
        world_missing = world_key is not None and world_key not in self._kept
        if missing or world_missing:
            made = visibilities(
                cloud,
                [lights[index] for index in missing],
                world if world_missing else None,
                meshes=meshes,
                shadow_resolution=shadow_resolution,
                blockers={k: blockers[i] for k, i in enumerate(missing) if i in blockers},
                mesh_blockers={k: linked[i] for k, i in enumerate(missing) if i in linked},
                **options,
            )
            self._kept.update({keys[index]: made.get(k) for k, index in enumerate(missing)})
            if "world" in made:
                self._kept[world_key] = made["world"]
        used = [*keys.values()] + ([world_key] if world_key is not None else [])
        self._kept = {key: self._kept[key] for key in used}  # a light moved every frame keeps one
        visible = {index: self._kept[key] for index, key in keys.items() if self._kept[key] is not None}
        if world_key is not None:
            visible["world"] = self._kept[world_key]
        return visible

    def _hold(self, scene):
        """Keep `scene` (arrays), forgetting every kept visibility, unless it equals the held one."""
        same = len(scene) == len(self._scene) and all(
            a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b)
            for a, b in zip(scene, self._scene, strict=True)  # the centres first: a moved scene fails there
        )
        if not same:
            self._scene, self._kept = [np.array(a, copy=True) for a in scene], {}


def _scene_arrays(cloud, surfaces):
    """What every shadow map of `cloud` and `surfaces` depends on, as arrays."""
    normals = material.normal_columns(cloud) or ()
    splats = [cloud.positions, cloud.rotations, cloud.log_scales, cloud.opacity_logits, *normals]
    return [np.asarray(a) for a in splats] + [np.asarray(a) for m in surfaces for a in m.occluding_arrays()]


def _light_values(light):
    """A light's fields as a tuple that compares by value (its arrays as bytes)."""
    values = (getattr(light, f.name) for f in dataclasses.fields(light))
    return tuple(np.asarray(v).tobytes() if isinstance(v, np.ndarray) else v for v in values)


def _check_linking(lights, blockers, mesh_blockers):
    """ValueError where shadow linking names a light that is not there."""
    for name, links in (("blockers", blockers), ("mesh_blockers", mesh_blockers)):
        wrong = [index for index in links or {} if not 0 <= index < len(lights)]
        if wrong:
            raise ValueError(f"{name} names light {wrong[0]}, but there are {len(lights)} lights")


def lit_colors(
    cloud: SplatCloud,
    camera: Camera,
    lights: list[Light],
    world: World | None = None,
    *,
    meshes=None,
    shadow_resolution: dict | int | None = None,
    threads: int | None = None,
    visible: dict[int | str, np.ndarray] | None = None,
    receivers: dict[int, np.ndarray] | None = None,
    blockers: dict[int, np.ndarray] | None = None,
    mesh_blockers: dict[int, list] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    shapes: Shapes | None = None,
    kept: KeptVisibilities | None = None,
    shown: np.ndarray | None = None,
):
    """(rows (N,) bool, Shading of cloud[rows]): the splats with a material and their shading,
    each light's share scaled by its visibility (`visible`, visibilities()'s result, or made here for
    the lights that cast shadows and an occluded world: all splats and `meshes` occlude; `progress`
    and `shapes` as visibilities') and, with `receivers` (light linking: a light's index to the (N,)
    bool splats it lights), given only to the splats each light is linked to; `blockers` and
    `mesh_blockers` as visibilities' (when the visibilities are made here, by `kept` when given).
    shown: (N,) bool, the splats a picture through `camera` may show (may_show): only they are
    shaded (the others' shading is 0) and, where the visibilities are made here without `kept`,
    tested for shadows (visibilities' camera and shown)."""
    rows = material.carried(cloud)
    if not rows.any():
        return rows, None
    if visible is None:
        options = dict(shadow_resolution=shadow_resolution, threads=threads, progress=progress, shapes=shapes)
        options.update(meshes=meshes, blockers=blockers, mesh_blockers=mesh_blockers)
        if kept is None and shown is not None:  # for this picture alone (an eye's position: no facing test)
            picture = camera if isinstance(camera, Camera) else None
            visible = visibilities(cloud, lights, world, camera=picture, shown=shown, **options)
        else:
            visible = (kept or visibilities)(cloud, lights, world, **options)
    receivers = linked_masks(receivers, len(cloud))
    if rows.all():
        return rows, shade(cloud, camera, lights, world, visible, receivers=receivers, shown=shown)
    part = {i: v[rows] for i, v in visible.items()}
    linked = {i: m[rows] for i, m in receivers.items()}
    return rows, shade(
        cloud[rows], camera, lights, world, part, receivers=linked, shown=None if shown is None else shown[rows]
    )


def may_show(cloud: SplatCloud, camera: Camera, shapes: Shapes | None = None) -> Annotated[np.ndarray, "(N,)"]:
    """(N,) bool: a superset of the splats core.render draws of `cloud` through `camera`
    (core.shadow_cameras.may_show): a picture needs the light of no others. shapes: the cloud's
    core.render.Shapes, when the caller has them."""
    reach, _ = shadow_cameras.reach_and_gap(cloud, None, shapes)
    return shadow_cameras.may_show(camera, cloud.positions, reach)


def lit_cloud(cloud: SplatCloud, rows: np.ndarray, shading) -> SplatCloud:
    """A shallow copy of `cloud` whose splats `rows` show their shading's radiance (lit_colors'
    result) as display sRGB in every direction; the others keep their own SH."""
    return _with_dc(cloud, rows, display_dc(shading.radiance))


def display_dc(radiance: Annotated[np.ndarray, "(N, 3)"]) -> Annotated[np.ndarray, "(N, 3)"]:
    """(N,3) float32 degree-0 SH coefficients that show scene-linear `radiance` (N,3) as display
    sRGB from every direction (light below 0 clipped): sh.rgb_to_dc(color.linear_to_srgb(...)), by
    the compiled kernel where it loads (the sRGB curve costs NumPy most of a lit frame's colouring)."""
    radiance = np.ascontiguousarray(radiance, np.float32)
    kernel = jit.compiled(__name__, ("_display_dc_loop",))
    if kernel is None:
        srgb = color.linear_to_srgb(np.maximum(radiance, 0.0), np.float32)
        return shmod.rgb_to_dc(srgb).astype(np.float32)
    out = scratch.empty(radiance.shape, np.float32)
    in_chunks(len(radiance), lambda lo, hi: kernel(lo, hi, radiance, out))
    return out


def _display_dc_loop(lo, hi, radiance, out):
    """display_dc for rows lo..hi. The curve in float32, as NumPy's path: the power is most of the
    cost, and float32's is about twice as fast."""
    toe, slope, zero = np.float32(color.LINEAR_TOE), np.float32(color.SLOPE), np.float32(0.0)
    gain, offset, exponent = np.float32(color.GAIN), np.float32(color.OFFSET), np.float32(1.0 / color.GAMMA)
    for i in range(lo, hi):
        for c in range(radiance.shape[1]):
            x = max(radiance[i, c], zero)
            srgb = slope * x if x <= toe else gain * x**exponent - offset
            out[i, c] = (np.float64(srgb) - 0.5) / shmod.C0


def render_lit(
    cloud: SplatCloud,
    camera: Camera,
    lights: list[Light],
    world: World | None = None,
    *,
    meshes=None,
    layer: Layer | None = None,
    passes: bool = False,
    background: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
    shadow_resolution: dict | int | None = None,
    threads: int | None = None,
    visible: dict[int | str, np.ndarray] | None = None,
    receivers: dict[int, np.ndarray] | None = None,
    blockers: dict[int, np.ndarray] | None = None,
    mesh_blockers: dict[int, list] | None = None,
    kept: KeptVisibilities | None = None,
    **render_options,
) -> LitRender:
    """Render `cloud` through `camera` lit by `lights` (core.lights.Light) and `world`.

    meshes: core.mesh.Surface meshes that cast shadows on the splats (the picture's meshes come in
    through `layer`, core.render's). passes: also the diffuse, specular and shadow images.
    shadow_resolution: texels a side of the shadow maps, one number or a dict by light kind
    (default SHADOW_RESOLUTION). visible: visibilities()'s result when the caller has it (they do
    not depend on the camera), else made here. receivers: light linking, a light's index to the (N,)
    bool splats it lights (absent: all; core.shading.shade); blockers and mesh_blockers: shadow
    linking, the splats and the meshes that shadow each light (visibilities'). kept: a
    KeptVisibilities that makes them, keeping what an earlier frame made. Other keywords go to
    core.render (mode, tile_size, backend, ...); its `progress` follows the shadow maps first (label
    "shadows"; the world's, "world occlusion"), then the render's tiles."""
    t0 = time.perf_counter()
    # The splats' shapes, made once for the shadow maps and the picture (the lit copy keeps them).
    shapes = Shapes(cloud, threads)
    shown = may_show(cloud, camera, shapes) if isinstance(camera, Camera) else None
    rows, shading = lit_colors(
        cloud,
        camera,
        lights,
        world,
        meshes=meshes,
        shadow_resolution=shadow_resolution,
        threads=threads,
        visible=visible,
        receivers=receivers,
        blockers=blockers,
        mesh_blockers=mesh_blockers,
        progress=render_options.get("progress"),
        shapes=shapes,
        kept=kept,
        shown=shown,
    )
    shading_time = time.perf_counter() - t0
    options = dict(render_options, threads=threads, shapes=shapes)
    if shading is None:
        result = render(cloud, camera, background, layer=layer, **options)
        return LitRender(result, stats=dict(result.stats, shading_s=0.0))
    lit = lit_cloud(cloud, rows, shading)
    result = render(lit, camera, background, layer=layer, **options)
    out = LitRender(result, stats=dict(result.stats, shading_s=shading_time))
    if passes:
        dark = None if layer is None else Layer(np.zeros_like(layer.color), layer.alpha, layer.depth)
        # Passes are linear radiance blended as colours are; splats without a material add nothing.
        pass_image = lambda values: (
            render(  # noqa: E731
                _with_dc(lit, rows, shmod.rgb_to_dc(values).astype(np.float32), own=0.0),
                camera,
                None,
                layer=dark,
                **options,
            ).color
        )
        out.diffuse = pass_image(shading.diffuse)
        out.specular = pass_image(shading.specular)
        out.shadow = pass_image(np.repeat(shading.shadow[:, None], 3, axis=1))[..., 0]
    return out


def _with_dc(cloud, rows, dc, own=None):
    """A shallow copy of `cloud` whose splats `rows` show the degree-0 coefficients `dc` (M,3) float32
    in every direction; the others keep their own SH, or with `own` that constant display colour.
    Degree 0 when every splat is set."""
    if rows.all():
        return cloud.replace(sh=dc[:, None, :])
    sh = cloud.sh.copy() if own is None else np.zeros((len(cloud), 1, 3), np.float32)
    if own is not None:
        sh[:, 0] = shmod.rgb_to_dc(np.full(3, own))
    sh[rows] = 0.0
    sh[rows, 0] = dc
    return cloud.replace(sh=sh)


def _resolution(setting, light):
    if setting is None:
        return SHADOW_RESOLUTION[light.kind]
    if isinstance(setting, dict):
        return setting.get(light.kind, SHADOW_RESOLUTION[light.kind])
    return int(setting)
