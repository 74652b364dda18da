"""The mesh layer of a SPLATWRIGHT render: everything in the scene that is not a splat (meshes,
curves, hair, volumes and the world), rendered by Cycles, EEVEE or Workbench with the user's
materials, lights and samples, and handed to the core renderer as a Layer (colour, alpha and the
surface depth per pixel), which composites the splats with it exactly in depth order.

How: a child Blender renders a snapshot of the scene. A Python render engine cannot start another
engine inside its own render: from the interface, render() runs in the render job's thread, where
operators are unsafe and the render pipeline is busy with our own job; Cycles and EEVEE have no API
that renders into a Python engine's result. So:

1. the scene is written to a snapshot .blend with bpy.data.libraries.write (the scene and all it
   uses). That must happen on Blender's main thread (before Blender 4.4 a partial write moves data
   blocks between lists of the open file): at once when render() runs there (background renders,
   `bpy.ops.render.render()` from a script), else through a timer that the extension keeps on the
   main thread and that the render thread waits for;
2. a child Blender (the same executable, or the same Python for the bpy module) started once and
   kept for later frames opens the snapshot, hides the splat objects, sets the frame and renders the
   view layer with the chosen engine to an uncompressed multilayer EXR (Combined and Depth);
3. io/exr_plain.py reads it back (Blender's Python has no EXR reader).

Limits: see "Meshes and splats in one picture" in docs/DESIGN.md.
"""

import atexit
import collections
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ...core.color import linear_to_srgb
from ...core.render import Layer
from ...io.exr_plain import read_plain_exr
from .. import data
from . import world_panorama

CHILD_SCRIPT = Path(__file__).with_name("child_blender.py")
REPLY = "@splatwright-mesh-layer "  # the child's answer lines start with this (child_blender.REPLY)
ENGINE_CHOICES = (
    ("CYCLES", "Cycles", "Meshes, curves, volumes and the world rendered by Cycles with the scene's Cycles settings"),
    ("EEVEE", "EEVEE", "Rendered by EEVEE with the scene's EEVEE settings (needs a GPU, also in background mode)"),
    ("WORKBENCH", "Workbench", "Rendered by Workbench (needs a GPU)"),
    ("NONE", "None", "Splats only: meshes do not show in the render"),
)
# every object type that Blender's engines draw as a surface, volume or strokes
GEOMETRY_TYPES = {
    "MESH",
    "CURVE",
    "SURFACE",
    "META",
    "FONT",
    "CURVES",
    "POINTCLOUD",
    "VOLUME",
    "GPENCIL",
    "GREASEPENCIL",
}
NO_SURFACE = 1e10  # what the Depth pass holds where nothing was hit
SAMPLE = re.compile(r"\| Sample (\d+)/(\d+)")  # a child's Cycles progress line


class MeshLayerError(RuntimeError):
    """The mesh layer could not be rendered; the message says why."""


class Cancelled(Exception):
    """The user stopped the render."""


def engine_id(choice):
    """Blender's engine identifier for an ENGINE_CHOICES key (EEVEE changed its name in 5.0)."""
    if choice == "EEVEE":
        return "BLENDER_EEVEE" if bpy.app.version >= (5, 0, 0) else "BLENDER_EEVEE_NEXT"
    return {"CYCLES": "CYCLES", "WORKBENCH": "BLENDER_WORKBENCH"}[choice]


