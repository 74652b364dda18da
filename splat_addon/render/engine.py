"""The SPLATWRIGHT render engine: every visible splat object, rendered by the core renderer from the
scene camera, composited in depth order with the meshes (and the world) that Cycles, EEVEE or
Workbench renders (mesh_layer.py), written as Combined (scene-linear), Depth, Splats and Meshes
passes so F12, render.render(write_still) and animations save through Blender's own output settings."""

import traceback

import bpy
import numpy as np

from ...core import scratch
from ...core.color import linear_to_srgb
from .. import data
from ..data import camera as blender_camera
from . import lights, mesh_layer, relit, viewport, world_panorama
from .lights import WORLD_OCCLUSION, scene_world
from .scene import MESH_ENGINE, mesh_engine, textured_world, to_scene_linear, world_background

ORIGIN_GRID = 16.0  # metres: a power of two, so the snapped origin is exact (render_origin)
EMPTY_DEPTH = 1e10  # what Blender's own engines write in the Depth pass where nothing was hit


def render_origin(camera_object) -> np.ndarray:
    """(3,) float64: the origin of the frame a final render works in, the camera's position snapped
    to a grid of ORIGIN_GRID metres. Splat centres are float32, and a scene far from the world's
    origin keeps its precision only near the camera; snapped, the frames of an animation whose
    camera moves within a cell share their splats' coordinates, so the shadows of what stays still
    are kept from frame to frame (_FRAMES)."""
    position = np.array(camera_object.matrix_world.translation, dtype=np.float64)
    return np.round(position / ORIGIN_GRID) * ORIGIN_GRID


