"""The Blender side of tests/test_blender_artist.py (run in each Blender of the version matrix; see
workers/base.py): the Splats panel and preferences, export options through the operators and the
command, the modal jobs' steps and cancelling, and pose matrices of a real armature."""

import numpy as np

from workers.base import MODULE, BlenderWorker, worker_main

PANEL_CLOUD = (700, 2, 7)  # count, SH degree, seed of the cloud the panel's numbers are checked on
OPTIONS_CLOUD = (400, 3, 8)  # the cloud the export options are checked on
CHAIN = 12  # bones in the armature's longest chain
POSES = 60  # random poses of the armature
SCALED_BONE = 3  # scaled by 1.001 in the last pose
PREFERRED = dict(export_format="spz", sh_degree="2", spz_version="2", use_half=True)


class Recorder:
    """A stand-in for a panel's UILayout that records the calls made on it."""

    def __init__(self, calls=None):
        self.calls = [] if calls is None else calls

    def _record(self, kind, *args, **kw):
        self.calls.append((kind, args, kw))

    def box(self):
        return Recorder(self.calls)

    def column(self, **kw):
        return Recorder(self.calls)

    def label(self, **kw):
        self._record("label", **kw)

    def prop(self, owner, prop, **kw):
        self._record("prop", owner, prop, **kw)

    def operator(self, idname, **kw):
        settings = {}
        self._record("operator", idname, **kw, _set=settings)
        return _Settings(settings)

    def operator_menu_enum(self, idname, prop, **kw):
        self._record("operator_menu_enum", idname, prop, **kw)


class _Settings:
    """What a panel sets on an operator button, recorded."""

    def __init__(self, settings):
        object.__setattr__(self, "settings", settings)

    def __setattr__(self, name, value):
        self.settings[name] = value


def _resolves(owner, prop):
    try:
        owner.path_resolve(prop)
        return True
    except ValueError:
        return False


