"""The Blender side of tests/test_blender_addon.py (run in each Blender of the version matrix; see
workers/base.py)."""

import numpy as np

from workers.base import MODULE, BlenderWorker, point_attribute, point_attributes, splat_total, worker_main

# menu -> entries the extension adds to it (the Object menu gets Join Splats and Check Collisions)
MENUS = {"TOPBAR_MT_file_import": 1, "TOPBAR_MT_file_export": 1, "VIEW3D_MT_object_apply": 1, "VIEW3D_MT_object": 2}
ROTATION, LOG_SCALE, OPACITY, SH = "splat_rotation", "splat_log_scale", "splat_opacity_logit", "splat_sh_"
# Blender 5.3's own Gaussian-splat point clouds (the form new splat objects take there): linear scales,
# radiance:base = DC and opacity, radiance:sh_<j> = SH coefficient j + 1; the exact log-scales and logits
# Splatwright keeps beside them in hidden attributes
NATIVE_ROTATION, NATIVE_SCALE, NATIVE_BASE, NATIVE_SH = "rotation", "scale", "radiance:base", "radiance:sh_"
EXACT = (".splatwright_log_scale", ".splatwright_opacity_logit")
SPLAT_TYPES = ("MESH", "POINTCLOUD")  # the object types splat objects have, in either form
# file (x, y, z) -> Blender (x, z, -y): the documented default for 3DGS captures (-Y up, +Z forward)
DEFAULT_AXES = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
WORLD_COLOR = (0.2, 0.35, 0.5)
RENDER_CASES = {
    # name: resolution x, y, percentage, camera settings, film transparent
    "persp": dict(
        res=(64, 48, 100),
        cam=dict(
            type="PERSP", lens=35.0, sensor_fit="AUTO", shift_x=0.08, shift_y=-0.05, clip_start=0.1, clip_end=100.0
        ),
        loc=(0.6, -4.0, 0.9),
        transparent=False,
    ),
    "persp_vertical": dict(
        res=(50, 70, 100),
        cam=dict(
            type="PERSP",
            lens=40.0,
            sensor_fit="VERTICAL",
            sensor_height=20.0,
            shift_x=-0.05,
            clip_start=3.4,
            clip_end=100.0,
        ),
        loc=(-1.0, -3.5, 1.5),
        transparent=True,
    ),
    "ortho": dict(
        res=(96, 64, 50),
        cam=dict(type="ORTHO", ortho_scale=3.0, sensor_fit="AUTO", shift_y=0.1, clip_start=0.1, clip_end=100.0),
        loc=(0.0, -5.0, 0.0),
        transparent=False,
    ),
}
ANIM_OFFSET = (0.25, 0.0, -0.1)
FAR = (1.0e6, -2.0e6, 5.0e5)  # a scene far from the origin, the camera close to it
FORMAT_CLOUD = (200, 3, 2)  # _self.random_cloud(n, degree, seed) written as USD, SPZ and .splat


# the worker (runs inside a separate Python process with bpy) ---------------------------------------


