"""The Blender side of tests/test_blender_workflows.py (run in each Blender of the version matrix; see
workers/base.py)."""

import contextlib
import io
import json

import numpy as np

from workers.base import MODULE, BlenderWorker, point_attributes, splat_total, worker_main

C0 = 0.28209479177387814
# file (x, y, z) -> Blender (x, z, -y): the default export axes are its inverse
DEFAULT_AXES = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
TEXTURE_SIZE = (7, 5)  # width, height: small, so every splat sees texel boundaries
PLANE_TRANSFORM = dict(location=(1.0, -2.0, 0.5), rotation_euler=(0.4, -0.3, 0.9), scale=(2.0, 0.5, 1.5))
BUDGETS = (400, 37)
MATERIAL_COLORS = ((0.8, 0.1, 0.05), (0.02, 0.6, 0.1), (0.1, 0.2, 0.9))
BALL_PLACE = ((0.5, -0.3, 1.2), (0.3, 0.2, 0.9), (1.0, 1.0, 1.3))  # location, rotation, scale
EDGE_VIEW = (64, 7.0)  # pixels square, and the angle (degrees) of the edge Cycles' pixel filter is measured on
PIXEL_FILTERS = (("BLACKMAN_HARRIS", 1.5), ("GAUSSIAN", 2.5), ("BOX", 1.5))  # Cycles' Film settings measured
ANIM = {
    1: dict(location=(0.0, 0.0, 0.0), rotation_euler=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0)),
    4: dict(location=(0.5, -1.0, 2.0), rotation_euler=(0.3, 0.0, 1.1), scale=(1.5, 1.5, 1.5)),
}


# the worker (a separate Python process with bpy) -----------------------------------------------------


def srgb_bytes(rng, shape):
    return rng.integers(0, 256, shape) / 255.0


def grid_vertices(nx=4, ny=3, size=(2.0, 1.5), wobble=0.0):
    """(nx+1)(ny+1) vertices of a grid in the surface z = wobble sin(2x) cos(3y), row by row."""
    xs, ys = np.meshgrid(np.linspace(-size[0] / 2, size[0] / 2, nx + 1), np.linspace(-size[1] / 2, size[1] / 2, ny + 1))
    x, y = xs.ravel(), ys.ravel()
    return np.column_stack([x, y, wobble * np.sin(2 * x) * np.cos(3 * y)])


def skewed_uv(p):
    """UVs that are not a plain projection and reach below 0 (the texture repeats)."""
    return np.column_stack([0.1 + 0.6 * p[:, 0] + 0.1 * p[:, 1], 0.55 + 0.5 * p[:, 1] - 0.05 * p[:, 0]])


