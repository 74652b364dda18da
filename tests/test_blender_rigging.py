"""Splats bound to armatures and collisions between splat objects, headless, with the extension
installed from its zip as in test_blender_addon.py.

One worker process (this file run as a script) does every Blender-side step and saves what Blender
itself computes (the Armature modifier's evaluated vertices, bone matrices, vertex-group weights read
one vertex at a time, renders) next to what the extension produced. The tests judge the extension
against those Blender numbers and against references computed here in float64: barycentric weight
interpolation, distances to bone segments, L Sigma L^T for rigidly bound splats, renders of splats
made from the posed mesh, and a brute-force ellipsoid contact test.
"""

import contextlib
import io
import json

import numpy as np
import pytest
from blender_session import MODULE, BlenderWorker, run_worker, worker_main
from helpers import covariances, linear_to_srgb, psnr

pytestmark = [pytest.mark.blender, pytest.mark.slow]      # one Blender worker for the module

# A rig that exercises every part of Blender's skinning: bone rolls, an unconnected child, scaled
# bones (uniform and not), a bone that does not deform, and an armature object placed off the origin.
RIG_BONES = {  # name: head, tail, parent, connected, roll, deforms
    "Root": ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), None, False, 0.0, True),
    "Mid": ((0.0, 0.0, 1.0), (0.2, 0.1, 2.0), "Root", True, 0.3, True),
    "Side": ((0.1, 0.0, 0.9), (1.0, 0.2, 1.2), "Root", False, -0.4, True),
    "Tip": ((0.2, 0.1, 2.0), (0.3, 0.1, 2.7), "Mid", True, 0.0, True),
    "Ctrl": ((0.0, 0.0, -0.5), (0.0, 0.5, -0.5), None, False, 0.0, False),
}
RIG_POSE = {  # name: location, Euler XYZ rotation, scale (bone space)
    "Root": ((0.1, -0.2, 0.05), (0.3, -0.2, 0.4), (1.0, 1.0, 1.0)),
    "Mid": ((0.0, 0.0, 0.0), (0.9, 0.2, -0.5), (1.3, 0.8, 1.1)),
    "Side": ((0.05, 0.0, 0.0), (-0.6, 0.7, 0.1), (1.5, 1.5, 1.5)),
    "Tip": ((0.0, 0.0, 0.0), (0.2, -1.2, 0.8), (0.7, 1.2, 0.9)),
    "Ctrl": ((0.5, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
}
GROUP_ORDER = ("Side", "Root", "Ctrl", "Tip", "Mid")      # not the bone order
ARM_TRANSFORM = dict(location=(0.3, -0.2, 0.1), rotation_euler=(0.1, 0.2, -0.3), scale=(1.1, 1.1, 1.1))
SPLAT_TRANSFORM = dict(location=(0.5, 0.4, -0.2), rotation_euler=(0.3, -0.1, 0.5), scale=(1.0, 1.3, 0.8))
RIG_SPLATS = 400
RENDER_SIZE = (480, 360)
BENT_FRAME = 12


# the worker (a separate Python process with bpy) -----------------------------------------------------

def rig_cloud_arrays(n, seed=3):
    """Splats scattered around the rig's bones, anisotropic, with non-unit quaternions and SH degree 1."""
    rng = np.random.default_rng(seed)
    heads = np.array([RIG_BONES[b][0] for b in GROUP_ORDER if RIG_BONES[b][5]])
    tails = np.array([RIG_BONES[b][1] for b in GROUP_ORDER if RIG_BONES[b][5]])
    pick, t = rng.integers(0, len(heads), n), rng.uniform(0, 1, (n, 1))
    positions = heads[pick] + t * (tails[pick] - heads[pick]) + rng.normal(0, 0.15, (n, 3))
    return dict(positions=positions, rotations=rng.normal(0, 1, (n, 4)) * rng.uniform(0.5, 2, (n, 1)),
                log_scales=rng.uniform(-4, -2, (n, 3)), opacity_logits=rng.normal(2, 1, n),
                sh=rng.normal(0, 0.3, (n, 4, 3)))


def rig_weights(n, seed=4):
    """Sparse group weights {group: {vertex: weight}} that do not sum to one: splats 0-9 in no group,
    10-19 only in the non-deforming Ctrl, 20-119 in one deforming group, the rest in 2-4 groups."""
    rng = np.random.default_rng(seed)
    deforming = [g for g in GROUP_ORDER if RIG_BONES[g][5]]
    weights = {g: {} for g in GROUP_ORDER}
    for v in range(10, 20):
        weights["Ctrl"][v] = float(rng.uniform(0.2, 0.9))
    for v in range(20, 120):
        weights[deforming[v % len(deforming)]][v] = float(rng.uniform(0.2, 0.9))
    for v in range(120, n):
        for g in rng.choice(GROUP_ORDER, size=rng.integers(2, 5), replace=False):
            weights[g][v] = float(rng.uniform(0.05, 0.9))
    return weights


class Worker(BlenderWorker):
    steps = ("install", "skinning", "transfer", "bone_weights", "render", "errors", "collide_small",
             "collide_demo", "reregister")

    # helpers -------------------------------------------------------------------------------------

    def splat_object(self, name, arrays, matrix=None):
        core = self.module("core")
        data = self.module("splat_addon.data")
        obj, _ = data.new_splat_object(core.SplatCloud(**arrays), name, self.bpy.context.scene.collection, matrix)
        return obj

    def group_matrix(self, obj, names):
        """(V, len(names)) weights read one vertex at a time through VertexGroup.weight."""
        out = np.zeros((len(obj.data.vertices), len(names)))
        for j, name in enumerate(names):
            group = obj.vertex_groups.get(name)
            for i in range(len(out)) if group is not None else ():
                with contextlib.suppress(RuntimeError):      # not in the group
                    out[i, j] = group.weight(i)
        return out

    def blender_positions(self, obj):
        """The evaluated mesh's vertices (object space) with the display modifier off."""
        depsgraph = self.bpy.context.evaluated_depsgraph_get()
        ev = obj.evaluated_get(depsgraph)
        mesh = ev.to_mesh()
        try:
            co = np.empty(len(mesh.vertices) * 3, np.float32)
            mesh.vertices.foreach_get("co", co)
            return co.reshape(-1, 3)
        finally:
            ev.to_mesh_clear()

    def display_positions(self, obj):
        """The viewport display's points (object space)."""
        geometry = obj.evaluated_get(self.bpy.context.evaluated_depsgraph_get()).evaluated_geometry()
        points = geometry.pointcloud
        co = np.empty(len(points.attributes["position"].data) * 3, np.float32)
        points.attributes["position"].data.foreach_get("vector", co)
        return co.reshape(-1, 3)

    def inventory(self):
        """What a failed bind or collision check must leave as it was (armature bindings included)."""
        bpy = self.bpy
        inv = {k: sorted(x.name for x in getattr(bpy.data, k)) for k in ("objects", "meshes", "armatures")}
        inv["groups"] = {o.name: [g.name for g in o.vertex_groups] for o in bpy.data.objects}
        inv["modifiers"] = {o.name: [m.name for m in o.modifiers] for o in bpy.data.objects}
        inv["parents"] = {o.name: o.parent.name if o.parent else None for o in bpy.data.objects}
        inv["attributes"] = {m.name: sorted(a.name for a in m.attributes) for m in bpy.data.meshes}
        return inv

    def build_rig(self):
        """The test rig's armature object, posed by RIG_POSE."""
        bpy = self.bpy
        arm = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
        bpy.context.scene.collection.objects.link(arm)
        for key, value in ARM_TRANSFORM.items():
            setattr(arm, key, value)
        self.select([arm])
        bpy.ops.object.mode_set(mode="EDIT")
        for name, (head, tail, parent, connected, roll, deforms) in RIG_BONES.items():
            bone = arm.data.edit_bones.new(name)
            bone.head, bone.tail, bone.roll, bone.use_deform = head, tail, roll, deforms
            if parent is not None:
                bone.parent, bone.use_connect = arm.data.edit_bones[parent], connected
        bpy.ops.object.mode_set(mode="OBJECT")
        for name, (loc, rot, scale) in RIG_POSE.items():
            pb = arm.pose.bones[name]
            pb.rotation_mode = "XYZ"
            pb.location, pb.rotation_euler, pb.scale = loc, rot, scale
        return arm

    def demo(self, environment_splats=0, body_splats=3000):
        """The demo rig and its arm converted to splats in the rest pose (selected, the armature active)."""
        bpy = self.bpy
        rig = self.module("splat_addon.demo_rig").build_demo_rig(bpy.context.scene, environment_splats)
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=body_splats)
        splats = bpy.context.active_object
        self.select([splats, rig.armature], active=rig.armature)
        return rig, splats

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        menus = {name: self.menu_entries(name) for name in ("VIEW3D_MT_object_parent", "VIEW3D_MT_object")}
        data = self.module("splat_addon.data")
        return {"operators": [hasattr(bpy.types, n) for n in ("SPLAT_OT_bind_armature", "SPLAT_OT_check_collisions")],
                "menus": menus, "deformers": [f.__name__ for f in data.DEFORMERS],
                "handlers": self.handler_count()}

    def handler_count(self):
        handlers = self.bpy.app.handlers
        return sum(1 for lst in (handlers.depsgraph_update_post, handlers.load_post, handlers.undo_post,
                                 handlers.redo_post) for f in lst if f.__module__.startswith(MODULE))

    def skinning(self):
        bpy = self.bpy
        data = self.module("splat_addon.data")
        display = self.module("splat_addon.display")
        arm = self.build_rig()
        arrays = rig_cloud_arrays(RIG_SPLATS)
        obj = self.splat_object("RigSplats", arrays)
        for key, value in SPLAT_TRANSFORM.items():
            setattr(obj, key, value)
        for name, members in rig_weights(RIG_SPLATS).items():      # groups in GROUP_ORDER
            group = obj.vertex_groups.new(name=name)
            for v, w in members.items():
                group.add([v], w, "REPLACE")
        mod = obj.modifiers.new("Armature", "ARMATURE")
        mod.object = arm
        shown = display.add_display(obj)
        display.set_input(shown, "Min Opacity", 0.0)
        bpy.context.view_layer.update()
        res = {"modifiers": [m.type for m in obj.modifiers]}
        names = list(RIG_BONES)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        arm_world, obj_world = np.array(arm.matrix_world), np.array(obj.matrix_world)
        to_obj = np.linalg.inv(obj_world) @ arm_world
        deform = np.stack([to_obj @ np.array(arm.pose.bones[n].matrix)
                           @ np.linalg.inv(np.array(arm.data.bones[n].matrix_local)) @ np.linalg.inv(to_obj)
                           for n in names])
        arrays_out = {}
        for mode, volume in (("lbs", False), ("dqs", True)):
            mod.use_deform_preserve_volume = volume
            depsgraph = bpy.context.evaluated_depsgraph_get()
            ours = data.evaluated_cloud(obj, depsgraph, np.eye(4))
            arrays_out[f"{mode}_display"] = self.display_positions(obj)
            shown.show_viewport = False
            arrays_out[f"{mode}_blender"] = self.blender_positions(obj)
            shown.show_viewport = True
            arrays_out.update({f"{mode}_positions": ours.positions, f"{mode}_rotations": ours.rotations,
                               f"{mode}_log_scales": ours.log_scales, f"{mode}_sh": ours.sh})
        weights = self.group_matrix(obj, names)
        # weights painted after the first evaluation: the cached weights must follow
        mod.use_deform_preserve_volume = False
        group = obj.vertex_groups["Tip"]
        group.add(list(range(20, 60)), 0.7, "REPLACE")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        arrays_out["repainted_positions"] = data.evaluated_cloud(obj, depsgraph, np.eye(4)).positions
        shown.show_viewport = False
        arrays_out["repainted_blender"] = self.blender_positions(obj)
        self.save("skinning", rest_positions=arrays["positions"], rest_rotations=arrays["rotations"],
                  rest_log_scales=arrays["log_scales"], deform=deform, bones=np.array(names),
                  weights=weights, **arrays_out)
        return res

    def transfer(self):
        bpy = self.bpy
        data = self.module("splat_addon.data")
        rig, splats = self.demo()
        names = [b.name for b in rig.armature.data.bones]
        res = {"bind": self.call(bpy.ops.splat.bind_armature, armature=rig.armature.name, max_influences=8)}
        extras = data.mesh_to_cloud(splats.data).extras
        res.update(groups=[g.name for g in splats.vertex_groups],
                   modifiers=[[m.type, m.object.name if m.type == "ARMATURE" else None] for m in splats.modifiers],
                   parent=splats.parent.name if splats.parent else None,
                   matrix_kept=bool(np.allclose(np.array(splats.matrix_world), np.array(rig.body.matrix_world))),
                   source=json.loads(splats.data["splatwright_source"]))
        self.save("transfer", weights=self.group_matrix(splats, names), source=self.group_matrix(rig.body, names),
                  source_vertices=extras["source_vertices"], barycentric=extras["barycentric"])
        # the active armature, one influence
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=3000)
        single = bpy.context.active_object
        self.select([single, rig.armature], active=rig.armature)
        res["single"] = self.call(bpy.ops.splat.bind_armature, max_influences=1)
        self.save("transfer_single", weights=self.group_matrix(single, names))
        # a source mesh that is gone: weights from the bones, with a warning
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=200)
        orphan = bpy.context.active_object
        rig.body.name = "Renamed Arm"
        warnings = []
        plans = self.module("splat_addon.rigging").bind_armature([orphan], rig.armature, warn=warnings.append)
        res["orphan"] = {"warnings": warnings, "source": plans[0].source}
        return res

    def bone_weights(self):
        """A splat object not made from a mesh gets weights from distances to the bones."""
        bpy = self.bpy
        arm = self.build_rig()
        arrays = rig_cloud_arrays(300, seed=9)
        obj = self.splat_object("Loose", arrays)
        for key, value in SPLAT_TRANSFORM.items():
            setattr(obj, key, value)
        bpy.context.view_layer.update()
        self.select([obj], active=arm)
        res = {"bind": self.call(bpy.ops.splat.bind_armature, max_influences=2, falloff=4.0, min_weight=0.01,
                                 preserve_volume=True)}
        names = list(RIG_BONES)
        res["preserve_volume"] = obj.modifiers[0].use_deform_preserve_volume
        res["groups"] = [g.name for g in obj.vertex_groups]
        to_arm = np.linalg.inv(np.array(arm.matrix_world)) @ np.array(obj.matrix_world)
        self.save("bone_weights", weights=self.group_matrix(obj, names), positions=arrays["positions"],
                  to_arm=to_arm, heads=np.array([arm.data.bones[n].head_local for n in names]),
                  tails=np.array([arm.data.bones[n].tail_local for n in names]), bones=np.array(names))
        return res

    def render(self):
        bpy = self.bpy
        scene = bpy.context.scene
        data = self.module("splat_addon.data")
        rigging = self.module("splat_addon.rigging")
        camera = self.module("splat_addon.camera")
        from_mesh = self.module("splat_addon.from_mesh")
        render = self.module("core.render").render
        rig, splats = self.demo(body_splats=8000)
        res = {"bind": self.call(bpy.ops.splat.bind_armature)}
        rest = data.evaluated_cloud(splats, bpy.context.evaluated_depsgraph_get())
        scene.frame_set(BENT_FRAME)
        reference = from_mesh.convert_objects(bpy.context, [rig.body], max_splats=8000, use_rest_pose=False)[0][1]
        depsgraph = bpy.context.evaluated_depsgraph_get()
        ours = data.evaluated_cloud(splats, depsgraph)
        reference = data.transform_cloud(reference, data.world_matrix(rig.body, depsgraph))
        width, height = RENDER_SIZE
        cam = camera.from_object(scene.camera.evaluated_get(depsgraph), scene, width, height)
        images = {name: render(cloud, cam, background=(0.0, 0.0, 0.0))
                  for name, cloud in (("ours", ours), ("reference", reference), ("rest", rest),
                                      ("centres_only", rest.replace(positions=ours.positions)))}
        # the render engine (its own render depsgraph), with the weights cache empty
        render_settings = scene.render
        render_settings.engine = "SPLATWRIGHT"
        render_settings.resolution_x, render_settings.resolution_y, render_settings.resolution_percentage = \
            width, height, 100
        render_settings.image_settings.file_format = "OPEN_EXR"
        render_settings.filepath = str(self.out / "engine.exr")
        scene.world = None
        rigging.forget_weights()
        res["engine"] = self.call(bpy.ops.render.render, write_still=True)
        channels = self.module("io.exr").read_exr(self.out / "engine.exr")
        self.save("render", engine=np.stack([channels[c] for c in "RGB"], axis=-1),
                  **{f"{k}_color": v.color for k, v in images.items()},
                  **{f"{k}_alpha": v.alpha for k, v in images.items()})
        return res

    def errors(self):
        bpy = self.bpy
        rig, splats = self.demo(body_splats=300)
        env = self.splat_object("Env", rig_cloud_arrays(50, seed=1))
        cases = {}
        bind = bpy.ops.splat.bind_armature
        for name, selected, active, kw in (
                ("active not an armature", [splats], splats, {}),
                ("unknown armature", [splats], splats, {"armature": "Nope"}),
                ("camera as armature", [splats], splats, {"armature": "Camera"}),
                ("no active object", [splats], None, {}),
                ("no splat objects", [rig.body], rig.armature, {}),
                ("nothing selected", [], rig.armature, {})):
            self.select(selected, active=active)
            if active is None:
                bpy.context.view_layer.objects.active = None
            before = self.inventory()
            cases[name] = {**self.call(bind, **kw), "unchanged": before == self.inventory()}
        collide = bpy.ops.splat.check_collisions
        base = dict(use_scene_range=False, frame_start=1, frame_end=2)
        for name, kw in (("unknown object", dict(object_a=splats.name, object_b="Nope")),
                         ("same object", dict(object_a=splats.name, object_b=splats.name)),
                         ("not splats", dict(object_a=splats.name, object_b=rig.body.name)),
                         ("backwards", dict(object_a=splats.name, object_b=env.name, frame_start=5, frame_end=2)),
                         ("unknown bone", dict(object_a=splats.name, object_b=env.name, ignore_bones="Nope"))):
            before = self.inventory()
            cases[name] = {**self.call(collide, **{**base, **kw}), "unchanged": before == self.inventory(),
                           "frame": bpy.context.scene.frame_current}
        return cases

    def collide_small(self):
        """A bound cloud (two bones, the lower one turning) and a cloud that flies in at frame 3."""
        bpy = self.bpy
        scene = bpy.context.scene
        data = self.module("splat_addon.data")
        collide = self.module("splat_addon.collide")
        arm = bpy.data.objects.new("Pole", bpy.data.armatures.new("Pole"))
        scene.collection.objects.link(arm)
        self.select([arm])
        bpy.ops.object.mode_set(mode="EDIT")
        lower = arm.data.edit_bones.new("Lower")
        lower.head, lower.tail = (0, 0, 0), (0, 0, 1)
        upper = arm.data.edit_bones.new("Upper")
        upper.head, upper.tail, upper.parent, upper.use_connect = (0, 0, 1), (0, 0, 2), lower, True
        bpy.ops.object.mode_set(mode="OBJECT")
        rng = np.random.default_rng(11)
        n_a, n_b = 60, 50
        pole = dict(positions=np.column_stack([rng.normal(0, 0.08, (n_a, 2)), rng.uniform(0, 2, n_a)]),
                    rotations=rng.normal(0, 1, (n_a, 4)), log_scales=rng.uniform(-3.2, -2.0, (n_a, 3)),
                    opacity_logits=np.full(n_a, 4.0), sh=np.zeros((n_a, 1, 3)))
        blob = dict(positions=rng.normal(0, 0.15, (n_b, 3)), rotations=rng.normal(0, 1, (n_b, 4)),
                    log_scales=rng.uniform(-3.0, -2.0, (n_b, 3)),
                    opacity_logits=np.where(np.arange(n_b) < 5, -6.0, 3.0), sh=np.zeros((n_b, 1, 3)))
        a, b = self.splat_object("PoleSplats", pole), self.splat_object("Blob", blob)
        self.select([a], active=arm)
        res = {"bind": self.call(bpy.ops.splat.bind_armature, max_influences=2)}
        pb = arm.pose.bones["Lower"]
        pb.rotation_mode = "XYZ"
        for frame, angle, where in ((1, 0.0, (0.0, -3.0, 1.5)), (3, 0.25, (0.0, -0.45, 1.45))):
            pb.rotation_euler = (angle, 0.0, 0.0)
            pb.keyframe_insert("rotation_euler", frame=frame)
            b.location = where
            b.keyframe_insert("location", frame=frame)
        scene.frame_set(2)
        res["op"] = self.call(bpy.ops.splat.check_collisions, object_a=a.name, object_b=b.name,
                              use_scene_range=False, frame_start=1, frame_end=3)
        res["frame_after"] = scene.frame_current
        report = collide.check_collisions(bpy.context, a, b, [1, 2, 3], write_attribute=False)
        res["report"] = report.as_dict()
        clouds = {}
        for frame in (1, 2, 3):
            scene.frame_set(frame)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            for key, obj in (("a", a), ("b", b)):
                cloud = data.evaluated_cloud(obj, depsgraph)
                clouds[f"{key}{frame}_positions"] = cloud.positions
                clouds[f"{key}{frame}_rotations"] = cloud.rotations
                clouds[f"{key}{frame}_log_scales"] = cloud.log_scales
                clouds[f"{key}{frame}_opacity_logits"] = cloud.opacity_logits
        contact = {}
        for key, obj in (("a", a), ("b", b)):
            values = np.empty(len(obj.data.vertices), np.float32)
            obj.data.attributes["splat_contact"].data.foreach_get("value", values)
            contact[f"contact_{key}"] = values
        self.save("collide_small", weights=self.group_matrix(a, ["Lower", "Upper"]), **clouds, **contact)
        return res

    def collide_demo(self):
        bpy = self.bpy
        scene = bpy.context.scene
        collide = self.module("splat_addon.collide")
        rig, splats = self.demo(environment_splats=20_000, body_splats=8000)
        res = {"bind": self.call(bpy.ops.splat.bind_armature)}
        env = rig.environment
        res["op"] = self.call(bpy.ops.splat.check_collisions, object_a=splats.name, object_b=env.name,
                              ignore_bones="Base")
        values = np.empty(len(splats.data.vertices), np.float32)
        splats.data.attributes["splat_contact"].data.foreach_get("value", values)
        res["contact_max"], res["contact_splats"] = float(values.max()), int((values > 0).sum())
        res["exported_extras"] = sorted(self.module("splat_addon.data").mesh_to_cloud(splats.data).extras)
        res["report"] = collide.check_collisions(bpy.context, splats, env, range(1, 25), ignore_bones=["Base"],
                                                 write_attribute=False).as_dict()
        res["with_base"] = collide.check_collisions(bpy.context, splats, env, [1], write_attribute=False).as_dict()
        execute = self.module("splat_addon.command").execute
        runs = {"ok": ["collide", splats.name, env.name, "--frames", "1-12:11", "--ignore-bones", "Base",
                       "--json", str(self.out / "collide.json")],
                "unknown": ["collide", splats.name, "Nope", "--frames", "1"],
                "bad sigma": ["collide", splats.name, env.name, "--frames", "1", "--sigma", "-1"],
                "missing folder": ["collide", splats.name, env.name, "--frames", "1",
                                   "--json", str(self.out / "nowhere" / "c.json")]}
        res["cli"] = {}
        for name, argv in runs.items():
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = execute(argv)
            res["cli"][name] = {"code": code, "stdout": out.getvalue(), "stderr": err.getvalue()}
        return res

    def reregister(self):
        import addon_utils
        addon_utils.disable(MODULE, default_set=True)
        off = self.handler_count()
        addon_utils.enable(MODULE, default_set=True)
        return {"off": off, "on": self.handler_count()}


