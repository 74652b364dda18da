"""The Blender extension, headless: built into a zip, installed into a temporary user repository
and enabled as Blender does it, then driven by one worker process.

The worker is this file run as a script (a pytest process imports bpy once, and
BLENDER_USER_RESOURCES must be set before that). It performs every Blender-side step, saving what
it exported, rendered and read back through Blender's own API into a work folder plus results.json.
The tests below judge those outputs against references computed here without Blender: the source
files read by splatwright.io, float64 covariances and SH colours, Blender's own camera projection
(world_to_camera_view) and the core renderer.
"""

import warnings

import numpy as np
import pytest
from blender_session import MODULE, BlenderWorker, run_worker, worker_main
from helpers import cloud_covariances, read

pytestmark = [pytest.mark.blender, pytest.mark.slow]      # one Blender worker for the module: ~5-15 s

# menu -> entries the extension adds to it (the Object menu gets Join Splats and Check Collisions)
MENUS = {"TOPBAR_MT_file_import": 1, "TOPBAR_MT_file_export": 1, "VIEW3D_MT_object_apply": 1, "VIEW3D_MT_object": 2}
ROTATION, LOG_SCALE, OPACITY, SH = "splat_rotation", "splat_log_scale", "splat_opacity_logit", "splat_sh_"
# file (x, y, z) -> Blender (x, z, -y): the documented default for 3DGS captures (-Y up, +Z forward)
DEFAULT_AXES = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
WORLD_COLOR = (0.2, 0.35, 0.5)
RENDER_CASES = {
    # name: resolution x, y, percentage, camera settings, film transparent
    "persp": dict(res=(64, 48, 100), cam=dict(type="PERSP", lens=35.0, sensor_fit="AUTO", shift_x=0.08,
                                               shift_y=-0.05, clip_start=0.1, clip_end=100.0),
                  loc=(0.6, -4.0, 0.9), transparent=False),
    "persp_vertical": dict(res=(50, 70, 100), cam=dict(type="PERSP", lens=40.0, sensor_fit="VERTICAL",
                                                        sensor_height=20.0, shift_x=-0.05, clip_start=3.4,
                                                        clip_end=100.0),
                           loc=(-1.0, -3.5, 1.5), transparent=True),
    "ortho": dict(res=(96, 64, 50), cam=dict(type="ORTHO", ortho_scale=3.0, sensor_fit="AUTO", shift_y=0.1,
                                              clip_start=0.1, clip_end=100.0),
                  loc=(0.0, -5.0, 0.0), transparent=False),
}
ANIM_OFFSET = (0.25, 0.0, -0.1)
FAR = (1.0e6, -2.0e6, 5.0e5)        # a scene far from the origin, the camera close to it
FORMAT_CLOUD = (200, 3, 2)          # _random_cloud(n, degree, seed) written as USD, SPZ and .splat


# the worker (runs inside a separate Python process with bpy) ---------------------------------------

