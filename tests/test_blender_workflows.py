"""Blender workflows, headless: mesh to splats, animated export, the `blender -b` command and the
demo rig, with the extension installed from its zip as in test_blender_addon.py.

One worker process (this file run as a script) does every Blender-side step and saves what Blender
itself reports (evaluated meshes, UVs, colour attributes, image pixels, matrices per frame) next to
what the extension produced. The tests judge the outputs against references computed here in
float64 from those Blender numbers: barycentric surface points, an independent bilinear texture
lookup and sRGB curve, object matrices per frame, and OpenUSD read with pxr directly.
"""

import contextlib
import io
import json

import numpy as np
import pytest
from blender_session import MODULE, BlenderWorker, run_worker, worker_main
from helpers import linear_to_srgb, random_cloud, read, srgb_to_linear

pytestmark = [pytest.mark.blender, pytest.mark.slow]      # one Blender worker for the module

C0 = 0.28209479177387814
# file (x, y, z) -> Blender (x, z, -y): the default export axes are its inverse
DEFAULT_AXES = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
TEXTURE_SIZE = (7, 5)          # width, height: small, so every splat sees texel boundaries
PLANE_TRANSFORM = dict(location=(1.0, -2.0, 0.5), rotation_euler=(0.4, -0.3, 0.9), scale=(2.0, 0.5, 1.5))
BUDGETS = (400, 37)
MATERIAL_COLORS = ((0.8, 0.1, 0.05), (0.02, 0.6, 0.1), (0.1, 0.2, 0.9))
ANIM = {1: dict(location=(0.0, 0.0, 0.0), rotation_euler=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0)),
        4: dict(location=(0.5, -1.0, 2.0), rotation_euler=(0.3, 0.0, 1.1), scale=(1.5, 1.5, 1.5))}


# the worker (a separate Python process with bpy) -----------------------------------------------------

def srgb_bytes(rng, shape):
    return rng.integers(0, 256, shape) / 255.0


def grid_vertices(nx=4, ny=3, size=(2.0, 1.5), wobble=0.0):
    """(nx+1)(ny+1) vertices of a grid in the surface z = wobble sin(2x) cos(3y), row by row."""
    xs, ys = np.meshgrid(np.linspace(-size[0] / 2, size[0] / 2, nx + 1),
                         np.linspace(-size[1] / 2, size[1] / 2, ny + 1))
    x, y = xs.ravel(), ys.ravel()
    return np.column_stack([x, y, wobble * np.sin(2 * x) * np.cos(3 * y)])


def skewed_uv(p):
    """UVs that are not a plain projection and reach below 0 (the texture repeats)."""
    return np.column_stack([0.1 + 0.6 * p[:, 0] + 0.1 * p[:, 1], 0.55 + 0.5 * p[:, 1] - 0.05 * p[:, 0]])