# the pytest side ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def blender(tmp_path_factory, extension_zip):
    return run_worker(__file__, tmp_path_factory.mktemp("rigging"), extension_zip)


def segment_distances(points, heads, tails):
    d = np.empty((len(points), len(heads)))
    for b, (h, t) in enumerate(zip(heads, tails)):
        axis = t - h
        s = np.clip((points - h) @ axis / (axis @ axis), 0.0, 1.0)
        d[:, b] = np.linalg.norm(points - h - s[:, None] * axis, axis=1)
    return d


# install --------------------------------------------------------------------------------------------

def test_install_registers_operators_menus_deformer_and_handlers(blender):
    res = blender.step("install")
    assert res["operators"] == [True, True]
    assert res["menus"] == {"VIEW3D_MT_object_parent": 1, "VIEW3D_MT_object": 2}     # Check Collisions, Join Splats
    assert "_armature_pose" in res["deformers"]
    assert res["handlers"] == 4


def test_handlers_follow_the_extension(blender):
    assert blender.step("reregister") == {"off": 0, "on": 4}


# posing against Blender's Armature modifier -----------------------------------------------------------

@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_skinned_centres_equal_blenders_armature_modifier(blender, mode):
    """Rolls, scaled bones (uniform and not), unnormalised and missing weights, a non-deforming bone, an
    object scaled non-uniformly and an armature placed off the origin: Blender's own result to 1e-5."""
    res = blender.step("skinning")
    assert res["modifiers"] == ["ARMATURE", "NODES"]
    d = blender.npz("skinning")
    ours, theirs = d[f"{mode}_positions"], d[f"{mode}_blender"]
    scale = np.abs(theirs).max()
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5 * scale)
    assert np.abs(theirs - d["rest_positions"]).max() > 0.3              # the pose really moves them
    unbound = slice(0, 20)                                                # no groups, or only Ctrl
    np.testing.assert_allclose(ours[unbound], d["rest_positions"][unbound], atol=1e-6)
    # the viewport display draws the posed centres (the Armature modifier runs before it)
    np.testing.assert_allclose(d[f"{mode}_display"], theirs, atol=1e-6)