class Worker(BlenderWorker):
    """Every Blender-side step; each records into self.results[step] (or the traceback on failure)."""

    steps = (
        "install",
        "import_ply",
        "formats",
        "export_axes",
        "edits",
        "join",
        "selected_only",
        "bad_inputs",
        "wrong_objects",
        "display",
        "render",
        "render_antialiased",
        "render_edges",
        "animation",
        "reregister",
    )
    keep_objects = ("Cube", "Camera", "Light")  # the startup scene; every step adds only splat objects
    orphan_kinds = ("meshes", "pointclouds")
    inventory_kinds = ("objects", "meshes", "pointclouds", "materials", "node_groups", "cameras", "collections")

    # helpers -----------------------------------------------------------------------------------

    def import_file(self, name, **kw):
        res = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name), **kw)
        if res["error"]:
            raise RuntimeError(res["error"])
        return self.bpy.context.active_object

    def export(self, name, **kw):
        return self.call(self.bpy.ops.splat.export_file, filepath=str(self.out / name), **kw)

    def dump(self, obj, name):
        """The object's point attributes read through Blender's API by their documented names (a native
        cloud's hidden exact values too); `marker`: the splat mesh's property, a point cloud's type."""
        geometry = obj.data
        arrays = point_attributes(geometry)
        for hidden in EXACT if obj.type == "POINTCLOUD" else ():
            arrays[hidden] = point_attribute(geometry, hidden)
        np.savez(self.out / f"{name}.npz", matrix_world=np.array(obj.matrix_world), **arrays)
        marker = geometry.type if obj.type == "POINTCLOUD" else "splatwright" in geometry.keys()
        return {
            "type": obj.type,
            "marker": marker,
            "modifiers": [m.name for m in obj.modifiers],
            "count": splat_total(obj),
        }

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        return {
            "addons": [a.module for a in bpy.context.preferences.addons],
            "operators": [hasattr(bpy.types, n) for n in ("SPLAT_OT_import_file", "SPLAT_OT_export_file")],
            "engine": self.engine_registered(),
            "menus": self.added_menus(),
        }

    def engine_registered(self):
        """Whether the scene accepts SPLATWRIGHT as its render engine (it must be registered)."""
        render = self.bpy.context.scene.render
        before = render.engine
        try:
            render.engine = "SPLATWRIGHT"
        except TypeError:
            return False
        render.engine = before
        return True

    def added_menus(self):
        return {menu: self.menu_entries(menu) for menu in MENUS}

    def import_ply(self):
        obj = self.import_file("a.ply")
        info = self.dump(obj, "import_a")
        flat = self.import_file("a.ply", axis_forward="Y", axis_up="Z")
        info["identity_matrix"] = np.array(flat.matrix_world).tolist()
        info["active"] = self.bpy.context.active_object.name
        info["selected"] = sorted(o.name for o in self.bpy.context.selected_objects)
        self.select([obj])
        info["export"] = self.export("a_roundtrip.ply", selected_only=True)
        before = set(self.bpy.data.objects)
        self.bpy.ops.splat.import_file(directory=str(self.work), files=[{"name": "a.ply"}, {"name": "b.ply"}])
        info["multi"] = sorted(splat_total(o) for o in set(self.bpy.data.objects) - before)
        info["multi_selected"] = len(self.bpy.context.selected_objects)
        # importing while another object is in Edit Mode (no operator that needs Object Mode may run)
        self.select([self.bpy.data.objects["Cube"]])
        self.bpy.ops.object.mode_set(mode="EDIT")
        res = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / "b.ply"))
        made = self.bpy.context.active_object
        info["in_edit_mode"] = {**res, "count": splat_total(made) if made.name != "Cube" else None}
        self.select([self.bpy.data.objects["Cube"]])
        self.bpy.ops.object.mode_set(mode="OBJECT")
        return info

    def formats(self):
        done = {}
        for name in ("fmt.usda", "fmt.spz", "fmt.splat"):
            obj = self.import_file(name)
            self.select([obj])
            done[name] = {
                "export": self.export("re_" + name, selected_only=True),
                "matrix_world": np.array(obj.matrix_world).tolist(),
                "count": splat_total(obj),
            }
        return done

    def export_axes(self):
        obj = self.import_file("a.ply")
        self.select([obj])
        return {"export": self.export("a_blender_axes.ply", selected_only=True, axis_forward="Y", axis_up="Z")}

    def delete_every_third(self, obj):
        """Delete splats 0, 3, 6, ... as an artist would: bmesh on a splat mesh, Edit Mode's Delete on a
        point cloud. Returns how many there were."""
        n = splat_total(obj)
        if obj.type == "MESH":
            import bmesh

            bm = bmesh.new()
            bm.from_mesh(obj.data)
            bm.verts.ensure_lookup_table()
            bmesh.ops.delete(bm, geom=[bm.verts[i] for i in range(0, n, 3)], context="VERTS")
            bm.to_mesh(obj.data)
            bm.free()
            return n
        selection = obj.data.attributes.get(".selection") or obj.data.attributes.new(".selection", "BOOLEAN", "POINT")
        selection.data.foreach_set("value", np.arange(n) % 3 == 0)
        self.select([obj])
        self.bpy.ops.object.mode_set(mode="EDIT")
        self.bpy.ops.pointcloud.delete()
        self.bpy.ops.object.mode_set(mode="OBJECT")
        return n

    def edits(self):
        obj = self.import_file("a.ply")
        n = self.delete_every_third(obj)
        obj.location = (1.0, -2.0, 0.5)
        obj.rotation_euler = (0.3, -0.2, 0.5)
        obj.scale = (1.5, 1.5, 1.5)
        stretched = self.import_file("a.ply")
        stretched.rotation_euler = (1.2, 0.4, -0.7)
        stretched.scale = (2.0, 0.5, 1.25)
        self.bpy.context.view_layer.update()
        res = {
            "kept": [i for i in range(n) if i % 3],
            "matrix_world": np.array(obj.matrix_world).tolist(),
            "stretched_matrix_world": np.array(stretched.matrix_world).tolist(),
        }
        self.select([obj])
        res["export"] = self.export("edited.ply", selected_only=True)
        self.select([stretched])
        res["export_stretched"] = self.export("stretched.ply", selected_only=True)
        self.select([obj])
        res["apply"] = self.call(self.bpy.ops.splat.apply_transform)
        res["applied_matrix"] = np.array(obj.matrix_world).tolist()
        res["export_applied"] = self.export("applied.ply", selected_only=True)
        return res

    def join(self):
        bpy = self.bpy
        a = self.import_file("a.ply")
        b = self.import_file("b.ply")
        b.location = (1.0, 2.0, 3.0)
        bpy.context.view_layer.update()
        with bpy.context.temp_override(active_object=a, selected_editable_objects=[a, b], selected_objects=[a, b]):
            bpy.ops.object.join()
        self.select([a])
        res = {
            "objects": [o.name for o in bpy.data.objects if o.type in SPLAT_TYPES],
            "export": self.export("joined.ply", selected_only=True),
        }
        # Join Splats: b turned and stretched, joined into a moved a; the splats keep their world shape.
        self.clear_scene()
        a, b = self.import_file("a.ply"), self.import_file("b.ply")
        a.location = (0.5, 0.0, -1.0)
        b.rotation_euler = (0.3, -0.7, 1.1)
        b.scale = (1.0, 2.0, 0.5)
        bpy.context.view_layer.update()
        res["world_a"], res["world_b"] = [list(map(list, o.matrix_world)) for o in (a, b)]
        self.select([a, b], active=a)
        res["join_splats"] = self.call(bpy.ops.splat.join)
        self.select([a])
        res["splat_objects"] = [o.name for o in bpy.data.objects if o.type in SPLAT_TYPES and o.name != "Cube"]
        res["export_splats"] = self.export("joined_splats.ply", selected_only=True)
        return res

    def selected_only(self):
        a = self.import_file("a.ply")
        b = self.import_file("b.ply")
        self.select([b])
        res = {"selected": self.export("selected.ply", selected_only=True)}
        a.hide_set(True)
        res["visible"] = self.export("visible.ply", selected_only=False)
        a.hide_set(False)
        res["all"] = self.export("all.ply", selected_only=False)
        return res

    def bad_inputs(self):
        cases = {}
        for name, kw in (
            ("garbage.ply", {}),
            ("truncated.ply", {}),
            ("wrong_ext.xyz", {}),
            ("missing.ply", {}),
            ("nan.ply", {"drop_invalid": False}),
            ("not_3dgs.ply", {}),
        ):
            before = self.inventory()
            res = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name), **kw)
            cases[name] = {**res, "unchanged": before == self.inventory()}
        before = self.inventory()
        res = self.call(
            self.bpy.ops.splat.import_file,
            directory=str(self.work),
            files=[{"name": "a.ply"}, {"name": "truncated.ply"}],
        )
        cases["good and bad together"] = {**res, "unchanged": before == self.inventory()}
        before = self.inventory()
        obj = self.import_file("nan.ply")  # drop_invalid defaults to True
        cases["nan.ply dropped"] = {
            "count": splat_total(obj),
            "added": len(self.inventory()["objects"]) - len(before["objects"]),
        }
        return cases

    def wrong_objects(self):
        bpy = self.bpy
        cases = {}
        self.select([bpy.data.objects["Cube"], bpy.data.objects["Camera"]])
        cases["non-splat selection"] = self.export("never1.ply", selected_only=True)
        self.select([])
        cases["empty selection"] = self.export("never2.ply", selected_only=True)
        obj = self.import_file("a.ply")
        obj.data.attributes.remove(obj.data.attributes[ROTATION if obj.type == "MESH" else NATIVE_ROTATION])
        self.select([obj])
        cases["missing attribute"] = self.export("never3.ply", selected_only=True)
        obj2 = self.import_file("a.ply")
        self.select([obj2])
        cases["unknown extension"] = self.export("never4.xyz", selected_only=True)
        cases["written"] = sorted(p.name for p in self.out.glob("never*"))
        return cases

    def display(self):
        """What the viewport draws of an imported object: the point cloud the display modifier makes of a
        splat mesh (its radii), or Blender's own Gaussian splats (their scales), read from the depsgraph."""
        bpy = self.bpy
        obj = self.import_file("a.ply")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        found = []
        size = "radius" if obj.type == "MESH" else NATIVE_SCALE
        for inst in depsgraph.object_instances:  # instance data is only valid during iteration
            if inst.object.type == "POINTCLOUD" and inst.object.original == obj:
                points = inst.object.data
                found.append(
                    {
                        "count": len(points.points),
                        "size": point_attribute(points, size),
                        "type": points.type if hasattr(points, "type") else None,
                        "material": [m.name for m in points.materials if m is not None],
                    }
                )
        if len(found) != 1:
            return {"pointclouds": len(found)}
        np.save(self.out / "display_size.npy", found[0].pop("size"))
        res = {
            "pointclouds": 1,
            **found[0],
            "modifiers": [m.name for m in obj.modifiers],
            "added": self.module("splat_addon.data.display").add_display(obj) is not None,
        }
        if obj.type != "MESH":
            return res
        res["show_render"] = obj.modifiers[0].show_render
        mod = obj.modifiers[0]
        self.module("splat_addon.data.display").set_input(mod, "Display Ratio", 0.5)
        obj.update_tag()
        depsgraph = bpy.context.evaluated_depsgraph_get()
        res["half_count"] = [
            len(inst.object.data.points)
            for inst in depsgraph.object_instances
            if inst.object.type == "POINTCLOUD" and inst.object.original == obj
        ]
        return res

    def setup_render(self, case):
        bpy = self.bpy
        from mathutils import Vector

        scene = bpy.context.scene
        scene.render.engine = "SPLATWRIGHT"
        scene.splatwright_mesh_engine = "NONE"  # splats alone: the startup Cube stays out
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
        scene.view_settings.exposure = 0.0
        scene.view_settings.gamma = 1.0
        scene.display_settings.display_device = "sRGB"
        scene.render.dither_intensity = 0.0  # Blender dithers 8-bit output by default
        x, y, pct = case["res"]
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = x, y, pct
        scene.render.film_transparent = case["transparent"]
        scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = case.get("aspect", (1.0, 1.0))
        world = scene.world
        background = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Color"].default_value = (*WORLD_COLOR, 1.0)
        background.inputs["Strength"].default_value = 1.0
        cam = scene.camera
        for key, value in case["cam"].items():
            setattr(cam.data, key, value)
        cam.location = case["loc"]
        cam.rotation_euler = (Vector((0.0, 0.0, 0.0)) - Vector(case["loc"])).to_track_quat("-Z", "Y").to_euler()
        bpy.context.view_layer.use_pass_z = True
        bpy.context.view_layer.update()
        return scene, cam

    def camera_record(self, scene, cam, points):
        """The camera's numbers and Blender's own projection of `points` (world space)."""
        from bpy_extras.object_utils import world_to_camera_view
        from mathutils import Vector

        proj = np.array([tuple(world_to_camera_view(scene, cam, Vector(p))) for p in points])
        d = cam.data
        return {
            "matrix_world": np.array(cam.matrix_world).tolist(),
            "lens": d.lens,
            "sensor_width": d.sensor_width,
            "sensor_height": d.sensor_height,
            "sensor_fit": d.sensor_fit,
            "shift_x": d.shift_x,
            "shift_y": d.shift_y,
            "type": d.type,
            "ortho_scale": d.ortho_scale,
            "clip_start": d.clip_start,
            "clip_end": d.clip_end,
            "projection": proj.tolist(),
            "pixel_aspect_x": scene.render.pixel_aspect_x,
            "pixel_aspect_y": scene.render.pixel_aspect_y,
            "resolution": [scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage],
        }

    def render(self):
        bpy = self.bpy
        obj = self.import_file("scene.ply", axis_forward="Y", axis_up="Z")  # world space = file space
        points = np.load(self.work / "scene_positions.npy")
        res = {}
        for name, case in RENDER_CASES.items():
            scene, cam = self.setup_render(case)
            settings = scene.render.image_settings
            self.image_format(settings, "PNG", color_mode="RGBA" if case["transparent"] else "RGB", color_depth="8")
            scene.render.filepath = str(self.out / f"render_{name}.png")
            bpy.ops.render.render(write_still=True)
            self.image_format(settings, "OPEN_EXR_MULTILAYER", color_depth="32")
            scene.render.filepath = str(self.out / f"render_{name}.exr")
            bpy.ops.render.render(write_still=True)
            res[name] = self.camera_record(scene, cam, points)
        # the same image under AgX, to show the view transform is what turns linear into display values
        scene, cam = self.setup_render(RENDER_CASES["persp"])
        scene.view_settings.view_transform = "AgX"
        settings = scene.render.image_settings
        self.image_format(settings, "PNG", color_mode="RGB")
        scene.render.filepath = str(self.out / "render_persp_agx.png")
        bpy.ops.render.render(write_still=True)
        res["hidden_render"] = obj.hide_render
        return res

    def render_antialiased(self):
        """Splats made for antialiased rendering (a PLY that says so): the object keeps the mark, the
        engine renders them so, export writes it; beside classic splats both render classic."""
        bpy = self.bpy
        obj = self.import_file("scene_aa.ply", axis_forward="Y", axis_up="Z")
        res = {"marked": bool(obj.data.get("splatwright_antialiased", False))}
        scene, cam = self.setup_render(RENDER_CASES["persp"])
        res["alone"] = self.render_png(scene, cam, "render_aa")
        res["export"] = self.export("aa.spz", axis_forward="Y", axis_up="Z")
        res["export_usd"] = self.export("aa.usd", axis_forward="Y", axis_up="Z")  # text on 4.2, crate after
        other = self.import_file("b.ply", axis_forward="Y", axis_up="Z")
        res["mixed"] = self.render_png(scene, cam, "render_aa_mixed")
        res["mixed_export"] = self.export("mixed.spz", axis_forward="Y", axis_up="Z")
        self.select([obj, other], active=obj)
        res["join"] = self.call(bpy.ops.splat.join)
        res["after_join"] = sorted(o.name for o in bpy.data.objects if o.type in SPLAT_TYPES and o.name != "Cube")
        return res

    def render_edges(self):
        bpy = self.bpy
        obj = self.import_file("scene.ply", axis_forward="Y", axis_up="Z")
        res = {}
        far = dict(RENDER_CASES["persp"], loc=tuple(np.add(FAR, RENDER_CASES["persp"]["loc"])))
        scene, cam = self.setup_render(far)
        obj.location = FAR
        cam.rotation_euler = (obj.location - cam.location).to_track_quat("-Z", "Y").to_euler()
        bpy.context.view_layer.update()
        res["far"] = self.render_png(scene, cam, "edge_far")
        res["far"]["object_matrix"] = np.array(obj.matrix_world).tolist()
        obj.location = (0.0, 0.0, 0.0)
        # non-square pixels: PNG only (Blender 5.0 cannot write them to a multilayer EXR with Depth)
        scene, cam = self.setup_render(dict(RENDER_CASES["persp_vertical"], aspect=(1.0, 1.5), transparent=False))
        res["aspect"] = self.render_png(scene, cam, "edge_aspect", np.load(self.work / "scene_positions.npy"))
        points = np.load(self.work / "scene_positions.npy")
        for name, lens in (("wide", 1.5), ("narrow", 3000.0)):  # ~170 and ~0.7 degrees across
            case = dict(RENDER_CASES["persp"], cam=dict(RENDER_CASES["persp"]["cam"], lens=lens))
            scene, cam = self.setup_render(case)
            res[name] = self.render_png(scene, cam, f"edge_{name}", points)
        scene, cam = self.setup_render(dict(RENDER_CASES["persp"], res=(4, 4, 25)))
        res["tiny"] = self.render_png(scene, cam, "edge_tiny")
        scene, cam = self.setup_render(RENDER_CASES["persp"])
        obj.hide_render = True
        res["hidden"] = self.render_png(scene, cam, "edge_hidden")
        obj.hide_render = False
        cam.data.type = "PANO"
        res["panoramic"] = self.call(bpy.ops.render.render, write_still=False)
        cam.data.type = "PERSP"
        return res

    def render_png(self, scene, cam, name, points=np.zeros((0, 3))):
        settings = scene.render.image_settings
        self.image_format(settings, "PNG", color_mode="RGB", color_depth="8")
        scene.render.filepath = str(self.out / f"{name}.png")
        self.bpy.ops.render.render(write_still=True)
        return self.camera_record(scene, cam, points)

    def animation(self):
        bpy = self.bpy
        obj = self.import_file("scene.ply", axis_forward="Y", axis_up="Z")
        scene, cam = self.setup_render(RENDER_CASES["persp"])
        obj.location = (0.0, 0.0, 0.0)
        obj.keyframe_insert("location", frame=1)
        obj.location = ANIM_OFFSET
        obj.keyframe_insert("location", frame=2)
        scene.frame_start, scene.frame_end = 1, 2
        settings = scene.render.image_settings
        self.image_format(settings, "PNG", color_mode="RGB")
        scene.render.filepath = str(self.out / "anim_")
        bpy.ops.render.render(animation=True)
        scene.frame_set(1)
        return {
            "camera": self.camera_record(scene, cam, np.zeros((0, 3))),
            "frames": sorted(p.name for p in self.out.glob("anim_*.png")),
        }

    def numpy_huge_pages(self):
        """NumPy's huge-page advice in this Blender, read by setting it and setting it back."""
        switch = self.module("core.memory").numpy_huge_pages
        now = switch(True)
        switch(now)
        return now

    def reregister(self):
        import addon_utils

        bpy = self.bpy
        addon_utils.disable(MODULE, default_set=True)  # each enable unpacks the bundled wheels again
        addon_utils.enable(MODULE, default_set=True)
        enabled = {
            "menus": self.added_menus(),
            "engine_panels": self.engine_panels(),
            "operators": hasattr(bpy.types, "SPLAT_OT_import_file"),
            "huge_pages": self.numpy_huge_pages(),
        }
        addon_utils.disable(MODULE, default_set=True)
        engine = self.engine_registered()
        left = [
            n
            for n in dir(bpy.types)
            if n.startswith(("SPLAT_", "RENDER_PT_splatwright")) or n == "SplatwrightRenderEngine"
        ]
        disabled = {
            "menus": self.added_menus(),
            "engine_panels": self.engine_panels(),
            "engine": engine,
            "types_left": left,
            "addons": [a.module for a in bpy.context.preferences.addons],
            "huge_pages": self.numpy_huge_pages(),
        }
        addon_utils.enable(MODULE, default_set=True)
        return {"enabled": enabled, "disabled": disabled, "re_enabled_menus": self.added_menus()}

    def engine_panels(self):
        """Blender's own panels that list our engine (ours are checked through bpy.types)."""
        return sum(
            1
            for p in self.bpy.types.Panel.__subclasses__()
            if "SPLATWRIGHT" in getattr(p, "COMPAT_ENGINES", ()) and not p.__module__.startswith(MODULE)
        )


if __name__ == "__main__":
    worker_main(Worker)