class Worker(BlenderWorker):
    steps = ("install", "textured", "colors", "errors", "demo_rig", "rest_pose", "target_psnr", "animation",
             "frame_names", "cli", "reregister")

    # helpers -------------------------------------------------------------------------------------

    def grid(self, name, nx=4, ny=3, size=(2.0, 1.5), uv=None, wobble=0.0):
        """A grid of quads in the z = wobble * f(x, y) surface with per-loop UVs."""
        bpy = self.bpy
        verts = grid_vertices(nx, ny, size, wobble)
        faces = [[j * (nx + 1) + i, j * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i]
                 for j in range(ny) for i in range(nx)]
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata(verts.tolist(), [], faces)
        layer = mesh.uv_layers.new(name="UVMap")
        loop_verts = np.array([v for f in faces for v in f])
        uvs = verts[loop_verts, :2] if uv is None else uv(verts[loop_verts])
        layer.uv.foreach_set("vector", np.asarray(uvs, np.float32).ravel())
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        return obj

    def material(self, name, color=(0.8, 0.8, 0.8), link=None):
        """A Principled material; link(nodes) returns an output socket to feed Base Color."""
        mat = self.bpy.data.materials.new(name)
        if self.bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*color, 1.0)
        if link is not None:
            mat.node_tree.links.new(link(mat.node_tree.nodes), bsdf.inputs["Base Color"])
        return mat

    def image(self, name, pixels, float_buffer=False):
        h, w = pixels.shape[:2]
        img = self.bpy.data.images.new(name, w, h, float_buffer=float_buffer)
        img.pixels.foreach_set(np.asarray(pixels, np.float32).ravel())
        back = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(back)
        return img, back.reshape(h, w, 4)

    def source_dump(self, obj):
        """What Blender says about the evaluated mesh: vertices, loop triangles, UVs, colours."""
        depsgraph = self.bpy.context.evaluated_depsgraph_get()
        ev = obj.evaluated_get(depsgraph)
        mesh = ev.to_mesh()
        try:
            mesh.calc_loop_triangles()
            lt = mesh.loop_triangles
            arrays = {}
            for key, prop, width, dtype in (("tri_verts", "vertices", 3, np.int32),
                                            ("tri_loops", "loops", 3, np.int32),
                                            ("tri_poly", "polygon_index", 1, np.int32),
                                            ("tri_mat", "material_index", 1, np.int32)):
                a = np.empty(len(lt) * width, dtype)
                lt.foreach_get(prop, a)
                arrays[key] = a.reshape(len(lt), width) if width > 1 else a
            co = np.empty(len(mesh.vertices) * 3, np.float32)
            mesh.vertices.foreach_get("co", co)
            arrays["co"] = co.reshape(-1, 3)
            if mesh.uv_layers.active is not None:
                uv = np.empty(len(mesh.loops) * 2, np.float32)
                mesh.uv_layers.active.uv.foreach_get("vector", uv)
                arrays["uv"] = uv.reshape(-1, 2)
            for attr in mesh.color_attributes:
                c = np.empty(len(attr.data) * 4, np.float32)
                attr.data.foreach_get("color", c)
                arrays[f"color_{attr.name}"] = c.reshape(-1, 4)
            return arrays
        finally:
            ev.to_mesh_clear()

    def splat_dump(self, obj):
        mesh = obj.data
        n = len(mesh.vertices)
        arrays = {}
        props = {"FLOAT": ("value", 1), "INT": ("value", 1), "FLOAT_VECTOR": ("vector", 3),
                 "QUATERNION": ("value", 4)}
        for attr in mesh.attributes:
            if attr.domain == "POINT" and attr.data_type in props and not attr.name.startswith("."):
                prop, width = props[attr.data_type]
                values = np.empty(n * width, np.int32 if attr.data_type == "INT" else np.float32)
                attr.data.foreach_get(prop, values)
                arrays[attr.name] = values.reshape(n, width)
        return arrays

    def convert(self, objects, **kw):
        """Run from_mesh on `objects`; returns (result, the new active object or None)."""
        self.select(objects)
        before = set(self.bpy.data.objects)
        res = self.call(self.bpy.ops.splat.from_mesh, **kw)
        created = [o for o in self.bpy.data.objects if o not in before]
        return res, created

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        return {"operators": [hasattr(bpy.types, n) for n in ("SPLAT_OT_from_mesh", "SPLAT_OT_export_animation")],
                "command_registered": self.module("splat_addon.command")._handle is not None,
                "convert_menu": self.menu_entries("VIEW3D_MT_object_convert")}

    def textured(self):
        bpy = self.bpy
        rng = np.random.default_rng(1)
        res = {}
        w, h = TEXTURE_SIZE
        cases = {"srgb": (srgb_bytes(rng, (h, w, 4)), False), "float": (rng.uniform(0, 1, (h, w, 4)), True)}
        for name, (pixels, is_float) in cases.items():
            img, stored = self.image(f"tex_{name}", pixels, float_buffer=is_float)

            def texture(nodes, img=img):
                node = nodes.new("ShaderNodeTexImage")
                node.image = img
                return node.outputs["Color"]
            obj = self.grid(f"plane_{name}", wobble=0.2, uv=skewed_uv)
            obj.data.materials.append(self.material(f"mat_{name}", (0.3, 0.3, 0.3), texture))
            for key, value in PLANE_TRANSFORM.items():
                setattr(obj, key, value)
            bpy.context.view_layer.update()
            counts = []
            for budget in BUDGETS:
                op, created = self.convert([obj], max_splats=budget)
                counts.append(len(created[0].data.vertices) if created else None)
                res[f"{name}_{budget}"] = op
                if budget == BUDGETS[0]:
                    splats = created[0]
                    selected = sorted(o.name for o in bpy.context.selected_objects)
            self.save(f"textured_{name}", texels=stored, splat_matrix=np.array(splats.matrix_world),
                      source_matrix=np.array(obj.matrix_world), **self.source_dump(obj), **self.splat_dump(splats))
            res[name] = {"counts": counts, "colorspace": img.colorspace_settings.name, "is_float": img.is_float,
                         "source": json.loads(splats.data["splatwright_source"]),
                         "modifiers": [m.name for m in splats.modifiers], "name": splats.name,
                         "selected": selected}
        # modifiers applied: an Array modifier doubles the surface
        cube = self.grid("arrayed", nx=2, ny=2)
        mod = cube.modifiers.new("Array", "ARRAY")
        mod.count, mod.relative_offset_displace = 2, (1.5, 0.0, 0.0)
        cube.data.materials.append(self.material("plain", (0.2, 0.5, 0.8)))
        op, created = self.convert([cube], max_splats=300)
        res["arrayed"] = {**op, "original_faces": len(cube.data.polygons),
                          "source": json.loads(created[0].data["splatwright_source"])}
        self.save("arrayed", **self.source_dump(cube), **self.splat_dump(created[0]))
        return res

    def colors(self):
        bpy = self.bpy
        rng = np.random.default_rng(2)
        res = {}
        # a corner colour attribute feeding Base Color through a Color Attribute node
        painted = self.grid("painted", wobble=0.1)
        attr = painted.data.color_attributes.new("Paint", "BYTE_COLOR", "CORNER")
        attr.data.foreach_set("color", srgb_bytes(rng, (len(attr.data), 4)).astype(np.float32).ravel())
        painted.data.color_attributes.new("Other", "FLOAT_COLOR", "POINT")      # not the one the material names

        def paint(nodes):
            node = nodes.new("ShaderNodeVertexColor")
            node.layer_name = "Paint"
            return node.outputs["Color"]
        painted.data.materials.append(self.material("painted", (0.1, 0.1, 0.1), paint))
        op, created = self.convert([painted], max_splats=300)
        res["painted"] = op
        self.save("painted", **self.source_dump(painted), **self.splat_dump(created[0]))
        # no material: the render colour attribute (point domain, float)
        bare = self.grid("bare")
        attr = bare.data.color_attributes.new("Tint", "FLOAT_COLOR", "POINT")
        attr.data.foreach_set("color", rng.uniform(0, 1, (len(attr.data), 4)).astype(np.float32).ravel())
        op, created = self.convert([bare], max_splats=300)
        res["bare"] = op
        self.save("bare", **self.source_dump(bare), **self.splat_dump(created[0]))
        # one material per face, plain values
        multi = self.grid("multi", nx=3, ny=3)
        for i, color in enumerate(MATERIAL_COLORS):
            multi.data.materials.append(self.material(f"multi_{i}", color))
        multi.data.polygons.foreach_set("material_index", (np.arange(9) * 7 % 3).astype(np.int32))
        multi.data.update()
        op, created = self.convert([multi], max_splats=500)
        res["multi"] = op
        self.save("multi", **self.source_dump(multi), **self.splat_dump(created[0]))
        # a Base Color fed by a node the converter does not follow: warned, the socket's value used
        warnings = []

        def rgb(nodes):
            return nodes.new("ShaderNodeRGB").outputs[0]
        look = self.module("splat_addon.from_mesh").material_appearance(
            self.material("odd", (0.25, 0.5, 0.75), rgb), warnings.append)
        res["odd"] = {"warnings": warnings, "base": list(look.material.base_color)}
        # an image whose file is missing has no pixels: warned, the base colour used
        missing = bpy.data.images.new("missing", 4, 4)
        missing.source, missing.filepath = "FILE", str(self.work / "no_such_texture.png")

        def texture(nodes):
            node = nodes.new("ShaderNodeTexImage")
            node.image = missing
            return node.outputs["Color"]
        warnings = []
        look = self.module("splat_addon.from_mesh").material_appearance(
            self.material("lost", (0.5, 0.25, 0.125), texture), warnings.append)
        res["missing image"] = {"warnings": warnings, "base": list(look.material.base_color),
                                "texture": look.material.texture is not None}
        # a NaN vertex: the faces around it get no splats, the rest converts, nothing is NaN
        broken = self.grid("broken")
        co = np.empty(len(broken.data.vertices) * 3, np.float32)
        broken.data.vertices.foreach_get("co", co)
        co[3 * 6 + 2] = np.nan
        broken.data.vertices.foreach_set("co", co)
        broken.data.update()
        op, created = self.convert([broken], max_splats=200)
        res["nan vertex"] = op
        self.save("nan_vertex", **self.splat_dump(created[0]))
        return res

    def errors(self):
        bpy = self.bpy
        cases = {}
        good = self.grid("good")
        empty = bpy.data.objects.new("empty_mesh", bpy.data.meshes.new("empty_mesh"))
        empty.data.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [])
        flat = bpy.data.objects.new("collapsed", bpy.data.meshes.new("collapsed"))
        flat.data.from_pydata([(0, 0, 0), (1, 0, 0), (2, 0, 0)], [], [(0, 1, 2)])
        for obj in (empty, flat):
            bpy.context.scene.collection.objects.link(obj)
        op, created = self.convert([good], max_splats=50)
        splat_obj = created[0]
        for name, objects in (("camera", [bpy.data.objects["Camera"]]), ("empty mesh", [empty]),
                              ("good and empty", [good, empty]), ("zero-area faces", [flat]),
                              ("splat object", [splat_obj]), ("nothing", [])):
            self.select(objects)
            before = self.inventory()
            res = self.call(bpy.ops.splat.from_mesh, max_splats=50)
            cases[name] = {**res, "unchanged": before == self.inventory()}
        self.select([good, bpy.data.objects["Camera"]])
        res, created = self.convert([good, bpy.data.objects["Camera"]], max_splats=50)
        cases["good and camera"] = {**res, "created": [o.name for o in created]}
        return cases

    def demo_rig(self):
        bpy = self.bpy
        scene = bpy.context.scene
        rig = self.module("splat_addon.demo_rig").build_demo_rig(scene, environment_splats=3000)
        body, arm = rig.body, rig.armature
        mesh = body.data
        weights = np.zeros((len(mesh.vertices), len(arm.data.bones)))
        names = [b.name for b in arm.data.bones]
        for group in body.vertex_groups:
            for i in range(len(mesh.vertices)):
                try:
                    weights[i, names.index(group.name)] = group.weight(i)
                except RuntimeError:       # vertex not in the group
                    pass
        rest = np.array([tuple(v.co) for v in mesh.vertices])
        scene.frame_set(12)
        posed = self.source_dump(body)["co"]
        deform = {b.name: np.array(arm.pose.bones[b.name].matrix) @ np.linalg.inv(np.array(b.matrix_local))
                  for b in arm.data.bones}
        self.save("demo_rig", weights=weights, rest=rest, posed=posed,
                  deform=np.stack([deform[n] for n in names]), body_matrix=np.array(body.matrix_world),
                  arm_matrix=np.array(arm.matrix_world))
        scene.frame_set(1)
        env = rig.environment
        return {"bones": names, "parents": [b.parent.name if b.parent else None for b in arm.data.bones],
                "groups": [g.name for g in body.vertex_groups],
                "modifiers": [(m.type, m.object.name if m.type == "ARMATURE" else None) for m in body.modifiers],
                "frames": [scene.frame_start, scene.frame_end], "camera": scene.camera.name,
                "light": rig.light.type, "materials": [m.name for m in mesh.materials],
                "textured": any(n.bl_idname == "ShaderNodeTexImage"
                                for m in mesh.materials for n in m.node_tree.nodes),
                "environment": {"splat": self.module("splat_addon.data").is_splat_object(env),
                                "count": len(env.data.vertices), "source": json.loads(env.data["splatwright_source"])},
                "animated": arm.animation_data is not None and arm.animation_data.action is not None}

    def rest_pose(self):
        bpy = self.bpy
        scene = bpy.context.scene
        rig = self.module("splat_addon.demo_rig").build_demo_rig(scene, environment_splats=0)
        scene.frame_set(12)
        rest = np.array([tuple(v.co) for v in rig.body.data.vertices])
        posed = self.source_dump(rig.body)
        res = {}
        for key, use_rest in (("rest", True), ("posed", False)):
            op, created = self.convert([rig.body], max_splats=800, use_rest_pose=use_rest)
            res[key] = {**op, "source": json.loads(created[0].data["splatwright_source"])}
            self.save(f"rig_{key}", **self.splat_dump(created[0]))
        res["pose_position"] = rig.armature.data.pose_position
        self.save("rig_mesh", rest=rest, posed=posed["co"], tri_verts=posed["tri_verts"])
        return res

    def target_psnr(self):
        obj = self.grid("quality", nx=2, ny=2)
        rng = np.random.default_rng(3)
        img, _ = self.image("quality_tex", srgb_bytes(rng, (4, 4, 4)))

        def texture(nodes):
            node = nodes.new("ShaderNodeTexImage")
            node.image = img
            return node.outputs["Color"]
        obj.data.materials.append(self.material("quality", link=texture))
        op, created = self.convert([obj], mode="QUALITY", target_psnr=28.0, max_splats=4000)
        return {**op, "count": len(created[0].data.vertices) if created else None}

    def animated_splats(self, name="moving"):
        """A splat object imported with identity axes, keyed at frames 1 and 4."""
        bpy = self.bpy
        bpy.ops.splat.import_file(filepath=str(self.work / "cloud.ply"), axis_forward="Y", axis_up="Z")
        obj = bpy.context.active_object
        obj.name = name
        for frame, values in ANIM.items():
            for key, value in values.items():
                setattr(obj, key, value)
                obj.keyframe_insert(key, frame=frame)
        return obj

    def matrices(self, obj, frames):
        scene = self.bpy.context.scene
        out = {}
        for f in frames:
            scene.frame_set(f)
            out[str(f)] = np.array(obj.matrix_world).tolist()
        return out

    def animation(self):
        bpy = self.bpy
        scene = bpy.context.scene
        obj = self.animated_splats()
        res = {"matrices": self.matrices(obj, range(1, 5))}
        scene.frame_set(3)
        self.select([obj])
        exp = bpy.ops.splat.export_animation
        (self.out / "seq").mkdir()
        res["ply"] = self.call(exp, filepath=str(self.out / "seq" / "anim_####.ply"), use_scene_range=False,
                               frame_start=2, frame_end=4)
        res["frame_after"] = scene.frame_current
        (self.out / "plain").mkdir()
        scene.frame_start, scene.frame_end, scene.frame_step = 1, 3, 2
        res["plain"] = self.call(exp, filepath=str(self.out / "plain" / "anim.ply"))
        scene.render.fps, scene.render.fps_base = 30, 1.001          # NTSC 29.97
        res["usd"] = self.call(exp, filepath=str(self.out / "anim.usdc"), use_scene_range=False,
                               frame_start=1, frame_end=4)
        scene.render.fps, scene.render.fps_base = 24, 1.0
        res["usd_selected"] = self.call(exp, filepath=str(self.out / "anim_sel.usda"), use_scene_range=False,
                                        frame_start=1, frame_end=2, selected_only=True)
        bad = {}
        for name, kw in (("missing folder", dict(filepath=str(self.out / "nowhere" / "a.ply"))),
                         ("backwards", dict(filepath=str(self.out / "never.ply"), use_scene_range=False,
                                            frame_start=5, frame_end=2)),
                         ("unknown extension", dict(filepath=str(self.out / "never.xyz")))):
            bad[name] = self.call(exp, **kw)
        self.select([bpy.data.objects["Camera"]])
        bad["not splats"] = self.call(exp, filepath=str(self.out / "never2.ply"), selected_only=True)
        bad["written"] = sorted(p.name for pattern in ("never*", "nowhere*") for p in self.out.glob(pattern))
        res["bad"] = bad
        return res

    def frame_names(self):
        frame_path = self.module("splat_addon.animation").frame_path
        cases = [("/a/shot_####.ply", 7), ("/a/shot.ply", 7), ("/a/shot_##.ply", 123), ("/a/v#_f###.spz", 5),
                 ("/a/shot_####.ply", -3), ("/a/shot.ply", 12345), ("/a/shot", 2)]
        return {"names": [[p, f, str(frame_path(p, f))] for p, f in cases]}

    def cli(self):
        bpy = self.bpy
        scene = bpy.context.scene
        execute = self.module("splat_addon.command").execute
        obj = self.animated_splats()
        grid = self.grid("Grid", wobble=0.2)
        grid.location = (0.0, 3.0, 0.0)
        grid.data.materials.append(self.material("grid", (0.7, 0.3, 0.1)))
        res = {"matrices": self.matrices(obj, range(1, 5)), "grid_matrix": np.array(grid.matrix_world).tolist()}
        scene.frame_set(2)
        render = scene.render
        render.resolution_x, render.resolution_y, render.resolution_percentage = 32, 24, 100
        render.image_settings.file_format = "PNG"
        render.filepath = "//untouched_"
        cam = bpy.data.objects["Camera"]
        cam.location, cam.rotation_euler = (0.0, -8.0, 1.0), (1.45, 0.0, 0.0)
        scene.camera = cam
        (self.out / "cli").mkdir()
        d = self.out / "cli"
        runs = {
            "export ply": ["export", str(d / "seq_####.ply"), "--frames", "1-3"],
            "export usd": ["export", str(d / "anim"), "--format", "usd", "--frames", "2-4", "--objects", "moving"],
            "export step": ["export", str(d / "step.ply"), "--frames", "1-4:3", "--objects", "moving"],
            "export axes": ["export", str(d / "axes.ply"), "--frames", "4", "--axis-forward", "Y", "--axis-up", "Z"],
            "backwards": ["export", str(d / "x.ply"), "--frames", "3-1"],
            "not frames": ["export", str(d / "x.ply"), "--frames", "a-b"],
            "unknown object": ["export", str(d / "x.ply"), "--objects", "moving,Nope"],
            "not splats": ["export", str(d / "x.ply"), "--objects", "Grid"],
            "missing folder": ["export", str(d / "nowhere" / "x.ply"), "--frames", "1"],
            "format clash": ["export", str(d / "x.usdc"), "--format", "ply"],
            "unknown extension": ["export", str(d / "x.xyz")],
            "no output": ["export"],
            "unknown verb": ["frobnicate"],
            "render": ["render", str(d / "frame_####.png"), "--frames", "1-2"],
            "render unknown object": ["render", str(d / "none_"), "--frames", "4", "--objects", "moving_missing"],
            "render no hash": ["render", str(d / "plain_"), "--frames", "4"],
            "render exr": ["render", str(d / "deep_####.exr"), "--frames", "3"],
            "from-mesh ply": ["from-mesh", str(d / "grid.ply"), "--objects", "Grid", "--max-splats", "250"],
            "from-mesh blend": ["from-mesh", str(d / "grid.blend"), "--objects", "Grid", "--max-splats", "100"],
            "from-mesh camera": ["from-mesh", str(d / "cam.ply"), "--objects", "Camera"],
            "from-mesh unknown": ["from-mesh", str(d / "cam.ply"), "--objects", "Nope"],
            "from-mesh bad extension": ["from-mesh", str(d / "grid.xyz"), "--objects", "Grid"],
        }
        outcomes = {}
        for name, argv in runs.items():
            out, err = io.StringIO(), io.StringIO()
            before = len(bpy.data.objects)
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = execute(argv)
            outcomes[name] = {"code": code, "stdout": out.getvalue(), "stderr": err.getvalue(),
                              "new_objects": len(bpy.data.objects) - before}
        res["after"] = {"frame": scene.frame_current, "engine": render.engine, "filepath": render.filepath,
                        "hidden": [o.name for o in scene.objects if o.hide_render],
                        "format": render.image_settings.file_format}
        cam.data.type = "PANO"
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            outcomes["render panoramic"] = {"code": execute(["render", str(d / "pano_"), "--frames", "1"]),
                                            "stderr": err.getvalue()}
        cam.data.type = "PERSP"
        scene.camera = None
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            outcomes["render no camera"] = {"code": execute(["render", str(d / "nocam_"), "--frames", "1"]),
                                            "stderr": err.getvalue()}
        scene.camera = cam
        res["outcomes"] = outcomes
        res["files"] = sorted(p.name for p in d.iterdir())
        return res

    def reregister(self):
        import addon_utils
        for _ in range(2):
            addon_utils.disable(MODULE, default_set=True)
            addon_utils.enable(MODULE, default_set=True)
        command = self.module("splat_addon.command")
        on = command._handle is not None
        addon_utils.disable(MODULE, default_set=True)
        off = command._handle is not None          # unregister() gave the command back
        left = [n for n in dir(self.bpy.types) if n.startswith("SPLAT_")]
        addon_utils.enable(MODULE, default_set=True)
        return {"enabled": on, "disabled_handle": off, "types_left": left,
                "re_enabled": self.module("splat_addon.command")._handle is not None}


