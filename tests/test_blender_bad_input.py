"""The Blender extension against wrong and bad input, headless, with the extension installed from its
zip as in test_blender_addon.py.

Every operator (import, export, apply transform, join, animated export, collisions, binding, mesh to
splats), the render engine and the `--command splatwright` handler meet broken splat objects (NaN
values, no splats, each attribute deleted, a wrong attribute type, a zero or NaN transform), objects
of the wrong type, bad paths and files, degenerate meshes, armatures and cameras. A refusal must
cancel with a message naming the problem and leave the scene (objects, meshes, transforms, every
attribute's bytes) and the disk as they were; what is accepted must give a correct, finite result,
judged against references outside the code under test (splat files read back, Blender's own
Armature modifier, a render of the same splats without the broken ones).
"""

import contextlib
import hashlib
import io
import os
from pathlib import Path

import numpy as np
import pytest
from blender_session import BlenderWorker, run_worker, worker_main
from helpers import random_cloud, read

pytestmark = [pytest.mark.blender, pytest.mark.slow]      # one Blender worker for the module: ~3 s

N = 40                                   # splats of every test object
RENDER_SIZE = (24, 16)
# splat objects with a defect, each named by it (built by Worker.defective), and what is tried on them
DEFECTS = ("nan_values", "empty", "no_splat_rotation", "no_splat_log_scale", "no_splat_opacity_logit",
           "no_splat_sh_0", "no_splat_sh_2", "int_opacity", "zero_scale", "nan_location")
OPERATIONS = ("export", "apply", "join_into_good", "join_good_into", "anim_ply", "anim_usd", "collide", "bind",
              "render")
WRONG_KINDS = ("camera", "empty_object", "curve", "armature", "plain_mesh", "nothing")
# Blender attribute type -> (foreach property, components, dtype), for fingerprints of every attribute
FOREACH = {"FLOAT": ("value", 1, np.float32), "INT": ("value", 1, np.int32), "INT8": ("value", 1, np.int32),
           "BOOLEAN": ("value", 1, bool), "QUATERNION": ("value", 4, np.float32),
           "FLOAT_VECTOR": ("vector", 3, np.float32), "FLOAT2": ("vector", 2, np.float32),
           "INT32_2D": ("value", 2, np.int32), "FLOAT_COLOR": ("color", 4, np.float32),
           "BYTE_COLOR": ("color", 4, np.float32)}


# the worker (a separate Python process with bpy) -----------------------------------------------------

