"""Interactive previews of splats with meshes, as the SPLATWRIGHT engine's Rendered viewport shows them.

- `camera_from_opengl`: a viewport's view and projection matrices -> a core Camera;
- `preview_image`: the splats composited exactly (core.render.Layer) with triangles rasterised at
  pixel centres and shaded flat with a headlight, as a solid view shades them; a quick stand-in for
  the Cycles or EEVEE meshes of a final render, composited by the same rule;
- `Progressive`: renders on a thread of its own, a coarse pass while the view changes and the full
  picture once it has stayed still, so whoever asks never waits.

NumPy only (no bpy): splat_addon/viewport.py hands these Blender's data and draws the result.
"""

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from .camera import GL_TO_CV, Camera
from .color import linear_to_srgb
from .render import Layer, render

HEADLIGHT_AMBIENT = 0.25  # shading: ambient + (1 - ambient) |cos| between the face normal and the view ray


def camera_from_opengl(view_matrix, projection_matrix, width, height):
    """The core Camera of an OpenGL view (world -> eye, eye looks down -Z) and projection (eye ->
    clip) seen in a width x height region. Orthographic views whose clip range starts behind the
    eye are moved back along their axis until it starts in front (depth order is unchanged)."""
    view = np.asarray(view_matrix, np.float64)
    p = np.asarray(projection_matrix, np.float64)
    w2c = GL_TO_CV @ view
    w2c[:3, :3] /= np.linalg.norm(w2c[:3, :3], axis=1, keepdims=True)  # a view may carry scale
    fx, fy = 0.5 * width * p[0, 0], 0.5 * height * p[1, 1]
    if p[3, 3] == 0.0:  # perspective: clip w = -z
        cx, cy = 0.5 * width * (1.0 - p[0, 2]), 0.5 * height * (1.0 + p[1, 2])
        near, far = p[2, 3] / (p[2, 2] - 1.0), p[2, 3] / (p[2, 2] + 1.0)
        return Camera(width, height, fx, fy, cx, cy, w2c, near=max(near, 0.0), far=far)
    cx, cy = 0.5 * width * (1.0 + p[0, 3]), 0.5 * height * (1.0 - p[1, 3])
    near, far = (p[2, 3] + 1.0) / p[2, 2], (p[2, 3] - 1.0) / p[2, 2]
    back = max(0.0, 1e-3 - near)
    w2c[2, 3] += back
    return Camera(width, height, fx, fy, cx, cy, w2c, near=near + back, far=far + back, projection="orthographic")


def scaled(camera, scale):
    """The same view at `scale` times the resolution (at least one pixel)."""
    w, h = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
    sx, sy = w / camera.width, h / camera.height
    return camera.with_(width=w, height=h, fx=camera.fx * sx, fy=camera.fy * sy, cx=camera.cx * sx, cy=camera.cy * sy)


@dataclass
class Triangles:
    """Meshes for a preview: corners (F,3,3) in world space and a scene-linear colour per face (F,3)."""

    corners: np.ndarray
    colors: np.ndarray

    @classmethod
    def empty(cls):
        return cls(np.zeros((0, 3, 3)), np.zeros((0, 3)))

    def __len__(self):
        return len(self.corners)


def mesh_layer(triangles, camera):
    """The triangles as a core Layer: at each pixel centre the nearest face, its colour shaded by a
    headlight (display sRGB), opaque, at its camera depth; nothing (depth inf) elsewhere."""
    shape = (camera.height, camera.width)
    if not len(triangles):
        return Layer(np.zeros(shape + (3,)), np.zeros(shape), np.full(shape, np.inf))
    from .mesh import Surface
    from .mesh_render import rasterize

    flat = triangles.corners.reshape(-1, 3)
    surface = Surface(flat, np.arange(len(flat)).reshape(-1, 3))
    face, _, depth = rasterize(surface, camera)
    hit = face >= 0
    f = face[hit]
    if camera.is_orthographic:
        rays = np.broadcast_to(camera.forward, (len(f), 3))
    else:
        rows, cols = np.nonzero(hit)
        local = np.stack(
            [(cols + 0.5 - camera.cx) / camera.fx, (rows + 0.5 - camera.cy) / camera.fy, np.ones(len(f))], axis=1
        )
        rays = local @ camera.rotation
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ij,ij->i", surface.normal[f], rays))
    color = np.zeros(shape + (3,))
    color[hit] = linear_to_srgb(triangles.colors[f] * (HEADLIGHT_AMBIENT + (1 - HEADLIGHT_AMBIENT) * cos)[:, None])
    return Layer(color, hit.astype(np.float64), np.where(hit, depth, np.inf))


