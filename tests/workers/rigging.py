"""The Blender side of tests/test_blender_rigging.py (run in each Blender of the version matrix; see
workers/base.py)."""

import contextlib
import io
import json

import numpy as np

from workers.base import MODULE, BlenderWorker, worker_main

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
GROUP_ORDER = ("Side", "Root", "Ctrl", "Tip", "Mid")  # not the bone order
ARM_TRANSFORM = dict(location=(0.3, -0.2, 0.1), rotation_euler=(0.1, 0.2, -0.3), scale=(1.1, 1.1, 1.1))
SPLAT_TRANSFORM = dict(location=(0.5, 0.4, -0.2), rotation_euler=(0.3, -0.1, 0.5), scale=(1.0, 1.3, 0.8))
DRAWN_TYPES = {
    "FLOAT": ("value", 1),
    "FLOAT_VECTOR": ("vector", 3),
    "QUATERNION": ("value", 4),
    "FLOAT4": ("vector", 4),
    "FLOAT_COLOR": ("color", 4),
}
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
    return dict(
        positions=positions,
        rotations=rng.normal(0, 1, (n, 4)) * rng.uniform(0.5, 2, (n, 1)),
        log_scales=rng.uniform(-4, -2, (n, 3)),
        opacity_logits=rng.normal(2, 1, n),
        sh=rng.normal(0, 0.3, (n, 4, 3)),
    )


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
    steps = (
        "install",
        "skinning",
        "weights_read_aside",
        "transfer",
        "bone_weights",
        "render",
        "errors",
        "collide_small",
        "collide_demo",
        "reregister",
    )

    # helpers -------------------------------------------------------------------------------------

    def splat_object(self, name, arrays, matrix=None, form=None):
        core = self.module("core")
        data = self.module("splat_addon.data")
        scene = self.bpy.context.scene
        obj, _ = data.new_splat_object(core.SplatCloud(**arrays), name, scene.collection, matrix, form)
        return obj

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

    def drawn(self, obj):
        """What Blender draws of native splats: their visible attributes as stored (float32)."""
        out = {}
        for attr in obj.data.attributes:
            if attr.domain == "POINT" and not attr.name.startswith(".") and attr.data_type in DRAWN_TYPES:
                prop, width = DRAWN_TYPES[attr.data_type]
                values = np.empty(len(attr.data) * width, np.float32)
                attr.data.foreach_get(prop, values)
                out[attr.name] = values.reshape(-1, width)
        return out

    def repose(self):
        """A frame change, which writes bound native splats posed into what Blender draws."""
        scene = self.bpy.context.scene
        scene.frame_set(scene.frame_current)

    def write_weights(self, obj, weights):
        """Bone weights {group: {splat: weight}} as a user stores them: vertex groups of a splat mesh,
        FLOAT attributes splat_weight:<group> of native splats."""
        if obj.type == "MESH":
            for name, members in weights.items():
                group = obj.vertex_groups.get(name) or obj.vertex_groups.new(name=name)
                for v, w in members.items():
                    group.add([v], w, "REPLACE")
            return
        count = len(obj.data.points)
        for name, members in weights.items():
            attr = obj.data.attributes.get("splat_weight:" + name)
            column = np.zeros(count, np.float32)
            if attr is None:
                attr = obj.data.attributes.new("splat_weight:" + name, "FLOAT", "POINT")
            else:
                attr.data.foreach_get("value", column)
            column[list(members)] = list(members.values())
            attr.data.foreach_set("value", column)
        obj.data.update_tag()

    def twin_mesh(self, obj, weights, arm):
        """A plain mesh of the centres of `obj`'s own splats with its transform, the vertex groups
        `weights` and an Armature modifier: Blender's own skinning of those points."""
        bpy = self.bpy
        centres = self.module("splat_addon.data").object_cloud(obj).positions
        mesh = bpy.data.meshes.new(obj.name + " Twin")
        mesh.from_pydata([tuple(map(float, c)) for c in centres], [], [])
        twin = bpy.data.objects.new(obj.name + " Twin", mesh)
        bpy.context.scene.collection.objects.link(twin)
        twin.matrix_world = obj.matrix_world.copy()
        self.write_weights(twin, weights)
        twin.modifiers.new("Armature", "ARMATURE").object = arm
        return twin

    def display_positions(self, obj):
        """The viewport display's points (object space)."""
        depsgraph = self.bpy.context.evaluated_depsgraph_get()
        for inst in depsgraph.object_instances:  # instance data is only valid during iteration
            if inst.object.type == "POINTCLOUD" and inst.object.original == obj:
                points = inst.object.data
                co = np.empty(len(points.points) * 3, np.float32)
                points.attributes["position"].data.foreach_get("vector", co)
                return co.reshape(-1, 3)
        raise RuntimeError(f"'{obj.name}' shows no display points")

    def inventory(self):
        """What a failed bind or collision check must leave as it was (armature bindings included)."""
        bpy = self.bpy
        inv = {k: sorted(x.name for x in getattr(bpy.data, k)) for k in ("objects", "meshes", "armatures")}
        inv["groups"] = {o.name: [g.name for g in o.vertex_groups] for o in bpy.data.objects}
        inv["modifiers"] = {o.name: [m.name for m in o.modifiers] for o in bpy.data.objects}
        inv["parents"] = {o.name: o.parent.name if o.parent else None for o in bpy.data.objects}
        inv["properties"] = {o.name: sorted(o.keys()) for o in bpy.data.objects}
        inv["attributes"] = {
            g.name: sorted(a.name for a in g.attributes) for g in (*bpy.data.meshes, *bpy.data.pointclouds)
        }
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
        rig = self.module("splat_addon.convert.demo_rig").build_demo_rig(
            bpy.context.scene, environment_splats, calibrate=False
        )
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=body_splats, calibrate=False)
        splats = bpy.context.active_object
        self.select([splats, rig.armature], active=rig.armature)
        return rig, splats

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        menus = {name: self.menu_entries(name) for name in ("VIEW3D_MT_object_parent", "VIEW3D_MT_object")}
        data = self.module("splat_addon.data")
        return {
            "operators": [hasattr(bpy.types, n) for n in ("SPLAT_OT_bind_armature", "SPLAT_OT_check_collisions")],
            "menus": menus,
            "posers": [f"{f.__module__.rpartition('splat_addon.')[2]}.{f.__name__}" for f in data.POSERS],
            "handlers": self.handler_count(),
        }

    def handler_count(self):
        handlers = self.bpy.app.handlers
        return sum(
            1
            for lst in (handlers.depsgraph_update_post, handlers.load_post, handlers.undo_post, handlers.redo_post)
            for f in lst
            if f.__module__.startswith(MODULE)
        )

    def skinning(self):
        """Weights stored by hand as a user does (vertex groups and an Armature modifier on a splat mesh;
        splat_weight:<bone> attributes and the armature property on native splats), posed against
        Blender's Armature modifier on the same centres: the splat mesh's own, or a plain twin mesh
        of native splats' centres with the same groups."""
        bpy = self.bpy
        data = self.module("splat_addon.data")
        display = self.module("splat_addon.data.display")
        rigging = self.module("splat_addon.rig.armature")
        arm = self.build_rig()
        arrays = rig_cloud_arrays(RIG_SPLATS)
        obj = self.splat_object("RigSplats", arrays)
        for key, value in SPLAT_TRANSFORM.items():
            setattr(obj, key, value)
        bpy.context.view_layer.update()
        native = data.splat_form(obj) == data.NATIVE_FORM
        weights_given = rig_weights(RIG_SPLATS)  # groups in GROUP_ORDER
        self.write_weights(obj, weights_given)
        if native:
            obj[rigging.ARMATURE_PROPERTY] = arm
            twin = self.twin_mesh(obj, weights_given, arm)  # Blender's Armature modifier on the same points
            mod, shown = twin.modifiers["Armature"], None
        else:
            twin = obj
            mod = obj.modifiers.new("Armature", "ARMATURE")
            mod.object = arm
            shown = display.add_display(obj)
            display.set_input(shown, "Min Opacity", 0.0)

        def set_volume(volume):
            mod.use_deform_preserve_volume = volume
            if native:
                obj[rigging.PRESERVE_VOLUME_PROPERTY] = volume
                self.repose()

        def theirs():
            """Blender's Armature modifier's vertices (object space), the display modifier off."""
            if shown is None:
                return self.blender_positions(twin)
            shown.show_viewport = False
            try:
                return self.blender_positions(obj)
            finally:
                shown.show_viewport = True

        bpy.context.view_layer.update()
        res = {
            "modifiers": [m.type for m in obj.modifiers],
            "form": data.splat_form(obj),
            "armature": rigging.rig_of(obj)[0].name,
        }
        names = list(RIG_BONES)
        arm_world, obj_world = np.array(arm.matrix_world), np.array(obj.matrix_world)
        to_obj = np.linalg.inv(obj_world) @ arm_world
        deform = np.stack(
            [
                to_obj
                @ np.array(arm.pose.bones[n].matrix)
                @ np.linalg.inv(np.array(arm.data.bones[n].matrix_local))
                @ np.linalg.inv(to_obj)
                for n in names
            ]
        )
        arrays_out = {}
        for mode, volume in (("lbs", False), ("dqs", True)):
            set_volume(volume)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            ours = data.evaluated_cloud(obj, depsgraph, np.eye(4))
            if native:  # what Blender draws: the posed splats, every attribute
                drawn = self.drawn(obj)
                arrays_out[f"{mode}_display"] = drawn["position"]
                arrays_out.update(
                    {
                        f"{mode}_drawn_{k.replace(':', '_')}": v
                        for k, v in drawn.items()
                        if k in ("rotation", "scale") or k.startswith("radiance:")
                    }
                )
            else:
                arrays_out[f"{mode}_display"] = self.display_positions(obj)
            arrays_out[f"{mode}_blender"] = theirs()
            arrays_out.update(
                {
                    f"{mode}_positions": ours.positions,
                    f"{mode}_rotations": ours.rotations,
                    f"{mode}_log_scales": ours.log_scales,
                    f"{mode}_sh": ours.sh,
                    f"{mode}_opacity_logits": ours.opacity_logits,
                }
            )
        weights = self.weight_matrix(obj, names)
        kept = data.object_cloud(obj)  # the rest pose, however often it was drawn posed
        # weights painted after the first evaluation: the cached weights must follow
        set_volume(False)
        repaint = {"Tip": {v: 0.7 for v in range(20, 60)}}
        self.write_weights(obj, repaint)
        if native:
            self.write_weights(twin, repaint)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        arrays_out["repainted_positions"] = data.evaluated_cloud(obj, depsgraph, np.eye(4)).positions
        arrays_out["repainted_blender"] = theirs()
        # a mask painted by hand and inverted on the modifier: every fifth splat is outside the group;
        # native splats hold it as the binding strength itself (1 - weight, 1 outside the group)
        fade = {v: float(w) for v, w in enumerate(np.random.default_rng(5).uniform(0, 1, RIG_SPLATS)) if v % 5}
        self.write_weights(twin, {"Fade": fade})
        mod.vertex_group, mod.invert_vertex_group = "Fade", True
        if native:
            strength = np.ones(RIG_SPLATS, np.float32)
            strength[list(fade)] = 1.0 - np.array(list(fade.values()), np.float32)
            attr = obj.data.attributes.new(rigging.MASK_GROUP, "FLOAT", "POINT")
            attr.data.foreach_set("value", strength)
            obj.data.update_tag()
        for mode, volume in (("lbs", False), ("dqs", True)):
            set_volume(volume)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            arrays_out[f"masked_{mode}_positions"] = data.evaluated_cloud(obj, depsgraph, np.eye(4)).positions
            arrays_out[f"masked_{mode}_blender"] = theirs()
            if native:
                arrays_out[f"masked_{mode}_display"] = self.drawn(obj)["position"]
        self.save(
            "skinning",
            rest_positions=arrays["positions"],
            rest_rotations=arrays["rotations"],
            rest_log_scales=arrays["log_scales"],
            deform=deform,
            bones=np.array(names),
            weights=weights,
            kept_positions=kept.positions,
            kept_rotations=kept.rotations,
            kept_log_scales=kept.log_scales,
            kept_sh=kept.sh,
            rest_sh=arrays["sh"],
            **arrays_out,
        )
        return res

    def weights_read_aside(self):
        """A splat mesh's first pose reads its weights and mask group (the cache empty) while the caller
        holds the scene's depsgraph, as an exporter or a background render does: which scenes were
        evaluated meanwhile, the depsgraph's instances before and after, and what is left behind."""
        bpy = self.bpy
        data = self.module("splat_addon.data")
        rigging = self.module("splat_addon.rig.armature")
        arm = self.build_rig()
        obj = self.splat_object("AsideSplats", rig_cloud_arrays(RIG_SPLATS), form=data.MESH_FORM)
        self.write_weights(obj, rig_weights(RIG_SPLATS))
        self.write_weights(obj, {"Fade": {v: 0.5 for v in range(0, RIG_SPLATS, 3)}})
        mod = obj.modifiers.new("Armature", "ARMATURE")
        mod.object, mod.vertex_group = arm, "Fade"
        rigging.forget_weights()
        depsgraph = bpy.context.evaluated_depsgraph_get()

        def instances():
            return sorted(inst.object.original.name for inst in depsgraph.object_instances)

        before, inventory = instances(), (self.inventory(), sorted(s.name for s in bpy.data.scenes))
        evaluated = []

        def record(scene, _depsgraph):
            evaluated.append(scene.name)

        bpy.app.handlers.depsgraph_update_post.append(record)
        try:
            posed = data.evaluated_cloud(obj, depsgraph, np.eye(4)).positions
        finally:
            bpy.app.handlers.depsgraph_update_post.remove(record)
        return {
            "scene": bpy.context.scene.name,
            "evaluated": evaluated,
            "instances": [before, instances()],
            "unchanged": inventory == (self.inventory(), sorted(s.name for s in bpy.data.scenes)),
            "cached": [obj.data.session_uid in cache for cache in (rigging._CACHE, rigging._STRENGTHS)],
            "moved": float(np.abs(posed - data.object_cloud(obj).positions).max()),
        }

    def transfer(self):
        bpy = self.bpy
        data = self.module("splat_addon.data")
        rig, splats = self.demo()
        names = [b.name for b in rig.armature.data.bones]
        res = {"bind": self.call(bpy.ops.splat.bind_armature, armature=rig.armature.name, max_influences=8)}
        rigging = self.module("splat_addon.rig.armature")
        extras = data.object_cloud(splats).extras
        res.update(
            groups=rigging.weight_names(splats),
            form=data.splat_form(splats),
            armature=rigging.rig_of(splats)[0].name,
            modifiers=[[m.type, m.object.name if m.type == "ARMATURE" else None] for m in splats.modifiers],
            parent=splats.parent.name if splats.parent else None,
            matrix_kept=bool(np.allclose(np.array(splats.matrix_world), np.array(rig.body.matrix_world))),
            source=json.loads(splats.data["splatwright_source"]),
        )
        self.save(
            "transfer",
            weights=self.weight_matrix(splats, names),
            source=self.group_matrix(rig.body, names),
            source_vertices=extras["source_vertices"],
            barycentric=extras["barycentric"],
        )
        # the active armature, one influence
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=3000, calibrate=False)
        single = bpy.context.active_object
        self.select([single, rig.armature], active=rig.armature)
        res["single"] = self.call(bpy.ops.splat.bind_armature, max_influences=1)
        self.save("transfer_single", weights=self.weight_matrix(single, names))
        # a source mesh that is gone: weights from the bones, with a warning
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=200, calibrate=False)
        orphan = bpy.context.active_object
        rig.body.name = "Renamed Arm"
        warnings = []
        plans = self.module("splat_addon.rig.armature").bind_armature([orphan], rig.armature, warn=warnings.append)
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
        res = {
            "bind": self.call(
                bpy.ops.splat.bind_armature, max_influences=2, falloff=4.0, min_weight=0.01, preserve_volume=True
            )
        }
        names = list(RIG_BONES)
        rigging = self.module("splat_addon.rig.armature")
        res["preserve_volume"] = rigging.rig_of(obj)[1]
        res["preserve_volume_stored"] = (
            obj.modifiers[0].use_deform_preserve_volume
            if obj.type == "MESH"
            else bool(obj[rigging.PRESERVE_VOLUME_PROPERTY])
        )
        res["groups"] = rigging.weight_names(obj)
        if obj.type == "POINTCLOUD":  # bound to a posed armature: Blender draws them posed at once
            posed = self.module("splat_addon.data").evaluated_cloud(
                obj, bpy.context.evaluated_depsgraph_get(), np.eye(4)
            )
            drawn = self.drawn(obj)["position"]
            res["drawn_posed"] = [
                float(np.abs(drawn - posed.positions).max()),
                float(np.abs(drawn - arrays["positions"]).max()),
            ]
        to_arm = np.linalg.inv(np.array(arm.matrix_world)) @ np.array(obj.matrix_world)
        self.save(
            "bone_weights",
            weights=self.weight_matrix(obj, names),
            positions=arrays["positions"],
            to_arm=to_arm,
            heads=np.array([arm.data.bones[n].head_local for n in names]),
            tails=np.array([arm.data.bones[n].tail_local for n in names]),
            bones=np.array(names),
        )
        return res

    def render(self):
        bpy = self.bpy
        scene = bpy.context.scene
        data = self.module("splat_addon.data")
        rigging = self.module("splat_addon.rig.armature")
        camera = self.module("splat_addon.data.camera")
        from_mesh = self.module("splat_addon.convert.from_mesh")
        render = self.module("core.render").render
        rig, splats = self.demo(body_splats=8000)
        res = {"bind": self.call(bpy.ops.splat.bind_armature)}
        rest = data.evaluated_cloud(splats, bpy.context.evaluated_depsgraph_get())
        scene.frame_set(BENT_FRAME)
        reference = from_mesh.convert_objects(
            bpy.context, [rig.body], max_splats=8000, calibrate=False, use_rest_pose=False
        )[0][1]
        depsgraph = bpy.context.evaluated_depsgraph_get()
        ours = data.evaluated_cloud(splats, depsgraph)
        reference = data.transform_cloud(reference, data.world_matrix(rig.body, depsgraph))
        width, height = RENDER_SIZE
        cam = camera.from_object(scene.camera.evaluated_get(depsgraph), scene, width, height)
        images = {
            name: render(cloud, cam, background=(0.0, 0.0, 0.0))
            for name, cloud in (
                ("ours", ours),
                ("reference", reference),
                ("rest", rest),
                ("centres_only", rest.replace(positions=ours.positions)),
            )
        }
        # the render engine (its own render depsgraph), with the weights cache empty
        render_settings = scene.render
        render_settings.engine = "SPLATWRIGHT"
        scene.splatwright_mesh_engine = "NONE"  # splats alone: the skinned mesh stays out
        render_settings.resolution_x, render_settings.resolution_y, render_settings.resolution_percentage = (
            width,
            height,
            100,
        )
        self.image_format(render_settings.image_settings, "OPEN_EXR")
        render_settings.filepath = str(self.out / "engine.exr")
        scene.world = None
        rigging.forget_weights()
        res["engine"] = self.call(bpy.ops.render.render, write_still=True)
        self.save(
            "render",
            **{f"{k}_color": v.color for k, v in images.items()},
            **{f"{k}_alpha": v.alpha for k, v in images.items()},
        )
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
            ("nothing selected", [], rig.armature, {}),
        ):
            self.select(selected, active=active)
            if active is None:
                bpy.context.view_layer.objects.active = None
            before = self.inventory()
            cases[name] = {**self.call(bind, **kw), "unchanged": before == self.inventory()}
        collide = bpy.ops.splat.check_collisions
        base = dict(use_scene_range=False, frame_start=1, frame_end=2)
        for name, kw in (
            ("unknown object", dict(object_a=splats.name, object_b="Nope")),
            ("same object", dict(object_a=splats.name, object_b=splats.name)),
            ("not splats", dict(object_a=splats.name, object_b=rig.body.name)),
            ("backwards", dict(object_a=splats.name, object_b=env.name, frame_start=5, frame_end=2)),
            ("unknown bone", dict(object_a=splats.name, object_b=env.name, ignore_bones="Nope")),
        ):
            before = self.inventory()
            cases[name] = {
                **self.call(collide, **{**base, **kw}),
                "unchanged": before == self.inventory(),
                "frame": bpy.context.scene.frame_current,
            }
        return cases

    def collide_small(self):
        """A bound cloud (two bones, the lower one turning) and a cloud that flies in at frame 3."""
        bpy = self.bpy
        scene = bpy.context.scene
        data = self.module("splat_addon.data")
        collide = self.module("splat_addon.rig.collide")
        arm = self.two_bone_armature("Pole")
        rng = np.random.default_rng(11)
        n_a, n_b = 60, 50
        pole = dict(
            positions=np.column_stack([rng.normal(0, 0.08, (n_a, 2)), rng.uniform(0, 2, n_a)]),
            rotations=rng.normal(0, 1, (n_a, 4)),
            log_scales=rng.uniform(-3.2, -2.0, (n_a, 3)),
            opacity_logits=np.full(n_a, 4.0),
            sh=np.zeros((n_a, 1, 3)),
        )
        blob = dict(
            positions=rng.normal(0, 0.15, (n_b, 3)),
            rotations=rng.normal(0, 1, (n_b, 4)),
            log_scales=rng.uniform(-3.0, -2.0, (n_b, 3)),
            opacity_logits=np.where(np.arange(n_b) < 5, -6.0, 3.0),
            sh=np.zeros((n_b, 1, 3)),
        )
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
        res["op"] = self.call(
            bpy.ops.splat.check_collisions,
            object_a=a.name,
            object_b=b.name,
            use_scene_range=False,
            frame_start=1,
            frame_end=3,
        )
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
            values = np.empty(data.splat_count(obj.data), np.float32)
            obj.data.attributes["splat_contact"].data.foreach_get("value", values)
            contact[f"contact_{key}"] = values
        self.save("collide_small", weights=self.weight_matrix(a, ["Lower", "Upper"]), **clouds, **contact)
        return res

    def collide_demo(self):
        bpy = self.bpy
        collide = self.module("splat_addon.rig.collide")
        rig, splats = self.demo(environment_splats=20_000, body_splats=8000)
        res = {"bind": self.call(bpy.ops.splat.bind_armature)}
        env = rig.environment
        res["op"] = self.call(
            bpy.ops.splat.check_collisions, object_a=splats.name, object_b=env.name, ignore_bones="Base"
        )
        data = self.module("splat_addon.data")
        values = np.empty(data.splat_count(splats.data), np.float32)
        splats.data.attributes["splat_contact"].data.foreach_get("value", values)
        res["contact_max"], res["contact_splats"] = float(values.max()), int((values > 0).sum())
        res["exported_extras"] = sorted(data.object_cloud(splats).extras)
        res["report"] = collide.check_collisions(
            bpy.context, splats, env, range(1, 25), ignore_bones=["Base"], write_attribute=False
        ).as_dict()
        res["with_base"] = collide.check_collisions(bpy.context, splats, env, [1], write_attribute=False).as_dict()
        execute = self.module("splat_addon.command").execute
        runs = {
            "ok": [
                "collide",
                splats.name,
                env.name,
                "--frames",
                "1-12:11",
                "--ignore-bones",
                "Base",
                "--json",
                str(self.out / "collide.json"),
            ],
            "unknown": ["collide", splats.name, "Nope", "--frames", "1"],
            "bad sigma": ["collide", splats.name, env.name, "--frames", "1", "--sigma", "-1"],
            "missing folder": [
                "collide",
                splats.name,
                env.name,
                "--frames",
                "1",
                "--json",
                str(self.out / "nowhere" / "c.json"),
            ],
        }
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


if __name__ == "__main__":
    worker_main(Worker)