# the pytest side ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blender(tmp_path_factory, extension_zip):
    from splatwright.io import write_splats
    work = tmp_path_factory.mktemp("workflows")
    write_splats(work / "cloud.ply", random_cloud(150, sh_degree=1, seed=5))
    return run_worker(__file__, work, extension_zip)


def bilinear_blender(pixels, uv):
    """Blender's Linear interpolation with Repeat: texel centres at (i + 0.5) / size, row 0 at v = 0."""
    h, w = pixels.shape[:2]
    x, y = uv[:, 0] * w - 0.5, uv[:, 1] * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    at = lambda yy, xx: pixels[yy % h, xx % w]
    return (at(y0, x0) * (1 - fx) * (1 - fy) + at(y0, x0 + 1) * fx * (1 - fy)
            + at(y0 + 1, x0) * (1 - fx) * fy + at(y0 + 1, x0 + 1) * fx * fy)


def dc_color(d):
    return 0.5 + C0 * d["splat_sh_0"].astype(np.float64)


def source_vertices(d):
    return np.column_stack([d[f"splat_extra_source_vertices.{i}"][:, 0] for i in range(3)])


def surface_points(d, vertices=None):
    """Each splat's barycentric point on its evaluated loop triangle, plus its normal offset; with
    `vertices`, on the triangle of those vertices its source_vertices name."""
    tri = d["splat_extra_source_triangle"][:, 0]
    if vertices is None:
        corners = d["co"].astype(np.float64)[d["tri_verts"][tri]]
    else:
        corners = vertices.astype(np.float64)[source_vertices(d)]
    bary = d["splat_extra_barycentric"].astype(np.float64)
    points = np.einsum("nk,nkc->nc", bary, corners)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = d.get("splat_extra_normal_offset", np.zeros((len(tri), 1)))[:, 0]
    return points + offset[:, None] * normal