class Worker(BlenderWorker):
    steps = ("install", "defects", "wrong_objects", "files", "animation_files", "read_only", "from_mesh", "rigs",
             "cameras", "cli")
    inventory_kinds = ("objects", "meshes", "materials", "node_groups", "collections", "armatures", "cameras")

    # helpers -------------------------------------------------------------------------------------

    def splat(self, name, cloud):
        obj, _ = self.module("splat_addon.data").new_splat_object(cloud, name, self.bpy.context.scene.collection)
        return obj

    def defective(self, defect):
        """A splat object of N splats (degree 1) with `defect` (see DEFECTS)."""
        cloud = random_cloud(0 if defect == "empty" else N, sh_degree=1, seed=3)
        if defect == "nan_values":
            cloud.positions[3, 1] = np.nan
            cloud.opacity_logits[5] = np.inf
            cloud.sh[7, 2, 0] = np.nan
        obj = self.splat(defect, cloud)
        attrs = obj.data.attributes
        if defect.startswith("no_"):
            attrs.remove(attrs[defect[3:]])
        elif defect == "int_opacity":
            attrs.remove(attrs["splat_opacity_logit"])
            attrs.new("splat_opacity_logit", "INT", "POINT")
        elif defect == "zero_scale":
            obj.scale = (0.0, 0.0, 0.0)
        elif defect == "nan_location":
            obj.location = (float("nan"), 0.0, 0.0)
        return obj

    def armature(self, name, bones=(("Bone", (0, 0, -1), (0, 0, 1), True),)):
        """An armature object with bones (name, head, tail, deforms)."""
        bpy = self.bpy
        arm = bpy.data.objects.new(name, bpy.data.armatures.new(name))
        bpy.context.scene.collection.objects.link(arm)
        self.select([arm])
        bpy.ops.object.mode_set(mode="EDIT")
        for bone, head, tail, deform in bones:
            edit = arm.data.edit_bones.new(bone)
            edit.head, edit.tail, edit.use_deform = head, tail, deform
        bpy.ops.object.mode_set(mode="OBJECT")
        return arm

    def mesh(self, name, vertices, faces=(), edges=()):
        bpy = self.bpy
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([tuple(v) for v in vertices], list(edges), [list(f) for f in faces])
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        return obj

    def fingerprint(self):
        """Names of the data (inventory) and, per object, a digest of its transform, parent,
        modifiers, vertex groups and the bytes of every point attribute: what a refusal must keep."""
        state = self.inventory()
        for obj in self.bpy.data.objects:
            digest = hashlib.sha1(np.array(obj.matrix_world, np.float64).tobytes())
            digest.update(repr((obj.parent and obj.parent.name, [m.name for m in obj.modifiers],
                                [g.name for g in obj.vertex_groups])).encode())
            if obj.type == "MESH":
                for attr in sorted(obj.data.attributes, key=lambda a: a.name):
                    digest.update(f"{attr.name}:{attr.data_type}:{attr.domain}".encode())
                    if attr.data_type in FOREACH:
                        prop, width, dtype = FOREACH[attr.data_type]
                        values = np.empty(len(attr.data) * width, dtype)
                        attr.data.foreach_get(prop, values)
                        digest.update(values.tobytes())
            state[f"object {obj.name}"] = digest.hexdigest()
        return state

    def attempt(self, op, **kw):
        """Run an operator; its outcome, whether the scene kept its fingerprint, and the scene frame."""
        self.bpy.context.view_layer.update()          # matrix_world of objects just edited
        before = self.fingerprint()
        res = self.call(op, **kw)
        return {**res, "unchanged": before == self.fingerprint(), "frame": self.bpy.context.scene.frame_current}

    def written(self, prefix):
        return sorted(p.name for p in self.out.rglob(f"{prefix}*"))

    def setup_render(self, name, transparent=True):
        scene = self.bpy.context.scene
        render = scene.render
        render.engine = "SPLATWRIGHT"
        render.resolution_x, render.resolution_y, render.resolution_percentage = *RENDER_SIZE, 100
        render.image_settings.file_format = "OPEN_EXR"
        render.film_transparent = transparent
        render.filepath = str(self.out / name)
        cam = self.bpy.data.objects["Camera"]
        cam.location, cam.rotation_euler, cam.scale = (0.0, -7.0, 0.0), (np.pi / 2, 0.0, 0.0), (1, 1, 1)
        scene.camera = cam
        return self.out / f"{name}.exr"

    def run_cli(self, argv):
        execute = self.module("splat_addon.command").execute
        out, err = io.StringIO(), io.StringIO()
        objects = len(self.bpy.data.objects)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = execute(argv)
        return {"code": code, "stderr": err.getvalue(), "new_objects": len(self.bpy.data.objects) - objects}

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        self.install_extension()
        return {"operators": sorted(n for n in dir(self.bpy.types) if n.startswith("SPLAT_OT_"))}

    def defects(self):
        """Each operation of OPERATIONS on each splat object of DEFECTS, on a fresh scene."""
        bpy = self.bpy
        cases = {}
        for defect in DEFECTS:
            for operation in OPERATIONS:
                self.clear_scene()
                obj = self.defective(defect)
                good = self.splat("good", random_cloud(N, sh_degree=1, seed=4))
                cases[f"{defect} {operation}"] = self.operate(operation, defect, obj, good)
        # the reference for the NaN render: the same object without its broken splats
        self.clear_scene()
        obj = self.defective("nan_values")
        cloud = self.module("splat_addon.data").mesh_to_cloud(obj.data)
        self.clear_scene()
        self.splat("finite", cloud[cloud.finite_mask()])
        self.setup_render("finite_render")
        cases["finite render"] = self.call(bpy.ops.render.render, write_still=True)
        return cases

    def operate(self, operation, defect, obj, good):
        bpy = self.bpy
        ops = bpy.ops.splat
        name = f"{defect}_{operation}"
        if operation == "export":
            self.select([obj])
            res = self.attempt(ops.export_file, filepath=str(self.out / f"{name}.ply"), selected_only=True)
        elif operation == "apply":
            self.select([obj])
            res = self.attempt(ops.apply_transform)
        elif operation in ("join_into_good", "join_good_into"):
            target = good if operation == "join_into_good" else obj
            self.select([good, obj], active=target)
            res = self.attempt(ops.join)
            res["count"] = len(target.data.vertices) if target.name in bpy.data.objects else None
            res["objects"] = sorted(o.name for o in bpy.context.scene.objects)
        elif operation.startswith("anim"):
            path = f"{name}_####.ply" if operation == "anim_ply" else f"{name}.usdc"
            self.select([obj])
            res = self.attempt(ops.export_animation, filepath=str(self.out / path), selected_only=True,
                               use_scene_range=False, frame_start=1, frame_end=2)
        elif operation == "collide":
            res = self.attempt(ops.check_collisions, object_a=obj.name, object_b=good.name,
                               use_scene_range=False, frame_start=1, frame_end=2)
        elif operation == "bind":
            arm = self.armature("Rig")
            self.select([obj], active=arm)
            res = self.attempt(ops.bind_armature)
        else:
            good.hide_render = True
            self.setup_render(name)
            res = self.attempt(bpy.ops.render.render, write_still=True)
        res["written"] = self.written(name)
        return res

    def wrong_objects(self):
        """Each operator with only an object of the wrong type selected (or nothing)."""
        bpy = self.bpy
        ops = bpy.ops.splat
        cases = {}
        for kind in WRONG_KINDS:
            self.clear_scene()
            good = self.splat("good", random_cloud(N, sh_degree=1, seed=4))
            rig = self.armature("Rig")
            obj = self.wrong_object(kind)
            selection = [obj] if obj is not None else []
            runs = {
                "export": (ops.export_file, dict(filepath=str(self.out / f"wrong_{kind}.ply"), selected_only=True)),
                "anim": (ops.export_animation, dict(filepath=str(self.out / f"wrong_{kind}.usdc"),
                                                    selected_only=True, use_scene_range=False, frame_end=2)),
                "apply": (ops.apply_transform, {}),
                "join": (ops.join, {}),
                "from_mesh": (ops.from_mesh, dict(max_splats=20)),
                "bind onto splats": (ops.bind_armature, dict(armature="good")),
            }
            for name, (op, kw) in runs.items():
                if name == "from_mesh" and kind == "plain_mesh":
                    continue                     # a plain mesh is what it converts
                self.select(selection)
                cases[f"{kind} {name}"] = self.attempt(op, **kw)
            self.select(selection, active=rig)
            cases[f"{kind} bind"] = self.attempt(ops.bind_armature)
            self.select([good, *selection], active=good)
            cases[f"{kind} join into splats"] = self.attempt(ops.join)
            if obj is not None:
                cases[f"{kind} collide"] = self.attempt(ops.check_collisions, object_a="good", object_b=obj.name,
                                                        use_scene_range=False, frame_end=1)
            cases[f"{kind} written"] = self.written("wrong_")
        return cases

    def wrong_object(self, kind):
        bpy = self.bpy
        if kind == "camera":
            return bpy.data.objects["Camera"]
        if kind == "empty_object":
            obj = bpy.data.objects.new("Empty", None)
        elif kind == "curve":
            curve = bpy.data.curves.new("Curve", "CURVE")
            curve.splines.new("POLY").points.add(2)
            obj = bpy.data.objects.new("Curve", curve)
        elif kind == "armature":
            return self.armature("NoBones", bones=())
        elif kind == "plain_mesh":
            return self.mesh("Plain", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
        else:
            return None
        bpy.context.scene.collection.objects.link(obj)
        return obj

    def files(self):
        """Import and export against bad paths and files; an empty file is a valid empty cloud."""
        ops = self.bpy.ops.splat
        cases = {}
        for name in ("empty.ply", "truncated.ply", "missing.ply", "cloud.xyz", "folder.ply"):
            cases[f"import {name}"] = self.attempt(ops.import_file, filepath=str(self.work / name))
        cases["import nothing"] = self.attempt(ops.import_file, filepath="")
        self.clear_scene()
        res = self.call(ops.import_file, filepath=str(self.work / "empty.ply"))
        obj = self.bpy.context.active_object
        res["attributes"] = sorted(a.name for a in obj.data.attributes if not a.name.startswith("."))
        res["count"] = len(obj.data.vertices)
        res["export"] = self.call(ops.export_file, filepath=str(self.out / "empty_again.ply"), selected_only=True)
        cases["import empty.ply contents"] = res
        good = self.splat("good", random_cloud(N, sh_degree=1, seed=4))
        self.select([good])
        for name, path in (("missing folder", self.out / "nowhere" / "x.ply"), ("a folder", self.work / "folder.ply"),
                           ("no extension", self.out / "noext")):
            cases[f"export {name}"] = self.attempt(ops.export_file, filepath=str(path), selected_only=True)
        (self.out / "precious.ply").write_bytes(b"precious")
        self.select([self.defective("nan_values")])
        cases["export NaN over a file"] = self.attempt(ops.export_file, filepath=str(self.out / "precious.ply"),
                                                       selected_only=True)
        cases["precious kept"] = (self.out / "precious.ply").read_bytes() == b"precious"
        cases["export NaN dropped"] = self.call(ops.export_file, filepath=str(self.out / "dropped.ply"),
                                                selected_only=True, drop_invalid=True)
        return cases

    def animation_files(self):
        """Sequences are all or nothing: a frame that fails leaves every file as it was."""
        ops = self.bpy.ops.splat
        obj = self.splat("moving", random_cloud(N, sh_degree=1, seed=4))
        obj.keyframe_insert("location", frame=1)
        obj.location = (float("nan"), 0.0, 0.0)         # frames 2 and 3 interpolate towards NaN
        obj.keyframe_insert("location", frame=3)
        self.bpy.context.scene.frame_set(1)
        seq = self.out / "seq"
        seq.mkdir()
        (seq / "shot_0001.ply").write_bytes(b"old frame 1")
        cases = {}
        self.select([obj])
        kw = dict(selected_only=True, use_scene_range=False, frame_start=1, frame_end=3)
        cases["nan at frame 2"] = self.attempt(ops.export_animation, filepath=str(seq / "shot_####.ply"), **kw)
        cases["nan at frame 2 files"] = sorted(p.name for p in seq.iterdir())
        cases["old frame kept"] = (seq / "shot_0001.ply").read_bytes() == b"old frame 1"
        cases["nan at frame 2 usd"] = self.attempt(ops.export_animation, filepath=str(seq / "shot.usdc"), **kw)
        obj.animation_data_clear()
        obj.location = (0.0, 0.0, 0.0)
        (seq / "shot_0002.ply").mkdir()
        cases["folder in the way"] = self.attempt(ops.export_animation, filepath=str(seq / "shot_####.ply"), **kw)
        cases["folder in the way files"] = sorted(p.name for p in seq.iterdir())
        return cases

    def read_only(self):
        """Every writer against a folder it may not write to (root may write anywhere but /sys)."""
        ops = self.bpy.ops.splat
        folder = Path("/sys") if os.geteuid() == 0 else self.work / "read_only"
        self.splat("splats", random_cloud(N, sh_degree=1, seed=4))
        self.mesh("Grid", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(0, 1, 3, 2)])
        self.setup_render("unused")
        self.bpy.context.scene.frame_end = 2
        cases = {"folder": str(folder)}
        for name in ("ro.ply", "ro.usdc", "ro.spz", "ro.splat"):
            cases[f"export {name}"] = self.attempt(ops.export_file, filepath=str(folder / name))
        for name in ("ro_####.ply", "ro.usdc"):
            cases[f"animation {name}"] = self.attempt(ops.export_animation, filepath=str(folder / name))
        for name, argv in (("export", ["export", str(folder / "ro_####.ply")]),
                           ("render", ["render", str(folder / "ro_####.png"), "--frames", "1"]),
                           ("from-mesh", ["from-mesh", str(folder / "ro.ply"), "--objects", "Grid",
                                          "--max-splats", "20"]),
                           ("from-mesh blend", ["from-mesh", str(folder / "ro.blend"), "--objects", "Grid",
                                                "--max-splats", "20"])):
            cases[f"cli {name}"] = self.run_cli(argv)
        self.splat("other", random_cloud(N, sh_degree=1, seed=5))
        cases["cli collide json"] = self.run_cli(["collide", "splats", "other", "--frames", "1",
                                                  "--json", str(folder / "ro.json")])
        cases["written"] = sorted(p.name for p in folder.glob("ro*"))
        return cases

    def from_mesh(self):
        """Meshes with nothing to convert: no vertices, no faces, only faces at NaN."""
        cases = {}
        nan = float("nan")
        for name, verts, faces, edges in (("no_vertices", [], [], []),
                                          ("edges_only", [(0, 0, 0), (1, 0, 0), (1, 1, 0)], [], [(0, 1), (1, 2)]),
                                          ("nan_faces", [(nan, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)], [])):
            self.clear_scene()
            self.select([self.mesh(name, verts, faces, edges)])
            cases[name] = self.attempt(self.bpy.ops.splat.from_mesh, max_splats=20)
        return cases

    def rigs(self):
        """Armatures without (deforming) bones; vertex groups that match no bone."""
        bpy = self.bpy
        rigging = self.module("splat_addon.rigging")
        cases = {}
        splats = self.splat("splats", random_cloud(N, sh_degree=1, seed=4))
        for name, bones in (("no bones", ()), ("no deforming bones", (("Ctrl", (0, 0, 0), (0, 0, 1), False),))):
            arm = self.armature(name, bones)
            self.select([splats], active=arm)
            cases[name] = self.attempt(bpy.ops.splat.bind_armature)
        # splats made from a mesh whose vertex groups are named after no bone: weights from the bones
        self.clear_scene()
        grid = self.mesh("Skin", [(x, 0, z) for z in (-1, 0, 1) for x in (-0.5, 0.5)], [(0, 1, 3, 2), (2, 3, 5, 4)])
        grid.vertex_groups.new(name="NotABone").add(list(range(6)), 1.0, "REPLACE")
        made = self.module("splat_addon.from_mesh").from_mesh(bpy.context, [grid], max_splats=60)[0]
        arm = self.armature("Rig", (("Lower", (0, 0, -1), (0, 0, 0), True), ("Upper", (0, 0, 0), (0, 0, 1), True)))
        warnings = []
        plans = rigging.bind_armature([made], arm, warn=warnings.append)
        cases["groups match no bone"] = {"source": plans[0].source, "warnings": warnings,
                                         "groups": sorted(g.name for g in made.vertex_groups)}
        # a bound object whose groups match no bone once the bones are renamed: it stays put, as the
        # vertices under Blender's own Armature modifier do
        for bone in arm.data.bones:
            bone.name = "Renamed" + bone.name
        arm.pose.bones["RenamedLower"].rotation_mode = "XYZ"
        arm.pose.bones["RenamedLower"].rotation_euler = (0.7, 0.0, 0.0)
        made.modifiers["Splatwright Display"].show_viewport = False
        depsgraph = bpy.context.evaluated_depsgraph_get()
        evaluated = made.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        blender_co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", blender_co)
        evaluated.to_mesh_clear()
        self.select([made])
        res = self.attempt(bpy.ops.splat.export_file, filepath=str(self.out / "renamed.ply"), selected_only=True,
                           axis_forward="Y", axis_up="Z")
        cases["bones renamed"] = res
        self.save("renamed", blender_co=blender_co.reshape(-1, 3), matrix_world=np.array(made.matrix_world))
        return cases

    def cameras(self):
        """Scene cameras the engine cannot render from: an empty, a mesh, a zero or NaN transform."""
        bpy = self.bpy
        scene = bpy.context.scene
        self.splat("splats", random_cloud(N, sh_degree=1, seed=4))
        cases = {}
        empty = bpy.data.objects.new("Rig Empty", None)
        scene.collection.objects.link(empty)
        cam = bpy.data.objects["Camera"]
        setups = {"empty as camera": lambda: setattr(scene, "camera", empty),
                  "mesh as camera": lambda: setattr(scene, "camera", bpy.data.objects["splats"]),
                  "zero scale camera": lambda: setattr(cam, "scale", (0.0, 0.0, 0.0)),
                  "nan camera": lambda: setattr(cam, "location", (0.0, float("nan"), 0.0))}
        for name, setup in setups.items():
            path = self.setup_render(name.replace(" ", "_"))
            setup()
            cases[name] = {**self.attempt(bpy.ops.render.render, write_still=True), "image": path.exists()}
            cases[name]["cli"] = self.run_cli(["render", str(self.out / f"cli_{name.replace(' ', '_')}.png"),
                                               "--frames", "1"])
        cases["written"] = self.written("cli_")
        return cases

    def cli(self):
        bpy = self.bpy
        cases = {}
        self.mesh("Grid", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(0, 1, 3, 2)])
        self.splat("a", random_cloud(N, sh_degree=1, seed=4))
        self.splat("b", random_cloud(N, sh_degree=1, seed=5))
        self.defective("nan_location")
        for name, argv in {
                "psnr nan": ["from-mesh", str(self.out / "f.ply"), "--objects", "Grid", "--target-psnr", "nan"],
                "psnr negative": ["from-mesh", str(self.out / "f.ply"), "--objects", "Grid", "--target-psnr", "-3"],
                "no splats": ["from-mesh", str(self.out / "f.ply"), "--objects", "Grid", "--max-splats", "0"],
                "ply is a folder": ["from-mesh", str(self.work / "folder.ply"), "--objects", "Grid",
                                    "--max-splats", "20"],
                "blend is a folder": ["from-mesh", str(self.work / "folder.blend"), "--objects", "Grid",
                                      "--max-splats", "20"],
                "sigma inf": ["collide", "a", "b", "--frames", "1", "--sigma", "inf"],
                "min opacity nan": ["collide", "a", "b", "--frames", "1", "--min-opacity", "nan"],
                "min opacity 2": ["collide", "a", "b", "--frames", "1", "--min-opacity", "2"],
                "export nan location": ["export", str(self.out / "cli_nan.ply"), "--frames", "1",
                                        "--objects", "nan_location"],
                "collide nan location": ["collide", "a", "nan_location", "--frames", "1"]}.items():
            cases[name] = self.run_cli(argv)
        cases["written"] = self.written("cli_") + self.written("f.")
        cases["folders"] = [p.is_dir() for p in (self.work / "folder.ply", self.work / "folder.blend")]
        bpy.context.scene.frame_set(1)
        return cases