def test_modes_differ_where_bones_disagree(blender):
    d = blender.npz("skinning")
    assert np.abs(d["lbs_positions"] - d["dqs_positions"]).max() > 1e-2


def test_weights_edited_after_posing_are_followed(blender):
    d = blender.npz("skinning")
    theirs = d["repainted_blender"]
    np.testing.assert_allclose(d["repainted_positions"], theirs, rtol=0, atol=1e-5 * np.abs(theirs).max())
    assert np.abs(d["repainted_positions"] - d["lbs_positions"]).max() > 1e-2


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_rigidly_bound_splats_turn_and_stretch_with_their_bone(blender, mode):
    """A splat in one group moves by that bone's deform matrix D (object space) exactly: its
    covariance becomes L Sigma L^T, L the linear part of D, whatever D's scale."""
    d = blender.npz("skinning")
    names = list(d["bones"])
    w = d["weights"]
    deforming = [names.index(b) for b in RIG_BONES if RIG_BONES[b][5]]
    single = np.flatnonzero(((w[:, deforming] > 0).sum(axis=1) == 1) & (w[:, names.index("Ctrl")] == 0))
    assert len(single) >= 100
    bone = np.array(deforming)[np.argmax(w[single][:, deforming], axis=1)]
    lin = d["deform"][bone, :3, :3]
    rest = covariances(d["rest_rotations"][single], d["rest_log_scales"][single])
    expected = lin @ rest @ np.swapaxes(lin, 1, 2)
    posed = covariances(d[f"{mode}_rotations"][single], d[f"{mode}_log_scales"][single])
    size = np.abs(expected).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(posed / size, expected / size, atol=2e-5)
    assert {names[b] for b in bone} == {"Root", "Mid", "Side", "Tip"}