@dataclass
class MeshLayer:
    """The rendered mesh layer, rows top first: rgba (H,W,4) scene-linear premultiplied, depth (H,W)
    camera z (NO_SURFACE where nothing was hit) and, when the world was rendered apart (the engine
    renders an opaque film as a transparent one plus its Environment pass), environment (H,W,3): the
    world seen through each pixel, in front of nothing else; seconds it took."""

    rgba: np.ndarray
    depth: np.ndarray
    environment: np.ndarray | None = None
    seconds: float = 0.0

    @property
    def alpha(self):
        return np.clip(self.rgba[..., 3], 0.0, 1.0, dtype=np.float32)

    def world(self):
        """(H,W,3) display sRGB of the world behind each pixel, or None (a transparent film, or an
        engine whose picture already holds the world)."""
        if self.environment is None:
            return None
        clear = 1.0 - self.alpha
        behind = np.where(clear[..., None] > 1e-6, self.environment / np.maximum(clear, 1e-6)[..., None], 0.0)
        return linear_to_srgb(behind, np.float32)

    def picture(self):
        """The meshes as their engine shows them, scene-linear premultiplied (the Meshes pass)."""
        if self.environment is None:
            return self.rgba
        out = self.rgba.copy()
        out[..., :3] += self.environment
        out[..., 3] = 1.0
        return out

    def as_layer(self):
        """The core renderer's Layer: display sRGB premultiplied, alpha, depth. The curve goes on the
        straight colour, as the engine treats splats. With the world apart, the colour is chosen so
        that the layer over the world (in display terms, as splats meet it) is the engine's own
        mix of meshes and world, which the engine makes in linear light: at a partly covered pixel,
        display(meshes + world) - (1 - alpha) display(world)."""
        alpha = self.alpha
        if self.environment is not None:
            color = linear_to_srgb(self.rgba[..., :3] + self.environment, np.float32)
            color -= (1.0 - alpha)[..., None] * self.world()
            return Layer(np.maximum(color, 0.0, out=color), alpha, self.depth)
        straight = self.rgba[..., :3] / np.where(alpha > 0, alpha, np.float32(1))[..., None]
        color = linear_to_srgb(straight, np.float32)
        color *= alpha[..., None]
        return Layer(color, alpha, self.depth)


def has_geometry(depsgraph):
    """Whether the depsgraph renders anything besides splats (a mesh, curve, volume, ...)."""
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type in GEOMETRY_TYPES and not data.is_splat_object(obj.original):
            return True
    return False


def render(
    depsgraph,
    engine,
    width,
    height,
    test_break=lambda: False,
    progress=lambda fraction: None,
    shadow_casters=None,
    layer=True,
    world=False,
):
    """Render the mesh layer of the depsgraph's scene and view layer at its current frame with
    `engine` (an ENGINE_CHOICES key), and with `world` the world's light (world_panorama.py); returns
    (a MeshLayer of width x height or None without `layer`, the world's scene.Background or None).
    progress(fraction) is called while Cycles reports its samples. `shadow_casters`, a
    relit.StandIn, is a mesh the child adds visible to shadow rays only (relit splats' shadows on
    meshes), in the lights' shadow linking as its parts' objects are."""
    start = time.perf_counter()
    scene = depsgraph.scene
    key = world_panorama.state(scene.world) if world else ""
    light = world_panorama.kept(key) if world else None
    rendering = world and light is None  # a world as the last one rendered is not rendered again
    if not (layer or rendering):
        return None, light
    work = _workdir()
    stamp = f"{os.getpid()}_{next(_counter)}"
    blend, exr, casters = work / f"scene_{stamp}.blend", work / f"layer_{stamp}.exr", work / f"casters_{stamp}.npz"
    pictures = world_panorama.files(work, stamp)
    try:
        if layer:
            hide = on_main_thread(lambda: write_snapshot(scene.name, blend), test_break)
        else:  # the world alone: a file of it and what it uses, not of the whole scene
            hide = on_main_thread(lambda: write_world(scene.world.name, blend), test_break)
        # Cycles renders the world apart (its Environment pass) when the film is opaque, so that
        # splats behind a translucent surface show through it; the others render the film as set.
        apart = engine == "CYCLES" and not scene.render.film_transparent
        request = {
            "blend": str(blend),
            "scene": scene.name,
            "view_layer": depsgraph.view_layer.name,
            "frame": scene.frame_current,
            "subframe": scene.frame_subframe,
            "camera": scene.camera.name if scene.camera else "",
            "engine": engine_id(engine),
            "hide": hide,
            "out": str(exr) if layer else "",
            "autoexec": not bpy.app.autoexec_fail,
            "environment": apart,
            "world_name": scene.world.name if rendering else "",
        }
        if shadow_casters is not None and len(shadow_casters.faces):
            stand_in = shadow_casters
            np.savez(casters, vertices=stand_in.vertices, faces=stand_in.faces, groups=stand_in.groups)
            request.update(shadow_casters=str(casters), caster_links=stand_in.links)
        discs = world_panorama.sun_discs(scene.world) if rendering else None
        failure = f"{engine.title()} could not render the meshes" if layer else "Cycles could not render the world"
        found = _rendered(request, discs, pictures, test_break, progress, failure)
        if rendering:
            light = found
            world_panorama.keep(key, light)
        meshes = None
        if layer:
            channels = read_plain_exr(exr)
            meshes = _layer_from_channels(channels, depsgraph.view_layer.name, width, height, apart, 0.0)
            meshes.seconds = time.perf_counter() - start
    finally:
        for path in (blend, exr, casters, *pictures.values()):
            path.unlink(missing_ok=True)
    return meshes, light


