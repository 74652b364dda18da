"""The Blender side of tests/test_blender_bad_input.py (run in each Blender of the version matrix; see
workers/base.py)."""

import contextlib
import hashlib
import importlib.util
import io
import os
from pathlib import Path

import numpy as np

from workers.base import BlenderWorker, point_attribute, splat_total, worker_main

N = 40  # splats of every test object
RENDER_SIZE = (24, 16)
# splat objects with a defect, each named by it (built by Worker.defective), and what is tried on them
DEFECTS = (
    "nan_values",
    "empty",
    "no_rotation",
    "no_scale",
    "no_opacity",
    "no_first_sh",
    "no_middle_sh",
    "int_opacity",
    "zero_scale",
    "nan_location",
)
# the attribute each attribute defect deletes (or, int_opacity, turns into INT), by the object's type: a
# splat mesh's, or a native cloud's (Blender 5.3's Gaussian splats, the form new objects take there)
DEFECT_ATTRIBUTES = {
    "MESH": dict(
        no_rotation="splat_rotation",
        no_scale="splat_log_scale",
        no_opacity="splat_opacity_logit",
        no_first_sh="splat_sh_0",
        no_middle_sh="splat_sh_2",
        int_opacity="splat_opacity_logit",
    ),
    "POINTCLOUD": dict(
        no_rotation="rotation",
        no_scale="scale",
        no_opacity="radiance:base",
        no_first_sh="radiance:sh_0",
        no_middle_sh="radiance:sh_1",
        int_opacity="radiance:base",
    ),
}
OPERATIONS = (
    "export",
    "apply",
    "join_into_good",
    "join_good_into",
    "anim_ply",
    "anim_usd",
    "collide",
    "bind",
    "convert",
    "render",
)
WRONG_KINDS = ("camera", "empty_object", "curve", "armature", "plain_mesh", "nothing")
# Blender attribute type -> (foreach property, components, dtype), for fingerprints of every attribute
FOREACH = {
    "FLOAT": ("value", 1, np.float32),
    "INT": ("value", 1, np.int32),
    "INT8": ("value", 1, np.int32),
    "BOOLEAN": ("value", 1, bool),
    "QUATERNION": ("value", 4, np.float32),
    "FLOAT_VECTOR": ("vector", 3, np.float32),
    "FLOAT2": ("vector", 2, np.float32),
    "INT32_2D": ("value", 2, np.int32),
    "FLOAT_COLOR": ("color", 4, np.float32),
    "BYTE_COLOR": ("color", 4, np.float32),
}


def _plain(value):
    """A custom property's value as plain Python (ID property groups and arrays repr by address)."""
    for convert in ("to_dict", "to_list"):
        if hasattr(value, convert):
            return repr(getattr(value, convert)())
    return repr(value)


# the worker (a separate Python process with bpy) -----------------------------------------------------