def corner_values(d, per_loop):
    tri = d["splat_extra_source_triangle"][:, 0]
    return np.einsum("nk,nkc->nc", d["splat_extra_barycentric"].astype(np.float64),
                     per_loop[d["tri_loops"][tri]].astype(np.float64))


# install -------------------------------------------------------------------------------------------

def test_install_registers_operators_command_and_menu(blender):
    res = blender.step("install")
    assert res == {"operators": [True, True], "command_registered": True, "convert_menu": 1}


# mesh to splats ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["srgb", "float"])
def test_from_mesh_samples_the_texture_at_each_splat(blender, case):
    res = blender.step("textured")[case]
    d = blender.npz(f"textured_{case}")
    assert res["is_float"] == (case == "float")
    texels = d["texels"][..., :3].astype(np.float64)        # Blender's own pixels, bottom row first
    linear = texels if case == "float" else srgb_to_linear(texels)
    uv = corner_values(d, d["uv"])
    assert uv.min() < 0.0                                  # the repeat wrap is exercised
    expected = linear_to_srgb(bilinear_blender(linear, uv))
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)
    assert np.ptp(expected, axis=0).min() > 0.3            # a real texture, not a flat colour


@pytest.mark.parametrize("case", ["srgb", "float"])
def test_from_mesh_budget_placement_and_provenance(blender, case):
    res = blender.step("textured")[case]
    d = blender.npz(f"textured_{case}")
    assert res["counts"] == list(BUDGETS)
    assert blender.step("textured")[f"{case}_{BUDGETS[0]}"]["result"] == ["FINISHED"]
    np.testing.assert_allclose(d["splat_matrix"], d["source_matrix"], atol=1e-7)
    np.testing.assert_allclose(d["position"], surface_points(d), atol=1e-5)
    tri = d["splat_extra_source_triangle"][:, 0]
    np.testing.assert_array_equal(source_vertices(d), d["tri_verts"][tri])
    np.testing.assert_allclose(d["splat_extra_barycentric"].sum(axis=1), 1.0, atol=1e-6)
    assert res["source"] == {"object": f"plane_{case}", "mesh": f"plane_{case}", "vertices": 20,
                             "original_vertices": 20, "rest_pose": True}
    assert res["modifiers"] == ["Splatwright Display"] and res["selected"] == [res["name"]]