class Worker(BlenderWorker):
    """Every Blender-side step; each records into self.results[step] (or the traceback on failure)."""

    steps = ("install", "import_ply", "formats", "export_axes", "edits", "join", "selected_only", "bad_inputs",
             "wrong_objects", "display", "render", "render_edges", "animation", "reregister")
    keep_objects = ("Cube", "Camera", "Light")     # the startup scene; every step adds only splat meshes
    orphan_kinds = ("meshes",)
    inventory_kinds = ("objects", "meshes", "materials", "node_groups", "cameras", "collections")

    # helpers -----------------------------------------------------------------------------------

    def import_file(self, name, **kw):
        res = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name), **kw)
        if res["error"]:
            raise RuntimeError(res["error"])
        return self.bpy.context.active_object

    def export(self, name, **kw):
        return self.call(self.bpy.ops.splat.export_file, filepath=str(self.out / name), **kw)

    def dump(self, obj, name):
        """The object's point attributes read through Blender's API by their documented names."""
        mesh = obj.data
        n = len(mesh.vertices)
        arrays = {"co": np.empty(n * 3, np.float32)}
        mesh.vertices.foreach_get("co", arrays["co"])
        props = {"FLOAT": ("value", 1), "INT": ("value", 1), "FLOAT_VECTOR": ("vector", 3),
                 "FLOAT2": ("vector", 2), "QUATERNION": ("value", 4)}
        for attr in mesh.attributes:
            if attr.domain == "POINT" and attr.data_type in props and not attr.name.startswith("."):
                prop, width = props[attr.data_type]
                values = np.empty(n * width, np.int32 if attr.data_type == "INT" else np.float32)
                attr.data.foreach_get(prop, values)
                arrays[attr.name] = values
        arrays = {k: v.reshape(n, -1) for k, v in arrays.items()}
        np.savez(self.out / f"{name}.npz", matrix_world=np.array(obj.matrix_world), **arrays)
        return {"type": obj.type, "marker": "splatwright" in mesh.keys(),
                "modifiers": [m.name for m in obj.modifiers], "count": n}

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        return {"addons": [a.module for a in bpy.context.preferences.addons],
                "operators": [hasattr(bpy.types, n) for n in ("SPLAT_OT_import_file", "SPLAT_OT_export_file")],
                "engine": self.engine_registered(),
                "menus": self.added_menus()}

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
        info["multi"] = sorted(len(o.data.vertices) for o in set(self.bpy.data.objects) - before)
        info["multi_selected"] = len(self.bpy.context.selected_objects)
        return info

    def formats(self):
        done = {}
        for name in ("fmt.usdc", "fmt.spz", "fmt.splat"):
            obj = self.import_file(name)
            self.select([obj])
            done[name] = {"export": self.export("re_" + name, selected_only=True),
                          "matrix_world": np.array(obj.matrix_world).tolist(), "count": len(obj.data.vertices)}
        return done

    def export_axes(self):
        obj = self.import_file("a.ply")
        self.select([obj])
        return {"export": self.export("a_blender_axes.ply", selected_only=True, axis_forward="Y", axis_up="Z")}

    def edits(self):
        import bmesh
        obj = self.import_file("a.ply")
        mesh = obj.data
        bm = bmesh.new()
        bm.from_mesh(mesh)
        bm.verts.ensure_lookup_table()
        n = len(bm.verts)
        bmesh.ops.delete(bm, geom=[bm.verts[i] for i in range(0, n, 3)], context="VERTS")
        bm.to_mesh(mesh)
        bm.free()
        obj.location = (1.0, -2.0, 0.5)
        obj.rotation_euler = (0.3, -0.2, 0.5)
        obj.scale = (1.5, 1.5, 1.5)
        stretched = self.import_file("a.ply")
        stretched.rotation_euler = (1.2, 0.4, -0.7)
        stretched.scale = (2.0, 0.5, 1.25)
        self.bpy.context.view_layer.update()
        res = {"kept": [i for i in range(n) if i % 3], "matrix_world": np.array(obj.matrix_world).tolist(),
               "stretched_matrix_world": np.array(stretched.matrix_world).tolist()}
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
        res = {"objects": [o.name for o in bpy.data.objects if o.type == "MESH"],
               "export": self.export("joined.ply", selected_only=True)}
        # Join Splats: b turned and stretched, joined into a moved a; the splats keep their world shape.
        self.clear_scene()
        a, b = self.import_file("a.ply"), self.import_file("b.ply")
        a.location = (0.5, 0.0, -1.0)
        b.rotation_euler = (0.3, -0.7, 1.1)
        b.scale = (1.0, 2.0, 0.5)
        bpy.context.view_layer.update()
        res["world_a"], res["world_b"] = ([list(map(list, o.matrix_world)) for o in (a, b)])
        self.select([a, b], active=a)
        res["join_splats"] = self.call(bpy.ops.splat.join)
        self.select([a])
        res["splat_objects"] = [o.name for o in bpy.data.objects if o.type == "MESH" and o.name != "Cube"]
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
        for name, kw in (("garbage.ply", {}), ("truncated.ply", {}), ("wrong_ext.xyz", {}), ("missing.ply", {}),
                         ("nan.ply", {"drop_invalid": False}), ("not_3dgs.ply", {})):
            before = self.inventory()
            res = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name), **kw)
            cases[name] = {**res, "unchanged": before == self.inventory()}
        before = self.inventory()
        res = self.call(self.bpy.ops.splat.import_file, directory=str(self.work),
                        files=[{"name": "a.ply"}, {"name": "truncated.ply"}])
        cases["good and bad together"] = {**res, "unchanged": before == self.inventory()}
        before = self.inventory()
        obj = self.import_file("nan.ply")      # drop_invalid defaults to True
        cases["nan.ply dropped"] = {"count": len(obj.data.vertices), "added": len(self.inventory()["objects"]) -
                                    len(before["objects"])}
        return cases

    def wrong_objects(self):
        bpy = self.bpy
        cases = {}
        self.select([bpy.data.objects["Cube"], bpy.data.objects["Camera"]])
        cases["non-splat selection"] = self.export("never1.ply", selected_only=True)
        self.select([])
        cases["empty selection"] = self.export("never2.ply", selected_only=True)
        obj = self.import_file("a.ply")
        obj.data.attributes.remove(obj.data.attributes[ROTATION])
        self.select([obj])
        cases["missing attribute"] = self.export("never3.ply", selected_only=True)
        obj2 = self.import_file("a.ply")
        self.select([obj2])
        cases["unknown extension"] = self.export("never4.xyz", selected_only=True)
        cases["written"] = sorted(p.name for p in self.out.glob("never*"))
        return cases

    def display(self):
        bpy = self.bpy
        obj = self.import_file("a.ply")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        found = []
        for inst in depsgraph.object_instances:      # instance data is only valid during iteration
            if inst.object.type == "POINTCLOUD" and inst.object.original == obj:
                points = inst.object.data
                radius = np.empty(len(points.points), np.float32)
                points.attributes["radius"].data.foreach_get("value", radius)
                found.append({"count": len(points.points), "radius": radius,
                              "material": [m.name for m in points.materials if m is not None]})
        if len(found) != 1:
            return {"pointclouds": len(found)}
        np.save(self.out / "display_radius.npy", found[0].pop("radius"))
        res = {"pointclouds": 1, **found[0], "show_render": obj.modifiers[0].show_render}
        mod = obj.modifiers[0]
        mod[next(i.identifier for i in mod.node_group.interface.items_tree
                 if getattr(i, "name", "") == "Display Ratio")] = 0.5
        obj.update_tag()
        depsgraph = bpy.context.evaluated_depsgraph_get()
        res["half_count"] = [len(inst.object.data.points) for inst in depsgraph.object_instances
                             if inst.object.type == "POINTCLOUD" and inst.object.original == obj]
        return res

    def setup_render(self, case):
        bpy = self.bpy
        from mathutils import Vector
        scene = bpy.context.scene
        scene.render.engine = "SPLATWRIGHT"
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
        scene.view_settings.exposure = 0.0
        scene.view_settings.gamma = 1.0
        scene.display_settings.display_device = "sRGB"
        scene.render.dither_intensity = 0.0      # Blender dithers 8-bit output by default
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
        return {"matrix_world": np.array(cam.matrix_world).tolist(), "lens": d.lens, "sensor_width": d.sensor_width,
                "sensor_height": d.sensor_height, "sensor_fit": d.sensor_fit, "shift_x": d.shift_x,
                "shift_y": d.shift_y, "type": d.type, "ortho_scale": d.ortho_scale, "clip_start": d.clip_start,
                "clip_end": d.clip_end, "projection": proj.tolist(),
                "pixel_aspect_x": scene.render.pixel_aspect_x, "pixel_aspect_y": scene.render.pixel_aspect_y,
                "resolution": [scene.render.resolution_x, scene.render.resolution_y,
                               scene.render.resolution_percentage]}

    def render(self):
        bpy = self.bpy
        obj = self.import_file("scene.ply", axis_forward="Y", axis_up="Z")   # world space = file space
        points = np.load(self.work / "scene_positions.npy")
        res = {}
        for name, case in RENDER_CASES.items():
            scene, cam = self.setup_render(case)
            settings = scene.render.image_settings
            settings.media_type = "IMAGE"
            settings.file_format = "PNG"
            settings.color_mode = "RGBA" if case["transparent"] else "RGB"
            settings.color_depth = "8"
            scene.render.filepath = str(self.out / f"render_{name}.png")
            bpy.ops.render.render(write_still=True)
            settings.media_type = "MULTI_LAYER_IMAGE"
            settings.file_format = "OPEN_EXR_MULTILAYER"
            settings.color_depth = "32"
            scene.render.filepath = str(self.out / f"render_{name}.exr")
            bpy.ops.render.render(write_still=True)
            res[name] = self.camera_record(scene, cam, points)
        # the same image under AgX, to show the view transform is what turns linear into display values
        scene, cam = self.setup_render(RENDER_CASES["persp"])
        scene.view_settings.view_transform = "AgX"
        settings = scene.render.image_settings
        settings.media_type, settings.file_format, settings.color_mode = "IMAGE", "PNG", "RGB"
        scene.render.filepath = str(self.out / "render_persp_agx.png")
        bpy.ops.render.render(write_still=True)
        res["hidden_render"] = obj.hide_render
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
        for name, lens in (("wide", 1.5), ("narrow", 3000.0)):     # ~170 and ~0.7 degrees across
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
        settings.media_type, settings.file_format, settings.color_mode = "IMAGE", "PNG", "RGB"
        settings.color_depth = "8"
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
        settings.media_type, settings.file_format, settings.color_mode = "IMAGE", "PNG", "RGB"
        scene.render.filepath = str(self.out / "anim_")
        bpy.ops.render.render(animation=True)
        scene.frame_set(1)
        return {"camera": self.camera_record(scene, cam, np.zeros((0, 3))),
                "frames": sorted(p.name for p in self.out.glob("anim_*.png"))}

    def reregister(self):
        import addon_utils
        bpy = self.bpy
        for _ in range(2):
            addon_utils.disable(MODULE, default_set=True)
            addon_utils.enable(MODULE, default_set=True)
        enabled = {"menus": self.added_menus(), "engine_panels": self.engine_panels(),
                   "operators": hasattr(bpy.types, "SPLAT_OT_import_file")}
        addon_utils.disable(MODULE, default_set=True)
        engine = self.engine_registered()
        left = [n for n in dir(bpy.types) if n.startswith(("SPLAT_", "RENDER_PT_splatwright"))
                or n == "SplatwrightRenderEngine"]
        disabled = {"menus": self.added_menus(), "engine_panels": self.engine_panels(),
                    "engine": engine, "types_left": left,
                    "addons": [a.module for a in bpy.context.preferences.addons]}
        addon_utils.enable(MODULE, default_set=True)
        return {"enabled": enabled, "disabled": disabled, "re_enabled_menus": self.added_menus()}

    def engine_panels(self):
        """Blender's own panels that list our engine (ours are checked through bpy.types)."""
        return sum(1 for p in self.bpy.types.Panel.__subclasses__()
                   if "SPLATWRIGHT" in getattr(p, "COMPAT_ENGINES", ()) and not p.__module__.startswith(MODULE))