if __name__ == "__main__":
    worker_main(Worker)


# the pytest side -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blender(tmp_path_factory, extension_zip):
    from splatwright.io import write_splats
    work = tmp_path_factory.mktemp("blender_bad")
    write_splats(work / "empty.ply", random_cloud(0, sh_degree=1))
    write_splats(work / "cloud.ply", random_cloud(N, sh_degree=1))
    full = (work / "cloud.ply").read_bytes()
    (work / "truncated.ply").write_bytes(full[: len(full) * 2 // 3])
    (work / "cloud.xyz").write_bytes(full)
    for folder in ("folder.ply", "folder.blend", "read_only"):
        (work / folder).mkdir()
    (work / "read_only").chmod(0o555)
    return run_worker(__file__, work, extension_zip)


def assert_refused(case, *words):
    """Cancelled with an error holding `words`, the scene exactly as it was, the frame restored."""
    assert case["result"] == ["CANCELLED"], case
    assert case["error"] is not None and "Traceback" not in case["error"], case["error"]
    for word in words:
        assert word in case["error"], case["error"]
    assert case["unchanged"], case
    assert case["frame"] == 1


def test_every_operator_is_exercised(blender):
    assert blender.step("install")["operators"] == [
        "SPLAT_OT_apply_transform", "SPLAT_OT_bind_armature", "SPLAT_OT_check_collisions",
        "SPLAT_OT_export_animation", "SPLAT_OT_export_file", "SPLAT_OT_from_mesh", "SPLAT_OT_import_file",
        "SPLAT_OT_join"]


# broken splat objects --------------------------------------------------------------------------------

MISSING = {f"no_{a}": f"no '{a}' point attribute" for a in ("splat_rotation", "splat_log_scale",
                                                           "splat_opacity_logit")}
MISSING.update(no_splat_sh_0="missing [0]", no_splat_sh_2="missing [2]",
               int_opacity="'splat_opacity_logit' is INT on POINT, expected FLOAT")
READERS = ("export", "apply", "join_into_good", "join_good_into", "anim_ply", "anim_usd", "collide", "bind", "render")


@pytest.mark.parametrize("defect", sorted(MISSING))
@pytest.mark.parametrize("operation", READERS)
def test_missing_or_wrong_attributes_are_refused_by_name(blender, defect, operation):
    case = blender.step("defects")[f"{defect} {operation}"]
    assert_refused(case, f"'{defect}'", MISSING[defect])
    assert case["written"] == []


@pytest.mark.parametrize("defect, words", [
    ("zero_scale", ["'zero_scale'", "singular"]),
    ("nan_location", ["'nan_location'", "NaN or Inf"]),
])
@pytest.mark.parametrize("operation", ["export", "apply", "join_into_good", "anim_ply", "anim_usd", "collide"])
def test_degenerate_transforms_are_refused_by_name(blender, defect, words, operation):
    case = blender.step("defects")[f"{defect} {operation}"]
    assert_refused(case, *words)
    assert case["written"] == []


@pytest.mark.parametrize("defect, words", [("zero_scale", ["'zero_scale'", "zero scale"]),
                                           ("nan_location", ["'nan_location'", "NaN or Inf"])])
def test_joining_into_a_degenerate_transform_is_refused(blender, defect, words):
    assert_refused(blender.step("defects")[f"{defect} join_good_into"], *words)


def test_a_nan_transform_binds_and_renders_nothing(blender):
    d = blender.step("defects")
    assert_refused(d["nan_location bind"], "'nan_location'", f"{N} splat centres are NaN")
    assert_refused(d["nan_location render"], "'nan_location'", "NaN or Inf")
    assert d["nan_location render"]["written"] == []


def test_a_zero_scale_object_renders_as_nothing(blender):
    from splatwright.io.exr import read_exr
    case = blender.step("defects")["zero_scale render"]
    assert case["result"] == ["FINISHED"]
    alpha = read_exr(blender.out / "zero_scale_render.exr")["A"]
    assert alpha.shape == RENDER_SIZE[::-1] and np.all(alpha == 0)


@pytest.mark.parametrize("operation, words", [
    ("export", ["nan_values_export.ply", "3 of 40 splats have non-finite values", "positions in 1",
                "opacity_logits in 1", "sh in 1"]),
    ("anim_ply", ["nan_values_anim_ply_0001.ply", "non-finite"]),
    ("anim_usd", ["nan_values_anim_usd.usdc", "non-finite"]),
    ("collide", ["frame 1", "2 splats of 'nan_values'", "NaN"]),
    ("bind", ["'nan_values'", "1 splat centres are NaN"]),
])
def test_nan_values_never_reach_a_file_or_a_binding(blender, operation, words):
    case = blender.step("defects")[f"nan_values {operation}"]
    assert_refused(case, *words)
    assert case["written"] == []


def test_nan_splats_are_left_out_of_a_render(blender):
    from splatwright.io.exr import read_exr
    d = blender.step("defects")
    assert d["nan_values render"]["result"] == ["FINISHED"] and d["finite render"]["result"] == ["FINISHED"]
    image = read_exr(blender.out / "nan_values_render.exr")
    reference = read_exr(blender.out / "finite_render.exr")     # the 37 finite splats alone
    assert reference["A"].max() > 0.3                           # the splats are in view
    for channel in "RGBA":
        assert np.isfinite(image[channel]).all()
        np.testing.assert_allclose(image[channel], reference[channel], rtol=0, atol=1e-6)


def test_an_empty_splat_object_is_a_valid_empty_cloud(blender):
    from splatwright.io.exr import read_exr
    d = blender.step("defects")
    for operation in ("export", "apply", "anim_ply", "anim_usd", "collide", "render"):
        assert d[f"empty {operation}"]["result"] == ["FINISHED"], (operation, d[f"empty {operation}"])
    assert len(read(blender.out / "empty_export.ply")) == 0
    assert [len(read(blender.out / f"empty_anim_ply_000{f}.ply")) for f in (1, 2)] == [0, 0]
    assert len(read(blender.out / "empty_anim_usd.usdc")) == 0
    assert np.all(read_exr(blender.out / "empty_render.exr")["A"] == 0)
    joined = d["empty join_good_into"]
    assert joined["result"] == ["FINISHED"] and joined["count"] == N and "good" not in joined["objects"]
    assert_refused(d["empty join_into_good"], "nothing to join", "empty")
    assert_refused(d["empty bind"], "'empty' has no splats to bind")


# objects of the wrong type ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", WRONG_KINDS)
def test_wrong_objects_are_refused_or_hidden(blender, kind):
    d = blender.step("wrong_objects")
    name = {"camera": "'Camera' (CAMERA)", "empty_object": "'Empty' (EMPTY)", "curve": "'Curve' (CURVE)",
            "armature": "'NoBones' (ARMATURE)", "plain_mesh": "'Plain' (MESH)", "nothing": "nothing is selected"}[kind]
    assert_refused(d[f"{kind} export"], name)
    assert_refused(d[f"{kind} anim"], name)
    for op in ("apply", "join"):                       # poll() hides them: no splat object is active
        assert_refused(d[f"{kind} {op}"], "poll() failed")
    if kind != "plain_mesh":
        assert_refused(d[f"{kind} from_mesh"], "nothing is selected" if kind == "nothing" else "no mesh objects")
    assert_refused(d[f"{kind} bind onto splats"], "'good' is mesh, not an armature")
    assert d[f"{kind} written"] == []
    if kind == "nothing":
        assert_refused(d[f"{kind} bind"], "no splat objects to bind")
        assert_refused(d[f"{kind} join into splats"], "select the splat objects to join")
        return
    short = name.split(" (")[0]
    assert_refused(d[f"{kind} bind"], "no splat objects to bind", short)
    assert_refused(d[f"{kind} join into splats"], "not splat objects", short.strip("'"))
    assert_refused(d[f"{kind} collide"], short, "is not a splat object")


# files and paths -------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, words", [
    ("import truncated.ply", ["truncated.ply"]),
    ("import missing.ply", ["missing.ply", "no such file"]),
    ("import cloud.xyz", ["cloud.xyz", "unknown splat file extension"]),
    ("import folder.ply", ["folder.ply"]),
    ("import nothing", ["no file to import"]),
    ("export missing folder", ["nowhere", "x.ply"]),
    ("export a folder", ["folder.ply", "directory"]),
    ("export no extension", ["noext", "unknown splat file extension"]),
    ("export NaN over a file", ["precious.ply", "non-finite"]),
])
def test_bad_paths_and_files_are_refused(blender, name, words):
    assert_refused(blender.step("files")[name], *words)