def test_from_mesh_applies_modifiers(blender):
    res = blender.step("textured")["arrayed"]
    d = blender.npz("arrayed")
    assert res["result"] == ["FINISHED"]
    assert len(d["tri_verts"]) == 4 * res["original_faces"]          # two copies of 4 quads, triangulated
    assert res["source"]["vertices"] == 2 * res["source"]["original_vertices"]
    np.testing.assert_allclose(d["position"], surface_points(d), atol=1e-5)
    assert d["position"][:, 0].max() > 2.5                            # splats on the arrayed copy too
    np.testing.assert_allclose(dc_color(d), np.broadcast_to(linear_to_srgb([0.2, 0.5, 0.8]), (300, 3)), atol=2e-4)


def test_from_mesh_corner_colour_attribute(blender):
    assert blender.step("colors")["painted"]["result"] == ["FINISHED"]
    d = blender.npz("painted")
    expected = linear_to_srgb(corner_values(d, d["color_Paint"][:, :3]))
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)


def test_from_mesh_point_colours_without_material(blender):
    assert blender.step("colors")["bare"]["result"] == ["FINISHED"]
    d = blender.npz("bare")
    tri = d["splat_extra_source_triangle"][:, 0]
    corner = d["color_Tint"][:, :3].astype(np.float64)[d["tri_verts"][tri]]
    expected = linear_to_srgb(np.einsum("nk,nkc->nc", d["splat_extra_barycentric"].astype(np.float64), corner))
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)