# binding ----------------------------------------------------------------------------------------------

def test_weights_transfer_exactly_from_the_skinned_mesh(blender):
    res = blender.step("transfer")
    assert res["bind"]["result"] == ["FINISHED"]
    assert sorted(res["groups"]) == ["Base", "Fore", "Hand", "Upper"]
    assert res["modifiers"] == [["ARMATURE", "Demo Arm Rig"], ["NODES", None]]
    assert res["parent"] == "Demo Arm Rig" and res["matrix_kept"]
    d = blender.npz("transfer")
    corners = d["source_vertices"].astype(int)
    expected = np.einsum("nk,nkb->nb", d["barycentric"].astype(np.float64), d["source"][corners])
    expected /= expected.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(d["weights"], expected, atol=2e-6)
    assert ((d["weights"] > 0).sum(axis=1) > 1).mean() > 0.2              # joints blend


def test_a_lost_source_mesh_falls_back_to_bone_weights(blender):
    orphan = blender.step("transfer")["orphan"]
    assert orphan["source"] == "bones"
    assert any("source mesh 'Demo Arm' is gone" in w for w in orphan["warnings"])


def test_one_influence_keeps_the_largest_bone(blender):
    assert blender.step("transfer")["single"]["result"] == ["FINISHED"]
    d, single = blender.npz("transfer"), blender.npz("transfer_single")["weights"]
    np.testing.assert_array_equal((single > 0).sum(axis=1), 1)
    np.testing.assert_allclose(single.sum(axis=1), 1.0, atol=1e-6)
    clear = np.sort(d["weights"], axis=1)[:, -1] > np.sort(d["weights"], axis=1)[:, -2] + 1e-4
    np.testing.assert_array_equal(np.argmax(single, axis=1)[clear], np.argmax(d["weights"], axis=1)[clear])