class Worker(BlenderWorker):
    steps = (
        "install",
        "panel_draw",
        "panel_numbers",
        "export_options",
        "animation_options",
        "command_options",
        "preferences_defaults",
        "collide_job",
        "from_mesh_job",
        "armature_matrices",
    )
    keep_objects = ("Cube", "Camera", "Light")
    orphan_kinds = ("meshes", "armatures", "actions")

    # helpers ------------------------------------------------------------------------------------

    def import_cloud(self, name, count, degree, seed):
        cloud = self.random_cloud(count, degree, seed)
        self.module("io").write_splats(self.work / name, cloud)
        self.bpy.ops.splat.import_file(filepath=str(self.work / name))
        obj = self.bpy.context.active_object
        self.select([obj])
        return obj

    def export(self, name, **options):
        return self.call(self.bpy.ops.splat.export_file, filepath=str(self.out / name), selected_only=True, **options)

    def preferences(self):
        return self.bpy.context.preferences.addons[MODULE].preferences

    def scene_state(self, objects=()):
        """What a cancelled job must leave as it was: objects, data, frame, and the objects' attributes."""
        bpy = self.bpy
        state = self.inventory()
        state["frame"] = [bpy.context.scene.frame_current, bpy.context.scene.frame_subframe]
        for obj in objects:
            attrs = {}
            for attr in obj.data.attributes:
                if attr.data_type == "FLOAT" and attr.domain == "POINT":
                    values = np.empty(len(attr.data), np.float32)
                    attr.data.foreach_get("value", values)
                    attrs[attr.name] = values.tolist()
                else:
                    attrs[attr.name] = attr.data_type
            state[obj.name] = attrs
            state[obj.name + " location"] = list(obj.location)
        state["pose_positions"] = {a.name: a.pose_position for a in bpy.data.armatures}
        return state

    # steps ----------------------------------------------------------------------------------------

    def install(self):
        bpy = self.bpy
        self.install_extension()
        data = self.module("splat_addon.data")
        prefs = self.preferences()
        obj = self.import_cloud("poll.ply", 50, 1, 1)
        polls = {}
        for name in ("Cube", "Camera", obj.name):
            bpy.context.view_layer.objects.active = bpy.data.objects[name]
            polls[name] = [bpy.types.SPLAT_PT_object.poll(bpy.context), bpy.types.SPLAT_PT_view3d.poll(bpy.context)]
        if data.native_supported():
            native, _ = data.new_splat_object(
                self.random_cloud(30, 2, 2), "native", bpy.context.scene.collection, form=data.NATIVE_FORM
            )
            bpy.context.view_layer.objects.active = native
            polls["native"] = [bpy.types.SPLAT_PT_object.poll(bpy.context), bpy.types.SPLAT_PT_view3d.poll(bpy.context)]
            polls["native_stats"] = list(self.module("splat_addon.ui.panel").splat_stats(native)[:3])
        return {
            "panels": [cls.is_registered for cls in (bpy.types.SPLAT_PT_object, bpy.types.SPLAT_PT_view3d)],
            "panel_spaces": [
                (cls.bl_space_type, cls.bl_region_type, getattr(cls, "bl_category", ""), getattr(cls, "bl_context", ""))
                for cls in (bpy.types.SPLAT_PT_object, bpy.types.SPLAT_PT_view3d)
            ],
            "preferences": type(prefs).__name__,
            "preferences_idname": type(prefs).bl_idname,
            "defaults": {name: getattr(prefs, name) for name in PREFERRED},
            "polls": polls,
        }

    def panel_draw(self):
        """The panel's draw() on a recording layout: every label it shows, and whether every property
        and operator it names exists (Blender would draw an error or nothing for a wrong one)."""
        bpy = self.bpy
        obj = self.import_cloud("draw.ply", 123, 1, 3)
        bpy.context.view_layer.objects.active = obj
        layout = Recorder()
        panel = bpy.types.SPLAT_PT_view3d
        panel.draw(type("Drawn", (), {"layout": layout})(), bpy.context)
        checks = []
        for kind, args, kw in layout.calls:
            if kind == "prop":
                owner, prop = args[:2]
                checks.append([kind, kw.get("text"), _resolves(owner, prop)])
            elif kind in ("operator", "operator_menu_enum"):
                module, name = args[0].split(".")
                op = getattr(getattr(bpy.ops, module), name)
                props = op.get_rna_type().properties.keys()
                set_props = [key for key in kw.get("_set", {})]
                ok = (kind != "operator_menu_enum" or args[1] in props) and all(k in props for k in set_props)
                checks.append([kind, args[0], ok])
        labels = lambda calls: [kw.get("text") for kind, _, kw in calls if kind == "label"]  # noqa: E731
        obj.data[self.module("splat_addon.data").ANTIALIASED] = True  # as splats made for that mode
        marked = Recorder()
        panel.draw(type("Drawn", (), {"layout": marked})(), bpy.context)
        return {"labels": labels(layout.calls), "checks": checks, "marked_labels": labels(marked.calls)}

    def panel_numbers(self):
        """The panel's numbers for an imported cloud, and files written from the same object."""
        panel = self.module("splat_addon.ui.panel")
        obj = self.import_cloud("panel.ply", *PANEL_CLOUD)
        usd = self.module("io.usd")
        out = {"stats": {}, "exports": {}, "pxr": usd.stages.PXR is not None}
        for version in (2, 3, 4):
            for half in (False, True):
                stats = panel.splat_stats(obj, spz_version=version, half=half)
                out["stats"][f"{version}_{half}"] = {
                    "count": stats.count,
                    "sh_degree": stats.sh_degree,
                    "memory": stats.memory,
                    "sizes": stats.sizes,
                }
        for name, options in (
            ("size.ply", {}),
            ("size.splat", {}),
            ("size_v2.spz", dict(spz_version="2")),
            ("size_v3.spz", dict(spz_version="3")),
            ("size_v4.spz", dict(spz_version="4")),
            ("size.usda", {}),
            ("size_half.usda", dict(use_half=True)),
        ):
            out["exports"][name] = self.export(name, **options)
        if usd.stages.PXR is not None:
            out["exports"]["size.usdc"] = self.export("size.usdc")
            out["exports"]["size_half.usdc"] = self.export("size_half.usdc", use_half=True)
        return out

    def export_options(self):
        self.import_cloud("options.ply", *OPTIONS_CLOUD)
        cases = {
            "degree1.ply": dict(sh_degree="1"),
            "degree0.spz": dict(sh_degree="0", spz_version="4"),
            "v2.spz": dict(spz_version="2"),
            "v4.spz": dict(spz_version="4"),
            "half.usda": dict(use_half=True),
            "full.usda": dict(use_half=False),
            "pruned.ply": dict(prune_opacity=0.6),
            "keep.ply": dict(sh_degree="KEEP"),
            "ignored.ply": dict(prune_opacity=0.6, sh_degree="1", spz_version="2", use_half=True),
        }
        return {name: self.export(name, **options) for name, options in cases.items()}

    def animation_options(self):
        bpy = self.bpy
        obj = self.import_cloud("anim.ply", *OPTIONS_CLOUD)
        obj.location = (0, 0, 0)
        obj.keyframe_insert("location", frame=1)
        obj.location = (0.5, 0, 0)
        obj.keyframe_insert("location", frame=3)
        bpy.context.scene.frame_set(2)
        done = {}
        done["seq"] = self.call(
            bpy.ops.splat.export_animation,
            filepath=str(self.out / "anim_####.spz"),
            selected_only=True,
            use_scene_range=False,
            frame_start=1,
            frame_end=3,
            sh_degree="1",
            spz_version="4",
            prune_opacity=0.6,
        )
        done["usd"] = self.call(
            bpy.ops.splat.export_animation,
            filepath=str(self.out / "anim.usda"),
            selected_only=True,
            use_scene_range=False,
            frame_start=1,
            frame_end=3,
            use_half=True,
            sh_degree="0",
        )
        done["frame"] = bpy.context.scene.frame_current
        return done

    def command_options(self):
        command = self.module("splat_addon.command")
        self.import_cloud("cmd.ply", *OPTIONS_CLOUD)
        runs = {
            "cmd_degree1.ply": ["--sh-degree", "1"],
            "cmd_v2.spz": ["--spz-version", "2", "--prune-opacity", "0.6"],
            "cmd_v4.spz": ["--spz-version", "4", "--sh-degree", "0"],
            "cmd_half.usda": ["--half", "--sh-degree", "2"],
            "cmd_wrong.ply": ["--spz-version", "4"],
            "cmd_wrong_half.spz": ["--half"],
            "cmd_bad_prune.ply": ["--prune-opacity", "1.5"],
        }
        return {
            name: command.execute(["export", str(self.out / name), "--frames", "1", *args])
            for name, args in runs.items()
        }

    def preferences_defaults(self):
        """Options left unset take the preferences' values, in the operator and in the command."""
        command = self.module("splat_addon.command")
        prefs = self.preferences()
        saved = {name: getattr(prefs, name) for name in PREFERRED}
        self.import_cloud("prefs.ply", *OPTIONS_CLOUD)
        try:
            for name, value in PREFERRED.items():
                setattr(prefs, name, value)
            out = {
                "op_spz": self.export("prefs.spz"),
                "op_ply": self.export("prefs.ply"),
                "op_usda": self.export("prefs.usda"),
                "op_override": self.export("prefs_override.ply", sh_degree="KEEP"),
                "cmd_spz": command.execute(["export", str(self.out / "prefs_cmd.spz"), "--frames", "1"]),
                "cmd_noext": command.execute(["export", str(self.out / "prefs_noext"), "--frames", "1"]),
                "cmd_override": command.execute(
                    [
                        "export",
                        str(self.out / "prefs_cmd3.spz"),
                        "--frames",
                        "1",
                        "--spz-version",
                        "3",
                        "--sh-degree",
                        "3",
                    ]
                ),
            }
        finally:
            for name, value in saved.items():
                setattr(prefs, name, value)
        return out

    def collide_job(self):
        """Step the collision job, cancel it part-way: frame and attributes as they were; then finish it
        and compare with check_collisions and the operator."""
        bpy = self.bpy
        collide = self.module("splat_addon.rig.collide")
        a = self.import_cloud("col_a.ply", 300, 1, 11)
        b = self.import_cloud("col_b.ply", 300, 1, 12)
        a.location = (-8, 0, 0)
        a.keyframe_insert("location", frame=1)
        a.location = (8, 0, 0)
        a.keyframe_insert("location", frame=9)
        collide.write_contact(b, np.linspace(0, 1, 300))  # an earlier check's result, to be kept
        bpy.context.scene.frame_set(5)
        before = self.scene_state([a, b])
        frames = list(range(1, 10))
        job = collide.CollisionJob(bpy.context, a, b, frames)
        stepped = [job.step() for _ in range(4)]
        mid_frame = bpy.context.scene.frame_current
        job.cancel()
        after = self.scene_state([a, b])
        job = collide.CollisionJob(bpy.context, a, b, frames)
        while job.step():
            pass
        stepped_report = job.finish().as_dict()
        direct = collide.check_collisions(bpy.context, a, b, frames).as_dict()
        operator = self.call(
            bpy.ops.splat.check_collisions,
            object_a=a.name,
            object_b=b.name,
            use_scene_range=False,
            frame_start=1,
            frame_end=9,
        )
        contact = np.empty(300, np.float32)
        a.data.attributes[collide.CONTACT_ATTRIBUTE].data.foreach_get("value", contact)
        return {
            "stepped": stepped,
            "mid_frame": mid_frame,
            "done": job.done,
            "before": before,
            "after": after,
            "stepped_report": stepped_report,
            "direct": direct,
            "operator": operator,
            "frame_end": bpy.context.scene.frame_current,
            "contact_a": contact.tolist(),
        }

    def from_mesh_job(self):
        """Step a target-PSNR conversion of an armature-deformed mesh, cancel it part-way: nothing made,
        the armature posed again; then run it through."""
        bpy = self.bpy
        from_mesh = self.module("splat_addon.convert.from_mesh")
        bpy.ops.mesh.primitive_uv_sphere_add(segments=24, ring_count=12)
        sphere = bpy.context.active_object
        arm = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
        bpy.context.scene.collection.objects.link(arm)
        mod = sphere.modifiers.new("Armature", "ARMATURE")
        mod.object = arm
        before = self.scene_state()
        # One small view: the steps, not the quality they reach, are checked here.
        views = dict(view_size=32, view_count=1, view_distances=(1.0,))
        job = from_mesh.ConversionJob(bpy.context, [sphere], target_psnr=45.0, max_splats=3000, **views)
        during = self.scene_state()
        steps = [job.step() for _ in range(2)]
        label, done = job.label, job.done
        job.cancel()
        after = self.scene_state()
        full = from_mesh.ConversionJob(bpy.context, [sphere], target_psnr=30.0, max_splats=3000, **views)
        progress = []
        results = full.run(lambda d, t, label: progress.append(d))
        direct = from_mesh.convert_objects(bpy.context, [sphere], target_psnr=30.0, max_splats=3000, **views)
        self.save("from_mesh_job", stepped=results[0][1].positions, direct=direct[0][1].positions)
        return {
            "before": before,
            "during": during,
            "after": after,
            "steps": steps,
            "label": label,
            "done": done,
            "progress": progress,
            "count": len(results[0][1]),
        }

    def armature_matrices(self):
        """Rest and pose matrices (armature space, as Blender stores them) of a rig with a 12-bone chain
        and short branches, turned many ways; the last pose also scales one bone by 1.001."""
        bpy = self.bpy
        rng = np.random.default_rng(0)
        arm = bpy.data.armatures.new("Chain")
        obj = bpy.data.objects.new("Chain", arm)
        bpy.context.scene.collection.objects.link(obj)
        bpy.context.view_layer.objects.active = obj
        bpy.ops.object.mode_set(mode="EDIT")
        chain = []
        for i in range(CHAIN):
            bone = arm.edit_bones.new(f"c{i}")
            bone.head = chain[-1].tail if chain else (0.2, -0.1, 0.3)
            bone.tail = bone.head + self.vector(rng.normal(0, 0.4, 3) + (0, 0, 0.3))
            bone.roll = rng.uniform(-3, 3)
            if chain:
                bone.parent, bone.use_connect = chain[-1], True
            chain.append(bone)
        for i in range(4):  # branches off the chain, not connected
            bone = arm.edit_bones.new(f"b{i}")
            bone.head = chain[3 * i].head + self.vector(rng.normal(0, 0.2, 3))
            bone.tail = bone.head + self.vector(rng.normal(0, 0.3, 3))
            bone.roll = rng.uniform(-3, 3)
            bone.parent = chain[3 * i]
        bpy.ops.object.mode_set(mode="OBJECT")
        modes = ("QUATERNION", "XYZ", "ZXY", "YZX", "AXIS_ANGLE")
        rest = np.array([np.array(b.matrix_local) for b in arm.bones])
        poses = []
        for t in range(POSES):
            for pb in obj.pose.bones:
                pb.rotation_mode = modes[rng.integers(len(modes))]
                if pb.rotation_mode == "QUATERNION":
                    q = rng.normal(size=4)
                    pb.rotation_quaternion = q / np.linalg.norm(q)
                elif pb.rotation_mode == "AXIS_ANGLE":
                    pb.rotation_axis_angle = (rng.uniform(-7, 7), *rng.normal(size=3))
                else:
                    pb.rotation_euler = rng.uniform(-7, 7, 3)
                pb.location = rng.normal(0, 0.3, 3)
                pb.scale = (1.0, 1.0, 1.0)
            if t == POSES - 1:
                obj.pose.bones[SCALED_BONE].scale = (1.001, 1.001, 1.001)
            bpy.context.view_layer.update()
            poses.append([np.array(pb.matrix) for pb in obj.pose.bones])
        names = [b.name for b in arm.bones]
        self.save("armature", rest=rest, poses=np.array(poses))
        return {"names": names, "dtype": str(np.array(obj.pose.bones[0].matrix).dtype)}

    def vector(self, values):
        from mathutils import Vector

        return Vector([float(v) for v in values])


if __name__ == "__main__":
    worker_main(Worker)