def test_from_mesh_one_colour_per_material(blender):
    assert blender.step("colors")["multi"]["result"] == ["FINISHED"]
    d = blender.npz("multi")
    tri = d["splat_extra_source_triangle"][:, 0]
    material = d["tri_mat"][tri]
    assert set(material) == {0, 1, 2}
    expected = linear_to_srgb(np.array(MATERIAL_COLORS))[material]
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)


def test_from_mesh_warns_about_unfollowed_nodes(blender):
    res = blender.step("colors")["odd"]
    assert len(res["warnings"]) == 1 and "'odd'" in res["warnings"][0] and "Color node" in res["warnings"][0]
    np.testing.assert_allclose(res["base"], [0.25, 0.5, 0.75], atol=1e-6)


def test_from_mesh_falls_back_when_an_image_has_no_pixels(blender):
    res = blender.step("colors")["missing image"]
    assert len(res["warnings"]) == 1 and "'lost'" in res["warnings"][0] and "no pixels" in res["warnings"][0]
    assert not res["texture"]
    np.testing.assert_allclose(res["base"], [0.5, 0.25, 0.125], atol=1e-6)


def test_from_mesh_skips_faces_with_non_finite_vertices(blender):
    assert blender.step("colors")["nan vertex"]["result"] == ["FINISHED"]
    d = blender.npz("nan_vertex")
    assert len(d["position"]) == 200
    assert all(np.isfinite(v).all() for v in d.values())
    assert not (source_vertices(d) == 6).any()            # the faces around vertex 6 are left out


@pytest.mark.parametrize("name, words", [
    ("camera", ["'Camera' (CAMERA)", "no mesh objects"]),
    ("empty mesh", ["'empty_mesh' has no faces"]),
    ("good and empty", ["'empty_mesh' has no faces"]),
    ("zero-area faces", ["'collapsed'", "positive area"]),
    ("splat object", ["splat cloud"]),
    ("nothing", ["nothing is selected"]),
])
def test_from_mesh_errors_leave_the_scene_unchanged(blender, name, words):
    case = blender.step("errors")[name]
    assert case["result"] == ["CANCELLED"]
    for word in words:
        assert word in case["error"], case["error"]
    assert case["unchanged"]


def test_from_mesh_skips_non_meshes_in_a_mixed_selection(blender):
    case = blender.step("errors")["good and camera"]
    assert case["result"] == ["FINISHED"] and case["created"] == ["good_splats.001"]


def test_from_mesh_target_psnr(blender):
    res = blender.step("target_psnr")
    assert res["result"] == ["FINISHED"], res["error"]
    assert 0 < res["count"] <= 4000


# the demo rig --------------------------------------------------------------------------------------

def test_demo_rig_structure(blender):
    res = blender.step("demo_rig")
    assert res["bones"] == ["Base", "Upper", "Fore", "Hand"]
    assert res["parents"] == [None, "Base", "Upper", "Fore"]
    assert sorted(res["groups"]) == sorted(res["bones"])
    assert res["modifiers"] == [["ARMATURE", "Demo Arm Rig"]]
    assert res["frames"] == [1, 24] and res["animated"] and res["camera"] == "Demo Camera"
    assert res["textured"] and len(res["materials"]) == 4
    env = res["environment"]
    assert env["splat"] and env["count"] == 3000 and env["source"]["object"] == "Demo Environment"


def test_demo_rig_weights_are_smooth_and_normalised(blender):
    d = blender.npz("demo_rig")
    w = d["weights"]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    blended = (w > 1e-3).sum(axis=1) > 1
    assert blended.sum() > 0.2 * len(w)                    # joints bend, they do not break
    z = d["rest"][:, 2]
    # weights are a smooth function of height: no jump between neighbouring rings
    order = np.argsort(z)
    assert np.abs(np.diff(w[order], axis=0)).max() < 0.6


