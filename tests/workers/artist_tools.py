"""The Blender side of tests/test_blender_artist_tools.py: clean-up, grading and binding captured
splats through a proxy mesh (run in each Blender of the version matrix; see workers/base.py)."""

import json
import math

import numpy as np

from workers.base import BlenderWorker, worker_main

SPLATS = 500
BOX = dict(location=(0.2, -0.1, 0.1), rotation_euler=(0.3, 0.2, 0.5), scale=(1.0, 0.7, 1.2), size=0.6)
GRADE = dict(exposure=0.4, saturation=0.6, hue=0.5, white=(1.0, 0.9, 0.7))
TUBE = dict(radius=0.3, height=2.0, rings=13, segments=16)
NEAR, FAR = 300, 20  # capture splats around the proxy's surface, and farther away
FADING = 240  # capture splats at distances 0..FADE_SPAN from the tube, to test the falloff
FALLOFF_START, MAX_DISTANCE, FADE_SPAN = 0.04, 0.1, 0.14
POSE = (("Upper", (0.87, 0.0, 0.0)), ("Lower", (0.0, 0.26, 0.0)))  # Upper 50 degrees about x, Lower 15 about y


def tube_mesh():
    """An open tube along z from 0 to height: vertices (V,3) and quads as triangles (F,3)."""
    r, h, rings, seg = TUBE["radius"], TUBE["height"], TUBE["rings"], TUBE["segments"]
    angle = 2 * np.pi * np.arange(seg) / seg
    z = np.linspace(0, h, rings)
    verts = np.stack([np.tile(r * np.cos(angle), rings), np.tile(r * np.sin(angle), rings), np.repeat(z, seg)], -1)
    faces = []
    for i in range(rings - 1):
        for j in range(seg):
            a, b, c, d = i * seg + j, i * seg + (j + 1) % seg, (i + 1) * seg + (j + 1) % seg, (i + 1) * seg + j
            faces += [(a, b, c), (a, c, d)]
    return verts, np.array(faces)


def tube_weights(verts):
    """(V, 2) weights of the bones Lower (0..1) and Upper (1..2), blended over z in 0.6..1.4."""
    upper = np.clip((verts[:, 2] - 0.6) / 0.8, 0.0, 1.0)
    return np.stack([1.0 - upper, upper], axis=1)


def capture_positions(seed=11):
    """Splats scattered around the tube's surface (not made from it) and some far from it."""
    rng = np.random.default_rng(seed)
    angle, z = rng.uniform(0, 2 * np.pi, NEAR), rng.uniform(0.05, 1.95, NEAR)
    radius = TUBE["radius"] + rng.normal(0, 0.015, NEAR)
    near = np.stack([radius * np.cos(angle), radius * np.sin(angle), z], -1)
    far_angle = rng.uniform(0, 2 * np.pi, FAR)
    far = np.stack([1.2 * np.cos(far_angle), 1.2 * np.sin(far_angle), rng.uniform(0, 2, FAR)], -1)
    return np.concatenate([near, far])


def fading_positions(seed=13):
    """Splats outside the tube at radial gaps spread evenly over 0..FADE_SPAN: some within the falloff
    start, some fading, some beyond the max distance."""
    rng = np.random.default_rng(seed)
    angle, z = rng.uniform(0, 2 * np.pi, FADING), rng.uniform(0.05, 1.95, FADING)
    radius = TUBE["radius"] + np.linspace(0.0, FADE_SPAN, FADING)
    return np.stack([radius * np.cos(angle), radius * np.sin(angle), z], -1)