# the pytest side --------------------------------------------------------------------------------

def _random_cloud(n, degree, seed, spread=1.0):
    from splatwright.core import SplatCloud
    rng = np.random.default_rng(seed)
    return SplatCloud(rng.normal(0, spread, (n, 3)), rng.normal(size=(n, 4)) * rng.uniform(0.5, 2, (n, 1)),
                      rng.uniform(-4, -1.5, (n, 3)), rng.normal(0, 2, n), rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)))


def _write_inputs(work):
    """Every file the worker reads, written with splatwright.io (the formats under test elsewhere)."""
    from splatwright.io import write_splats
    a = _random_cloud(300, 3, 0)
    a.extras["nx"] = np.linspace(-1, 1, 300, dtype=np.float32)   # kept: PLY normals that are not all zero
    a.extras["ny"] = np.zeros(300, np.float32)
    a.extras["nz"] = np.ones(300, np.float32)
    a.extras["segment"] = (np.arange(300) % 7).astype(np.uint8)
    write_splats(work / "a.ply", a)
    write_splats(work / "b.ply", _random_cloud(120, 1, 1))
    fmt = _random_cloud(*FORMAT_CLOUD)
    for name in ("fmt.usdc", "fmt.spz", "fmt.splat"):
        write_splats(work / name, fmt)
    scene = _random_cloud(250, 3, 3, spread=0.5)
    scene.log_scales[:] = np.random.default_rng(4).uniform(-3.2, -1.8, scene.log_scales.shape)
    scene.opacity_logits[:] = np.random.default_rng(5).normal(1.0, 1.5, len(scene))
    write_splats(work / "scene.ply", scene)
    np.save(work / "scene_positions.npy", scene.positions.astype(np.float64))
    (work / "garbage.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n" + bytes(200))
    full = (work / "a.ply").read_bytes()
    (work / "truncated.ply").write_bytes(full[: len(full) // 2])
    (work / "wrong_ext.xyz").write_bytes(b"1 2 3\n")
    (work / "not_3dgs.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                        b"property float y\nproperty float z\nend_header\n0 0 0\n")
    bad = _random_cloud(50, 0, 6)
    bad.positions[3, 1] = np.nan
    bad.opacity_logits[7] = np.inf
    write_splats(work / "nan.ply", bad, nonfinite="keep")


@pytest.fixture(scope="module")
def blender(tmp_path_factory, extension_zip):
    work = tmp_path_factory.mktemp("blender")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _write_inputs(work)
    return run_worker(__file__, work, extension_zip)


def assert_clouds_equal(a, b):
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def check_transformed(source, result, matrix, sh_rotation=None):
    """`result` is `source` under the affine `matrix`: centres, covariances L Sigma L^T and (when the
    linear part is a rotation times a uniform scale, `sh_rotation`) the colour seen from every side."""
    from splatwright.core import sh as shmod
    lin, t = matrix[:3, :3], matrix[:3, 3]
    np.testing.assert_allclose(result.positions, source.positions.astype(np.float64) @ lin.T + t, atol=2e-5, rtol=1e-5)
    expected = lin @ cloud_covariances(source) @ lin.T
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
    assert np.abs(cloud_covariances(result) - expected).max(initial=0) <= 0 or \
        np.max(np.abs(cloud_covariances(result) - expected) / scale) < 2e-5
    np.testing.assert_allclose(result.opacity_logits, source.opacity_logits, rtol=0, atol=0)
    if sh_rotation is not None:
        dirs = np.random.default_rng(9).normal(size=(len(source), 3))
        np.testing.assert_allclose(shmod.colors(result.sh, dirs @ sh_rotation.T), shmod.colors(source.sh, dirs),
                                   atol=2e-5)


# install, import, export -------------------------------------------------------------------------

def test_install_enables_operators_engine_and_menus(blender):
    res = blender.step("install")
    assert MODULE in res["addons"]
    assert res["operators"] == [True, True]
    assert res["engine"]
    assert res["menus"] == MENUS


def test_import_ply_stores_documented_attributes_upright(blender):
    res = blender.step("import_ply")
    source = read(blender.work / "a.ply")
    d = np.load(blender.out / "import_a.npz")
    assert res["type"] == "MESH" and res["marker"] and res["count"] == len(source)
    assert res["modifiers"] == ["Splatwright Display"]
    np.testing.assert_array_equal(d["co"], source.positions)
    np.testing.assert_array_equal(d[ROTATION], source.rotations)
    np.testing.assert_array_equal(d[LOG_SCALE], source.log_scales)
    np.testing.assert_array_equal(d[OPACITY][:, 0], source.opacity_logits)
    for k in range(16):
        np.testing.assert_array_equal(d[f"{SH}{k}"], source.sh[:, k])
    assert f"{SH}16" not in d
    np.testing.assert_array_equal(d["splat_extra_nx"][:, 0], source.extras["nx"])
    np.testing.assert_array_equal(d["splat_extra_segment"][:, 0], source.extras["segment"])
    # upright: the file's -Y (up in a COLMAP capture) is Blender's +Z, its +Z (forward) is Blender's +Y
    np.testing.assert_allclose(d["matrix_world"], DEFAULT_AXES, atol=1e-7)
    np.testing.assert_allclose(res["identity_matrix"], np.eye(4), atol=0)
    assert res["selected"] == [res["active"]]


def test_import_of_several_files_at_once(blender):
    res = blender.step("import_ply")
    assert res["multi"] == [120, 300] and res["multi_selected"] == 2


def test_ply_import_export_is_lossless(blender):
    assert blender.step("import_ply")["export"]["error"] is None
    assert (blender.out / "a_roundtrip.ply").read_bytes() == (blender.work / "a.ply").read_bytes()


@pytest.mark.parametrize("name", ["fmt.usdc", "fmt.spz", "fmt.splat"])
def test_each_format_imports_and_exports(blender, name):
    res = blender.step("formats")
    assert res[name]["export"]["error"] is None
    source, back = read(blender.work / name), read(blender.out / ("re_" + name))
    assert res[name]["count"] == len(source) == len(back)
    # Every reader hands the core its 3DGS axes (the USD reader turns Y-up stages into them), so one
    # default stands every format upright.
    np.testing.assert_allclose(res[name]["matrix_world"], DEFAULT_AXES, atol=1e-7)
    # Blender writes back what it read: re-encoding the decoded splats may lose no more than the
    # first encoding of the original cloud did (zero for lossless formats)
    first = _format_errors(read(blender.work / name), _random_cloud(*FORMAT_CLOUD))
    second = _format_errors(back, source)
    for key, value in second.items():
        assert value <= max(2 * first[key], 1e-6), (key, value, first[key])


def _format_errors(a, b):
    """Largest differences a format can make: centres, covariances (relative), opacity, colours."""
    from splatwright.core import sh as shmod
    dirs = np.random.default_rng(8).normal(size=(len(a), 3))
    cov_a, cov_b = cloud_covariances(a), cloud_covariances(b)
    degree = min(a.sh_degree, b.sh_degree)
    return {"positions": np.abs(a.positions - b.positions).max(),
            "covariance": np.max(np.abs(cov_a - cov_b).max(axis=(1, 2)) / np.abs(cov_b).max(axis=(1, 2))),
            "opacity": np.abs(a.opacities - b.opacities).max(),
            "colour": np.abs(shmod.colors(a.with_sh_degree(degree).sh, dirs)
                             - shmod.colors(b.with_sh_degree(degree).sh, dirs)).max()}


def test_export_axes_are_the_inverse_convention(blender):
    res = blender.step("export_axes")
    assert res["export"]["error"] is None
    source, result = read(blender.work / "a.ply"), read(blender.out / "a_blender_axes.ply")
    # exporting with forward Y / up Z writes Blender's own coordinates: the default import matrix applied
    check_transformed(source, result, DEFAULT_AXES, sh_rotation=DEFAULT_AXES[:3, :3])


def test_export_reflects_deleted_vertices_and_object_transform(blender):
    res = blender.step("edits")
    assert res["export"]["error"] is None and res["export_stretched"]["error"] is None
    source = read(blender.work / "a.ply")
    edited = read(blender.out / "edited.ply")
    kept = np.array(res["kept"])
    assert len(edited) == len(kept)
    total = np.linalg.inv(DEFAULT_AXES) @ np.array(res["matrix_world"])
    rotation = total[:3, :3] / 1.5
    check_transformed(source[kept], edited, total, sh_rotation=rotation)
    np.testing.assert_array_equal(edited.extras["segment"], source.extras["segment"][kept])
    stretched = read(blender.out / "stretched.ply")
    total = np.linalg.inv(DEFAULT_AXES) @ np.array(res["stretched_matrix_world"])
    check_transformed(source, stretched, total)


def test_apply_splat_transform_bakes_the_object_transform(blender):
    res = blender.step("edits")
    assert res["apply"]["error"] is None and res["export_applied"]["error"] is None
    np.testing.assert_allclose(res["applied_matrix"], np.eye(4), atol=0)
    edited, applied = read(blender.out / "edited.ply"), read(blender.out / "applied.ply")
    # baked once into the data, then exported through the default axes: the same splats
    kept = np.array(res["kept"])
    total = np.linalg.inv(DEFAULT_AXES) @ np.array(res["matrix_world"])
    check_transformed(read(blender.work / "a.ply")[kept], applied, total, sh_rotation=total[:3, :3] / 1.5)
    np.testing.assert_allclose(applied.positions, edited.positions, atol=1e-5)


def test_export_of_joined_objects(blender):
    res = blender.step("join")
    assert res["export"]["error"] is None
    assert len(res["objects"]) == 2          # the Cube and the joined splat object
    a, b = read(blender.work / "a.ply"), read(blender.out / "joined.ply")
    b_src = read(blender.work / "b.ply")
    assert len(b) == len(a) + len(b_src)
    head, tail = b[: len(a)], b[len(a):]
    for name in ("positions", "rotations", "log_scales", "opacity_logits"):
        np.testing.assert_array_equal(getattr(head, name), getattr(a, name))
    np.testing.assert_array_equal(head.sh, a.sh)
    # b moved by (1, 2, 3) in Blender: in file axes that is (1, -3, 2)
    np.testing.assert_allclose(tail.positions, b_src.positions + [1.0, -3.0, 2.0], atol=1e-6)
    np.testing.assert_array_equal(tail.rotations, b_src.rotations)
    np.testing.assert_array_equal(tail.sh[:, :4], b_src.sh)           # degree 1 joined into degree 3:
    assert not tail.sh[:, 4:].any()                                  # zero-padded, same colours


def test_join_splats_keeps_every_splat_in_world_space(blender):
    res = blender.step("join")
    assert res["join_splats"]["error"] is None and res["export_splats"]["error"] is None
    assert len(res["splat_objects"]) == 1
    a, b = read(blender.work / "a.ply"), read(blender.work / "b.ply")
    joined = read(blender.out / "joined_splats.ply")
    to_file = np.linalg.inv(DEFAULT_AXES)
    # Independent reference: each source transformed on its own by its world matrix.
    for part, src, world in ((joined[: len(a)], a, res["world_a"]), (joined[len(a):], b, res["world_b"])):
        total = to_file @ np.array(world)
        u, _, vt = np.linalg.svd(total[:3, :3])            # SH turn with the polar rotation U V^T
        check_transformed(src, part, total, sh_rotation=u @ vt)


def test_export_selected_visible_and_all(blender):
    res = blender.step("selected_only")
    a, b = read(blender.work / "a.ply"), read(blender.work / "b.ply")
    assert all(res[k]["error"] is None for k in ("selected", "visible", "all"))
    assert len(read(blender.out / "selected.ply")) == len(b)
    assert len(read(blender.out / "visible.ply")) == len(b)
    assert len(read(blender.out / "all.ply")) == len(a) + len(b)


# errors --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, words", [
    ("garbage.ply", ["garbage.ply", "truncated"]),
    ("truncated.ply", ["truncated.ply", "truncated"]),
    ("wrong_ext.xyz", ["wrong_ext.xyz", ".xyz"]),
    ("missing.ply", ["missing.ply", "no such file"]),
    ("nan.ply", ["nan.ply", "non-finite"]),
    ("not_3dgs.ply", ["not_3dgs.ply", "f_dc_0"]),
    ("good and bad together", ["truncated.ply", "truncated"]),
])
def test_bad_files_report_and_leave_scene_unchanged(blender, name, words):
    case = blender.step("bad_inputs")[name]
    assert case["result"] == ["CANCELLED"]
    for word in words:
        assert word.lower() in case["error"].lower(), case["error"]
    assert case["unchanged"]


def test_non_finite_splats_are_dropped_by_default(blender):
    case = blender.step("bad_inputs")["nan.ply dropped"]
    assert case == {"count": 48, "added": 1}


@pytest.mark.parametrize("name, words", [
    ("non-splat selection", ["no splat objects selected", "'Cube' (MESH)"]),
    ("empty selection", ["nothing is selected"]),
    ("missing attribute", ["no 'splat_rotation' point attribute"]),
    ("unknown extension", ["never4.xyz", "unknown splat file extension"]),
])
def test_wrong_objects_report_and_write_nothing(blender, name, words):
    res = blender.step("wrong_objects")
    assert res[name]["result"] == ["CANCELLED"]
    for word in words:
        assert word in res[name]["error"], res[name]["error"]
    assert res["written"] == []


# viewport display ------------------------------------------------------------------------------------

def test_viewport_display_points_sized_by_scale(blender):
    res = blender.step("display")
    source = read(blender.work / "a.ply")
    assert res["pointclouds"] == 1 and res["material"] == ["Splatwright Splat"]
    assert res["show_render"] is False
    visible = source.opacities > 0.05
    assert res["count"] == int(visible.sum())
    n, half = int(visible.sum()), res["half_count"][0]
    assert abs(half - n / 2) < 4 * np.sqrt(n / 4)           # Display Ratio 0.5 keeps about half
    radius = np.load(blender.out / "display_radius.npy")
    np.testing.assert_allclose(np.sort(radius), np.sort(source.scales.max(axis=1)[visible]), rtol=1e-5)


# render engine -----------------------------------------------------------------------------------------

def _core_camera(rec):
    from splatwright.core.camera import Camera
    x, y, pct = rec["resolution"]
    w, h = x * pct // 100, y * pct // 100
    lens = {k: rec[k] for k in ("lens", "sensor_width", "sensor_height", "sensor_fit", "shift_x", "shift_y",
                                "type", "ortho_scale", "pixel_aspect_x", "pixel_aspect_y")}
    return Camera.from_blender(np.array(rec["matrix_world"]), w, h, clip_start=rec["clip_start"],
                               clip_end=rec["clip_end"], **lens)


def _core_image(cloud, rec, transparent):
    from splatwright.core.color import linear_to_srgb
    from splatwright.core.render import render
    background = None if transparent else linear_to_srgb(np.array(WORLD_COLOR))
    return render(cloud, _core_camera(rec), background=background)


def _png(path):
    from PIL import Image
    return np.asarray(Image.open(path), dtype=np.float64) / 255.0


@pytest.mark.parametrize("case", list(RENDER_CASES))
def test_camera_matches_blender_projection(blender, case):
    rec = blender.step("render")[case]
    cam = _core_camera(rec)
    points = np.load(blender.work / "scene_positions.npy")
    pixels, depth = cam.project(points)
    u, v, z = np.array(rec["projection"]).T
    np.testing.assert_allclose(pixels[:, 0], u * cam.width, atol=1e-3)
    np.testing.assert_allclose(pixels[:, 1], (1 - v) * cam.height, atol=1e-3)
    np.testing.assert_allclose(depth, z, atol=1e-4)


@pytest.mark.parametrize("case", list(RENDER_CASES))
def test_render_png_matches_core_renderer(blender, case):
    rec = blender.step("render")[case]
    transparent = RENDER_CASES[case]["transparent"]
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent)
    png = _png(blender.out / f"render_{case}.png")
    assert png.shape == (*image.color.shape[:2], 4 if transparent else 3)
    assert image.alpha.max() > 0.5 and image.alpha.min() < 0.5        # the cloud is in frame, not filling it
    if transparent:
        np.testing.assert_allclose(png[..., 3], image.alpha, atol=1 / 255)
        seen = image.alpha > 0.05                          # straight colour is defined where there is alpha
        straight = np.clip(image.color / np.maximum(image.alpha, 1e-12)[..., None], 0, 1)
        assert np.abs(png[..., :3][seen] - straight[seen]).max() <= 1 / 255
    else:
        assert np.abs(png - np.clip(image.color, 0, 1)).max() <= 1 / 255     # 8 bits hold 0..1