def test_export_can_drop_invalid_splats(blender):
    """Asked to, export leaves out exactly the splats that hold NaN/Inf and says how many."""
    case = blender.step("files")["export NaN dropped"]
    assert case["result"] == ["FINISHED"], case
    source = random_cloud(N, sh_degree=1, seed=3)            # as Worker.defective("nan_values") made it
    finite = np.ones(N, bool)
    finite[[3, 5, 7]] = False                                # the splats it gave NaN or Inf
    got = read(blender.out / "dropped.ply")
    np.testing.assert_array_equal(got.opacity_logits, source.opacity_logits[finite])
    np.testing.assert_array_equal(got.log_scales, source.log_scales[finite])


def test_a_failed_export_keeps_the_file_it_would_replace(blender):
    assert blender.step("files")["precious kept"] is True
    assert (blender.out / "precious.ply").read_bytes() == b"precious"


def test_an_empty_file_imports_as_an_empty_splat_object(blender):
    case = blender.step("files")["import empty.ply contents"]
    assert case["result"] == ["FINISHED"] and case["count"] == 0
    assert {"position", "splat_rotation", "splat_log_scale", "splat_opacity_logit", "splat_sh_0",
            "splat_sh_3"} <= set(case["attributes"])
    assert case["export"]["result"] == ["FINISHED"]
    header = (blender.out / "empty_again.ply").read_bytes().split(b"end_header")[0]
    assert b"element vertex 0" in header and b"f_rest_8" in header
    assert len(read(blender.out / "empty_again.ply")) == 0