def preview_image(cloud, triangles, camera, background=None, threads=None, progress=None):
    """The splats and the triangles in one picture (a core RenderResult, display sRGB)."""
    return render(
        cloud, camera, background=background, layer=mesh_layer(triangles, camera), threads=threads, progress=progress
    )


# progressive rendering -------------------------------------------------------------------------


class Stale(Exception):
    """A render given up because a newer view or scene came in."""


@dataclass
class Frame:
    """A finished picture: what `render` returned, the view it shows and the scale it was made at."""

    image: object
    view: object
    scale: float


class Progressive:
    """Pictures of a changing view, made on a thread of its own.

    render(view, scale, check) makes the picture of `view` at `scale` times its resolution and calls
    check() now and then, which raises Stale once a newer request is waiting. show(view) never
    waits: it asks for `view` and returns the latest finished Frame (or None). A new view (or
    refresh(), after the scene changed) gets a pass at `coarse` scale at once; when nothing new has
    come for `settle` seconds after that, the full picture follows. on_ready() is called from the
    thread after each finished frame (e.g. to ask the viewport for a redraw).
    """

    def __init__(self, render, on_ready=lambda: None, coarse=0.25, settle=0.25, clock=time.monotonic):
        self.render, self.on_ready, self.coarse, self.settle, self.clock = render, on_ready, coarse, settle, clock
        self.lock = threading.Condition()
        self.wanted, self.generation, self.frame, self.error = None, 0, None, None
        self.stopped = False
        self.thread = threading.Thread(target=self._run, daemon=True, name="splatwright-preview")
        self.thread.start()

    def show(self, view):
        """Ask for `view` (anything comparable with ==) and return the latest Frame, at once."""
        with self.lock:
            if view != self.wanted:
                self._request(view)
            return self.frame

    def refresh(self):
        """The scene changed: picture the current view again, coarse first."""
        with self.lock:
            if self.wanted is not None:
                self._request(self.wanted)

    def stop(self):
        with self.lock:
            self.stopped = True
            self.lock.notify_all()

    def _request(self, view):
        self.wanted, self.generation = view, self.generation + 1
        self.lock.notify_all()

    def _run(self):
        done = 0
        while True:
            with self.lock:
                while not self.stopped and self.generation == done:
                    self.lock.wait()
                if self.stopped:
                    return
                view, generation = self.wanted, self.generation
            done = generation
            if not self._make(view, generation, self.coarse):
                continue
            with self.lock:  # wait for the view to settle
                until = self.clock() + self.settle
                while not self.stopped and self.generation == generation and self.clock() < until:
                    self.lock.wait(max(0.0, until - self.clock()))
                if self.stopped or self.generation != generation:
                    continue
            self._make(view, generation, 1.0)

    def _make(self, view, generation, scale):
        """Render and publish one frame; False if a newer request made it stale."""

        def check():
            if self.stopped or self.generation != generation:
                raise Stale

        try:
            image = self.render(view, scale, check)
        except Stale:
            return False
        except Exception as exc:  # kept for whoever draws; the thread goes on
            self.error = exc
            return False
        with self.lock:
            if self.generation != generation:
                return False
            self.frame, self.error = Frame(image, view, scale), None
        self.on_ready()
        return True


def view_key(camera):
    """Hashable, comparable numbers that identify a view (its camera)."""
    return (
        camera.width,
        camera.height,
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        camera.near,
        camera.far if math.isfinite(camera.far) else -1.0,
        camera.projection,
        tuple(np.round(camera.world_to_camera.ravel(), 12)),
    )