def _rendered(request, discs, pictures, test_break, progress, failure):
    """Send `request` to the child (MeshLayerError: `failure` and the child's error) and, with
    `discs` (world_panorama.sun_discs'; None: the world not asked for), the world of its
    "world_name" too: its light, as world_panorama reads the pictures, else None."""
    child = _child()
    with child.busy:  # a search for the sun reuses the file the request opened: nothing between them
        close = None
        if discs is not None:
            ask, close = world_panorama.first_ask(discs, pictures)
            request = {**request, "world": ask}
        _asked(child, request, test_break, progress, failure)
        if discs is None:
            return None
        disc = None if close is None else world_panorama.view_sun(pictures, close)
        if discs and not world_panorama.shows_sun(disc, close):  # not where the node puts it: searched for
            again = {"reuse": True, "world_name": request["world_name"], **_frame(request)}
            failure = "Cycles could not render the world's sun"
            _asked(child, {**again, "world": world_panorama.search_ask(discs, pictures)}, test_break, progress, failure)
            ask, close = world_panorama.found_ask(discs, pictures)
            _asked(child, {**again, "world": ask}, test_break, progress, failure)
            disc = world_panorama.view_sun(pictures, close)
    return world_panorama.world_light(pictures, disc)


def _frame(request):
    return {"frame": request["frame"], "subframe": request["subframe"]}


def _asked(child, request, test_break, progress, failure):
    """The child's reply to `request`, or MeshLayerError: `failure` and the child's error."""
    reply = child.ask(request, test_break, progress)
    if not reply.get("ok"):
        raise MeshLayerError(f"{failure}: {reply.get('error')}")
    return reply


# the world's light for the Rendered viewport ---------------------------------------------------------


def render_world_soon(world, frame, subframe, done=lambda: None):
    """Have the child render `world`'s light (world_panorama.py) on a thread of its own and keep it
    (world_panorama.kept then finds it), then call done() from that thread. Called on the main
    thread, which writes the world's file at once (the world and what it uses: small). A world
    already under way, waiting or failed is not asked for again; a newer one takes the place of one
    waiting."""
    key = world_panorama.state(world)
    with _lock:
        running, waiting = _jobs["running"], _jobs["waiting"]
        if key == running or key in _jobs["failed"] or (waiting is not None and waiting["key"] == key):
            return
    work = _workdir()
    stamp = f"{os.getpid()}_{next(_counter)}"
    blend = work / f"world_{stamp}.blend"
    write_world(world.name, blend)
    request = {"blend": str(blend), "world_name": world.name, "frame": frame, "subframe": subframe}
    request["autoexec"] = not bpy.app.autoexec_fail
    discs, pictures = world_panorama.sun_discs(world), world_panorama.files(work, stamp)
    job = dict(key=key, request=request, discs=discs, pictures=pictures, done=done)
    with _lock:
        replaced, _jobs["waiting"] = _jobs["waiting"], job
        if _jobs["thread"] is None:
            _jobs["thread"] = threading.Thread(target=_world_jobs, daemon=True)
            _jobs["thread"].start()
    if replaced is not None:
        Path(replaced["request"]["blend"]).unlink(missing_ok=True)


def wait_world_jobs(timeout=None):
    """Wait for the worlds render_world_soon was asked for (the thread's end)."""
    with _lock:
        thread = _jobs["thread"]
    if thread is not None:
        thread.join(timeout)