def test_demo_rig_pose_is_blenders_armature_deformation(blender):
    """At frame 12 Blender's evaluated mesh equals the weighted bone deformation of the rest mesh."""
    d = blender.npz("demo_rig")
    np.testing.assert_allclose(d["body_matrix"], d["arm_matrix"], atol=1e-7)     # armature space = object space
    rest = np.column_stack([d["rest"], np.ones(len(d["rest"]))])
    blended = np.einsum("vb,bij->vij", d["weights"], d["deform"])
    expected = np.einsum("vij,vj->vi", blended, rest)[:, :3]
    np.testing.assert_allclose(d["posed"], expected, atol=1e-5)
    assert np.abs(d["posed"] - d["rest"]).max() > 1.0                               # the pose really bends


def test_from_mesh_of_a_posed_rig_uses_the_rest_pose(blender):
    res = blender.step("rest_pose")
    assert res["pose_position"] == "POSE"                 # restored after the conversion
    mesh = blender.npz("rig_mesh")
    for key, verts in (("rest", mesh["rest"]), ("posed", mesh["posed"])):
        assert res[key]["result"] == ["FINISHED"]
        assert res[key]["source"]["rest_pose"] == (key == "rest")
        # source_vertices index the original vertices (a deform-only stack keeps them); the rest and
        # posed meshes may split quads along different diagonals, so source_triangle is not enough
        assert res[key]["source"]["vertices"] == res[key]["source"]["original_vertices"]
        d = blender.npz(f"rig_{key}")
        np.testing.assert_allclose(d["position"], surface_points(d, verts), atol=1e-5)
    rest, posed = blender.npz("rig_rest")["position"], blender.npz("rig_posed")["position"]
    assert np.abs(rest - posed).max() > 1.0


# animated export ---------------------------------------------------------------------------------------

def _moved(cloud, matrix, conversion=np.linalg.inv(DEFAULT_AXES)):
    m = conversion @ np.array(matrix)
    return cloud.positions.astype(np.float64) @ m[:3, :3].T + m[:3, 3]


def test_animation_ply_sequence_follows_the_object(blender):
    res = blender.step("animation")
    assert res["ply"]["result"] == ["FINISHED"]
    files = sorted(p.name for p in (blender.out / "seq").iterdir())
    assert files == ["anim_0002.ply", "anim_0003.ply", "anim_0004.ply"]
    source = read(blender.work / "cloud.ply")
    for frame in (2, 3, 4):
        got = read(blender.out / "seq" / f"anim_{frame:04d}.ply")
        np.testing.assert_allclose(got.positions, _moved(source, res["matrices"][str(frame)]), atol=2e-5)
    assert res["frame_after"] == 3                                       # the scene's frame is restored


def test_animation_without_hashes_uses_the_scene_range(blender):
    res = blender.step("animation")
    assert res["plain"]["result"] == ["FINISHED"]
    assert sorted(p.name for p in (blender.out / "plain").iterdir()) == ["anim_0001.ply", "anim_0003.ply"]


def test_animation_usd_has_one_time_sample_per_frame(blender):
    """Read with pxr directly: Y-up stage, time codes = frames, world positions = Blender's (x, z, -y)."""
    from pxr import Usd, UsdGeom
    res = blender.step("animation")
    assert res["usd"]["result"] == ["FINISHED"]
    stage = Usd.Stage.Open(str(blender.out / "anim.usdc"))
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1.0, 4.0)
    assert stage.GetTimeCodesPerSecond() == pytest.approx(30 / 1.001, rel=1e-6)   # the scene's rate
    assert stage.GetFramesPerSecond() == pytest.approx(30 / 1.001, rel=1e-6)
    prim = stage.GetPrimAtPath("/Splats")
    positions = prim.GetAttribute("positions")
    assert positions.GetTimeSamples() == [1.0, 2.0, 3.0, 4.0]
    source = read(blender.work / "cloud.ply")
    blender_to_usd = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
    for frame in range(1, 5):
        world = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(frame)).T     # stands the values up
        got = np.array(positions.Get(frame), dtype=np.float64) @ world[:3, :3].T + world[:3, 3]
        np.testing.assert_allclose(got, _moved(source, res["matrices"][str(frame)], blender_to_usd), atol=2e-5)
    # the uniform scale keyed at frame 4 scales every sigma
    scales = np.sort(np.array(prim.GetAttribute("scales").Get(4), dtype=np.float64), axis=1)
    np.testing.assert_allclose(scales, np.sort(source.scales, axis=1) * 1.5, rtol=2e-5)


def test_animation_selected_only(blender):
    from pxr import Usd
    res = blender.step("animation")
    assert res["usd_selected"]["result"] == ["FINISHED"]
    stage = Usd.Stage.Open(str(blender.out / "anim_sel.usda"))
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetAttribute("positions").GetTimeSamples() == [1.0, 2.0]


@pytest.mark.parametrize("name, words", [
    ("missing folder", ["nowhere", "does not exist"]),
    ("backwards", ["5-2", "ends before it starts"]),
    ("unknown extension", ["never.xyz", "unknown splat file extension"]),
    ("not splats", ["no splat objects selected", "'Camera' (CAMERA)"]),
])
def test_animation_errors_write_nothing(blender, name, words):
    res = blender.step("animation")["bad"]
    assert res[name]["result"] == ["CANCELLED"]
    for word in words:
        assert word in res[name]["error"], res[name]["error"]
    assert res["written"] == []


def test_sequence_names_are_deterministic(blender):
    names = {(p, f): name for p, f, name in blender.step("frame_names")["names"]}
    assert names[("/a/shot_####.ply", 7)] == "/a/shot_0007.ply"
    assert names[("/a/shot.ply", 7)] == "/a/shot_0007.ply"
    assert names[("/a/shot_##.ply", 123)] == "/a/shot_123.ply"          # padding is a minimum width
    assert names[("/a/v#_f###.spz", 5)] == "/a/v#_f005.spz"             # the last run of # is the frame
    assert names[("/a/shot_####.ply", -3)] == "/a/shot_-003.ply"
    assert names[("/a/shot.ply", 12345)] == "/a/shot_12345.ply"
    assert names[("/a/shot", 2)] == "/a/shot_0002"