class Worker(BlenderWorker):
    steps = (
        "install",
        "cleanup_mesh",
        "cleanup_native",
        "visibility",
        "cleanup_refusals",
        "proxy_bind",
        "proxy_falloff",
        "proxy_refusals",
    )

    def splat_object(self, name, cloud, form=None):
        data = self.module("splat_addon.data")
        obj, _ = data.new_splat_object(cloud, name, self.bpy.context.scene.collection, form=form)
        return obj

    def world_cloud(self, obj, edits=True):
        data = self.module("splat_addon.data")
        return data.evaluated_cloud(obj, self.bpy.context.evaluated_depsgraph_get(), edits=edits)

    def mesh_object(self, name, verts, faces):
        bpy = self.bpy
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([tuple(v) for v in verts], [], [tuple(int(i) for i in f) for f in faces])
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        return obj

    def export_count(self, path):
        bpy = self.bpy
        bpy.ops.splat.export_file(filepath=str(path), selected_only=True)
        return len(self.module("io").read_splats(str(path)))

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        self.install_extension()
        names = (
            "SPLAT_OT_crop",
            "SPLAT_OT_prune",
            "SPLAT_OT_grade",
            "SPLAT_OT_reduce_sh",
            "SPLAT_OT_bind_proxy",
            "SPLAT_OT_clear_cleanup",
        )
        return {
            "operators": {n: hasattr(self.bpy.types, n) for n in names},
            "edits": [f.__name__ for f in self.module("splat_addon.data").EDITS],
        }

    def cleanup(self, form):
        """Every clean-up on one object, each checked against the unedited splats (world space)."""
        bpy = self.bpy
        data = self.module("splat_addon.data")
        if form == "NATIVE" and not data.native_supported():
            return {"skipped": True}
        obj = self.splat_object("Capture", self.random_cloud(SPLATS, sh_degree=3, seed=21, spread=0.8), form)
        obj.location, obj.scale = (0.1, 0.2, -0.1), (1.2, 1.2, 1.2)
        box = bpy.data.objects.new("CropBox", None)
        box.empty_display_type, box.empty_display_size = "CUBE", BOX["size"]
        for key in ("location", "rotation_euler", "scale"):
            setattr(box, key, BOX[key])
        bpy.context.scene.collection.objects.link(box)
        bpy.ops.mesh.primitive_torus_add(major_radius=0.6, minor_radius=0.3, location=(0.1, 0, 0.05))
        torus = bpy.context.active_object
        bpy.context.view_layer.update()
        before = self.world_cloud(obj)
        out, res = {}, {}

        def step(name, op, **kw):
            self.select([obj], active=kw.pop("active", obj))
            res[name] = self.call(op, **kw)
            res[name]["report"] = json.loads(obj.get("splatwright_cleanup_report", "null"))
            res[name]["exported"] = self.export_count(self.out / f"{form}_{name}.ply")
            after = self.world_cloud(obj)
            out[f"{name}_positions"], out[f"{name}_sh"] = after.positions, after.sh
            bpy.ops.splat.clear_cleanup()

        self.select([obj, box], active=box)
        res["crop_box"] = self.call(bpy.ops.splat.crop)
        res["crop_box"]["report"] = json.loads(obj["splatwright_cleanup_report"])
        res["crop_box"]["exported"] = self.export_count(self.out / f"{form}_box.ply")
        out["crop_box_positions"] = self.world_cloud(obj).positions
        out["box_matrix"] = np.array(box.matrix_world) @ np.diag([BOX["size"]] * 3 + [1.0])
        res["settings"] = json.loads(obj["splatwright_cleanup"])
        self.select([obj])
        bpy.ops.splat.clear_cleanup()
        step("crop_mesh", bpy.ops.splat.crop, volume=torus.name, invert=True)
        mesh = torus.data
        co = np.empty(len(mesh.vertices) * 3)
        mesh.vertices.foreach_get("co", co)
        world = np.array(torus.matrix_world)
        out["torus_vertices"] = co.reshape(-1, 3) @ world[:3, :3].T + world[:3, 3]
        tris = np.empty(len(mesh.loop_triangles) * 3, np.int64)
        mesh.loop_triangles.foreach_get("vertices", tris)
        out["torus_triangles"] = tris.reshape(-1, 3)
        step("opacity", bpy.ops.splat.prune, by="OPACITY", threshold=0.6)
        step("size", bpy.ops.splat.prune, by="SIZE", min_size=0.05, max_size=0.25)
        step("grade", bpy.ops.splat.grade, **GRADE)
        step("reduce_sh", bpy.ops.splat.reduce_sh, degree=1)
        res["cleared_export"] = self.export_count(self.out / f"{form}_cleared.ply")
        res["matrix"] = np.array(obj.matrix_world).tolist()
        self.save(
            f"cleanup_{form}",
            before_positions=before.positions,
            before_sh=before.sh,
            before_opacity=before.opacity_logits,
            before_log_scales=before.log_scales,
            **out,
        )
        return res

    def cleanup_mesh(self):
        return self.cleanup("MESH")

    def cleanup_native(self):
        return self.cleanup("NATIVE")

    def visibility(self):
        """The scene camera moves over three frames and sees only part of the cloud."""
        bpy = self.bpy
        cam = bpy.data.objects["Camera"]
        bpy.context.scene.camera = cam
        scene = bpy.context.scene
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 320, 240, 100
        scene.frame_start, scene.frame_end = 1, 3
        cam.rotation_mode = "XYZ"
        cam.data.lens = 60
        for frame, x in ((1, -0.5), (3, 0.5)):
            cam.location, cam.rotation_euler = (x, -4.0, 0.0), (math.pi / 2, 0.0, 0.0)
            cam.keyframe_insert("location", frame=frame)
            cam.keyframe_insert("rotation_euler", frame=frame)
        rng = np.random.default_rng(31)
        cloud = self.random_cloud(SPLATS, sh_degree=1, seed=31, spread=1.0)
        cloud = cloud.replace(
            positions=np.c_[
                rng.uniform(-3, 3, SPLATS), rng.uniform(-5.5, 1, SPLATS), rng.uniform(-2, 2, SPLATS)
            ].astype(np.float32)
        )
        obj = self.splat_object("Room", cloud)
        self.select([obj])
        res = {"prune": self.call(bpy.ops.splat.prune, by="VISIBILITY", min_weight=0.004)}
        weights = np.empty(SPLATS, np.float32)
        obj.data.attributes[".splatwright_visibility"].data.foreach_get("value", weights)
        cams = []
        for frame in (1, 2, 3):
            scene.frame_set(frame)
            cams.append(np.array(cam.evaluated_get(bpy.context.evaluated_depsgraph_get()).matrix_world))
        scene.frame_set(1)
        res["frame"] = scene.frame_current
        res["report"] = json.loads(obj["splatwright_cleanup_report"])
        unedited = self.world_cloud(obj, edits=False)
        self.save(
            "visibility",
            positions=unedited.positions,
            rotations=unedited.rotations,
            log_scales=unedited.log_scales,
            opacity_logits=unedited.opacity_logits,
            sh=unedited.sh,
            kept=self.world_cloud(obj).positions,
            weights=weights,
            cameras=np.stack(cams),
            lens=cam.data.lens,
            sensor=[cam.data.sensor_width, cam.data.sensor_height],
            clip=[cam.data.clip_start, cam.data.clip_end],
        )
        return res

    def cleanup_refusals(self):
        """Bad input: a clear error, and nothing changed."""
        bpy = self.bpy
        obj = self.splat_object("Capture", self.random_cloud(50, seed=41))
        flat = self.mesh_object("Flat", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [])
        plain = self.mesh_object("Plain", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
        res = {}
        bpy.context.scene.camera = None
        camera = bpy.data.objects["Camera"]
        cases = {
            "camera_volume": ([obj, camera], camera, bpy.ops.splat.crop, {}),
            "faceless_volume": ([obj, flat], flat, bpy.ops.splat.crop, {}),
            "missing_volume": ([obj], obj, bpy.ops.splat.crop, {"volume": "Nowhere"}),
            "not_splats": ([plain], plain, bpy.ops.splat.grade, {"exposure": 1.0}),
            "nothing": ([], None, bpy.ops.splat.reduce_sh, {}),
            "no_camera": ([obj], obj, bpy.ops.splat.prune, {"by": "VISIBILITY"}),
            "sizes": ([obj], obj, bpy.ops.splat.prune, {"by": "SIZE", "min_size": 0.5, "max_size": 0.1}),
        }
        for name, (selected, active, op, kw) in cases.items():
            self.select(selected, active=active)
            before = self.inventory()
            res[name] = self.call(op, **kw)
            res[name]["unchanged"] = self.inventory() == before and "splatwright_cleanup" not in obj
        return res

    def rigged_tube(self):
        """(armature, proxy): a two-bone armature and the tube skinned to it (Armature modifier)."""
        arm = self.two_bone_armature("Rig", location=(0.2, 0.1, 0.0))
        verts, faces = tube_mesh()
        proxy = self.mesh_object("Proxy", verts, faces)
        proxy.location = arm.location
        weights = tube_weights(verts)
        for b, name in enumerate(("Lower", "Upper")):
            group = proxy.vertex_groups.new(name=name)
            for v in np.flatnonzero(weights[:, b] > 0):
                group.add([int(v)], float(weights[v, b]), "REPLACE")
        proxy.modifiers.new("Armature", "ARMATURE").object = arm
        proxy.parent = arm
        proxy.matrix_parent_inverse = arm.matrix_world.inverted()
        return arm, proxy

    def pose_rig(self, arm):
        for name, euler in POSE:
            pb = arm.pose.bones[name]
            pb.rotation_mode = "XYZ"
            pb.rotation_euler = euler
        self.bpy.context.view_layer.update()

    def capture_cloud(self, positions, seed=12):
        n = len(positions)
        rng = np.random.default_rng(seed)
        return self.module("core").SplatCloud(
            positions=positions,
            rotations=rng.normal(size=(n, 4)),
            log_scales=rng.uniform(-4, -3, (n, 3)),
            opacity_logits=rng.normal(1, 1, n),
            sh=rng.normal(0, 0.2, (n, 4, 3)),
        )

    def proxy_bind(self):
        bpy = self.bpy
        data = self.module("splat_addon.data")
        arm, proxy = self.rigged_tube()
        verts, faces = tube_mesh()
        weights = tube_weights(verts)
        rng = np.random.default_rng(12)
        n = NEAR + FAR
        core = self.module("core")
        positions = capture_positions() + np.array(arm.location)
        cloud = core.SplatCloud(
            positions=positions,
            rotations=rng.normal(size=(n, 4)),
            log_scales=rng.uniform(-4, -3, (n, 3)),
            opacity_logits=rng.normal(1, 1, n),
            sh=rng.normal(0, 0.2, (n, 4, 3)),
        )
        forms = ["MESH"] + (["NATIVE"] if data.native_supported() else [])
        objects = {form: self.splat_object(f"Capture{form}", cloud, form) for form in forms}
        bpy.context.view_layer.update()
        res = {}
        self.select([objects["MESH"], proxy], active=proxy)
        res["bind"] = self.call(bpy.ops.splat.bind_proxy, max_distance=0.1, far="STAY", min_weight=0.0)
        if "NATIVE" in objects:
            results = self.module("splat_addon.rig.proxy").bind_proxy(
                [objects["NATIVE"]], proxy, 0.1, "STAY", min_weight=0.0
            )
            res["native_far"] = results[0][1]
        res["modifiers"] = [m.type for m in objects["MESH"].modifiers]
        res["parent"] = objects["MESH"].parent.name if objects["MESH"].parent else None
        bound = {f"bound_{form}": self.weight_matrix(obj, ["Lower", "Upper"]) for form, obj in objects.items()}
        res["native"] = self.native_binding(objects.get("NATIVE"))
        self.pose_rig(arm)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        posed = {form: data.evaluated_cloud(obj, depsgraph).positions for form, obj in objects.items()}
        drawn = {f"drawn_{form}": self.drawn_world(obj) for form, obj in objects.items() if form == "NATIVE"}
        arm_world = np.array(arm.matrix_world)
        deform = np.stack(
            [
                arm_world
                @ np.array(arm.pose.bones[b].matrix)
                @ np.linalg.inv(np.array(arm.data.bones[b].matrix_local))
                @ np.linalg.inv(arm_world)
                for b in ("Lower", "Upper")
            ]
        )
        self.save(
            "proxy_bind",
            rest=positions,
            proxy_rest=verts + np.array(arm.location),
            triangles=faces,
            vertex_weights=weights,
            proxy_posed=self.evaluated_world(proxy, depsgraph),
            deform=deform,
            **bound,
            **drawn,
            **{f"posed_{f}": p for f, p in posed.items()},
        )
        return res

    def native_binding(self, obj):
        """How native splats hold their binding: (armature, preserve volume, has a strength mask)."""
        if obj is None:
            return None
        rigging = self.module("splat_addon.rig.armature")
        arm = obj.get(rigging.ARMATURE_PROPERTY)
        return [
            arm.name if arm is not None else None,
            bool(obj.get(rigging.PRESERVE_VOLUME_PROPERTY, False)),
            rigging.MASK_GROUP in obj.data.attributes,
        ]

    def drawn_world(self, obj):
        """The centres Blender draws of native splats (their position attribute), in world space."""
        co = np.empty(len(obj.data.points) * 3, np.float32)
        obj.data.attributes["position"].data.foreach_get("vector", co)
        world = np.array(obj.matrix_world)
        return co.reshape(-1, 3).astype(np.float64) @ world[:3, :3].T + world[:3, 3]

    def proxy_falloff(self):
        """Splats at spread distances bound with the falloff, by linear blend (proxy as it is) and by dual
        quaternions (the proxy's modifier preserving volume); Blender's own Armature modifier poses a
        plain mesh of the same points with the same groups and modifier, with the mask and without."""
        bpy = self.bpy
        data = self.module("splat_addon.data")
        rigging = self.module("splat_addon.rig.armature")
        arm, proxy = self.rigged_tube()
        positions = fading_positions() + np.array(arm.location)
        cloud = self.capture_cloud(positions, seed=14)
        forms = ["MESH"] + (["NATIVE"] if data.native_supported() else [])
        res, arrays = {}, {"rest": positions}
        for mode in ("lbs", "dqs"):
            proxy.modifiers["Armature"].use_deform_preserve_volume = mode == "dqs"
            objects = {form: self.splat_object(f"Fading{form}{mode}", cloud, form) for form in forms}
            bpy.context.view_layer.update()
            self.select([objects["MESH"], proxy], active=proxy)
            res[f"bind_{mode}"] = self.call(
                bpy.ops.splat.bind_proxy, falloff_start=FALLOFF_START, max_distance=MAX_DISTANCE, min_weight=0.0
            )
            if "NATIVE" in objects:
                self.select([objects["NATIVE"], proxy], active=proxy)
                self.call(
                    bpy.ops.splat.bind_proxy, falloff_start=FALLOFF_START, max_distance=MAX_DISTANCE, min_weight=0.0
                )
            mesh_obj = objects["MESH"]
            mod = mesh_obj.modifiers[0]
            res[f"modifier_{mode}"] = [
                mod.type,
                mod.vertex_group,
                mod.invert_vertex_group,
                mod.use_deform_preserve_volume,
            ]
            groups = self.group_matrix(mesh_obj, ["Lower", "Upper", rigging.MASK_GROUP])
            arrays[f"bound_{mode}"], arrays[f"strength_{mode}"] = groups[:, :2], groups[:, 2]
            if "NATIVE" in objects:
                native = self.weight_matrix(objects["NATIVE"], ["Lower", "Upper", rigging.MASK_GROUP])
                arrays[f"bound_NATIVE_{mode}"], arrays[f"strength_NATIVE_{mode}"] = native[:, :2], native[:, 2]
                res[f"native_{mode}"] = self.native_binding(objects["NATIVE"])
            plain = {masked: self.plain_twin(mesh_obj, groups, arm, masked) for masked in (True, False)}
            self.pose_rig(arm)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            for form, obj in objects.items():
                arrays[f"posed_{form}_{mode}"] = data.evaluated_cloud(obj, depsgraph).positions
                if form == "NATIVE":
                    arrays[f"drawn_{form}_{mode}"] = self.drawn_world(obj)
            for masked, obj in plain.items():
                arrays[f"blender_{'masked' if masked else 'full'}_{mode}"] = self.evaluated_world(obj, depsgraph)
            for pb in arm.pose.bones:  # back to rest for the next binding
                pb.rotation_euler = (0.0, 0.0, 0.0)
            bpy.context.view_layer.update()
        self.save("proxy_falloff", **arrays)
        return res

    def plain_twin(self, splats, groups, arm, masked):
        """A plain mesh of the splat centres of `splats` with its transform, its groups' weights (N, 3:
        Lower, Upper, mask) and a copy of its Armature modifier (mask left out unless `masked`)."""
        rigging = self.module("splat_addon.rig.armature")
        centres = self.module("splat_addon.data").object_cloud(splats).positions
        obj = self.mesh_object(f"Plain{splats.name}{masked}", centres, [])
        for j, name in enumerate(["Lower", "Upper", rigging.MASK_GROUP]):
            group = obj.vertex_groups.new(name=name)
            for i in np.flatnonzero(groups[:, j] > 0):
                group.add([int(i)], float(groups[i, j]), "REPLACE")
        source = splats.modifiers[0]
        mod = obj.modifiers.new("Armature", "ARMATURE")
        mod.object, mod.use_deform_preserve_volume = arm, source.use_deform_preserve_volume
        if masked:
            mod.vertex_group = source.vertex_group
        obj.parent, obj.matrix_parent_inverse = splats.parent, splats.matrix_parent_inverse.copy()
        obj.matrix_world = splats.matrix_world.copy()
        return obj

    def evaluated_world(self, obj, depsgraph):
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        co = np.empty(len(mesh.vertices) * 3)
        mesh.vertices.foreach_get("co", co)
        evaluated.to_mesh_clear()
        world = np.array(evaluated.matrix_world)
        return co.reshape(-1, 3) @ world[:3, :3].T + world[:3, 3]

    def inventory(self):
        bpy = self.bpy
        inv = super().inventory()
        inv["groups"] = {o.name: [g.name for g in o.vertex_groups] for o in bpy.data.objects}
        inv["modifiers"] = {o.name: [m.name for m in o.modifiers] for o in bpy.data.objects}
        inv["parents"] = {o.name: o.parent.name if o.parent else None for o in bpy.data.objects}
        inv["properties"] = {o.name: sorted(o.keys()) for o in bpy.data.objects}
        return inv

    def proxy_refusals(self):
        bpy = self.bpy
        obj = self.splat_object("Capture", self.random_cloud(50, seed=51))
        unrigged = self.mesh_object("Unrigged", *tube_mesh())
        faceless = self.mesh_object("Faceless", [(0, 0, 0), (1, 0, 0)], [])
        arm = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
        bpy.context.scene.collection.objects.link(arm)
        faceless.modifiers.new("Armature", "ARMATURE").object = arm
        rigged = self.mesh_object("Rigged", *tube_mesh())
        rigged.modifiers.new("Armature", "ARMATURE").object = arm  # an armature without bones
        other = self.splat_object("Other", self.random_cloud(20, seed=52))
        cases = {
            "camera": ([obj], bpy.data.objects["Camera"], {}),
            "splats_as_proxy": ([obj], other, {}),
            "faceless": ([obj], faceless, {}),
            "no_armature": ([obj], unrigged, {}),
            "no_bones": ([obj], rigged, {}),
            "no_splats": ([rigged], rigged, {}),
            "missing": ([obj], obj, {"proxy": "Nowhere"}),
        }
        res = {}
        for name, (selected, active, kw) in cases.items():
            self.select(selected + [active], active=active)
            before = self.inventory()
            res[name] = self.call(bpy.ops.splat.bind_proxy, **kw)
            res[name]["unchanged"] = self.inventory() == before
        return res


if __name__ == "__main__":
    worker_main(Worker)