def test_a_sequence_that_fails_at_a_frame_changes_no_file(blender):
    d = blender.step("animation_files")
    assert_refused(d["nan at frame 2"], "frame 2", "'moving'", "NaN or Inf")
    assert d["nan at frame 2 files"] == ["shot_0001.ply"]          # no new frame, no temporary file
    assert d["old frame kept"] is True
    assert_refused(d["nan at frame 2 usd"], "frame 2", "'moving'")
    assert_refused(d["folder in the way"], "shot_0002.ply", "folder")
    assert d["folder in the way files"] == ["shot_0001.ply", "shot_0002.ply"]
    assert (blender.out / "seq" / "shot_0001.ply").read_bytes() == b"old frame 1"


@pytest.mark.parametrize("name", ["export ro.ply", "export ro.usdc", "export ro.spz", "export ro.splat",
                                  "animation ro_####.ply", "animation ro.usdc"])
def test_a_read_only_folder_is_refused(blender, name):
    assert_refused(blender.step("read_only")[name], blender.step("read_only")["folder"], "ermission denied")


@pytest.mark.parametrize("name, words", [
    ("export", ["ermission denied"]),
    ("render", ["cannot save", "ro_0001.png"]),
    ("from-mesh", ["ro.ply", "ermission denied"]),
    ("from-mesh blend", ["ro.blend"]),
    ("collide json", ["ro.json", "ermission denied"]),
])
def test_cli_jobs_into_a_read_only_folder_fail_cleanly(blender, name, words):
    run = blender.step("read_only")[f"cli {name}"]
    assert run["code"] == 1 and run["new_objects"] == 0, run
    assert "Traceback" not in run["stderr"] and "internal error" not in run["stderr"]
    for word in words:
        assert word in run["stderr"], run["stderr"]
    assert blender.step("read_only")["written"] == []