def test_weights_from_bones_follow_segment_distances(blender):
    """Without a source mesh: (d_min / d_b)^4 over the deforming bones' rest segments (armature
    space), weights under 1% dropped, the two largest kept, normalised."""
    res = blender.step("bone_weights")
    assert res["bind"]["result"] == ["FINISHED"] and res["preserve_volume"] is True
    assert sorted(res["groups"]) == ["Mid", "Root", "Side", "Tip"]        # Ctrl does not deform
    d = blender.npz("bone_weights")
    names = list(d["bones"])
    deforming = [names.index(b) for b in RIG_BONES if RIG_BONES[b][5]]
    points = d["positions"] @ d["to_arm"][:3, :3].T + d["to_arm"][:3, 3]
    dist = segment_distances(points, d["heads"][deforming], d["tails"][deforming])
    raw = (dist.min(axis=1, keepdims=True) / dist) ** 4
    raw[raw < 0.01 * raw.sum(axis=1, keepdims=True)] = 0.0
    order = np.argsort(-raw, axis=1)
    raw[np.arange(len(raw))[:, None], order[:, 2:]] = 0.0
    expected = np.zeros_like(d["weights"])
    expected[:, deforming] = raw / raw.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(d["weights"], expected, atol=2e-6)
    assert ((d["weights"] > 0).sum(axis=1) == 2).any()


