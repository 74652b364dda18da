"""The Blender side of tests/test_blender_scene_data.py (run in each Blender of the version matrix; see
workers/base.py): splat objects as users leave them (Edit Mode, modifiers, shape keys, instances) and
Blender 5.3's own splat point clouds, built here attribute by attribute as Blender's importer makes them
(on 4.5-5.2, which have no Gaussian-splat type, without it; before 5.2, which has no FLOAT4, with
radiance:base a colour, the layout guessed before 5.3)."""

import numpy as np

from workers.base import BlenderWorker, random_cloud_arrays, worker_main

N = 60  # splats of the test clouds
RENDER_SIZE = (40, 30)
EDIT_OFFSET = (0.3, -0.2, 0.1)  # vertex 0 moved in Edit Mode
ARRAY_OFFSET = (0.75, 0.0, 0.0)  # the Array modifier's constant offset
GN_ROTATION, GN_SCALE = (0.3, -0.2, 0.5), (1.0, 1.7, 0.6)  # a geometry-nodes Transform Geometry
SHAPE_OFFSET = (0.0, 0.0, 0.4)  # a shape key moves splat 1
INSTANCE = dict(location=(1.5, -0.5, 0.25), rotation_euler=(0.4, 0.1, -0.7), scale=(1.3, 1.3, 1.3))
DUPLICATE = dict(location=(-1.0, 0.5, 0.0), rotation_euler=(0.0, 0.6, 0.2), scale=(0.8, 1.0, 1.2))
APPLIED = dict(location=(0.5, 0.2, -0.3), rotation_euler=(0.7, -0.4, 1.1), scale=(1.5, 0.6, 1.0))
NATIVE_TRANSFORM = dict(location=(0.2, -0.4, 0.3), rotation_euler=(0.5, -0.3, 0.8), scale=(1.2, 0.9, 1.1))
BONES = {"Upper": ((0, 0, -1.5), (0, 0, 0)), "Lower": ((0, 0, 0), (0, 0, 1.5))}  # head, tail
POSE = {"Upper": (0.2, 0.0, 0.1), "Lower": (0.0, 0.7, -0.3)}  # Euler XYZ


def native_arrays(arrays, base_type="FLOAT4"):
    """A cloud's fields as Blender 5.3's importer stores them (see splat_addon/data/forms.py): linear scale,
    the sigmoid of the logit in radiance:base's fourth value, higher SH as radiance:sh_<j>; float32.
    `base_type`: radiance:base's type, FLOAT4 as 5.3 writes it, FLOAT_COLOR where a Blender lacks FLOAT4."""
    sh = np.asarray(arrays["sh"], np.float32)
    base = np.c_[sh[:, 0], 1.0 / (1.0 + np.exp(-np.asarray(arrays["opacity_logits"], np.float64)))]
    out = {
        "position": ("FLOAT_VECTOR", arrays["positions"]),
        "scale": ("FLOAT_VECTOR", np.exp(np.asarray(arrays["log_scales"], np.float64))),
        "rotation": ("QUATERNION", arrays["rotations"]),
        "radiance:base": (base_type, base),
    }
    for j in range(1, sh.shape[1]):
        out[f"radiance:sh_{j - 1}"] = ("FLOAT_VECTOR", sh[:, j])
    return out


FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh")
FOREACH = {
    "FLOAT": ("value", 1),
    "FLOAT_VECTOR": ("vector", 3),
    "QUATERNION": ("value", 4),
    "FLOAT_COLOR": ("color", 4),
    "FLOAT4": ("vector", 4),
}