@pytest.mark.parametrize("case", list(RENDER_CASES))
def test_render_exr_is_scene_linear_with_depth(blender, case):
    import OpenEXR
    from splatwright.core.color import srgb_to_linear
    rec = blender.step("render")[case]
    transparent = RENDER_CASES[case]["transparent"]
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent)
    with OpenEXR.File(str(blender.out / f"render_{case}.exr")) as exr:
        channels = {name: ch.pixels for part in exr.parts for name, ch in part.channels.items()}
    rgba = channels["ViewLayer.Combined"]
    alpha = image.alpha if transparent else np.ones_like(image.alpha)
    straight = np.where(alpha[..., None] > 0, image.color / np.maximum(alpha, 1e-12)[..., None], 0)
    # float32 rounding only (the engine renders in a camera-centred frame, the reference in the world's)
    np.testing.assert_allclose(rgba[..., :3], srgb_to_linear(straight) * alpha[..., None], atol=2e-5)
    np.testing.assert_allclose(rgba[..., 3], alpha, atol=1e-6)
    depth = channels["ViewLayer.Depth.Z"]
    hit = np.isfinite(image.depth) & (image.alpha > 0)
    np.testing.assert_allclose(depth[hit], image.depth[hit], rtol=1e-5)
    assert (depth[~hit] == 1e10).all()