# rendering --------------------------------------------------------------------------------------------

def test_posed_splat_avatar_renders_like_splats_of_the_posed_mesh(blender):
    """The demo arm bent at frame 12: its bound splats against splats made from the posed mesh, over
    the box around both renders (the background would flatter the number)."""
    res = blender.step("render")
    assert res["bind"]["result"] == ["FINISHED"] and res["engine"]["result"] == ["FINISHED"]
    d = blender.npz("render")
    covered = (d["ours_alpha"] > 0.01) | (d["reference_alpha"] > 0.01)
    rows, cols = np.nonzero(covered)
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    scores = {name: psnr(d[f"{name}_color"][box], d["reference_color"][box])
              for name in ("ours", "centres_only", "rest")}
    print(f"\nposed splats vs splats of the posed mesh, {RENDER_SIZE} px, over "
          f"{np.ptp(rows) + 1}x{np.ptp(cols) + 1} px: "
          f"PSNR {scores['ours']:.1f} dB (whole image {psnr(d['ours_color'], d['reference_color']):.1f} dB); "
          f"centres only {scores['centres_only']:.1f} dB; unposed {scores['rest']:.1f} dB")
    assert scores["ours"] >= 30.0
    assert scores["centres_only"] < scores["ours"] - 3 and scores["rest"] < 20
    # the render engine poses the same splats through its own render depsgraph
    engine = linear_to_srgb(d["engine"])
    np.testing.assert_allclose(engine, np.clip(d["ours_color"], 0, 1), atol=1e-3)


