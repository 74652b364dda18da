"""The main job: everything Splatwright does, on the built-in demo rig, into one folder.

It runs inside Blender's `bpy` module in this process, with the extension registered as a plain
package (no zip installed), and goes through the same functions as the interface and the
`blender -b --command splatwright` verbs: build the demo rig (its environment made with Mesh to
Splats), convert the arm's mesh to splats, bind them to the armature (weights transferred exactly
from the skinned mesh), measure the posed splats against splats made from the posed mesh, render
frames to PNG and EXR with the SPLATWRIGHT engine through Blender's output settings, export one
frame as PLY, the animation as a PLY sequence and as one animated OpenUSD file, check the arm
against the environment for collisions over the animation, and save the scene. The frames show the
arm's splats standing on the environment's meshes (a floor and a box, rendered by Cycles and
composited with the splats in depth order); the environment's splats are there for the collision
check. A summary with timings and errors ends the run and is also written to summary.json.
"""

import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from .core.frames import frame_ranges
from .io.common import atomic_write

ARM_SPLATS = 20_000
ENVIRONMENT_SPLATS = 20_000
BENT_FRAME = 12  # the demo rig's most bent pose
RENDER_FRAMES = "6-24:6"  # frames 6, 12, 18, 24
RENDER_SIZE = (480, 360)
CYCLES_SAMPLES = 16  # the floor and box, lit by the sun: few samples suffice
WORLD_COLOR = (0.03, 0.035, 0.045)  # a dim sky, which also lights the shadows
IGNORE_BONES = ("Base",)  # the base stands on the floor: not a collision


class DemoError(Exception):
    """A step that did not do what it should; the message says what."""


def run_demo(out_dir, progress=None):
    """Run the demo into `out_dir`; returns the exit code (0, or 1 after printing the error)."""
    out = Path(out_dir).resolve()
    try:
        out.mkdir(parents=True, exist_ok=True)
        import bpy
    except ImportError:
        return _fail(
            "the demo needs Blender's bpy module (Python 3.11, `pip install bpy==5.0.1`); `./run demo` sets it up"
        )
    except OSError as exc:
        return _fail(f"cannot create the output folder {out}: {exc}")
    return Demo(bpy, out, progress).run()


def _fail(message):
    print(f"splatwright demo: error: {message}", file=sys.stderr, flush=True)
    return 1


def _image_format(settings, kind):
    """Blender's output image settings for 8-bit "png" or full-float multilayer "exr" (the bit depth
    set too: switching formats carries the last one's over)."""
    if hasattr(settings, "media_type"):  # Blender 5: the media type first
        settings.media_type = "IMAGE" if kind == "png" else "MULTI_LAYER_IMAGE"
    settings.file_format = "PNG" if kind == "png" else "OPEN_EXR_MULTILAYER"
    settings.color_depth = "8" if kind == "png" else "32"


def _size(path):
    return f"{path.stat().st_size / 1e6:.2f} MB"