# meshes, rigs, cameras -------------------------------------------------------------------------------

@pytest.mark.parametrize("name, words", [
    ("no_vertices", ["'no_vertices' has no faces", "0 vertices"]),
    ("edges_only", ["'edges_only' has no faces"]),
    ("nan_faces", ["'nan_faces'", "no face with positive area"]),
])
def test_meshes_without_a_surface_are_refused(blender, name, words):
    assert_refused(blender.step("from_mesh")[name], *words)


@pytest.mark.parametrize("name", ["no bones", "no deforming bones"])
def test_armatures_without_deforming_bones_are_refused(blender, name):
    assert_refused(blender.step("rigs")[name], f"armature '{name}' has no deforming bones")


def test_source_groups_that_match_no_bone_fall_back_with_a_warning(blender):
    case = blender.step("rigs")["groups match no bone"]
    assert case["source"] == "bones"
    assert len(case["warnings"]) == 1 and "'Skin'" in case["warnings"][0] and "no vertex group" in case["warnings"][0]
    assert case["groups"] == ["Lower", "Upper"]


def test_groups_that_match_no_bone_stay_put_as_in_blender(blender):
    case = blender.step("rigs")["bones renamed"]
    assert case["result"] == ["FINISHED"]
    d = blender.npz("renamed")
    expected = d["blender_co"].astype(np.float64) @ d["matrix_world"][:3, :3].T + d["matrix_world"][:3, 3]
    got = read(blender.out / "renamed.ply").positions
    np.testing.assert_allclose(got, expected, atol=1e-6)