# bad input ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, words", [
    ("active not an armature", ["not an armature"]),
    ("unknown armature", ["no object named 'Nope'"]),
    ("camera as armature", ["'Camera'", "not an armature"]),
    ("no active object", ["no armature given"]),
    ("no splat objects", ["no splat objects", "'Demo Arm'"]),
    ("nothing selected", ["no splat objects"]),
    ("unknown object", ["no object named 'Nope'"]),
    ("same object", ["itself"]),
    ("not splats", ["'Demo Arm'", "not a splat object"]),
    ("backwards", ["ends before it starts"]),
    ("unknown bone", ["no bones named Nope"]),
])
def test_bad_input_reports_and_changes_nothing(blender, name, words):
    case = blender.step("errors")[name]
    assert case["result"] == ["CANCELLED"] and case["unchanged"]
    for word in words:
        assert word in case["error"]
    assert case.get("frame", 1) == 1


# collisions ------------------------------------------------------------------------------------------------

def contact_sigma_brute(mean_a, cov_a, mean_b, cov_b, samples=401, refine=60):
    """Brute force: mu = sqrt(max_s f(s)), f(s) = s(1-s) d^T (s A + (1-s) B)^-1 d, by a grid over s in
    (0, 1), then a ternary search (f is concave) between the best grid point's neighbours."""
    d = mean_a - mean_b

    def f(s):                                           # s: (S, P) -> (S, P)
        m = s[..., None, None] * cov_a + (1 - s[..., None, None]) * cov_b
        x = np.linalg.solve(m, np.broadcast_to(d[..., None], m.shape[:-1] + (1,)))[..., 0]
        return s * (1 - s) * np.einsum("spi,pi->sp", x, d)

    grid = np.linspace(0, 1, samples)
    best = np.argmax(f(np.broadcast_to(grid[1:-1, None], (samples - 2, len(d)))), axis=0) + 1
    lo, hi = grid[best - 1], grid[best + 1]
    for _ in range(refine):
        a, b = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        fa, fb = f(np.stack([a, b]))
        lo, hi = np.where(fa < fb, a, lo), np.where(fa < fb, hi, b)
    return np.sqrt(np.maximum(f(0.5 * (lo + hi)[None])[0], 0.0))