def render_size(render):
    """Output pixels after the resolution percentage, as Blender computes them."""
    pct = render.resolution_percentage
    return max(1, render.resolution_x * pct // 100), max(1, render.resolution_y * pct // 100)


_Cancelled = mesh_layer.Cancelled

SPLAT_PASSES = "splatwright_use_pass_splats"  # ViewLayer property: write the Splats (and Meshes) pass
# An animation's relit shadows, kept from frame to frame (core.relight.KeptVisibilities: a still
# scene's lights and world occlusion are made once for a moving camera); a still render lets them go.
_FRAMES: dict = {}


class SplatwrightRenderEngine(bpy.types.RenderEngine):
    bl_idname = "SPLATWRIGHT"
    bl_label = "Splatwright"
    bl_use_preview = False
    bl_use_postprocess = True
    bl_use_eevee_viewport = True  # Material Preview: EEVEE draws the coloured display points

    def render(self, depsgraph):
        try:
            self._render(depsgraph)
        except _Cancelled:
            pass
        except (ValueError, data.SplatObjectError, mesh_layer.MeshLayerError) as exc:  # CameraError is a ValueError
            self.report({"ERROR"}, f"Splatwright: {exc}")
        except Exception as exc:
            # Reported, not raised: a traceback kept by Blender would hold evaluated data that the
            # render frees, and touching it later crashes.
            traceback.print_exc()
            self.report({"ERROR"}, f"Splatwright: internal error: {exc!r}")

    def _render(self, depsgraph):
        scene = depsgraph.scene
        width, height = render_size(scene.render)
        if scene.camera is None:
            raise blender_camera.CameraError("the scene has no camera to render from")
        cam_obj = scene.camera.evaluated_get(depsgraph)
        origin = render_origin(cam_obj)
        cam = blender_camera.from_object(cam_obj, scene, width, height, origin)
        with data.reported_warnings(self.report):
            cloud, lit, owners = relit.scene_cloud(depsgraph, origin)
            casters = relit.shadow_casters(cloud, lit, origin, owners, lights.blocker_collections(depsgraph))
        transparent = scene.render.film_transparent
        backdrop = world_background(scene)  # read once: the picture's background and the splats' light
        # Nodes that world_background does not read light relit splats as Cycles renders the world
        rendered = lit is not None and world_panorama.wanted(backdrop)
        meshes, world_light = self._mesh_layer(depsgraph, width, height, casters, rendered)
        layer = None if meshes is None else meshes.as_layer()
        background = None if transparent or layer is not None else linear_to_srgb(backdrop.color)
        self.update_stats("", f"Splatwright: {len(cloud) if cloud is not None else 0} splats")
        want_passes = getattr(depsgraph.view_layer, SPLAT_PASSES, False)
        if lit is None:
            image, lit_passes = self._image(cloud, cam, background, layer), {}
        else:
            image, lit_passes = self._lit_image(
                depsgraph, cloud, lit, owners, cam, background, layer, origin, want_passes, world_light or backdrop
            )
        passes = {**splat_passes(image, layer, meshes, background), **lit_passes} if want_passes else {}
        world = None if meshes is None else meshes.world()
        if world is not None:  # the world rendered apart: behind everything, per pixel
            image.color += (1.0 - image.alpha)[..., None] * world
        alpha = image.alpha if transparent else np.ones_like(image.alpha)
        self._write(width, height, to_scene_linear(image.color, alpha), composite_depth(image, layer), passes)

    # the Rendered viewport (viewport.py) ------------------------------------------------------------

    def view_update(self, context, depsgraph):
        try:
            self._viewport().update(depsgraph)
        except Exception:
            traceback.print_exc()

    def view_draw(self, context, depsgraph):
        try:
            self._viewport().draw(self, context)
        except Exception:
            traceback.print_exc()

    def _viewport(self):
        if getattr(self, "_preview", None) is None:
            self._preview = viewport.Viewport(self)
        return self._preview

    def __del__(self):
        preview = getattr(self, "_preview", None)
        if preview is not None:
            preview.stop()

    # final renders ------------------------------------------------------------------------------------

    def _mesh_layer(self, depsgraph, width, height, shadow_casters=None, world=False):
        """(the scene's meshes and world rendered by the chosen engine, or None: splats only, or
        nothing but splats to render; with `world`, the world's light as Cycles renders it
        (world_panorama.py), else None); `shadow_casters` is the relit splats' stand-in (see
        relit.py)."""
        engine = mesh_engine(depsgraph.scene)
        layer = engine != "NONE" and (mesh_layer.has_geometry(depsgraph) or textured_world(depsgraph.scene))
        if not (layer or world):
            return None, None
        if layer:
            self.update_stats("", f"Splatwright: rendering the meshes with {engine.title()}")
        else:
            self.update_stats("", "Splatwright: rendering the world's light with Cycles")
        return mesh_layer.render(
            depsgraph,
            engine if layer else "CYCLES",
            width,
            height,
            test_break=self.test_break,
            progress=self.update_progress,
            shadow_casters=shadow_casters,
            layer=layer,
            world=world,
        )

    def _image(self, cloud, cam, background, layer=None):
        """The core renderer's RenderResult (display-sRGB colour, transparent when `background` is
        None), composited with `layer`."""
        from ...core.render import kernels_loaded, render  # the renderer loads on first use

        if not kernels_loaded():
            # The first render after install compiles the kernels (about 15 s; later renders and
            # later sessions load them from the kernel cache in a fraction of a second).
            self.update_stats("", "Splatwright: preparing the compiled kernels (the first render compiles them)")
            self.update_progress(0.0)

        cloud = cloud if cloud is not None else _no_splats()
        return render(cloud, cam, background=background, layer=layer, progress=self._progress)

    def _progress(self, done, total, label=""):
        self.update_progress(done / total if total else 1.0)
        if self.test_break():
            raise _Cancelled

    def _lit_image(self, depsgraph, cloud, lit, owners, cam, background, layer, origin, passes, backdrop):
        """The RenderResult of `cloud` with its `lit` splats (those with a material; `owners` their
        objects, scene_cloud's) shaded by the scene's lights and world and shadowed by the cloud and
        the meshes (the lights' light and shadow linking read), the others with their
        own colour, in ONE core.render (core.relight.render_lit; the Depth and Splats passes need the
        whole RenderResult, a layer's transmittance with it), and the Diffuse, Specular and Shadow
        passes when `passes`; `backdrop`: the world's scene.Background (world_background's, or as
        Cycles rendered it where its nodes are more than that reads: world_panorama.py)."""
        from ...core.relight import KeptVisibilities, render_lit  # only when something is relit

        if self.is_animation:
            kept = _FRAMES.setdefault("shadows", KeptVisibilities())
        else:
            _FRAMES.clear()
            kept = None

        self.update_stats("", f"Splatwright: shading {int(lit.sum())} splats with the scene's lights")
        drawn = mesh_engine(depsgraph.scene) != "NONE"
        occluders = relit.occluders(depsgraph, origin) if drawn else relit.Occluders([])
        with data.reported_warnings(self.report):  # lights' and the world's nodes that are not read
            lights, receivers, blockers, mesh_blockers = relit.linked_lights(depsgraph, origin, owners, occluders)
            world = scene_world(depsgraph.scene, backdrop)
            lights = world.lights(lights)  # an environment map's sun after the scene's lights
        lit_render = render_lit(
            cloud,
            cam,
            lights,
            world,
            receivers=receivers,
            blockers=blockers,
            mesh_blockers=mesh_blockers,
            meshes=occluders.surfaces,
            background=background,
            layer=layer,
            passes=passes,
            progress=self._progress,
            kept=kept,
        )
        return lit_render.result, (relit.lit_passes(lit_render) if passes else {})

    def _write(self, width, height, rgba, depth, extra):
        result = self.begin_result(0, 0, width, height)
        layer = result.layers[0]
        # Blender's pixel rows start at the bottom; the core's row 0 is the top.
        layer.passes["Combined"].rect.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
        for name, pixels in (("Depth", depth), *extra.items()):
            if name in layer.passes:
                layer.passes[name].rect.foreach_set(np.ascontiguousarray(pixels[::-1], dtype=np.float32).ravel())
        self.end_result(result)

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        if getattr(renderlayer, SPLAT_PASSES, False):
            self.register_pass(scene, renderlayer, "Splats", 4, "RGBA", "COLOR")
            if mesh_engine(scene) != "NONE":
                self.register_pass(scene, renderlayer, "Meshes", 4, "RGBA", "COLOR")
            if relit.any_relit(scene):
                for name, channels, chan_id, kind in relit.PASSES:
                    self.register_pass(scene, renderlayer, name, channels, chan_id, kind)


def splat_alpha(image, layer):
    """The splats' own coverage in a render composited with `layer` (or without one)."""
    return image.alpha if layer is None else image.alpha - image.layer_transmittance * layer.alpha


def composite_depth(image, layer):
    """The Depth pass: the nearer of the splats' depth (where any splat shows) and the mesh
    surface; EMPTY_DEPTH where there is neither."""
    surface = np.full(image.depth.shape, EMPTY_DEPTH, np.float32) if layer is None else layer.depth
    return np.where(splat_alpha(image, layer) > 0, np.minimum(image.depth, surface), surface)


def splat_passes(image, layer, meshes, background=None):
    """The Splats pass (what the splats add to the picture, scene-linear, premultiplied, with their
    coverage in front of the meshes as alpha) and the Meshes pass (the mesh layer as its engine
    rendered it). In display sRGB, Splats over Meshes is Combined: the colour everywhere, the alpha
    where the meshes are opaque or absent. Without a layer, the `background` colour the image was
    rendered over (display sRGB) is taken out again."""
    color, alpha = image.color, splat_alpha(image, layer)
    if layer is not None:
        color = color - image.layer_transmittance[..., None] * layer.color
        alpha = 1.0 - image.layer_transmittance
    elif background is not None:
        color = color - (1.0 - image.alpha)[..., None] * np.asarray(background, np.float32)
    passes = {"Splats": to_scene_linear(np.maximum(color, 0.0), np.clip(alpha, 0.0, 1.0))}
    if meshes is not None:
        passes["Meshes"] = meshes.picture()
    return passes


def _no_splats():
    from ...core.splats import SplatCloud

    return SplatCloud.empty()


class RENDER_PT_splatwright(bpy.types.Panel):
    bl_label = "Splatwright"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {SplatwrightRenderEngine.bl_idname}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        scene = context.scene
        layout.prop(scene, MESH_ENGINE)
        engine = mesh_engine(scene)
        if engine == "CYCLES" and hasattr(scene, "cycles"):  # the mesh engine's own quality settings
            layout.prop(scene.cycles, "device", text="Cycles Device")
            layout.prop(scene.cycles, "samples", text="Cycles Samples")
            layout.prop(scene.cycles, "use_denoising", text="Denoise")
        elif engine == "EEVEE":
            layout.prop(scene.eevee, "taa_render_samples", text="EEVEE Samples")
        layout.prop(scene.render, "film_transparent")
        layout.prop(context.view_layer, "use_pass_z", text="Depth Pass")
        layout.prop(context.view_layer, SPLAT_PASSES)
        world = context.scene.world
        if world is not None:
            layout.prop(world, "color", text="World Colour (without nodes)")
        if relit.any_relit(scene):
            layout.prop(scene, WORLD_OCCLUSION)
        view = context.scene.view_settings
        if view.view_transform != "Standard":
            # Splat colours are display sRGB; other view transforms tone-map them.
            layout.label(text="Standard shows splats as 3DGS viewers do", icon="INFO")
        layout.prop(view, "view_transform")


CLASSES = (SplatwrightRenderEngine, RENDER_PT_splatwright)

# Blender's generic panels (output, format, colour management, camera lens, ...) show only for
# engines they list; this is how a Python engine joins them.
_SKIPPED_PANELS = {"VIEWLAYER_PT_filter", "VIEWLAYER_PT_layer_passes"}


def _generic_panels():
    for panel in bpy.types.Panel.__subclasses__():
        engines = getattr(panel, "COMPAT_ENGINES", None)
        if engines is not None and "BLENDER_RENDER" in engines and panel.__name__ not in _SKIPPED_PANELS:
            yield panel


def register():
    setattr(
        bpy.types.Scene,
        MESH_ENGINE,
        bpy.props.EnumProperty(
            name="Meshes",
            items=mesh_layer.ENGINE_CHOICES,
            default="CYCLES",
            description="What renders everything that is not a splat (meshes, curves, volumes, the world); "
            "the splats are composited with it in depth order",
        ),
    )
    setattr(
        bpy.types.ViewLayer,
        SPLAT_PASSES,
        bpy.props.BoolProperty(
            name="Splats and Meshes Passes",
            default=False,
            description="Also write the splats alone (with their alpha) and the meshes alone as passes, so a "
            "compositor can redo the mix",
        ),
    )
    for panel in _generic_panels():
        panel.COMPAT_ENGINES.add(SplatwrightRenderEngine.bl_idname)
    for handlers in (bpy.app.handlers.render_complete, bpy.app.handlers.render_cancel):
        handlers.append(_release_memory)
    mesh_layer.register()
    lights.register()


@bpy.app.handlers.persistent
def _release_memory(*_):
    """A render job done (a still, or an animation's last frame) gives its working memory back:
    the frames of an animation share it (core.scratch), Blender's other work may want it after."""
    scratch.release()


def unregister():
    for handlers in (bpy.app.handlers.render_complete, bpy.app.handlers.render_cancel):
        if _release_memory in handlers:
            handlers.remove(_release_memory)
    lights.unregister()
    mesh_layer.unregister()
    for panel in _generic_panels():
        panel.COMPAT_ENGINES.discard(SplatwrightRenderEngine.bl_idname)
    delattr(bpy.types.ViewLayer, SPLAT_PASSES)
    delattr(bpy.types.Scene, MESH_ENGINE)