def _world_jobs():
    """The thread of render_world_soon: the waiting world, then the next, until none waits. A world
    that fails is left (its traceback printed): the viewport keeps lighting by the world's colour."""
    while True:
        with _lock:
            job, _jobs["waiting"] = _jobs["waiting"], None
            _jobs["running"] = None if job is None else job["key"]
            if job is None:
                _jobs["thread"] = None
                return
        try:
            failure = "Cycles could not render the world"
            light = _rendered(job["request"], job["discs"], job["pictures"], lambda: False, lambda f: None, failure)
            world_panorama.keep(job["key"], light)
            job["done"]()
        except Exception:  # noqa: BLE001 - a viewport's helper thread: nothing above it to hand it to
            traceback.print_exc()
            with _lock:
                _jobs["failed"].add(job["key"])  # not asked for again while the world stays so
        finally:
            for path in (Path(job["request"]["blend"]), *job["pictures"].values()):
                path.unlink(missing_ok=True)


def _layer_from_channels(channels, view_layer, width, height, environment, seconds):
    """The MeshLayer in an EXR's channels, or MeshLayerError naming what is missing or wrong."""
    names = [f"{view_layer}.Combined.{c}" for c in "RGBA"] + [f"{view_layer}.Depth.Z"]
    if environment:  # the pass is "Env" before Blender 5.0
        env = "Environment" if f"{view_layer}.Environment.R" in channels else "Env"
        names += [f"{view_layer}.{env}.{c}" for c in "RGB"]
    missing = [n for n in names if n not in channels]
    if missing:
        raise MeshLayerError(f"the mesh layer has no {', '.join(missing)} (it has {', '.join(sorted(channels))})")
    rgba, depth = np.stack([channels[n] for n in names[:4]], axis=-1), channels[names[4]]
    env = np.stack([channels[n] for n in names[5:]], axis=-1) if environment else None
    if rgba.shape[:2] != (height, width):
        raise MeshLayerError(f"the mesh layer is {rgba.shape[1]}x{rgba.shape[0]}, the render {width}x{height}")
    bad = ~np.isfinite(rgba).all(axis=-1) | np.isnan(depth)
    if env is not None:
        bad |= ~np.isfinite(env).all(axis=-1)
    if bad.any():
        raise MeshLayerError(f"the mesh layer holds NaN or Inf at {int(bad.sum())} pixels")
    return MeshLayer(rgba, depth, env, seconds)


def write_world(world_name, path):
    """Write the world and everything it uses to `path` (main thread only)."""
    bpy.data.libraries.write(str(path), {bpy.data.worlds[world_name]}, path_remap="ABSOLUTE", fake_user=True)
    return []


def write_snapshot(scene_name, path):
    """Write the scene and everything it uses to `path` (main thread only); returns the names of
    the splat objects, which the child hides."""
    scene = bpy.data.scenes[scene_name]
    bpy.data.libraries.write(str(path), {scene}, path_remap="ABSOLUTE", fake_user=True)
    return sorted(o.name for o in bpy.data.objects if data.is_splat_object(o))


# the main thread ------------------------------------------------------------------------------------

_calls = queue.Queue()
MAIN_THREAD_POLL = 0.05  # seconds between the main-thread timer's looks at the queue


def on_main_thread(fn, test_break=lambda: False):
    """fn() run on Blender's main thread, its result returned (its exception raised). On the main
    thread it runs at once; from another thread (the render job of the interface) the extension's
    timer runs it while this thread waits, giving up if the render is cancelled."""
    if threading.current_thread() is threading.main_thread():
        return fn()
    done, box = threading.Event(), {}

    def call():
        if box.get("cancelled"):
            return
        try:
            box["value"] = fn()
        except Exception as exc:
            box["error"] = exc
        finally:
            done.set()

    _calls.put(call)
    while not done.wait(0.05):
        if test_break():
            box["cancelled"] = True
            raise Cancelled
    if "error" in box:
        raise box["error"]
    return box["value"]