def test_view_transform_is_applied_to_the_linear_result(blender):
    blender.step("render")
    standard, agx = _png(blender.out / "render_persp.png"), _png(blender.out / "render_persp_agx.png")
    assert np.abs(standard - agx).max() > 0.05      # AgX tone-maps; the exact match needs Standard


def test_render_near_clip_removes_splats(blender):
    rec = blender.step("render")["persp_vertical"]
    cloud = read(blender.work / "scene.ply")
    cam = _core_camera(rec)
    _, depth = cam.project(cloud.positions)
    assert 0 < (depth <= rec["clip_start"]).sum() < len(cloud)      # the case clips part of the cloud


def test_render_far_from_origin_keeps_precision(blender):
    rec = dict(blender.step("render_edges")["far"])
    # the same picture as the cloud at the origin seen from the same relative camera position
    camera = np.array(rec["matrix_world"])
    camera[:3, 3] -= np.array(rec["object_matrix"])[:3, 3]
    rec["matrix_world"] = camera.tolist()
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    assert image.alpha.max() > 0.5
    assert np.abs(_png(blender.out / "edge_far.png") - np.clip(image.color, 0, 1)).max() <= 1 / 255


def test_render_with_non_square_pixels(blender):
    rec = blender.step("render_edges")["aspect"]
    cam = _core_camera(rec)
    pixels, _ = cam.project(np.load(blender.work / "scene_positions.npy"))
    u, v, _ = np.array(rec["projection"]).T
    np.testing.assert_allclose(pixels, np.stack([u * cam.width, (1 - v) * cam.height], axis=1), atol=1e-3)
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    assert np.abs(_png(blender.out / "edge_aspect.png") - np.clip(image.color, 0, 1)).max() <= 1 / 255