class Demo:
    def __init__(self, bpy, out, progress=None):
        self.bpy, self.out, self.progress = bpy, out, progress
        self.registered = False
        self.summary = {"outputs": str(out), "seconds": {}, "files": {}}
        self.steps = [
            ("start Blender and register the extension", self.start),
            ("build the demo rig (its environment: Mesh to Splats)", self.build_rig),
            ("convert the arm's mesh to splats", self.convert_arm),
            ("bind the arm's splats to the armature", self.bind),
            (f"measure the posed splats at frame {BENT_FRAME}", self.measure_pose),
            ("render PNG and EXR frames: the arm's splats on the meshes", self.render),
            ("export PLY, a PLY sequence and an animated OpenUSD file", self.export),
            ("check the arm against the environment for collisions", self.collide),
            ("save the scene and the seed cube", self.save),
        ]

    # running ----------------------------------------------------------------------------------------

    def run(self):
        start = time.perf_counter()
        try:
            for i, (label, step) in enumerate(self.steps):
                print(f"[{i + 1}/{len(self.steps)}] {label} ...", flush=True)
                begin = time.perf_counter()
                try:
                    note = step()
                except Exception as exc:
                    expected = isinstance(exc, (DemoError, ValueError, OSError, RuntimeError))
                    if not expected:
                        traceback.print_exc()
                    return _fail(f"step '{label}' failed: {exc}" + ("" if expected else " (traceback above)"))
                seconds = time.perf_counter() - begin
                self.summary["seconds"][step.__name__] = round(seconds, 3)
                print(f"      {note} ({seconds:.1f} s)", flush=True)
        finally:
            if self.registered:
                from . import unregister

                unregister()
        self.summary["seconds"]["total"] = round(time.perf_counter() - start, 3)
        self.write_summary()
        return 0

    def _frames_progress(self, label):
        if self.progress is None:
            return None
        return lambda done, total, *_: self.progress(done, total, f"      {label}")

    # steps ------------------------------------------------------------------------------------------

    def start(self):
        bpy = self.bpy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        from . import register

        register()
        self.registered = True
        from .splat_addon.render import engine

        if not hasattr(bpy.types, "SPLAT_OT_bind_armature") or not engine.SplatwrightRenderEngine.is_registered:
            raise DemoError("the extension did not register its operators and render engine")
        return f"Blender {bpy.app.version_string}, extension registered from {Path(__file__).parent}"

    def build_rig(self):
        from .splat_addon import data
        from .splat_addon.convert import demo_rig

        # The environment's splats serve the collision check only (the frames show its meshes), so their
        # silhouettes are not calibrated for views no one renders: that took most of the rig's build.
        self.rig = demo_rig.build_demo_rig(
            self.bpy.context.scene, environment_splats=ENVIRONMENT_SPLATS, calibrate=False
        )
        self.env = self.rig.environment
        self.summary["environment_splats"] = data.splat_count(self.env.data)
        return (
            f"robot arm with {len(self.rig.armature.data.bones)} bones, frames 1-24; environment "
            f"'{self.env.name}': {data.splat_count(self.env.data)} splats"
        )

    def convert_arm(self):
        from .splat_addon import data
        from .splat_addon.convert import from_mesh

        self.arm = from_mesh.from_mesh(self.bpy.context, [self.rig.body], max_splats=ARM_SPLATS)[0]
        self.summary["arm_splats"] = data.splat_count(self.arm.data)
        return (
            f"'{self.arm.name}': {data.splat_count(self.arm.data)} splats from '{self.rig.body.name}' in its rest pose"
        )

    def bind(self):
        from .splat_addon.rig import armature as rigging

        warnings = []
        (plan,) = rigging.bind_armature([self.arm], self.rig.armature, warn=warnings.append)
        if not plan.source.startswith("mesh"):
            raise DemoError(f"the weights came from {plan.source}, not from the skinned mesh: {'; '.join(warnings)}")
        report = plan.report
        self.summary["binding"] = {"weights_from": plan.source, **report}
        return (
            f"weights from {plan.source} (exact transfer), up to {report['max_influences']} bones per splat, "
            f"{report['unbound']} unbound"
        )

    def measure_pose(self):
        """The bound splats posed at the bent frame against splats made from the posed mesh, both
        rendered from the scene camera; PSNR over the box the arm covers (the background would
        flatter it). Moving the centres alone, as Blender's modifier does, is the comparison."""
        from .core.metrics import psnr
        from .core.render import render
        from .splat_addon import data
        from .splat_addon.convert import from_mesh
        from .splat_addon.data import camera

        bpy, scene = self.bpy, self.bpy.context.scene
        scene.frame_set(BENT_FRAME)
        try:
            depsgraph = bpy.context.evaluated_depsgraph_get()
            posed = data.evaluated_cloud(self.arm, depsgraph)
            rest = data.object_cloud(self.arm)
            rest = data.transform_cloud(rest, data.world_matrix(self.arm, depsgraph))
            _, remade, _ = from_mesh.convert_objects(
                bpy.context, [self.rig.body], max_splats=ARM_SPLATS, use_rest_pose=False
            )[0]
            depsgraph = bpy.context.evaluated_depsgraph_get()
            remade = data.transform_cloud(remade, data.world_matrix(self.rig.body, depsgraph))
            cam = camera.from_object(scene.camera.evaluated_get(depsgraph), scene, *RENDER_SIZE)
        finally:
            scene.frame_set(1)
        images = {
            name: render(cloud, cam)
            for name, cloud in (
                ("posed", posed),
                ("remade", remade),
                ("centres", rest.replace(positions=posed.positions)),
            )
        }
        covered = (images["posed"].alpha > 0.01) | (images["remade"].alpha > 0.01)
        if not covered.any():
            raise DemoError("the arm is not in view of the scene camera")
        rows, cols = np.nonzero(covered)
        box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
        score = {name: psnr(images[name].color[box], images["remade"].color[box]) for name in ("posed", "centres")}
        self.summary["pose_check"] = {
            "frame": BENT_FRAME,
            "psnr_db": round(score["posed"], 2),
            "centres_only_psnr_db": round(score["centres"], 2),
            "region_px": [int(rows.ptp()) + 1, int(cols.ptp()) + 1],
        }
        return (
            f"PSNR {score['posed']:.1f} dB against splats of the posed mesh (centres only: "
            f"{score['centres']:.1f} dB) over {rows.ptp() + 1}x{cols.ptp() + 1} px"
        )

    def render(self):
        from .splat_addon import command

        scene = self.bpy.context.scene
        render = scene.render
        render.resolution_x, render.resolution_y = RENDER_SIZE
        render.resolution_percentage = 100
        scene.view_settings.view_transform = "Standard"  # PNG colours as 3DGS viewers show them
        self.bpy.context.view_layer.use_pass_z = True  # the EXR gets the depth pass too,
        self.bpy.context.view_layer.splatwright_use_pass_splats = True  # and the splats and meshes apart
        self._meshes_for_render(scene)
        folder = self.out / "render"
        folder.mkdir(exist_ok=True)
        frames = command.parse_frames(RENDER_FRAMES, scene)
        written = {kind: [folder / f"frame_{f:04d}.{kind}" for f in frames] for kind in ("png", "exr")}
        # Each frame is rendered once: the render command writes the multilayer EXR through the output
        # settings, and the same render result is saved as PNG through them (rendering the frames again
        # for the PNGs, the meshes' Cycles renders included, took a sixth of the demo).
        for frame, png in zip(frames, written["png"]):
            _image_format(render.image_settings, "exr")
            pattern = folder / "frame_####.exr"
            if command.execute(["render", str(pattern), "--frames", str(frame), "--meshes", "cycles"]) != 0:
                raise DemoError(f"rendering frame {frame} failed (the error is above)")
            _image_format(render.image_settings, "png")
            self.bpy.data.images["Render Result"].save_render(str(png), scene=scene)
        self.summary["render"] = {
            "frames": frames,
            "size": list(RENDER_SIZE),
            "meshes": "Cycles",
            "cycles_samples": CYCLES_SAMPLES,
            **{k: [p.name for p in v] for k, v in written.items()},
        }
        self._files(*written["png"], *written["exr"])
        return (
            f"{len(frames)} PNG + {len(frames)} EXR (Combined, Depth, Splats, Meshes) frames at "
            f"{RENDER_SIZE[0]}x{RENDER_SIZE[1]}, frames {', '.join(map(str, frames))}: the arm's splats on the "
            f"floor and box meshes (Cycles, {CYCLES_SAMPLES} samples), in {folder.name}/"
        )

    def _meshes_for_render(self, scene):
        """The environment shows as its meshes (Cycles renders them), the arm as its splats: the
        environment's splats and the arm's source mesh stay out of the picture."""
        bpy = self.bpy
        self.rig.environment_mesh.hide_render = False
        self.env.hide_render = True
        self.rig.body.hide_render = True
        scene.cycles.samples = CYCLES_SAMPLES
        scene.cycles.use_denoising = False  # OIDN would take longer than the render here
        scene.cycles.device = "CPU"
        if scene.world is None:
            scene.world = bpy.data.worlds.new("Splatwright Demo Sky")
        scene.world.color = WORLD_COLOR
        if scene.world.node_tree is not None:
            background = next((n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground"), None)
            if background is not None:
                background.inputs["Color"].default_value = (*WORLD_COLOR, 1.0)

    def export(self):
        from .splat_addon import data
        from .splat_addon.files import animation

        context, scene = self.bpy.context, self.bpy.context.scene
        frames = data.frame_range(scene.frame_start, scene.frame_end, scene.frame_step)
        everything = [self.arm, self.env]
        (one,) = animation.export_animation(context, everything, self.out / "scene_####.ply", [BENT_FRAME])
        (self.out / "arm_ply").mkdir(exist_ok=True)
        sequence = animation.export_animation(
            context,
            [self.arm],
            self.out / "arm_ply" / "arm_####.ply",
            frames,
            progress=self._frames_progress("PLY sequence"),
        )
        (usd,) = animation.export_animation(
            context, [self.arm], self.out / "arm.usdc", frames, progress=self._frames_progress("OpenUSD")
        )
        splats = data.splat_count(self.arm.data) + data.splat_count(self.env.data)
        self.summary["exports"] = {
            "ply": one.name,
            "ply_splats": splats,
            "ply_sequence": [p.relative_to(self.out).as_posix() for p in sequence],
            "usd": usd.name,
            "usd_frames": frames,
        }
        self._files(one, *sequence, usd)
        seq_bytes = sum(p.stat().st_size for p in sequence)
        return (
            f"{one.name} (arm and environment at frame {BENT_FRAME}, {_size(one)}); arm_ply/ ({len(sequence)} "
            f"files, {seq_bytes / 1e6:.2f} MB); {usd.name} ({len(frames)} time samples, {_size(usd)})"
        )

    def collide(self):
        from .splat_addon.rig import collide

        context, scene = self.bpy.context, self.bpy.context.scene
        frames = range(scene.frame_start, scene.frame_end + 1)
        report = collide.check_collisions(
            context, self.arm, self.env, frames, ignore_bones=IGNORE_BONES, progress=self._frames_progress("collisions")
        )
        path = self.out / "contacts.json"
        with atomic_write(path, "w") as f:
            json.dump(report.as_dict(), f, indent=1)
        self._files(path)
        bent = next(f for f in report.frames if f.frame == BENT_FRAME)
        bones = sorted({b for f in report.frames for b in f.bones_a})
        self.summary["collisions"] = {
            "contact_frames": report.contact_frames,
            "bones": bones,
            "pairs_at_bent_frame": bent.pairs,
            "deepest_sigma": None if np.isinf(bent.deepest) else round(bent.deepest, 3),
        }
        if not report.contact_frames:
            return f"no contact in frames {frames.start}-{frames.stop - 1}"
        return (
            f"contact at frames {frame_ranges(report.contact_frames)} (bones: {', '.join(bones)}); "
            f"{bent.pairs} splat pairs at frame {BENT_FRAME}, the deepest touching at {bent.deepest:.2f} sigma"
        )

    def save(self):
        from .core.scenes import seed_cube
        from .io import write_splats

        blend = self.out / "demo.blend"
        self.bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
        cube = self.out / "seed_cube.ply"
        write_splats(cube, seed_cube())
        self._files(blend, cube)
        return f"{blend.name} (open it in Blender with the extension enabled), {cube.name}"

    # summary ----------------------------------------------------------------------------------------

    def _files(self, *paths):
        for path in paths:
            if not path.is_file():
                raise DemoError(f"{path} was not written")
            self.summary["files"][path.relative_to(self.out).as_posix()] = path.stat().st_size

    def write_summary(self):
        s = self.summary
        pose, hits, seconds = s["pose_check"], s["collisions"], s["seconds"]
        lines = [
            f"summary (every output is in {s['outputs']}):",
            f"  splats: arm {s['arm_splats']}, environment {s['environment_splats']}",
            f"  binding: weights from {s['binding']['weights_from']}, up to {s['binding']['max_influences']} bones "
            f"per splat",
            f"  posed splats vs splats of the posed mesh, frame {pose['frame']}: PSNR {pose['psnr_db']:.2f} dB "
            f"(centres only: {pose['centres_only_psnr_db']:.2f} dB)",
            f"  renders: {len(s['render']['png'])} PNG + {len(s['render']['exr'])} EXR at "
            f"{s['render']['size'][0]}x{s['render']['size'][1]}, splats on Cycles meshes",
            f"  collisions: contact frames {frame_ranges(hits['contact_frames']) or 'none'}; "
            f"{hits['pairs_at_bent_frame']} splat pairs at frame {BENT_FRAME}",
            f"  files: {len(s['files'])}, {sum(s['files'].values()) / 1e6:.2f} MB in all (sizes in summary.json)",
            "  seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()),
        ]
        path = self.out / "summary.json"
        with atomic_write(path, "w") as f:
            json.dump(s, f, indent=1)
        print("\n".join(lines), flush=True)
