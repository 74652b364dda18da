"""The SPLATWRIGHT engine in a 3D viewport's Rendered shading: the splats composited with the meshes
(core/preview.py: triangles shaded flat with a headlight, composited by the final render's rule),
relit splats shaded by the scene's lights as the final render shades them (relit.py),
rendered progressively on a thread (a coarse pass while the view moves, the full picture once it
stops) so drawing never waits. Solid and Material Preview keep Blender's own drawing.

view_update (main thread) copies what the picture needs out of the depsgraph; view_draw builds the
camera of the region, asks for the picture and draws the latest finished one: the only lines that
need a GPU, which background mode does not have.
"""

import os
import weakref

import numpy as np

from ...core import scratch
from ...core.color import linear_to_srgb
from ...core.preview import Progressive, Triangles, camera_from_opengl, preview_image, scaled, view_key
from ...core.splats import SplatCloud
from . import mesh_layer, relit, world_panorama
from .lights import scene_world
from .scene import mesh_engine, surface_triangles, to_scene_linear, world_background


class View:
    """A region's camera, compared by its numbers."""

    def __init__(self, camera):
        self.camera, self.key = camera, view_key(camera)

    def __eq__(self, other):
        return isinstance(other, View) and self.key == other.key


def region_camera(region, region_3d):
    """The core Camera of a 3D viewport region."""
    return camera_from_opengl(
        np.array(region_3d.view_matrix), np.array(region_3d.window_matrix), region.width, region.height
    )


def triangles(depsgraph):
    """Every visible surface that is not a splat object as core.preview Triangles (world space, each
    face with its material's viewport colour)."""
    corners, colors = surface_triangles(depsgraph)
    return Triangles(corners, colors) if len(corners) else Triangles.empty()


class Lighting:
    """What shades the relit splats (those with a material) of a viewport picture: the lights, the
    world and the meshes that shadow them; the shadows themselves (view-independent) are made once
    per scene update, on the picture's thread, and kept. `kept` (a dict the viewport holds across
    updates) holds a core.relight.KeptVisibilities: a scene update makes again only the shadows of
    what changed (moving a light remakes its maps alone; recolouring the world, none)."""

    def __init__(self, lights, world, occluders, kept=None, linking=None):
        self.lights, self.world, self.occluders = lights, world, occluders
        self.kept = {} if kept is None else kept
        # light and shadow linking (relit.linked_lights): receivers, blockers, mesh_blockers
        self.receivers, self.blockers, self.mesh_blockers = linking or ({}, {}, {})
        self.visible = None

    def shade(self, cloud, camera, check=None):
        """`cloud` with the relit splats' colours for an eye at `camera`; `check()`, called as the
        shadow maps are made, may raise to stop them (a newer scene or view)."""
        from ...core.relight import KeptVisibilities, lit_cloud, lit_colors  # only when something is relit

        if self.visible is None:
            kept = self.kept.setdefault("shadows", KeptVisibilities())
            self.visible = kept(
                cloud,
                self.lights,
                self.world,
                meshes=self.occluders,
                progress=None if check is None else (lambda *_: check()),
                blockers=self.blockers,
                mesh_blockers=self.mesh_blockers,
            )
        rows, shading = lit_colors(
            cloud, camera, self.lights, self.world, visible=self.visible, receivers=self.receivers
        )
        return cloud if shading is None else lit_cloud(cloud, rows, shading)