@pytest.mark.parametrize("name", ["wide", "narrow"])
def test_render_very_wide_and_very_narrow_lenses(blender, name):
    rec = blender.step("render_edges")[name]
    cam = _core_camera(rec)
    pixels, depth = cam.project(np.load(blender.work / "scene_positions.npy"))
    u, v, _ = np.array(rec["projection"]).T
    near = np.abs(pixels).max(axis=1) < 1e4                  # beyond that, float32 in Blender's own math
    np.testing.assert_allclose(pixels[near], np.stack([u * cam.width, (1 - v) * cam.height], axis=1)[near],
                               rtol=1e-5, atol=1e-3)
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    assert np.abs(_png(blender.out / f"edge_{name}.png") - np.clip(image.color, 0, 1)).max() <= 1 / 255


def test_render_one_pixel(blender):
    rec = blender.step("render_edges")["tiny"]
    image = _core_image(read(blender.work / "scene.ply"), rec, transparent=False)
    png = _png(blender.out / "edge_tiny.png")
    assert png.shape == (1, 1, 3)
    assert np.abs(png - np.clip(image.color, 0, 1)).max() <= 1 / 255


def test_hidden_splats_leave_the_world_colour(blender):
    from splatwright.core.color import linear_to_srgb
    blender.step("render_edges")
    png = _png(blender.out / "edge_hidden.png")
    assert np.abs(png - linear_to_srgb(np.array(WORLD_COLOR))).max() <= 1 / 255