def _serve_main_thread():
    """The timer on Blender's main thread: run what render threads queued."""
    while True:
        try:
            call = _calls.get_nowait()
        except queue.Empty:
            return MAIN_THREAD_POLL
        call()


# the child Blender ----------------------------------------------------------------------------------

_counter = iter(range(1, 1 << 62))
_lock = threading.Lock()
_state = {"child": None, "workdir": None}
_jobs = {"thread": None, "running": None, "waiting": None, "failed": set()}  # render_world_soon's


def child_command():
    """How to start a Blender without a window that runs child_blender.py: this Blender's own
    executable, or, for the bpy module (no executable of its own), this Python."""
    binary = bpy.app.binary_path
    if binary and Path(binary).exists() and "python" not in Path(binary).name.lower():
        return [binary, "-b", "-noaudio", "--python", str(CHILD_SCRIPT)]
    return [sys.executable, str(CHILD_SCRIPT)]


class _Child:
    """One child Blender and the lines it prints, read by a thread so its pipe never fills."""

    def __init__(self):
        flags = subprocess.CREATE_NO_WINDOW if sys.platform == "win32" else 0
        try:
            self.proc = subprocess.Popen(
                child_command(),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                encoding="utf-8",
                errors="replace",
                bufsize=1,
                creationflags=flags,
            )
        except OSError as exc:
            raise MeshLayerError(f"cannot start a Blender to render the meshes ({child_command()[0]}): {exc}") from exc
        self.replies, self.log = queue.Queue(), collections.deque(maxlen=40)
        self.busy = threading.RLock()  # one request (or one world's two) at a time
        self.samples = None  # (done, total) of the frame being rendered
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            if line.startswith(REPLY):
                self.replies.put(json.loads(line[len(REPLY) :]))
            else:
                self.log.append(line.rstrip())
                found = SAMPLE.search(line)
                if found:
                    self.samples = (int(found.group(1)), int(found.group(2)))

    def alive(self):
        return self.proc.poll() is None

    def ask(self, request, test_break, progress=lambda fraction: None):
        """Send one request and wait for its reply, watching for a cancelled render."""
        with self.busy:
            self.samples = None
            try:
                self.proc.stdin.write(json.dumps(request) + "\n")
                self.proc.stdin.flush()
            except OSError:
                self.close(kill=True)
                raise MeshLayerError("the Blender rendering the meshes has ended:\n" + "\n".join(self.log)) from None
            while True:
                try:
                    return self.replies.get(timeout=0.05)
                except queue.Empty:
                    pass
                if self.samples is not None:
                    progress(self.samples[0] / max(self.samples[1], 1))
                if test_break():
                    self.close(kill=True)  # a render cannot be stopped half way: start afresh next time
                    raise Cancelled
                if not self.alive():
                    raise MeshLayerError("the Blender rendering the meshes ended unexpectedly:\n" + "\n".join(self.log))

    def close(self, kill=False):
        """Let the child end (its stdin closes), or kill it."""
        try:
            if kill:
                self.proc.kill()
            else:
                self.proc.stdin.close()
            self.proc.wait(timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


def _child():
    with _lock:
        child = _state["child"]
        if child is None or not child.alive():
            child = _state["child"] = _Child()
        return child


def _workdir():
    with _lock:
        if _state["workdir"] is None:
            _state["workdir"] = Path(tempfile.mkdtemp(prefix="splatwright-meshes-"))
        return _state["workdir"]


def stop():
    """End the child Blender and remove the snapshots' folder."""
    with _lock:
        child, work = _state["child"], _state["workdir"]
        _state["child"] = _state["workdir"] = None
    if child is not None:
        child.close()
    if work is not None:
        shutil.rmtree(work, ignore_errors=True)


def register():
    if not bpy.app.timers.is_registered(_serve_main_thread):
        bpy.app.timers.register(_serve_main_thread, first_interval=MAIN_THREAD_POLL, persistent=True)
    atexit.register(stop)


def unregister():
    if bpy.app.timers.is_registered(_serve_main_thread):
        bpy.app.timers.unregister(_serve_main_thread)
    atexit.unregister(stop)
    stop()