# the blender -b command ------------------------------------------------------------------------------

def _outcome(blender, name):
    return blender.step("cli")["outcomes"][name]


def test_cli_export_ply_sequence(blender):
    res = blender.step("cli")
    run = res["outcomes"]["export ply"]
    assert run["code"] == 0, run["stderr"]
    assert [line for line in run["stdout"].splitlines() if "frame" in line and "->" in line] != []
    source = read(blender.work / "cloud.ply")
    for frame in (1, 2, 3):
        got = read(blender.out / "cli" / f"seq_{frame:04d}.ply")
        np.testing.assert_allclose(got.positions, _moved(source, res["matrices"][str(frame)]), atol=2e-5)
    step = _outcome(blender, "export step")
    assert step["code"] == 0 and {"step_0001.ply", "step_0004.ply"} <= set(res["files"])
    assert "step_0002.ply" not in res["files"]


def test_cli_export_usd_with_format_and_objects(blender):
    from pxr import Usd
    run = _outcome(blender, "export usd")
    assert run["code"] == 0, run["stderr"]
    stage = Usd.Stage.Open(str(blender.out / "cli" / "anim.usdc"))
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetAttribute("positions").GetTimeSamples() == [2.0, 3.0, 4.0]


def test_cli_export_axes(blender):
    res = blender.step("cli")
    assert res["outcomes"]["export axes"]["code"] == 0
    got = read(blender.out / "cli" / "axes_0004.ply")
    source = read(blender.work / "cloud.ply")
    np.testing.assert_allclose(got.positions, _moved(source, res["matrices"]["4"], np.eye(4)), atol=2e-5)


@pytest.mark.parametrize("name, code, words", [
    ("backwards", 1, ["3-1", "ends before it starts"]),
    ("not frames", 1, ["a-b", "A-B"]),
    ("unknown object", 1, ["no object named 'Nope'"]),
    ("not splats", 1, ["not splat objects", "'Grid' (MESH)"]),
    ("missing folder", 1, ["nowhere", "does not exist"]),
    ("format clash", 1, ["x.usdc", "--format is ply"]),
    ("unknown extension", 1, ["x.xyz", "unknown splat file extension"]),
    ("no output", 2, ["output"]),
    ("unknown verb", 2, ["frobnicate"]),
    ("render unknown object", 1, ["no object named 'moving_missing'"]),
    ("from-mesh camera", 1, ["not mesh objects", "'Camera' (CAMERA)"]),
    ("from-mesh unknown", 1, ["no object named 'Nope'"]),
    ("from-mesh bad extension", 1, ["grid.xyz", "unknown splat file extension"]),
    ("render panoramic", 1, ["PANO"]),
    ("render no camera", 1, ["no camera"]),
])
def test_cli_failures_exit_non_zero_with_a_message(blender, name, code, words):
    run = _outcome(blender, name)
    assert run["code"] == code
    for word in words:
        assert word in run["stderr"], run["stderr"]
    if "new_objects" in run:
        assert run["new_objects"] == 0
    files = blender.step("cli")["files"]
    assert not any(f.startswith(("x.", "x_", "cam", "grid.xyz", "pano", "nocam", "none")) for f in files)


def test_cli_render_frames_through_the_engine(blender):
    from PIL import Image
    res = blender.step("cli")
    run = res["outcomes"]["render"]
    assert run["code"] == 0, run["stderr"]
    assert "frame_0001.png" in res["files"] and "frame_0002.png" in res["files"]
    first, second = (np.asarray(Image.open(blender.out / "cli" / f"frame_000{f}.png"), np.float64) for f in (1, 2))
    assert first.shape[:2] == (24, 32)
    assert np.abs(first - second).max() > 10                 # the splats moved between the frames
    assert _outcome(blender, "render no hash")["code"] == 0 and "plain_0004.png" in res["files"]
    assert _outcome(blender, "render exr")["code"] == 0
    assert (blender.out / "cli" / "deep_0003.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"    # OpenEXR magic
    # the scene's own settings are back as they were
    after = res["after"]
    assert after == {"frame": 2, "engine": after["engine"], "filepath": "//untouched_", "hidden": [], "format": "PNG"}
    assert after["engine"] != "SPLATWRIGHT"


def test_cli_from_mesh_writes_splats_in_world_space(blender):
    res = blender.step("cli")
    run = res["outcomes"]["from-mesh ply"]
    assert run["code"] == 0, run["stderr"]
    assert run["new_objects"] == 1
    cloud = read(blender.out / "cli" / "grid.ply")
    assert len(cloud) == 250
    # the file keeps the provenance extras: rebuild each centre from the grid's own quads
    verts = grid_vertices(wobble=0.2)
    columns = lambda name: np.column_stack([cloud.extras[f"{name}_{i}"] for i in range(3)])   # PLY splits them
    corners = verts[columns("source_vertices")]
    local = np.einsum("nk,nkc->nc", columns("barycentric").astype(np.float64), corners)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    local += cloud.extras.get("normal_offset", np.zeros(len(cloud)))[:, None] * normal
    world = local @ np.array(res["grid_matrix"])[:3, :3].T + np.array(res["grid_matrix"])[:3, 3]
    expected = world @ np.linalg.inv(DEFAULT_AXES)[:3, :3].T
    np.testing.assert_allclose(cloud.positions, expected, atol=2e-5)
    blend = _outcome(blender, "from-mesh blend")
    assert blend["code"] == 0 and (blender.out / "cli" / "grid.blend").stat().st_size > 1000


def test_command_survives_re_registration(blender):
    res = blender.step("reregister")
    assert res["enabled"] and res["re_enabled"]
    assert res["disabled_handle"] is False and res["types_left"] == []


if __name__ == "__main__":
    worker_main(Worker)