@pytest.mark.parametrize("name, words", [
    ("empty as camera", ["'Rig Empty' is empty, not a camera object"]),
    ("mesh as camera", ["'splats' is mesh, not a camera object"]),
    ("zero scale camera", ["'Camera'", "zero scale"]),
    ("nan camera", ["'Camera'", "NaN or Inf"]),
])
def test_cameras_the_engine_cannot_use_are_refused(blender, name, words):
    case = blender.step("cameras")[name]
    assert case["result"] == ["CANCELLED"] and not case["image"]
    assert "internal error" not in case["error"]
    for word in words:
        assert word in case["error"], case["error"]
        assert word in case["cli"]["stderr"], case["cli"]["stderr"]
    assert case["cli"]["code"] == 1


def test_refused_renders_write_no_image(blender):
    assert blender.step("cameras")["written"] == []


# the command -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, words", [
    ("psnr nan", ["--target-psnr", "nan"]),
    ("psnr negative", ["--target-psnr", "-3"]),
    ("no splats", ["max_splats must be at least 1"]),
    ("ply is a folder", ["folder.ply"]),
    ("blend is a folder", ["folder.blend"]),
    ("sigma inf", ["sigma", "finite", "inf"]),
    ("min opacity nan", ["minimum opacity", "nan"]),
    ("min opacity 2", ["minimum opacity", "between 0 and 1"]),
    ("export nan location", ["'nan_location'", "NaN or Inf"]),
    ("collide nan location", ["'nan_location'", "NaN or Inf"]),
])
def test_cli_refuses_bad_values_and_leaves_no_objects(blender, name, words):
    run = blender.step("cli")[name]
    assert run["code"] == 1, run
    assert "Traceback" not in run["stderr"] and "internal error" not in run["stderr"]
    for word in words:
        assert word in run["stderr"], run["stderr"]
    assert run["new_objects"] == 0


def test_cli_refusals_write_nothing(blender):
    res = blender.step("cli")
    assert res["written"] == [] and res["folders"] == [True, True]