class Worker(BlenderWorker):
    steps = (
        "install",
        "edit_mode",
        "modifiers",
        "instances",
        "nested_instances",
        "blender_apply",
        "native_forms",
        "native_rig",
    )
    keep_objects = ("Camera", "Light")
    orphan_kinds = ("meshes", "armatures", "materials", "collections", "pointclouds", "node_groups", "actions")

    # helpers -------------------------------------------------------------------------------------

    def splats(self, name, arrays, form="MESH", **transform):
        """A splat mesh (Splatwright's own form) holding `arrays`, with the display modifier; `form` None:
        the form this Blender makes new splat objects in (native on 5.3, which needs no display)."""
        ext = self.module("splat_addon")
        obj, _ = ext.data.new_splat_object(
            self.module("core").SplatCloud(**arrays), name, self.bpy.context.scene.collection, form=form
        )
        ext.data.display.add_display(obj)
        for key, value in transform.items():
            setattr(obj, key, value)
        return obj

    def reimported(self, name, path):
        """A splat mesh holding the splats of a file written earlier in the step."""
        cloud = self.module("io").read_splats(path)
        return self.splats(name, {f: getattr(cloud, f) for f in FIELDS})

    def native_object(self, name, arrays, **transform):
        """A point cloud with Blender 5.3's Gaussian-splat attributes, made without the extension: a mesh
        of loose vertices carrying them, converted by Blender (or a resized point cloud on 5.2+). As 5.3's
        importers make them where this Blender can: radiance:base FLOAT4 (5.2+, a colour before) and the
        point cloud's type GAUSSIAN_SPLAT (5.3+)."""
        bpy = self.bpy
        n = len(arrays["positions"])
        if hasattr(bpy.types.PointCloud, "resize"):
            geometry = bpy.data.pointclouds.new(name)
            geometry.resize(n)
            obj = bpy.data.objects.new(name, geometry)
            bpy.context.scene.collection.objects.link(obj)
        else:
            mesh = bpy.data.meshes.new(name)
            mesh.vertices.add(n)
            obj = bpy.data.objects.new(name, mesh)
            bpy.context.scene.collection.objects.link(obj)
            self.select([obj])
            bpy.ops.object.convert(target="POINTCLOUD")
            obj = bpy.context.view_layer.objects.active
            geometry = obj.data
        types = bpy.types.Attribute.bl_rna.properties["data_type"].enum_items.keys()
        base_type = "FLOAT4" if "FLOAT4" in types else "FLOAT_COLOR"
        for attr_name, (kind, values) in native_arrays(arrays, base_type).items():
            attr = geometry.attributes.get(attr_name) or geometry.attributes.new(attr_name, kind, "POINT")
            assert attr.data_type == kind, (attr_name, attr.data_type)
            attr.data.foreach_set(FOREACH[kind][0], np.ascontiguousarray(values, np.float32).ravel())
        if "GAUSSIAN_SPLAT" in getattr(geometry.bl_rna.properties.get("type"), "enum_items", {}).keys():
            geometry.type = "GAUSSIAN_SPLAT"
        for key, value in transform.items():
            setattr(obj, key, value)
        return obj

    def export(self, name, objects=None, file_axes=False):
        """Export (world space = file space) the visible splats, or `objects` selected. `file_axes`: for
        native clouds made without Splatwright, which stand in their file's own axes as Blender's PLY
        importer leaves them (splat_addon/data/forms.py, landed_raw): world space is written with the default
        axes then."""
        if objects is not None:
            self.select(objects)
        axes = {} if file_axes else dict(axis_forward="Y", axis_up="Z")
        return self.call(
            self.bpy.ops.splat.export_file, filepath=str(self.out / name), selected_only=objects is not None, **axes
        )

    def render(self, name, shown=None):
        """F12 through the engine to a 32-bit EXR (the tests read it); only `shown` splat objects when given."""
        bpy = self.bpy
        scene = bpy.context.scene
        hidden = []
        if shown is not None:
            hidden = [
                o for o in scene.objects if o not in shown and not o.hide_render and o.type in ("MESH", "POINTCLOUD")
            ]
            for obj in hidden:
                obj.hide_render = True
        scene.render.engine = "SPLATWRIGHT"
        scene.splatwright_mesh_engine = "NONE"  # splats alone
        scene.render.resolution_x, scene.render.resolution_y = RENDER_SIZE
        scene.render.resolution_percentage = 100
        scene.render.film_transparent = False
        scene.view_settings.view_transform = "Standard"
        scene.world = None
        self.image_format(scene.render.image_settings, "OPEN_EXR", color_depth="32")
        cam = scene.camera
        cam.location, cam.rotation_euler = (0.0, -7.0, 0.5), (np.pi / 2, 0.0, 0.0)
        scene.render.filepath = str(self.out / f"{name}.exr")
        done = self.call(bpy.ops.render.render, write_still=True)
        for obj in hidden:
            obj.hide_render = False
        return done

    def matrix(self, obj):
        self.bpy.context.view_layer.update()
        return np.array(obj.matrix_world, dtype=np.float64).tolist()

    def apply_transform(self, obj):
        self.select([obj])
        return self.call(self.bpy.ops.splat.apply_transform)

    def join(self, target, other):
        self.select([target, other], active=target)
        return self.call(self.bpy.ops.splat.join)

    def rig(self):
        """An armature of two bones, posed at frame 1."""
        bpy = self.bpy
        arm = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
        bpy.context.scene.collection.objects.link(arm)
        arm.location = (0.1, 0.0, -0.2)
        self.select([arm])
        bpy.ops.object.mode_set(mode="EDIT")
        for name, (head, tail) in BONES.items():
            bone = arm.data.edit_bones.new(name)
            bone.head, bone.tail = head, tail
        arm.data.edit_bones["Lower"].parent = arm.data.edit_bones["Upper"]
        bpy.ops.object.mode_set(mode="OBJECT")
        for name, euler in POSE.items():
            pose_bone = arm.pose.bones[name]
            pose_bone.rotation_mode = "XYZ"
            pose_bone.rotation_euler = euler
        return arm

    # steps ---------------------------------------------------------------------------------------

    def install(self):
        self.install_extension()
        return {"native_supported": self.module("splat_addon.data").native_supported()}

    def edit_mode(self):
        """A splat mesh left in Edit Mode after a vertex moved there: export, animation export and F12."""
        import bmesh
        from mathutils import Vector

        bpy = self.bpy
        obj = self.splats("edited", random_cloud_arrays(N, 2, seed=1))
        self.select([obj])
        bpy.ops.object.mode_set(mode="EDIT")
        edit = bmesh.from_edit_mesh(obj.data)
        edit.verts.ensure_lookup_table()
        edit.verts[0].co += Vector(EDIT_OFFSET)
        bmesh.update_edit_mesh(obj.data)
        res = {
            "export": self.export("edit.ply"),
            "animation": self.call(
                bpy.ops.splat.export_animation,
                filepath=str(self.out / "edit_####.ply"),
                use_scene_range=False,
                frame_start=1,
                frame_end=2,
                axis_forward="Y",
                axis_up="Z",
            ),
            "render": self.render("edit_render"),
            "mode": obj.mode,
        }
        bpy.ops.object.mode_set(mode="OBJECT")
        reference = self.reimported("reference", self.out / "edit.ply")
        res["reference_render"] = self.render("edit_reference", [reference])
        return res

    def modifiers(self):
        """Array, Mirror and a shape key, each on its own splat mesh after the display modifier, and a
        geometry-nodes Transform on splats of the form this Blender makes (native on 5.3)."""
        arrays = random_cloud_arrays(N, 2, seed=2)
        array = self.splats("array", arrays)
        mod = array.modifiers.new("Array", "ARRAY")
        mod.count, mod.use_relative_offset, mod.use_constant_offset = 2, False, True
        mod.constant_offset_displace = ARRAY_OFFSET
        mirror = self.splats("mirror", arrays)
        mod = mirror.modifiers.new("Mirror", "MIRROR")
        mod.use_axis = (True, False, False)
        mod.use_mirror_merge = False
        transform = self.splats("transform", arrays, form=None)
        transform.modifiers.new("Turn", "NODES").node_group = self.transform_group()
        shaped = self.splats("shaped", arrays)
        shaped.shape_key_add(name="Basis")
        key = shaped.shape_key_add(name="Lift")
        key.data[1].co = [a + b for a, b in zip(key.data[1].co, SHAPE_OFFSET)]
        key.value = 1.0
        res = {obj.name: self.export(f"mod_{obj.name}.ply", [obj]) for obj in (array, mirror, transform, shaped)}
        res["transform_form"] = self.module("splat_addon.data").splat_form(transform)
        return res

    def transform_group(self):
        bpy = self.bpy
        group = bpy.data.node_groups.new("Turn", "GeometryNodeTree")
        group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        gin, gout = group.nodes.new("NodeGroupInput"), group.nodes.new("NodeGroupOutput")
        node = group.nodes.new("GeometryNodeTransform")
        node.inputs["Rotation"].default_value = GN_ROTATION
        node.inputs["Scale"].default_value = GN_SCALE
        group.links.new(gin.outputs[0], node.inputs["Geometry"])
        group.links.new(node.outputs["Geometry"], gout.inputs[0])
        return group

    def instances(self):
        """A splat object (of the form this Blender makes) in a collection left out of the view layer,
        drawn by an Empty instancing that collection, and a linked duplicate of it: export and F12."""
        bpy = self.bpy
        scene = bpy.context.scene
        collection = bpy.data.collections.new("Splat Source")
        scene.collection.children.link(collection)
        source = self.splats("source", random_cloud_arrays(N, 3, seed=3), form=None)
        scene.collection.objects.unlink(source)
        collection.objects.link(source)
        bpy.context.view_layer.layer_collection.children[collection.name].exclude = True
        empty = bpy.data.objects.new("instancer", None)
        empty.instance_type, empty.instance_collection = "COLLECTION", collection
        for key, value in INSTANCE.items():
            setattr(empty, key, value)
        scene.collection.objects.link(empty)
        duplicate = source.copy()  # shares the mesh: a linked duplicate
        for key, value in DUPLICATE.items():
            setattr(duplicate, key, value)
        scene.collection.objects.link(duplicate)
        res = {
            "visible": self.export("inst_visible.ply"),
            "selected_empty": self.export("inst_empty.ply", [empty]),
            "matrices": {"instance": self.matrix(empty), "duplicate": self.matrix(duplicate)},
            "render": self.render("inst_render"),
            "form": self.module("splat_addon.data").splat_form(source),
        }
        reference = self.reimported("reference", self.out / "inst_visible.ply")
        res["reference_render"] = self.render("inst_reference", [reference])
        return res

    def nested_instances(self):
        """A splat object drawn through two levels of collection instances: an Empty in a collection
        left out of the view layer instances the splats' collection (also left out), and an Empty
        in the scene instances that collection. Export of the visible splats and of the outer Empty
        selected, the two Empties' matrices, and F12 of the splats so drawn against the exported splats
        reimported as an object."""
        bpy = self.bpy
        scene = bpy.context.scene

        def left_out(name):
            collection = bpy.data.collections.new(name)
            scene.collection.children.link(collection)
            bpy.context.view_layer.layer_collection.children[collection.name].exclude = True
            return collection

        def instancer(name, collection, transform, home):
            empty = bpy.data.objects.new(name, None)
            empty.instance_type, empty.instance_collection = "COLLECTION", collection
            for key, value in transform.items():
                setattr(empty, key, value)
            home.objects.link(empty)
            return empty

        sources, middle = left_out("Nested Source"), left_out("Nested Middle")
        source = self.splats("nested source", random_cloud_arrays(N, 3, seed=4), form=None)
        scene.collection.objects.unlink(source)
        sources.objects.link(source)
        inner = instancer("inner instancer", sources, INSTANCE, middle)
        outer = instancer("outer instancer", middle, DUPLICATE, scene.collection)
        res = {
            "visible": self.export("nested_visible.ply"),
            "selected_outer": self.export("nested_outer.ply", [outer]),
            "matrices": {"inner": self.matrix(inner), "outer": self.matrix(outer)},
            "render": self.render("nested_render"),
        }
        # the splats as exported (the outer scale is not uniform: under the inner rotation it shears,
        # which an object's matrix cannot hold but the splats' covariances can)
        reference = self.reimported("reference", self.out / "nested_visible.ply")
        res["reference_render"] = self.render("nested_reference", [reference])
        return res

    def blender_apply(self):
        """Blender's own Object > Apply on splat objects: rotation and scale, then all transforms, on a
        splat mesh and (where this Blender can make one) on native splats."""
        bpy = self.bpy
        res = {}
        objects = [self.splats("mesh_form", random_cloud_arrays(N, 2, seed=8), **APPLIED)]
        if self.module("splat_addon.data").native_supported():
            objects.append(self.native_object("native_form", random_cloud_arrays(N, 2, seed=8), **APPLIED))
        for obj in objects:
            res[f"{obj.name} before"] = self.export(f"apply_{obj.name}_before.ply", [obj])
            bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
            res[f"{obj.name} rotation_scale"] = self.export(f"apply_{obj.name}_rs.ply", [obj])
            res[f"{obj.name} basis"] = np.array(obj.matrix_basis).tolist()
            bpy.ops.object.transform_apply(location=True, rotation=True, scale=True)
            res[f"{obj.name} all"] = self.export(f"apply_{obj.name}_all.ply", [obj])
            res[f"{obj.name} identity"] = np.allclose(np.array(obj.matrix_basis), np.eye(4))
        return res

    def native_forms(self):
        """The same random SH-3 cloud as a splat mesh and as Blender's own splat point cloud, both under
        one object transform: export, Apply Splat Transform, Join, collisions, F12 and form conversion."""
        if not self.module("splat_addon.data").native_supported():
            return {"skipped": self.bpy.app.version_string}
        ext = self.module("splat_addon")
        arrays, second = random_cloud_arrays(N, 3, seed=4), random_cloud_arrays(N // 2, 3, seed=5)
        ours = self.splats("ours", arrays, **NATIVE_TRANSFORM)
        theirs = self.native_object("theirs", arrays, **NATIVE_TRANSFORM)
        res = {
            "forms": [ext.data.splat_form(ours), ext.data.splat_form(theirs)],
            "layout": [theirs.data.attributes["radiance:base"].data_type, getattr(theirs.data, "type", None)],
            "landed_raw": [ext.data.landed_raw(ours), ext.data.landed_raw(theirs)],
            "export": [self.export("nat_ours.ply", [ours]), self.export("nat_theirs.ply", [theirs], True)],
            "render": [self.render("nat_ours", [ours]), self.render("nat_theirs", [theirs])],
        }
        env = self.splats("env", random_cloud_arrays(N, 0, seed=6, spread=0.8))
        reports = [ext.rig.collide.check_collisions(self.bpy.context, obj, env, [1]) for obj in (ours, theirs)]
        res["contacts"] = [r.as_dict()["frames"][0] for r in reports]
        res["contact_values"] = [np.asarray(r.contact_a).tolist() for r in reports]
        res["apply"] = [self.apply_transform(ours), self.apply_transform(theirs)]
        res["applied_matrices"] = [self.matrix(ours), self.matrix(theirs)]
        for obj in (ours, theirs):
            self.export(f"nat_{obj.name}_applied.ply", [obj], obj is theirs)
        res["join"] = [
            self.join(ours, self.splats("ours_more", second, **DUPLICATE)),
            self.join(theirs, self.native_object("theirs_more", second, **DUPLICATE)),
        ]
        res["joined_forms"] = [ext.data.splat_form(ours), ext.data.splat_form(theirs)]
        res["joined_raw"] = [ext.data.landed_raw(ours), ext.data.landed_raw(theirs)]
        for obj in (ours, theirs):
            self.export(f"nat_{obj.name}_joined.ply", [obj], obj is theirs)
        self.select([ours])
        res["to_native"] = self.call(self.bpy.ops.splat.convert_form, form="NATIVE")
        converted = self.bpy.data.objects["ours"]
        res["converted_form"] = ext.data.splat_form(converted)
        self.export("nat_converted.ply", [converted])
        self.select([converted])
        res["to_mesh"] = self.call(self.bpy.ops.splat.convert_form, form="MESH")
        res["back_form"] = ext.data.splat_form(self.bpy.data.objects["ours"])
        self.export("nat_back.ply", [self.bpy.data.objects["ours"]])
        return res

    def native_rig(self):
        """Both forms bound to one two-bone armature (weights from the bones) and posed: export and F12."""
        if not self.module("splat_addon.data").native_supported():
            return {"skipped": self.bpy.app.version_string}
        bpy = self.bpy
        arrays = random_cloud_arrays(N, 3, seed=7)
        arrays["positions"] = arrays["positions"] * [0.4, 0.4, 1.2]  # along the bones
        ours = self.splats("ours", arrays, **NATIVE_TRANSFORM)
        theirs = self.native_object("theirs", arrays, **NATIVE_TRANSFORM)
        arm = self.rig()
        self.select([ours, theirs], active=arm)
        res = {"bind": self.call(bpy.ops.splat.bind_armature, armature=arm.name, use_source_weights=False)}
        bpy.context.view_layer.update()
        res["export"] = [self.export("rig_ours.ply", [ours]), self.export("rig_theirs.ply", [theirs], True)]
        res["render"] = [self.render("rig_ours", [ours]), self.render("rig_theirs", [theirs])]
        res["weights"] = sorted(a.name for a in theirs.data.attributes if a.name.startswith("splat_weight:"))
        # what Blender itself draws: the native attributes, written for the frame when it changes
        bpy.context.scene.frame_set(2)
        bpy.context.scene.frame_set(1)
        drawn = {}
        for name, attr in theirs.data.attributes.items():
            if not name.startswith(".") and attr.domain == "POINT" and attr.data_type in FOREACH:
                prop, width = FOREACH[attr.data_type]
                values = np.empty(len(attr.data) * width, np.float32)
                attr.data.foreach_get(prop, values)
                drawn[name] = values.reshape(-1, width)
        exact = self.module("splat_addon.data").evaluated_cloud(
            theirs, bpy.context.evaluated_depsgraph_get(), np.eye(4)
        )
        self.save(
            "rig_drawn",
            **{k.replace(":", "__"): v for k, v in drawn.items()},
            exact_positions=exact.positions,
            exact_rotations=exact.unit_rotations,
            exact_scales=exact.scales,
            exact_opacities=exact.opacities,
            exact_sh=exact.sh,
        )
        return res


if __name__ == "__main__":
    worker_main(Worker)
