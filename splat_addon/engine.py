"""The SPLATWRIGHT render engine: every visible splat object, rendered by the core renderer from the
scene camera, written as Combined (scene-linear) and Depth passes so F12, render.render(write_still)
and animations save through Blender's own output settings."""

import traceback

import bpy
import numpy as np

from ..core.color import linear_to_srgb, srgb_to_linear
from . import camera as blender_camera
from . import data

EMPTY_DEPTH = 1e10      # what Blender's own engines write in the Depth pass where nothing was hit


def render_size(render):
    """Output pixels after the resolution percentage, as Blender computes them."""
    pct = render.resolution_percentage
    return max(1, render.resolution_x * pct // 100), max(1, render.resolution_y * pct // 100)


def scene_splats(depsgraph, origin):
    """Every splat object and instance the depsgraph renders as one cloud, in world space shifted by
    -`origin` (None if there are none). Instances whose transform collapses them (zero scale) show
    nothing."""
    shift = np.eye(4)
    shift[:3, 3] = -origin
    instances = [(i.obj, i.matrix) for i in data.splat_instances(depsgraph)
                 if (i.instancer is not None or not i.obj.hide_render) and abs(np.linalg.det(i.matrix[:3, :3])) > 0]
    return data.instances_cloud(depsgraph, instances, shift) if instances else None


def world_color(scene):
    """The world's background colour (scene-linear RGB): colour x strength of the Background node
    feeding the world output; the world's plain colour when it uses no nodes or a texture drives
    the background; black without a world."""
    world = scene.world
    if world is None:
        return np.zeros(3)
    uses_nodes = world.node_tree is not None and (bpy.app.version >= (5, 0, 0) or world.use_nodes)
    node = _background_node(world.node_tree) if uses_nodes else None
    if node is None or node.inputs["Color"].is_linked or node.inputs["Strength"].is_linked:
        return np.array(world.color[:3], dtype=np.float64)
    return np.array(node.inputs["Color"].default_value[:3], dtype=np.float64) * node.inputs["Strength"].default_value


def _background_node(tree):
    output = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputWorld" and n.is_active_output), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return None
    node = output.inputs["Surface"].links[0].from_node
    return node if node.bl_idname == "ShaderNodeBackground" else None


def to_scene_linear(color, alpha):
    """Display-sRGB colour premultiplied by `alpha` -> premultiplied scene-linear RGBA. The curve is
    applied to the straight colour, so a transparent film saves exactly the core image's colours."""
    alpha = np.asarray(alpha, dtype=np.float64)[..., None]
    safe = np.where(alpha > 0, alpha, 1.0)
    straight = np.where(alpha > 0, np.asarray(color, dtype=np.float64) / safe, 0.0)
    rgba = np.empty(alpha.shape[:-1] + (4,), dtype=np.float32)
    rgba[..., :3] = srgb_to_linear(straight) * alpha
    rgba[..., 3] = alpha[..., 0]
    return rgba


class _Cancelled(Exception):
    pass


class SplatwrightRenderEngine(bpy.types.RenderEngine):
    bl_idname = "SPLATWRIGHT"
    bl_label = "Splatwright"
    bl_use_preview = False
    bl_use_postprocess = True
    bl_use_eevee_viewport = True     # Material Preview / Rendered viewport: the coloured display points

    def render(self, depsgraph):
        try:
            self._render(depsgraph)
        except _Cancelled:
            pass
        except (ValueError, data.SplatObjectError) as exc:     # CameraError is a ValueError
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
        # Render in a frame centred on the camera: splat centres are float32, and a scene far from
        # the origin keeps its precision only relative to the camera.
        cam_obj = scene.camera.evaluated_get(depsgraph)
        origin = np.array(cam_obj.matrix_world.translation, dtype=np.float64)
        cam = blender_camera.from_object(cam_obj, scene, width, height, origin)
        cloud = scene_splats(depsgraph, origin)
        transparent = scene.render.film_transparent
        background = None if transparent else linear_to_srgb(world_color(scene))
        self.update_stats("", f"Splatwright: {len(cloud) if cloud is not None else 0} splats")
        color, alpha, depth = self._image(cloud, cam, background)
        if not transparent:
            alpha = np.ones_like(alpha)
        self._write(width, height, to_scene_linear(color, alpha), depth)

    def _image(self, cloud, cam, background):
        """(display-sRGB colour, coverage, depth) from the core renderer; transparent when
        `background` is None (colour premultiplied by coverage)."""
        if cloud is None or len(cloud) == 0:
            shape = (cam.height, cam.width)
            color = np.zeros(shape + (3,)) if background is None else np.broadcast_to(background, shape + (3,))
            return color, np.zeros(shape), np.full(shape, EMPTY_DEPTH)
        from ..core.render import render     # the renderer loads on first use

        def progress(done, total, label=""):
            self.update_progress(done / total if total else 1.0)
            if self.test_break():
                raise _Cancelled

        image = render(cloud, cam, background=background, progress=progress)
        return image.color, image.alpha, np.where(image.alpha > 0, image.depth, EMPTY_DEPTH)

    def _write(self, width, height, rgba, depth):
        result = self.begin_result(0, 0, width, height)
        layer = result.layers[0]
        # Blender's pixel rows start at the bottom; the core's row 0 is the top.
        layer.passes["Combined"].rect.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
        if "Depth" in layer.passes:
            layer.passes["Depth"].rect.foreach_set(np.ascontiguousarray(depth[::-1], dtype=np.float32).ravel())
        self.end_result(result)

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")


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
        layout.prop(context.scene.render, "film_transparent")
        layout.prop(context.view_layer, "use_pass_z", text="Depth Pass")
        world = context.scene.world
        if world is not None:
            layout.prop(world, "color", text="World Colour (without nodes)")
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


def add_to_panels():
    for panel in _generic_panels():
        panel.COMPAT_ENGINES.add(SplatwrightRenderEngine.bl_idname)


def remove_from_panels():
    for panel in _generic_panels():
        panel.COMPAT_ENGINES.discard(SplatwrightRenderEngine.bl_idname)