def picture_inputs(depsgraph, kept=None, world_ready=None):
    """(splats, triangles, background, lighting) of the depsgraph's scene for the viewport picture;
    lighting is a Lighting (with `kept`, see Lighting), or None when no splat is relit. A world whose
    light needs Cycles' render (world_panorama.py) lights by what a render last read of it as it is
    now; with `world_ready`, one not read yet is rendered on a thread (mesh_layer.render_world_soon),
    which calls world_ready() once it is kept, and meanwhile lights by the world's colour."""
    scene = depsgraph.scene
    origin = np.zeros(3)
    cloud, lit, owners = relit.scene_cloud(depsgraph, origin)
    meshes = triangles(depsgraph) if mesh_engine(scene) != "NONE" else Triangles.empty()
    backdrop = world_background(scene)  # read once for the backdrop and the lighting
    background = None if scene.render.film_transparent else linear_to_srgb(backdrop[0])
    lighting = None
    if lit is not None:
        occluders = relit.occluders(depsgraph, origin) if len(meshes) else relit.Occluders([])
        lights, *linking = relit.linked_lights(depsgraph, origin, owners, occluders)
        rendered = None
        if world_panorama.wanted(backdrop):  # nodes world_background does not read drive the world
            rendered = world_panorama.kept(world_panorama.state(scene.world))
            if rendered is None and world_ready is not None:  # rendered on a thread: no scene update waits
                mesh_layer.render_world_soon(scene.world, scene.frame_current, scene.frame_subframe, world_ready)
        world = scene_world(scene, rendered or backdrop)
        lighting = Lighting(world.lights(lights), world, occluders.surfaces, kept, tuple(linking))
    return (cloud if cloud is not None else SplatCloud.empty()), meshes, background, lighting


class Viewport:
    """One viewport's pictures: the scene's inputs, the progressive renderer and the texture drawn."""

    def __init__(self, engine):
        engine_ref = weakref.ref(engine)
        self.world_ready = lambda: _tag(engine_ref, "tag_update")  # the world's light rendered: read the scene again
        self.inputs = (SplatCloud.empty(), Triangles.empty(), None, None)
        self.progressive = Progressive(self.picture, on_ready=lambda: _tag(engine_ref, "tag_redraw"))
        self.texture, self.drawn = None, None
        self.kept = {}  # the shadows across scene updates (Lighting)

    def update(self, depsgraph):
        self.inputs = picture_inputs(depsgraph, self.kept, self.world_ready)
        self.progressive.refresh()

    def picture(self, view, scale, check):
        """Scene-linear premultiplied RGBA (rows top first) of `view` at `scale` (on the thread)."""
        cloud, meshes, background, lighting = self.inputs
        if lighting is not None:
            check()
            cloud = lighting.shade(cloud, view.camera, check)
        image = preview_image(
            cloud,
            meshes,
            scaled(view.camera, scale),
            background=background,
            threads=max(1, (os.cpu_count() or 2) - 1),  # a core stays with the interface
            progress=lambda *_: check(),
        )
        return to_scene_linear(image.color, image.alpha if background is None else np.ones_like(image.alpha))

    def draw(self, engine, context):
        frame = self.progressive.show(View(region_camera(context.region, context.region_data)))
        if frame is None:
            return
        if frame is not self.drawn:
            self.texture, self.drawn = _texture(frame.image), frame
        _draw(engine, context, self.texture)

    def stop(self):
        self.progressive.stop()
        scratch.release()  # the working memory its frames shared (core.scratch)


def _tag(engine_ref, what):
    """Ask the viewport's engine for an update ("tag_update") or a redraw ("tag_redraw"), from any
    thread, unless the viewport has closed."""
    engine = engine_ref()
    if engine is not None:
        try:
            getattr(engine, what)()
        except ReferenceError:  # the viewport closed meanwhile
            pass


# the GPU: untestable without a window, kept to these lines ------------------------------------------


def _texture(rgba):
    import gpu

    h, w = rgba.shape[:2]
    pixels = np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel()  # GPU rows start at the bottom
    return gpu.types.GPUTexture((w, h), format="RGBA16F", data=gpu.types.Buffer("FLOAT", pixels.size, pixels))


def _draw(engine, context, texture):
    import gpu
    from gpu_extras.presets import draw_texture_2d

    gpu.state.blend_set("ALPHA_PREMULT")
    engine.bind_display_space_shader(context.scene)
    draw_texture_2d(texture, (0, 0), context.region.width, context.region.height)
    engine.unbind_display_space_shader()
    gpu.state.blend_set("NONE")