class Worker(BlenderWorker):
    steps = (
        "install",
        "defects",
        "wrong_objects",
        "files",
        "animation_files",
        "read_only",
        "from_mesh",
        "rigs",
        "cameras",
        "cli",
    )
    inventory_kinds = (
        "objects",
        "meshes",
        "pointclouds",
        "materials",
        "node_groups",
        "collections",
        "armatures",
        "cameras",
    )

    # helpers -------------------------------------------------------------------------------------

    def splat(self, name, cloud):
        obj, _ = self.module("splat_addon.data").new_splat_object(cloud, name, self.bpy.context.scene.collection)
        return obj

    def defective(self, defect):
        """A splat object of N splats (degree 1) with `defect` (see DEFECTS)."""
        cloud = self.random_cloud(0 if defect == "empty" else N, sh_degree=1, seed=3)
        if defect == "nan_values":
            cloud.positions[3, 1] = np.nan
            cloud.opacity_logits[5] = np.inf
            cloud.sh[7, 2, 0] = np.nan
        obj = self.splat(defect, cloud)
        attrs = obj.data.attributes
        name = DEFECT_ATTRIBUTES[obj.type].get(defect)
        if defect.startswith("no_"):
            attrs.remove(attrs[name])
        elif defect == "int_opacity":
            attrs.remove(attrs[name])
            attrs.new(name, "INT", "POINT")
        elif defect == "zero_scale":
            obj.scale = (0.0, 0.0, 0.0)
        elif defect == "nan_location":
            obj.location = (float("nan"), 0.0, 0.0)
        return obj

    @staticmethod
    def other_form(obj):
        """The form Convert Splat Form turns the splat object `obj` into."""
        return "NATIVE" if obj.type == "MESH" else "MESH"

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
        modifiers, vertex groups, custom properties (its own and its data's: a native binding's armature,
        say) and the bytes of every point attribute: what a refusal must keep."""
        state = self.inventory()
        for obj in self.bpy.data.objects:
            digest = hashlib.sha1(np.array(obj.matrix_world, np.float64).tobytes())
            digest.update(
                repr(
                    (
                        obj.parent and obj.parent.name,
                        [m.name for m in obj.modifiers],
                        [g.name for g in obj.vertex_groups],
                    )
                ).encode()
            )
            for owner in (obj, obj.data) if obj.data is not None else (obj,):
                digest.update(repr(sorted((key, _plain(owner[key])) for key in owner.keys())).encode())
            if obj.type in ("MESH", "POINTCLOUD"):
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
        self.bpy.context.view_layer.update()  # matrix_world of objects just edited
        before = self.fingerprint()
        res = self.call(op, **kw)
        return {**res, "unchanged": before == self.fingerprint(), "frame": self.bpy.context.scene.frame_current}

    def written(self, prefix):
        return sorted(p.name for p in self.out.rglob(f"{prefix}*"))

    def setup_render(self, name, transparent=True):
        scene = self.bpy.context.scene
        render = scene.render
        render.engine = "SPLATWRIGHT"
        scene.splatwright_mesh_engine = "NONE"  # splats alone
        render.resolution_x, render.resolution_y, render.resolution_percentage = *RENDER_SIZE, 100
        self.image_format(render.image_settings, "OPEN_EXR")
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
                good = self.splat("good", self.random_cloud(N, sh_degree=1, seed=4))
                cases[f"{defect} {operation}"] = self.operate(operation, defect, obj, good)
        # the reference for the NaN render: the same object without its broken splats
        self.clear_scene()
        obj = self.defective("nan_values")
        cloud = self.module("splat_addon.data").object_cloud(obj)
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
            res["count"] = splat_total(target) if target.name in bpy.data.objects else None
            res["objects"] = sorted(o.name for o in bpy.context.scene.objects)
        elif operation.startswith("anim"):
            path = f"{name}_####.ply" if operation == "anim_ply" else f"{name}.usd"
            self.select([obj])
            res = self.attempt(
                ops.export_animation,
                filepath=str(self.out / path),
                selected_only=True,
                use_scene_range=False,
                frame_start=1,
                frame_end=2,
            )
        elif operation == "collide":
            res = self.attempt(
                ops.check_collisions,
                object_a=obj.name,
                object_b=good.name,
                use_scene_range=False,
                frame_start=1,
                frame_end=2,
            )
        elif operation == "bind":
            arm = self.armature("Rig")
            self.select([obj], active=arm)
            res = self.attempt(ops.bind_armature)
        elif operation == "convert":
            self.select([obj])
            res = self.attempt(ops.convert_form, form=self.other_form(obj))
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
            good = self.splat("good", self.random_cloud(N, sh_degree=1, seed=4))
            rig = self.armature("Rig")
            obj = self.wrong_object(kind)
            selection = [obj] if obj is not None else []
            runs = {
                "export": (ops.export_file, dict(filepath=str(self.out / f"wrong_{kind}.ply"), selected_only=True)),
                "anim": (
                    ops.export_animation,
                    dict(
                        filepath=str(self.out / f"wrong_{kind}.usd"),
                        selected_only=True,
                        use_scene_range=False,
                        frame_end=2,
                    ),
                ),
                "apply": (ops.apply_transform, {}),
                "join": (ops.join, {}),
                "from_mesh": (ops.from_mesh, dict(max_splats=20)),
                "bind onto splats": (ops.bind_armature, dict(armature="good")),
                "convert": (ops.convert_form, dict(form=self.other_form(good))),
            }
            for name, (op, kw) in runs.items():
                if name == "from_mesh" and kind == "plain_mesh":
                    continue  # a plain mesh is what it converts
                self.select(selection)
                cases[f"{kind} {name}"] = self.attempt(op, **kw)
            self.select(selection, active=rig)
            cases[f"{kind} bind"] = self.attempt(ops.bind_armature)
            self.select([good, *selection], active=good)
            cases[f"{kind} join into splats"] = self.attempt(ops.join)
            if obj is not None:
                cases[f"{kind} collide"] = self.attempt(
                    ops.check_collisions, object_a="good", object_b=obj.name, use_scene_range=False, frame_end=1
                )
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
        for name in ("empty.ply", "truncated.ply", "missing.ply", "cloud.xyz", "folder.ply", "damaged.usdc"):
            cases[f"import {name}"] = self.attempt(ops.import_file, filepath=str(self.work / name))
        cases["import nothing"] = self.attempt(ops.import_file, filepath="")
        self.clear_scene()
        res = self.call(ops.import_file, filepath=str(self.work / "empty.ply"))
        obj = self.bpy.context.active_object
        res["attributes"] = sorted(a.name for a in obj.data.attributes if not a.name.startswith("."))
        res["count"] = splat_total(obj)
        res["export"] = self.call(ops.export_file, filepath=str(self.out / "empty_again.ply"), selected_only=True)
        cases["import empty.ply contents"] = res
        good = self.splat("good", self.random_cloud(N, sh_degree=1, seed=4))
        self.select([good])
        for name, path in (
            ("missing folder", self.out / "nowhere" / "x.ply"),
            ("a folder", self.work / "folder.ply"),
            ("no extension", self.out / "noext"),
        ):
            cases[f"export {name}"] = self.attempt(ops.export_file, filepath=str(path), selected_only=True)
        (self.out / "precious.ply").write_bytes(b"precious")
        self.select([self.defective("nan_values")])
        cases["export NaN over a file"] = self.attempt(
            ops.export_file, filepath=str(self.out / "precious.ply"), selected_only=True
        )
        cases["precious kept"] = (self.out / "precious.ply").read_bytes() == b"precious"
        cases["export NaN dropped"] = self.call(
            ops.export_file, filepath=str(self.out / "dropped.ply"), selected_only=True, drop_invalid=True
        )
        self.select([good])
        cases["export binary usd"] = self.attempt(
            ops.export_file, filepath=str(self.out / "binary.usdc"), selected_only=True
        )
        cases["export binary usd"]["written"] = (self.out / "binary.usdc").exists()
        cases["has pxr"] = importlib.util.find_spec("pxr") is not None
        return cases

    def animation_files(self):
        """Sequences are all or nothing: a frame that fails leaves every file as it was."""
        ops = self.bpy.ops.splat
        obj = self.splat("moving", self.random_cloud(N, sh_degree=1, seed=4))
        obj.keyframe_insert("location", frame=1)
        obj.location = (float("nan"), 0.0, 0.0)  # frames 2 and 3 interpolate towards NaN
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
        cases["nan at frame 2 usd"] = self.attempt(ops.export_animation, filepath=str(seq / "shot.usd"), **kw)
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
        self.splat("splats", self.random_cloud(N, sh_degree=1, seed=4))
        self.mesh("Grid", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(0, 1, 3, 2)])
        self.setup_render("unused")
        self.bpy.context.scene.frame_end = 2
        cases = {"folder": str(folder)}
        for name in ("ro.ply", "ro.usd", "ro.spz", "ro.splat"):
            cases[f"export {name}"] = self.attempt(ops.export_file, filepath=str(folder / name))
        for name in ("ro_####.ply", "ro.usd"):
            cases[f"animation {name}"] = self.attempt(ops.export_animation, filepath=str(folder / name))
        for name, argv in (
            ("export", ["export", str(folder / "ro_####.ply")]),
            ("render", ["render", str(folder / "ro_####.png"), "--frames", "1"]),
            (
                "from-mesh",
                ["from-mesh", str(folder / "ro.ply"), "--objects", "Grid", "--max-splats", "20", "--no-calibrate"],
            ),
            (
                "from-mesh blend",
                ["from-mesh", str(folder / "ro.blend"), "--objects", "Grid", "--max-splats", "20", "--no-calibrate"],
            ),
        ):
            cases[f"cli {name}"] = self.run_cli(argv)
        self.splat("other", self.random_cloud(N, sh_degree=1, seed=5))
        cases["cli collide json"] = self.run_cli(
            ["collide", "splats", "other", "--frames", "1", "--json", str(folder / "ro.json")]
        )
        cases["written"] = sorted(p.name for p in folder.glob("ro*"))
        return cases

    def from_mesh(self):
        """Meshes with nothing to convert: no vertices, no faces, only faces at NaN."""
        cases = {}
        nan = float("nan")
        for name, verts, faces, edges in (
            ("no_vertices", [], [], []),
            ("edges_only", [(0, 0, 0), (1, 0, 0), (1, 1, 0)], [], [(0, 1), (1, 2)]),
            ("nan_faces", [(nan, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)], []),
        ):
            self.clear_scene()
            self.select([self.mesh(name, verts, faces, edges)])
            cases[name] = self.attempt(self.bpy.ops.splat.from_mesh, max_splats=20)
        return cases

    def rigs(self):
        """Armatures without (deforming) bones; vertex groups that match no bone."""
        bpy = self.bpy
        rigging = self.module("splat_addon.rig.armature")
        cases = {}
        splats = self.splat("splats", self.random_cloud(N, sh_degree=1, seed=4))
        for name, bones in (("no bones", ()), ("no deforming bones", (("Ctrl", (0, 0, 0), (0, 0, 1), False),))):
            arm = self.armature(name, bones)
            self.select([splats], active=arm)
            cases[name] = self.attempt(bpy.ops.splat.bind_armature)
        # splats made from a mesh whose vertex groups are named after no bone: weights from the bones
        self.clear_scene()
        grid = self.mesh("Skin", [(x, 0, z) for z in (-1, 0, 1) for x in (-0.5, 0.5)], [(0, 1, 3, 2), (2, 3, 5, 4)])
        grid.vertex_groups.new(name="NotABone").add(list(range(6)), 1.0, "REPLACE")
        made = self.module("splat_addon.convert.from_mesh").from_mesh(
            bpy.context, [grid], max_splats=60, calibrate=False
        )[0]
        arm = self.armature("Rig", (("Lower", (0, 0, -1), (0, 0, 0), True), ("Upper", (0, 0, 0), (0, 0, 1), True)))
        warnings = []
        plans = rigging.bind_armature([made], arm, warn=warnings.append)
        cases["groups match no bone"] = {
            "source": plans[0].source,
            "warnings": warnings,
            "groups": sorted(self.weight_names(made)),
        }
        # the bones renamed and one posed: Blender renames a splat mesh's vertex groups with them (they
        # follow), a native cloud's splat_weight:<bone> attributes then match no bone (they stay put)
        rest = point_attribute(made.data, "position")  # as bound, before any pose
        for bone in arm.data.bones:
            bone.name = "Renamed" + bone.name
        arm.pose.bones["RenamedLower"].rotation_mode = "XYZ"
        arm.pose.bones["RenamedLower"].rotation_euler = (0.7, 0.0, 0.0)
        if made.type == "MESH":
            made.modifiers["Splatwright Display"].show_viewport = False
        depsgraph = bpy.context.evaluated_depsgraph_get()
        evaluated = made.evaluated_get(depsgraph)
        if made.type == "MESH":  # Blender's own Armature modifier's result
            mesh = evaluated.to_mesh()
            blender_co = np.empty(len(mesh.vertices) * 3, np.float32)
            mesh.vertices.foreach_get("co", blender_co)
            evaluated.to_mesh_clear()
        else:  # what Blender draws of the native splats
            blender_co = point_attribute(evaluated.data, "position")
        self.select([made])
        res = self.attempt(
            bpy.ops.splat.export_file,
            filepath=str(self.out / "renamed.ply"),
            selected_only=True,
            axis_forward="Y",
            axis_up="Z",
        )
        cases["bones renamed"] = res
        self.save(
            "renamed", blender_co=blender_co.reshape(-1, 3), rest_co=rest, matrix_world=np.array(made.matrix_world)
        )
        return cases

    @staticmethod
    def weight_names(obj):
        """The bone names a splat object holds weights for: a mesh's vertex groups, a native cloud's
        splat_weight:<bone> attributes."""
        if obj.type == "MESH":
            return [g.name for g in obj.vertex_groups]
        prefix = "splat_weight:"
        return [a.name[len(prefix) :] for a in obj.data.attributes if a.name.startswith(prefix)]

    def cameras(self):
        """Scene cameras the engine cannot render from: an empty, a mesh, a zero or NaN transform."""
        bpy = self.bpy
        scene = bpy.context.scene
        self.splat("splats", self.random_cloud(N, sh_degree=1, seed=4))
        cases = {}
        empty = bpy.data.objects.new("Rig Empty", None)
        scene.collection.objects.link(empty)
        cam = bpy.data.objects["Camera"]
        setups = {
            "empty as camera": lambda: setattr(scene, "camera", empty),
            "splats as camera": lambda: setattr(scene, "camera", bpy.data.objects["splats"]),
            "zero scale camera": lambda: setattr(cam, "scale", (0.0, 0.0, 0.0)),
            "nan camera": lambda: setattr(cam, "location", (0.0, float("nan"), 0.0)),
        }
        for name, setup in setups.items():
            path = self.setup_render(name.replace(" ", "_"))
            setup()
            cases[name] = {**self.attempt(bpy.ops.render.render, write_still=True), "image": path.exists()}
            cases[name]["cli"] = self.run_cli(
                ["render", str(self.out / f"cli_{name.replace(' ', '_')}.png"), "--frames", "1"]
            )
        cases["written"] = self.written("cli_")
        return cases

    def cli(self):
        bpy = self.bpy
        cases = {}
        self.mesh("Grid", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)], [(0, 1, 3, 2)])
        self.splat("a", self.random_cloud(N, sh_degree=1, seed=4))
        self.splat("b", self.random_cloud(N, sh_degree=1, seed=5))
        self.defective("nan_location")
        for name, argv in {
            "psnr nan": ["from-mesh", str(self.out / "f.ply"), "--objects", "Grid", "--target-psnr", "nan"],
            "psnr negative": ["from-mesh", str(self.out / "f.ply"), "--objects", "Grid", "--target-psnr", "-3"],
            "no splats": ["from-mesh", str(self.out / "f.ply"), "--objects", "Grid", "--max-splats", "0"],
            "ply is a folder": ["from-mesh", str(self.work / "folder.ply"), "--objects", "Grid", "--max-splats", "20"],
            "blend is a folder": [
                "from-mesh",
                str(self.work / "folder.blend"),
                "--objects",
                "Grid",
                "--max-splats",
                "20",
            ],
            "sigma inf": ["collide", "a", "b", "--frames", "1", "--sigma", "inf"],
            "min opacity nan": ["collide", "a", "b", "--frames", "1", "--min-opacity", "nan"],
            "min opacity 2": ["collide", "a", "b", "--frames", "1", "--min-opacity", "2"],
            "export nan location": [
                "export",
                str(self.out / "cli_nan.ply"),
                "--frames",
                "1",
                "--objects",
                "nan_location",
            ],
            "collide nan location": ["collide", "a", "nan_location", "--frames", "1"],
        }.items():
            cases[name] = self.run_cli(argv)
        cases["written"] = self.written("cli_") + self.written("f.")
        cases["folders"] = [p.is_dir() for p in (self.work / "folder.ply", self.work / "folder.blend")]
        bpy.context.scene.frame_set(1)
        return cases


if __name__ == "__main__":
    worker_main(Worker)