class Worker(BlenderWorker):
    steps = (
        "install",
        "textured",
        "colors",
        "errors",
        "calibration",
        "demo_rig",
        "rest_pose",
        "target_psnr",
        "pixel_filter",
        "from_mesh_panel",
        "baked_look",
        "baked_path",
        "animation",
        "frame_names",
        "cli",
        "cli_bake",
        "reregister",
    )

    # helpers -------------------------------------------------------------------------------------

    def grid(self, name, nx=4, ny=3, size=(2.0, 1.5), uv=None, wobble=0.0):
        """A grid of quads in the z = wobble * f(x, y) surface with per-loop UVs."""
        bpy = self.bpy
        verts = grid_vertices(nx, ny, size, wobble)
        faces = [
            [j * (nx + 1) + i, j * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i]
            for j in range(ny)
            for i in range(nx)
        ]
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
            for key, prop, width, dtype in (
                ("tri_verts", "vertices", 3, np.int32),
                ("tri_loops", "loops", 3, np.int32),
                ("tri_poly", "polygon_index", 1, np.int32),
                ("tri_mat", "material_index", 1, np.int32),
            ):
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
        """A splat object's point attributes as Blender stores them, in either form; a native cloud's DC
        (radiance:base's colour) also as splat_sh_0, the mesh form's name for it (':' saved as '__')."""
        arrays = point_attributes(obj.data)
        if "radiance:base" in arrays:
            arrays["splat_sh_0"] = arrays["radiance:base"][:, :3]
        return {name.replace(":", "__"): values for name, values in arrays.items()}

    def convert(self, objects, **kw):
        """Run from_mesh on `objects` (without silhouette calibration unless asked: these steps check
        what lands where, not how it renders); returns (result, the new active object or None)."""
        kw.setdefault("calibrate", False)
        self.select(objects)
        before = set(self.bpy.data.objects)
        res = self.call(self.bpy.ops.splat.from_mesh, **kw)
        created = [o for o in self.bpy.data.objects if o not in before]
        return res, created

    def path_views(self, obj, count, world=False):
        """The scene camera's `count` path views of `obj`, 32 pixels wide, as Mesh to Splats measures
        them (in its space) or, with `world`, as a bake renders them (without the views its spacing adds)."""
        from_mesh = self.module("splat_addon.convert.from_mesh")
        path = from_mesh.CameraPath(self.bpy.context.scene, [obj], 32, from_mesh.frames_looked_at(count))
        return path.views(obj, count, world)

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        return {
            "operators": [hasattr(bpy.types, n) for n in ("SPLAT_OT_from_mesh", "SPLAT_OT_export_animation")],
            "command_registered": self.module("splat_addon.command")._handle is not None,
            "convert_menu": self.menu_entries("VIEW3D_MT_object_convert"),
        }

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
                counts.append(splat_total(created[0]) if created else None)
                res[f"{name}_{budget}"] = op
                if budget == BUDGETS[0]:
                    splats = created[0]
                    selected = sorted(o.name for o in bpy.context.selected_objects)
            self.save(
                f"textured_{name}",
                texels=stored,
                splat_matrix=np.array(splats.matrix_world),
                source_matrix=np.array(obj.matrix_world),
                **self.source_dump(obj),
                **self.splat_dump(splats),
            )
            res[name] = {
                "counts": counts,
                "colorspace": img.colorspace_settings.name,
                "is_float": img.is_float,
                "source": json.loads(splats.data["splatwright_source"]),
                "modifiers": [m.name for m in splats.modifiers],
                "name": splats.name,
                "form": self.module("splat_addon.data").splat_form(splats),
                "selected": selected,
            }
        # modifiers applied: an Array modifier doubles the surface
        cube = self.grid("arrayed", nx=2, ny=2)
        mod = cube.modifiers.new("Array", "ARRAY")
        mod.count, mod.relative_offset_displace = 2, (1.5, 0.0, 0.0)
        cube.data.materials.append(self.material("plain", (0.2, 0.5, 0.8)))
        op, created = self.convert([cube], max_splats=300)
        res["arrayed"] = {
            **op,
            "original_faces": len(cube.data.polygons),
            "source": json.loads(created[0].data["splatwright_source"]),
        }
        self.save("arrayed", **self.source_dump(cube), **self.splat_dump(created[0]))
        # a memory budget holds the splats to what fits, whatever Max Splats asks
        held = self.grid("held", nx=2, ny=2)
        op, created = self.convert([held], max_splats=10**7, memory_budget=0.08)
        res["held"] = {
            **op,
            "faces": 2 * len(held.data.polygons),
            "splats": self.module("splat_addon.data.attributes").splat_count(created[0].data),
        }
        return res

    def colors(self):
        bpy = self.bpy
        rng = np.random.default_rng(2)
        res = {}
        # a corner colour attribute feeding Base Color through a Color Attribute node
        painted = self.grid("painted", wobble=0.1)
        attr = painted.data.color_attributes.new("Paint", "BYTE_COLOR", "CORNER")
        attr.data.foreach_set("color", srgb_bytes(rng, (len(attr.data), 4)).astype(np.float32).ravel())
        painted.data.color_attributes.new("Other", "FLOAT_COLOR", "POINT")  # not the one the material names

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

        look = self.module("splat_addon.convert.mesh_reading").material_appearance(
            self.material("odd", (0.25, 0.5, 0.75), rgb), warnings.append
        )
        res["odd"] = {"warnings": warnings, "base": list(look.material.base_color)}
        # an image whose file is missing has no pixels: warned, the base colour used
        missing = bpy.data.images.new("missing", 4, 4)
        missing.source, missing.filepath = "FILE", str(self.work / "no_such_texture.png")

        def texture(nodes):
            node = nodes.new("ShaderNodeTexImage")
            node.image = missing
            return node.outputs["Color"]

        warnings = []
        look = self.module("splat_addon.convert.mesh_reading").material_appearance(
            self.material("lost", (0.5, 0.25, 0.125), texture), warnings.append
        )
        res["missing image"] = {
            "warnings": warnings,
            "base": list(look.material.base_color),
            "texture": look.material.texture is not None,
        }
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
        for name, objects in (
            ("camera", [bpy.data.objects["Camera"]]),
            ("empty mesh", [empty]),
            ("good and empty", [good, empty]),
            ("zero-area faces", [flat]),
            ("splat object", [splat_obj]),
            ("nothing", []),
        ):
            self.select(objects)
            before = self.inventory()
            res = self.call(bpy.ops.splat.from_mesh, max_splats=50)
            cases[name] = {**res, "unchanged": before == self.inventory()}
        self.select([good, bpy.data.objects["Camera"]])
        res, created = self.convert([good, bpy.data.objects["Camera"]], max_splats=50)
        cases["good and camera"] = {**res, "created": [o.name for o in created]}
        return cases

    @contextlib.contextmanager
    def counted_renders(self):
        """{"mesh": renders of the mesh, "splats": renders of splats} that mesh conversion makes inside."""
        refine = self.module("core.mesh_refine")
        counts = {"mesh": 0, "splats": 0}
        originals = refine.render_mesh, refine.render

        def counting(key, function):
            def counted(*args, **kwargs):
                counts[key] += 1
                return function(*args, **kwargs)

            return counted

        refine.render_mesh, refine.render = counting("mesh", originals[0]), counting("splats", originals[1])
        try:
            yield counts
        finally:
            refine.render_mesh, refine.render = originals

    def calibration(self):
        """Mesh to Splats on a solid sphere with Calibrate Silhouettes off (no renders) and on (one small
        view, to keep it short)."""
        bpy = self.bpy
        bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, radius=0.8)
        sphere = bpy.context.active_object
        res = {}
        data = self.module("splat_addon.data")
        for key, calibrate, made_for in (
            ("off", False, "CLASSIC"),
            ("on", True, "CLASSIC"),
            ("antialiased", True, "ANTIALIASED"),
        ):
            with self.counted_renders() as renders:
                op, created = self.convert(
                    [sphere],
                    max_splats=1500,
                    calibrate=calibrate,
                    view_near=1.0,
                    view_far=1.0,
                    view_count=1,
                    view_size=48,
                    made_for=made_for,
                )
            res[key] = {
                **op,
                "renders": dict(renders),
                "count": splat_total(created[0]),
                "antialiased": data.object_cloud(created[0]).antialiased,
            }
            self.save(f"calibration_{key}", **self.source_dump(sphere), **self.splat_dump(created[0]))
        props = bpy.ops.splat.from_mesh.get_rna_type().properties
        res["default"], res["made_for"] = props["calibrate"].default, props["made_for"].default
        return res

    def demo_rig(self):
        bpy = self.bpy
        scene = bpy.context.scene
        rig = self.module("splat_addon.convert.demo_rig").build_demo_rig(
            scene, environment_splats=3000, calibrate=False
        )
        body, arm = rig.body, rig.armature
        mesh = body.data
        weights = np.zeros((len(mesh.vertices), len(arm.data.bones)))
        names = [b.name for b in arm.data.bones]
        for group in body.vertex_groups:
            for i in range(len(mesh.vertices)):
                try:
                    weights[i, names.index(group.name)] = group.weight(i)
                except RuntimeError:  # vertex not in the group
                    pass
        rest = np.array([tuple(v.co) for v in mesh.vertices])
        scene.frame_set(12)
        posed = self.source_dump(body)["co"]
        deform = {
            b.name: np.array(arm.pose.bones[b.name].matrix) @ np.linalg.inv(np.array(b.matrix_local))
            for b in arm.data.bones
        }
        self.save(
            "demo_rig",
            weights=weights,
            rest=rest,
            posed=posed,
            deform=np.stack([deform[n] for n in names]),
            body_matrix=np.array(body.matrix_world),
            arm_matrix=np.array(arm.matrix_world),
        )
        scene.frame_set(1)
        env = rig.environment
        return {
            "bones": names,
            "parents": [b.parent.name if b.parent else None for b in arm.data.bones],
            "groups": [g.name for g in body.vertex_groups],
            "modifiers": [(m.type, m.object.name if m.type == "ARMATURE" else None) for m in body.modifiers],
            "frames": [scene.frame_start, scene.frame_end],
            "camera": scene.camera.name,
            "light": rig.light.type,
            "materials": [m.name for m in mesh.materials],
            "textured": any(n.bl_idname == "ShaderNodeTexImage" for m in mesh.materials for n in m.node_tree.nodes),
            "environment": {
                "splat": self.module("splat_addon.data").is_splat_object(env),
                "count": splat_total(env),
                "source": json.loads(env.data["splatwright_source"]),
            },
            "animated": arm.animation_data is not None and arm.animation_data.action is not None,
        }

    def rest_pose(self):
        bpy = self.bpy
        scene = bpy.context.scene
        rig = self.module("splat_addon.convert.demo_rig").build_demo_rig(scene, environment_splats=0)
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
        op, created = self.convert([obj], mode="QUALITY", target_psnr=28.0, max_splats=4000, view_count=2, view_size=64)
        res = {**op, "count": splat_total(created[0]) if created else None}
        # Quality measured along the scene camera's path (frames 1 and 10), in the object's space.
        bpy, scene = self.bpy, self.bpy.context.scene
        obj.location = (0.5, 0.0, 0.0)
        cam = bpy.data.objects.new("quality_cam", bpy.data.cameras.new("quality_cam"))
        scene.collection.objects.link(cam)
        scene.camera, scene.frame_start, scene.frame_end = cam, 1, 10
        cam.rotation_euler = (1.2, 0.0, 0.0)
        for frame, x in ((1, 0.0), (10, 2.0)):
            cam.location = (x, -4.0, 1.0)
            cam.keyframe_insert("location", frame=frame)
        scene.frame_set(4)
        views = self.path_views(obj, 2)
        res["path_centres"] = [list(map(float, v.center)) for v in views]
        res["path_sizes"] = [[v.width, v.height] for v in views]
        res["frame_after"] = scene.frame_current
        missed, created = self.convert(
            [obj], mode="QUALITY", target_psnr=80.0, max_splats=300, view_source="CAMERA", view_count=2, view_size=32
        )
        res["missed"] = {**missed, "count": splat_total(created[0]) if created else None}
        # Mirrored, turned and scaled unevenly: its space mirrors and shears the camera.
        obj.rotation_euler, obj.scale = (0.0, 0.0, 0.3), (-1.0, 2.0, 1.0)
        bpy.context.view_layer.update()
        res["mirrored_matrix"] = np.array(obj.matrix_world).tolist()
        views = self.path_views(obj, 2)
        res["mirrored_centres"] = [list(map(float, v.center)) for v in views]
        mirrored, created = self.convert(
            [obj], mode="QUALITY", target_psnr=80.0, max_splats=300, view_source="CAMERA", view_count=2, view_size=32
        )
        res["mirrored"] = {**mirrored, "count": splat_total(created[0]) if created else None}
        # Moving from x = 0.5 (frame 1) to 3.5 (frame 10): the path as the object sees it, in world
        # space where it stands at frame 4 (the views a bake renders).
        obj.rotation_euler, obj.scale = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
        for frame, x in ((1, 0.5), (10, 3.5)):
            obj.location = (x, 0.0, 0.0)
            obj.keyframe_insert("location", frame=frame)
        scene.frame_set(4)
        res["moving_now"] = list(obj.matrix_world.translation)
        views = self.path_views(obj, 2, world=True)
        res["moving_world_centres"] = [list(map(float, v.center)) for v in views]
        obj.animation_data_clear()
        obj.location = (0.5, 0.0, 0.0)
        # Still for frames 1-20, then a quarter turn around the object (an empty it hangs from) by 40.
        pivot = bpy.data.objects.new("quality_pivot", None)
        scene.collection.objects.link(pivot)
        pivot.location = obj.location
        cam.animation_data_clear()
        cam.parent, cam.location, cam.rotation_euler = pivot, (0.0, -4.0, 0.0), (np.pi / 2, 0.0, 0.0)
        scene.frame_end = 40
        edit = bpy.context.preferences.edit
        interpolation, edit.keyframe_new_interpolation_type = edit.keyframe_new_interpolation_type, "LINEAR"
        for frame, angle in ((1, 0.0), (20, 0.0), (40, np.pi / 2)):
            pivot.rotation_euler = (0.0, 0.0, angle)
            pivot.keyframe_insert("rotation_euler", frame=frame)
        edit.keyframe_new_interpolation_type = interpolation
        views = self.path_views(obj, 4)
        res["turn_centres"] = [list(map(float, v.center)) for v in views]
        # Measured and baked from one walk along the path: every frame set once, then the current one.
        frame_sets = []
        count_frame_sets = lambda scene, *args: frame_sets.append(scene.frame_current)  # noqa: E731
        bpy.app.handlers.frame_change_pre.append(count_frame_sets)
        try:
            baked = self.module("splat_addon.convert.from_mesh").measured_views(
                scene, [obj], "CAMERA", 2, 32, 0.5, 3.0, bake=True
            )[1][obj]
        finally:
            bpy.app.handlers.frame_change_pre.remove(count_frame_sets)
        res["bake_frame_sets"] = len(frame_sets)
        res["baked_turn_centres"] = [list(map(float, v.center)) for v in baked]
        return res

    def pixel_filter(self):
        """Cycles' renders, under each of PIXEL_FILTERS' Film settings, of a white emission half-plane
        whose edge runs through the view's centre EDGE_VIEW[1] degrees off vertical, one unit per
        pixel, seen straight on (the rows of each image top first): the edge's profile is the pixel
        filter. Also what Mesh to Splats takes from the scene under each setting."""
        import math

        bpy, scene = self.bpy, self.bpy.context.scene
        size, angle = EDGE_VIEW[0], math.radians(EDGE_VIEW[1])
        along, across, far = (
            np.array([math.sin(angle), math.cos(angle)]),
            np.array([math.cos(angle), -math.sin(angle)]),
            1e3,
        )
        corners = [(*(far * a), 0.0) for a in (-along, along, along + across, across - along)]
        mesh = bpy.data.meshes.new("edge")
        mesh.from_pydata(corners, [], [(0, 1, 2, 3)])
        material = bpy.data.materials.new("edge")
        material.use_nodes = True
        nodes = material.node_tree.nodes
        nodes.clear()
        emission = nodes.new("ShaderNodeEmission")
        emission.inputs["Color"].default_value = (1, 1, 1, 1)
        material.node_tree.links.new(emission.outputs[0], nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
        mesh.materials.append(material)
        scene.collection.objects.link(bpy.data.objects.new("edge", mesh))
        camera = bpy.data.objects.new("edge_cam", bpy.data.cameras.new("edge_cam"))
        camera.data.type, camera.data.ortho_scale, camera.location = "ORTHO", float(size), (0.0, 0.0, 10.0)
        scene.collection.objects.link(camera)
        world = bpy.data.worlds.new("black")
        world.use_nodes = True
        world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
        render, cycles = scene.render, scene.cycles
        res = {"default": [cycles.pixel_filter_type, cycles.filter_width]}
        scene_filter = self.module("splat_addon.convert.from_mesh").scene_pixel_filter
        names = ("camera", "world", "engine", "resolution_x", "resolution_y", "resolution_percentage", "filepath")
        cycles_names = ("samples", "use_adaptive_sampling", "use_denoising", "pixel_filter_type", "filter_width")
        before = [getattr(scene if n in ("camera", "world") else render, n) for n in names]
        cycles_before = [getattr(cycles, n) for n in cycles_names]
        format_before = render.image_settings.file_format, render.image_settings.color_depth
        images = {}
        try:
            scene.camera, scene.world, render.engine = camera, world, "CYCLES"
            render.resolution_x = render.resolution_y = size
            render.resolution_percentage = 100
            cycles.device, cycles.samples, cycles.use_adaptive_sampling, cycles.use_denoising = (
                "CPU",
                1024,
                False,
                False,
            )
            render.filepath = str(self.out / "edge.exr")
            self.image_format(render.image_settings, "OPEN_EXR", color_depth="32")
            for kind, width in PIXEL_FILTERS:
                cycles.pixel_filter_type, cycles.filter_width = kind, width
                bpy.ops.render.render(write_still=True)
                image = bpy.data.images.load(render.filepath)
                images[f"{kind}_{width}"] = np.array(image.pixels[:], np.float64).reshape(size, size, image.channels)[
                    ::-1, :, 0
                ]
                bpy.data.images.remove(image)
                res[f"{kind}_{width}"] = scene_filter(scene)
        finally:
            for n, value in zip(names, before):
                setattr(scene if n in ("camera", "world") else render, n, value)
            for n, value in zip(cycles_names, cycles_before):
                setattr(cycles, n, value)
            self.image_format(render.image_settings, format_before[0], color_depth=format_before[1])
        self.save("pixel_filter", **images)
        return res

    def lit_ball(self):
        """A red ball "ball", moved, turned and scaled, above a floor that shadows nothing but must not
        be seen, lit by the startup scene's light; returns (ball, floor)."""
        bpy = self.bpy
        bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, radius=1.0)
        ball = bpy.context.active_object
        ball.name = "ball"
        ball.location, ball.rotation_euler, ball.scale = BALL_PLACE
        ball.data.materials.append(self.material("ball", (0.8, 0.1, 0.05)))
        bpy.ops.mesh.primitive_plane_add(size=8.0)
        return ball, bpy.context.active_object

    def save_object_cloud(self, name, obj):
        """A splat object's cloud (object space) and its world matrix, saved as `name` (saved_cloud reads it)."""
        cloud = self.module("splat_addon.data").object_cloud(obj)
        self.save(
            name,
            positions=cloud.positions,
            rotations=cloud.rotations,
            log_scales=cloud.log_scales,
            opacity_logits=cloud.opacity_logits,
            sh=cloud.sh,
            matrix=np.array(obj.matrix_world),
        )

    def held_out_view(self, ball, name):
        """Cycles' render of the ball (splat_addon.convert.bake.render_view) from a view no bake uses, saved as
        `name` with its camera."""
        camera = self.module("core.camera").Camera.look_at(
            (3.5, -4.0, 3.0), BALL_PLACE[0], up=(0, 0, -1), fov_deg=35, width=48, height=48
        )
        reference = self.module("splat_addon.convert.bake").render_view(
            self.bpy.context.scene, ball, camera, 32, str(self.out / f"{name}.png")
        )
        self.save(name, image=reference, world_to_camera=camera.world_to_camera, fx=camera.fx)

    def scene_state(self):
        """The data, render settings and visibility flags a bake must leave as they were."""
        bpy, scene = self.bpy, self.bpy.context.scene
        render = scene.render
        return {
            "data": {
                k: sorted(x.name for x in getattr(bpy.data, k))
                for k in ("objects", "cameras", "images", "meshes", "materials", "lights")
            },
            "settings": [
                render.engine,
                render.resolution_x,
                render.resolution_y,
                render.film_transparent,
                render.filepath,
                render.image_settings.file_format,
                getattr(scene.camera, "name", None),
                render.use_compositing,
                scene.cycles.samples,
            ],
            "flags": {o.name: [o.visible_camera, o.hide_render] for o in scene.objects},
        }

    def from_mesh_panel(self):
        """What Mesh to Splats' draw() puts in its panel for each choice of Size By, Measure From and
        Appearance (drawn into a layout that records, as drawing needs a window), and the numbers of
        the options the command mirrors."""
        import itertools
        from types import SimpleNamespace

        class Layout:
            def __init__(self):
                self.shown = []

            def column(self, **_):
                return self

            def separator(self, **_):
                self.shown.append("|")

            def prop(self, owner, name, **_):
                self.shown.append(name)

        bpy = self.bpy
        props = bpy.ops.splat.from_mesh.get_rna_type().properties
        shown = {}
        for mode, source, look in itertools.product(
            ("BUDGET", "QUALITY"), ("AROUND", "CAMERA"), ("BASE_COLOR", "RENDERED")
        ):
            fake = SimpleNamespace(layout=Layout(), mode=mode, view_source=source, appearance=look)
            bpy.types.SPLAT_OT_from_mesh.draw(fake, bpy.context)
            shown[f"{mode}/{source}/{look}"] = fake.layout.shown
        return {
            "shown": shown,
            "properties": [p.identifier for p in props if p.identifier != "rna_type"],
            "appearances": [item.identifier for item in props["appearance"].enum_items],
            "numbers": {
                name: [props[name].default, props[name].hard_min, props[name].hard_max]
                for name in ("bake_views", "bake_samples", "bake_degree", "bake_geometry_steps", "view_size")
            },
        }

    def baked_look(self):
        """The lit ball converted with Base Color and with the Rendered look; the scene's data and
        settings before and after, both clouds, and a held-out Cycles view."""
        ball, floor = self.lit_ball()
        options = dict(max_splats=600, view_size=32, use_rest_pose=False, calibrate=True)  # it measures the look
        base_op, base = self.convert([ball], **options)
        before = self.scene_state()
        baked_op, baked = self.convert(
            [ball], appearance="RENDERED", bake_views=3, bake_samples=4, bake_degree=1, **options
        )
        after = self.scene_state()
        for name, objs in (("base", base), ("baked", baked)):
            self.save_object_cloud(f"baked_look_{name}", objs[0])
            objs[0].hide_render = True
        self.held_out_view(ball, "baked_look_view")
        return {
            "base": base_op,
            "baked": baked_op,
            "before": before,
            "after": after,
            "new": [o.name for o in baked],
            "floor": floor.name,
        }

    def baked_path(self):
        """The lit ball (the other objects left out of renders) seen by a scene camera with a shifted
        lens, 32 x 20 pixels, moving from frame 1 to 2; converted with the Rendered look measured
        from that camera (its path baked from too) and measured around the ball. Saved: both clouds,
        and lens_pair's images at frame 1 with the camera perspective and orthographic."""
        bpy, scene = self.bpy, self.bpy.context.scene
        render, cycles = scene.render, scene.cycles
        kept = (
            [(scene, n) for n in ("camera", "frame_start", "frame_end", "frame_current")]
            + [
                (render, n)
                for n in (
                    "engine",
                    "resolution_x",
                    "resolution_y",
                    "resolution_percentage",
                    "film_transparent",
                    "use_border",
                    "use_compositing",
                    "use_sequencer",
                    "filepath",
                    "use_file_extension",
                )
            ]
            + [(cycles, n) for n in ("device", "samples", "use_denoising")]
        )
        before = [(owner, n, getattr(owner, n)) for owner, n in kept]
        fmt = render.image_settings
        format_before = (fmt.file_format, fmt.color_depth, fmt.color_mode)
        objects = {obj: obj.hide_render for obj in bpy.data.objects}
        try:
            return self._baked_path(scene)
        finally:  # the steps after this one find the scene as it was
            for obj in [o for o in bpy.data.objects if o not in objects]:
                bpy.data.objects.remove(obj)
            for obj, hidden in objects.items():
                obj.hide_render = hidden
            for owner, n, value in before:
                setattr(owner, n, value)
            self.image_format(fmt, format_before[0], color_depth=format_before[1], color_mode=format_before[2])

    def _baked_path(self, scene):
        import mathutils

        bpy, render = self.bpy, scene.render
        for obj in scene.objects:
            if obj.type != "LIGHT":
                obj.hide_render = True
        ball, floor = self.lit_ball()
        cam = bpy.data.objects.new("path_cam", bpy.data.cameras.new("path_cam"))
        scene.collection.objects.link(cam)
        cam.data.lens, cam.data.shift_x, cam.data.shift_y = 40.0, 0.12, -0.07
        scene.camera, scene.frame_start, scene.frame_end = cam, 1, 2
        render.resolution_x, render.resolution_y, render.resolution_percentage = 64, 40, 100
        for frame, eye in ((1, (3.0, -4.0, 2.5)), (2, (3.6, -3.4, 2.8))):
            cam.location = eye
            cam.rotation_euler = (
                (mathutils.Vector(BALL_PLACE[0]) - mathutils.Vector(eye)).to_track_quat("-Z", "Y").to_euler()
            )
            cam.keyframe_insert("location", frame=frame)
            cam.keyframe_insert("rotation_euler", frame=frame)
        scene.frame_set(1)
        self.lens_pair(scene, ball, floor, "persp")
        cam.data.type, cam.data.ortho_scale = "ORTHO", 4.0
        self.lens_pair(scene, ball, floor, "ortho")
        cam.data.type = "PERSP"
        options = dict(
            max_splats=600,
            view_size=32,
            use_rest_pose=False,
            calibrate=False,
            appearance="RENDERED",
            bake_views=2,
            bake_samples=8,
            bake_degree=3,
            view_count=2,
        )
        res = {}
        for source in ("CAMERA", "AROUND"):
            op, created = self.convert([ball], view_source=source, **options)
            if not created:
                return {source: op}
            self.save_object_cloud(f"baked_path_{source.lower()}", created[0])
            created[0].hide_render = True
            res[source] = op
        return res

    def lens_pair(self, scene, ball, floor, name):
        """Saved as baked_path_<name>: render_view's Cycles image of the scene camera's first path view
        (world space, through core.camera.blender_lens) with its camera, and Cycles' render through the
        scene camera itself at 32 x 20 pixels, the ball alone over black (the floor lights it unseen)."""
        bpy, render = self.bpy, scene.render
        path = self.path_views(ball, 2, world=True)
        view = path[0]
        image = self.module("splat_addon.convert.bake").render_view(
            scene, ball, view, 8, str(self.out / "path_view.png")
        )
        floor.visible_camera = False
        render.resolution_x, render.resolution_y = 32, 20
        render.engine, scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CYCLES", "CPU", 8, True
        render.film_transparent, render.use_border, render.use_compositing, render.use_sequencer = (
            True,
            False,
            False,
            False,
        )
        render.filepath, render.use_file_extension = str(self.out / "scene_camera.png"), False
        self.image_format(render.image_settings, "PNG", color_depth="8", color_mode="RGBA")
        bpy.ops.render.render(write_still=True)
        own = bpy.data.images.load(str(self.out / "scene_camera.png"))
        rgba = np.array(own.pixels[:], np.float64).reshape(20, 32, 4)[::-1]
        bpy.data.images.remove(own)
        floor.visible_camera = True
        render.resolution_x, render.resolution_y = 64, 40
        self.save(
            f"baked_path_{name}",
            image=image,
            scene_camera=rgba[..., :3] * rgba[..., 3:],
            world_to_camera=view.world_to_camera,
            projection=view.projection,
            intrinsics=[view.width, view.height, view.fx, view.fy, view.cx, view.cy],
        )

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
        res["ply"] = self.call(
            exp, filepath=str(self.out / "seq" / "anim_####.ply"), use_scene_range=False, frame_start=2, frame_end=4
        )
        res["frame_after"] = scene.frame_current
        (self.out / "plain").mkdir()
        scene.frame_start, scene.frame_end, scene.frame_step = 1, 3, 2
        res["plain"] = self.call(exp, filepath=str(self.out / "plain" / "anim.ply"))
        scene.render.fps, scene.render.fps_base = 30, 1.001  # NTSC 29.97
        res["usd"] = self.call(
            exp, filepath=str(self.out / "anim.usd"), use_scene_range=False, frame_start=1, frame_end=4
        )
        scene.render.fps, scene.render.fps_base = 24, 1.0
        res["usd_selected"] = self.call(
            exp,
            filepath=str(self.out / "anim_sel.usda"),
            use_scene_range=False,
            frame_start=1,
            frame_end=2,
            selected_only=True,
        )
        bad = {}
        for name, kw in (
            ("missing folder", dict(filepath=str(self.out / "nowhere" / "a.ply"))),
            (
                "backwards",
                dict(filepath=str(self.out / "never.ply"), use_scene_range=False, frame_start=5, frame_end=2),
            ),
            ("unknown extension", dict(filepath=str(self.out / "never.xyz"))),
        ):
            bad[name] = self.call(exp, **kw)
        self.select([bpy.data.objects["Camera"]])
        bad["not splats"] = self.call(exp, filepath=str(self.out / "never2.ply"), selected_only=True)
        bad["written"] = sorted(p.name for pattern in ("never*", "nowhere*") for p in self.out.glob(pattern))
        res["bad"] = bad
        return res

    def frame_names(self):
        frame_path = self.module("splat_addon.files.animation").frame_path
        cases = [
            ("/a/shot_####.ply", 7),
            ("/a/shot.ply", 7),
            ("/a/shot_##.ply", 123),
            ("/a/v#_f###.spz", 5),
            ("/a/shot_####.ply", -3),
            ("/a/shot.ply", 12345),
            ("/a/shot", 2),
        ]
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
        self.image_format(render.image_settings, "PNG")
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
            "from-mesh ply": [
                "from-mesh",
                str(d / "grid.ply"),
                "--objects",
                "Grid",
                "--max-splats",
                "250",
                "--no-calibrate",
            ],
            "from-mesh blend": [
                "from-mesh",
                str(d / "grid.blend"),
                "--objects",
                "Grid",
                "--max-splats",
                "100",
                "--no-calibrate",
            ],
            "from-mesh classic": [
                "from-mesh",
                str(d / "grid_classic.spz"),
                "--objects",
                "Grid",
                "--max-splats",
                "100",
                "--no-calibrate",
                "--mode",
                "classic",
            ],
            "from-mesh camera": ["from-mesh", str(d / "cam.ply"), "--objects", "Camera"],
            "from-mesh unknown": ["from-mesh", str(d / "cam.ply"), "--objects", "Nope"],
            "from-mesh bad extension": ["from-mesh", str(d / "grid.xyz"), "--objects", "Grid"],
            "from-mesh target uncalibrated": [
                "from-mesh",
                str(d / "t.ply"),
                "--objects",
                "Grid",
                "--target-psnr",
                "20",
                "--no-calibrate",
            ],
            "from-mesh bake views 0": [
                "from-mesh",
                str(d / "x.ply"),
                "--objects",
                "Grid",
                "--appearance",
                "rendered",
                "--bake-views",
                "0",
            ],
            "from-mesh bake samples 2.5": [
                "from-mesh",
                str(d / "x.ply"),
                "--objects",
                "Grid",
                "--appearance",
                "rendered",
                "--bake-samples",
                "2.5",
            ],
            "from-mesh bake degree 5": [
                "from-mesh",
                str(d / "x.ply"),
                "--objects",
                "Grid",
                "--appearance",
                "rendered",
                "--bake-degree",
                "5",
            ],
            "from-mesh appearance shiny": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--appearance", "shiny"],
            "from-mesh bake unlit": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--bake-samples", "8"],
            "from-mesh view size 8": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--view-size", "8"],
            "from-mesh help": ["from-mesh", "--help"],
            "from-mesh from camera": [
                "from-mesh",
                str(d / "from_camera.ply"),
                "--objects",
                "Grid",
                "--max-splats",
                "100",
                "--view-size",
                "32",
                "--measure-from",
                "camera",
                "--view-count",
                "2",
            ],
            "from-mesh around": [
                "from-mesh",
                str(d / "around.ply"),
                "--objects",
                "Grid",
                "--max-splats",
                "100",
                "--view-size",
                "32",
                "--view-count",
                "2",
                "--view-near",
                "0.7",
                "--view-far",
                "2.5",
            ],
            "from-mesh view count 0": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--view-count", "0"],
            "from-mesh view near x": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--view-near", "x"],
            "from-mesh view far 500": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--view-far", "500"],
            "from-mesh measure from sky": ["from-mesh", str(d / "x.ply"), "--objects", "Grid", "--measure-from", "sky"],
        }
        outcomes = {name: self.run_command(argv) for name, argv in runs.items()}
        res["calibrate_default"] = (
            self.module("splat_addon.command").parser().parse_args(["from-mesh", str(d / "x.ply")]).calibrate
        )
        res["after"] = {
            "frame": scene.frame_current,
            "engine": render.engine,
            "filepath": render.filepath,
            "hidden": [o.name for o in scene.objects if o.hide_render],
            "format": render.image_settings.file_format,
        }
        cam.data.type = "PANO"
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            outcomes["render panoramic"] = {
                "code": execute(["render", str(d / "pano_"), "--frames", "1"]),
                "stderr": err.getvalue(),
            }
        cam.data.type = "PERSP"
        scene.camera = None
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            outcomes["render no camera"] = {
                "code": execute(["render", str(d / "nocam_"), "--frames", "1"]),
                "stderr": err.getvalue(),
            }
        outcomes["from-mesh from no camera"] = self.run_command(
            ["from-mesh", str(d / "nocam.ply"), "--objects", "Grid", "--measure-from", "camera"]
        )
        scene.camera = cam
        res["outcomes"] = outcomes
        res["files"] = sorted(p.name for p in d.iterdir())
        return res

    def run_command(self, argv):
        """The command run on `argv`: its exit code, stdout, stderr, the objects it added and the
        renders mesh conversion made."""
        bpy = self.bpy
        out, err = io.StringIO(), io.StringIO()
        before = len(bpy.data.objects)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), self.counted_renders() as renders:
            code = self.module("splat_addon.command").execute(argv)
        return {
            "code": code,
            "stdout": out.getvalue(),
            "stderr": err.getvalue(),
            "new_objects": len(bpy.data.objects) - before,
            "renders": dict(renders),
        }

    def cli_bake(self):
        """The lit ball converted by the command to splat files with the Base Color and with the
        Rendered look; the scene, the output folder and the temporary folder's bake folders before and
        after the baked run, and a held-out Cycles view."""
        import tempfile

        ball, _ = self.lit_ball()
        d, temp = self.out / "cli_bake", self.work / "cli_bake_temp"  # a temporary folder of its own
        d.mkdir()
        temp.mkdir()

        def files():
            return {"out": sorted(p.name for p in d.iterdir()), "temp": sorted(p.name for p in temp.iterdir())}

        common = ["--objects", "ball", "--max-splats", "600", "--view-size", "32"]
        res = {"base": self.run_command(["from-mesh", str(d / "base.ply"), *common])}
        res["before"], res["files_before"] = self.scene_state(), files()
        tempfile.tempdir = str(temp)
        try:
            res["baked"] = self.run_command(
                [
                    "from-mesh",
                    str(d / "baked.ply"),
                    *common,
                    "--appearance",
                    "rendered",
                    "--bake-views",
                    "3",
                    "--bake-samples",
                    "4",
                    "--bake-degree",
                    "1",
                ]
            )
        finally:
            tempfile.tempdir = None
        res["after"], res["files_after"] = self.scene_state(), files()
        res["fitted"] = self.run_command(
            [
                "from-mesh",
                str(d / "fitted.ply"),
                *common,
                "--appearance",
                "rendered",
                "--bake-views",
                "3",
                "--bake-samples",
                "4",
                "--bake-degree",
                "1",
                "--bake-geometry-steps",
                "60",
            ]
        )
        self.held_out_view(ball, "cli_bake_view")
        return res

    def reregister(self):
        import addon_utils

        addon_utils.disable(MODULE, default_set=True)  # each enable unpacks the bundled wheels again
        addon_utils.enable(MODULE, default_set=True)
        command = self.module("splat_addon.command")
        on = command._handle is not None
        addon_utils.disable(MODULE, default_set=True)
        off = command._handle is not None  # unregister() gave the command back
        left = [n for n in dir(self.bpy.types) if n.startswith("SPLAT_")]
        addon_utils.enable(MODULE, default_set=True)
        return {
            "enabled": on,
            "disabled_handle": off,
            "types_left": left,
            "re_enabled": self.module("splat_addon.command")._handle is not None,
        }


if __name__ == "__main__":
    worker_main(Worker)