def small_case(d, key, frame):
    mean = d[f"{key}{frame}_positions"].astype(np.float64)
    cov = covariances(d[f"{key}{frame}_rotations"], d[f"{key}{frame}_log_scales"])
    opacity = 1 / (1 + np.exp(-d[f"{key}{frame}_opacity_logits"].astype(np.float64)))
    return mean, cov, opacity


def test_small_collision_case_against_brute_force_and_the_core(blender):
    from splatwright.core import SplatCloud
    from splatwright.core.collision import ellipsoid_contacts
    res = blender.step("collide_small")
    assert res["bind"]["result"] == ["FINISHED"] and res["op"]["result"] == ["FINISHED"]
    assert res["frame_after"] == 2
    d = blender.npz("collide_small")
    main_bone = np.argmax(d["weights"], axis=1)
    hits = {"a": np.zeros(len(d["contact_a"])), "b": np.zeros(len(d["contact_b"]))}
    for frame, found in zip((1, 2, 3), res["report"]["frames"]):
        (ma, ca, oa), (mb, cb, ob) = small_case(d, "a", frame), small_case(d, "b", frame)
        ka, kb = np.flatnonzero(oa >= 0.05), np.flatnonzero(ob >= 0.05)
        pa, pb = np.repeat(ka, len(kb)), np.tile(kb, len(ka))
        near = np.linalg.norm(ma[pa] - mb[pb], axis=1) <= 3.0 * (np.sqrt(np.linalg.eigvalsh(ca[pa])[:, 2])
                                                                 + np.sqrt(np.linalg.eigvalsh(cb[pb])[:, 2]))
        pa, pb = pa[near], pb[near]
        mu = contact_sigma_brute(ma[pa], ca[pa], mb[pb], cb[pb])
        assert np.all(np.abs(mu - 3.0) > 1e-6)                             # no pair on the fence
        touching = mu <= 3.0
        assert found["frame"] == frame and found["pairs"] == touching.sum()
        hits["a"][np.unique(pa[touching])] += 1
        hits["b"][np.unique(pb[touching])] += 1
        bones = np.bincount(main_bone[np.unique(pa[touching])], minlength=2)
        assert found["bones_a"] == {n: int(c) for n, c in zip(("Lower", "Upper"), bones) if c}
        # the core called directly on the same clouds agrees
        cloud = lambda key: SplatCloud(*(d[f"{key}{frame}_{f}"] for f in ("positions", "rotations", "log_scales",
                                                                           "opacity_logits")),
                                       np.zeros((len(d[f"{key}{frame}_positions"]), 1, 3)))
        core = ellipsoid_contacts(cloud("a")[ka], cloud("b")[kb], k=3.0)
        assert len(core) == found["pairs"]
    assert res["report"]["contact_frames"] == [3]
    assert hits["b"][:5].sum() == 0                                        # faint splats are left out
    np.testing.assert_allclose(d["contact_a"], hits["a"] / 3, atol=1e-7)
    np.testing.assert_allclose(d["contact_b"], hits["b"] / 3, atol=1e-7)
    assert d["contact_a"].max() == pytest.approx(1 / 3)


def test_demo_arm_touches_the_box_only_when_bent(blender):
    res = blender.step("collide_demo")
    assert res["bind"]["result"] == ["FINISHED"] and res["op"]["result"] == ["FINISHED"]
    frames = {f["frame"]: f for f in res["report"]["frames"]}
    contact = res["report"]["contact_frames"]
    print(f"\ndemo arm vs environment: contact at frames {contact}; "
          f"frame {BENT_FRAME}: {frames[BENT_FRAME]['bones_a']}")
    assert BENT_FRAME in contact and 1 not in contact and 24 not in contact
    assert set(frames[BENT_FRAME]["bones_a"]) <= {"Fore", "Hand"} and frames[BENT_FRAME]["bones_a"]
    assert res["contact_splats"] > 0 and 0 < res["contact_max"] <= len(contact) / 24 + 1e-6
    assert "splat_contact" not in res["exported_extras"] and "contact" not in res["exported_extras"]
    # without leaving the base out, the base stands on the floor at every frame
    assert res["with_base"]["frames"][0]["bones_a"].get("Base", 0) > 0


def test_cli_collide(blender):
    cli = blender.step("collide_demo")["cli"]
    ok = cli["ok"]
    assert ok["code"] == 0, ok["stderr"]
    lines = ok["stdout"].splitlines()
    assert lines[0].startswith("splatwright: collide 'Demo Arm_splats' with 'Demo Environment_splats', frames 1-12 (2)")
    assert "[2/2] frame 12:" in ok["stdout"] and "Fore" in lines[2] and lines[-1].startswith("splatwright: done:")
    report = json.loads((blender.out / "collide.json").read_text())
    assert report["contact_frames"] == [12] and [f["frame"] for f in report["frames"]] == [1, 12]
    for name, words in (("unknown", "no object named 'Nope'"), ("bad sigma", "must be positive"),
                        ("missing folder", "does not exist")):
        assert cli[name]["code"] == 1 and words in cli[name]["stderr"]
    assert not (blender.out / "nowhere").exists()


if __name__ == "__main__":
    worker_main(Worker)