def test_panoramic_camera_is_refused_clearly(blender):
    res = blender.step("render_edges")["panoramic"]
    assert "PANO" in res["error"] and "perspective and orthographic" in res["error"]


def test_animation_renders_each_frame(blender):
    res = blender.step("animation")
    assert res["frames"] == ["anim_0001.png", "anim_0002.png"]
    cloud = read(blender.work / "scene.ply")
    moved = cloud.replace(positions=cloud.positions + np.array(ANIM_OFFSET, np.float32))
    for frame, c in (("anim_0001.png", cloud), ("anim_0002.png", moved)):
        image = _core_image(c, res["camera"], transparent=False)
        assert np.abs(_png(blender.out / frame) - np.clip(image.color, 0, 1)).max() <= 1 / 255


# registration ------------------------------------------------------------------------------------------

def test_unregister_register_twice_leaves_nothing_behind(blender):
    res = blender.step("reregister")
    assert res["enabled"]["menus"] == MENUS
    assert res["enabled"]["operators"] and res["enabled"]["engine_panels"] > 10
    off = res["disabled"]
    assert off["menus"] == dict.fromkeys(MENUS, 0)
    assert off["engine_panels"] == 0 and off["types_left"] == []
    assert not off["engine"] and MODULE not in off["addons"]
    assert res["re_enabled_menus"] == MENUS


if __name__ == "__main__":
    worker_main(Worker)
