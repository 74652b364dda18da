"""Worker: Blender 5.3's own splat point clouds, as its PLY and SPZ importers make them, through
Splatwright's export, Apply Transform, Join and render engine (see tests/test_blender_native.py)."""

import numpy as np

from workers.base import BlenderWorker, worker_main

# Object transforms given to a cloud Blender imported: a turn with a uniform scale, and a shear-free
# stretch along a turned axis (no rotation times uniform scale: covariances re-diagonalised).
MOVES = {
    "turned": {"location": (0.5, -2.0, 1.25), "rotation_euler": (0.3, -1.1, 2.0), "scale": (1.5, 1.5, 1.5)},
    "stretched": {"location": (0.0, 1.0, 0.0), "rotation_euler": (0.0, 0.0, 0.7), "scale": (1.0, 2.0, 0.5)},
}
FORMATS = (".ply", ".spz", ".usd", ".usda", ".splat", ".glb")
CAMERA = {"location": (0.0, -6.0, 0.0), "rotation_euler": (np.pi / 2, 0.0, 0.0), "lens": 40.0}


class NativeWorker(BlenderWorker):
    steps = (
        "blender_ply",
        "blender_ply_moved",
        "blender_spz",
        "ours_native",
        "join",
        "render",
        "geometry_nodes",
        "tools",
        "bind",
        "collisions",
    )

    def __init__(self, work, zip_path):
        super().__init__(work, zip_path)
        self.install_extension()

    def blender_import(self, name, importer="ply"):
        """The object Blender's own importer makes of work/`name`."""
        bpy = self.bpy
        before = set(bpy.data.objects)
        getattr(bpy.ops.wm, f"{importer}_import")(filepath=str(self.work / name))
        (obj,) = set(bpy.data.objects) - before
        return obj

    def attributes(self, obj):
        """What Blender holds: the object's type and its attributes' types, and the rotations as stored."""
        pointcloud = obj.data
        rotation = np.empty(len(pointcloud.points) * 4, np.float32)
        pointcloud.attributes["rotation"].data.foreach_get("value", rotation)
        return {
            "type": obj.type,
            "data_type": getattr(pointcloud, "type", None),
            "attributes": {a.name: a.data_type for a in pointcloud.attributes},
            "matrix_world": np.array(obj.matrix_world).tolist(),
        }, rotation.reshape(-1, 4)

    def export(self, name, **kw):
        return self.call(self.bpy.ops.splat.export_file, filepath=str(self.out / name), **kw)

    def blender_ply(self):
        """Degree 3 and 4 PLYs opened by Blender's importer, left where they landed, exported with the
        default settings to every format."""
        res = {}
        for degree in (3, 4):
            obj = self.blender_import(f"src{degree}.ply")
            res[degree], rotation = self.attributes(obj)
            self.save(f"blender_rotation{degree}", rotation=rotation)
            self.select([obj])
            res[degree]["exports"] = {ext: self.export(f"blender{degree}{ext}") for ext in FORMATS}
            self.bpy.data.objects.remove(obj)
        return res

    def blender_ply_moved(self):
        """The degree-3 PLY given each object transform, exported; then Apply Splat Transform, exported again."""
        res = {}
        for name, move in MOVES.items():
            obj = self.blender_import("src3.ply")
            for key, value in move.items():
                setattr(obj, key, value)
            self.bpy.context.view_layer.update()
            self.select([obj])
            res[name] = {
                "matrix_world": np.array(obj.matrix_world).tolist(),
                "export": self.export(f"{name}.ply"),
                "apply": self.call(self.bpy.ops.splat.apply_transform),
            }
            res[name]["applied_matrix"] = np.array(obj.matrix_world).tolist()
            res[name]["applied_export"] = self.export(f"{name}_applied.ply")
            self.bpy.data.objects.remove(obj)
        return res

    def world_positions(self, obj):
        position = np.empty(len(obj.data.points) * 3, np.float32)
        obj.data.attributes["position"].data.foreach_get("vector", position)
        matrix = np.array(obj.matrix_world, dtype=np.float64)
        return position.reshape(-1, 3).astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]

    def blender_spz(self):
        """An SPZ opened by Blender's importer and by Splatwright's: where each stands in the world, and
        Blender's exported by Splatwright."""
        bpy = self.bpy
        theirs = self.blender_import("src.spz", importer="spz")
        self.select([theirs])
        res = {
            "blender": self.attributes(theirs)[0],
            "export_spz": self.export("spz_blender.spz"),
            "export_ply": self.export("spz_blender.ply"),
        }
        ours = self.call(bpy.ops.splat.import_file, filepath=str(self.work / "src.spz"))
        self.save(
            "spz_world",
            blender=self.world_positions(theirs),
            ours=self.world_positions(bpy.context.view_layer.objects.active),
        )
        return {**res, "import": ours}

    def ours_native(self):
        """Splatwright's import on this Blender: Blender's own splat point cloud."""
        bpy = self.bpy
        res = self.call(bpy.ops.splat.import_file, filepath=str(self.work / "src3.ply"))
        obj = bpy.context.view_layer.objects.active
        return {
            **res,
            "type": obj.type,
            "data_type": getattr(obj.data, "type", None),
            "attributes": {a.name: a.data_type for a in obj.data.attributes},
        }

    def join(self):
        """Two Blender-imported PLYs joined by Join Splats, exported with the default settings."""
        first, second = self.blender_import("src3.ply"), self.blender_import("other.ply")
        self.select([first, second], active=first)
        res = {"join": self.call(self.bpy.ops.splat.join)}
        self.select([first])
        res["export"] = self.export("joined.ply")
        return res

    def render(self):
        """F12 with the SPLATWRIGHT engine on a cloud Blender imported, and on the same file imported by
        Splatwright with a matrix that places it as Blender's importer does (the identity)."""
        bpy = self.bpy
        scene = self.setup_render()
        res = {}
        theirs = self.blender_import("scene.ply")
        scene.render.filepath = str(self.out / "render_blender.exr")
        res["blender"] = self.call(bpy.ops.render.render, write_still=True)
        bpy.data.objects.remove(theirs)
        res["ours"] = self.call(
            bpy.ops.splat.import_file, filepath=str(self.work / "scene.ply"), axis_forward="Y", axis_up="Z"
        )
        scene.render.filepath = str(self.out / "render_ours.exr")
        res["ours_render"] = self.call(bpy.ops.render.render, write_still=True)
        return res

    def setup_render(self):
        """The SPLATWRIGHT engine, splats alone, a fixed camera, float EXR output."""
        scene = self.bpy.context.scene
        scene.render.engine = "SPLATWRIGHT"
        scene.splatwright_mesh_engine = "NONE"
        scene.view_settings.view_transform = "Standard"
        scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 96, 72, 100
        for key, value in CAMERA.items():
            setattr(scene.camera.data if key == "lens" else scene.camera, key, value)
        self.image_format(scene.render.image_settings, "OPEN_EXR", color_depth="32")
        return scene

    def geometry_nodes(self):
        """Splats made by geometry nodes: a mesh carrying the native attributes, turned into points and
        given Blender's Gaussian-splat type by its modifier. Exported with the default settings, and
        rendered beside the same splats imported from that export."""
        bpy = self.bpy
        arrays = np.load(self.work / "generated.npz")
        mesh = bpy.data.meshes.new("generated")
        mesh.vertices.add(len(arrays["position"]))
        mesh.vertices.foreach_set("co", arrays["position"].ravel())
        kinds = {
            "scale": ("FLOAT_VECTOR", "vector"),
            "rotation": ("QUATERNION", "value"),
            "radiance:base": ("FLOAT4", "vector"),
        }
        kinds.update({f"radiance:sh_{j}": ("FLOAT_VECTOR", "vector") for j in range(3)})
        for name, (kind, prop) in kinds.items():
            mesh.attributes.new(name, kind, "POINT").data.foreach_set(prop, arrays[name].ravel())
        obj = bpy.data.objects.new("generated", mesh)
        bpy.context.scene.collection.objects.link(obj)
        tree = bpy.data.node_groups.new("Make Splats", "GeometryNodeTree")
        tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        given, made = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
        points, typed = tree.nodes.new("GeometryNodeMeshToPoints"), tree.nodes.new("GeometryNodePointsSetType")
        typed.inputs["Type"].default_value = "3D Gaussian Splat"
        tree.links.new(given.outputs[0], points.inputs["Mesh"])
        tree.links.new(points.outputs[0], typed.inputs["Points"])
        tree.links.new(typed.outputs[0], made.inputs[0])
        obj.modifiers.new("Make Splats", "NODES").node_group = tree
        self.select([obj])
        res = {"export": self.export("generated.ply")}
        scene = self.setup_render()
        scene.render.filepath = str(self.out / "render_generated.exr")
        res["render"] = self.call(bpy.ops.render.render, write_still=True)
        obj.hide_render = True
        res["import"] = self.call(bpy.ops.splat.import_file, filepath=str(self.out / "generated.ply"))
        scene.render.filepath = str(self.out / "render_generated_imported.exr")
        res["imported_render"] = self.call(bpy.ops.render.render, write_still=True)
        return res

    def tools(self):
        """Convert Splat Form both ways, Prune and the `blender -b` command's export on a cloud Blender's
        PLY importer made: each export must still give the file's own axes."""
        bpy = self.bpy
        obj = self.blender_import("src3.ply")
        self.select([obj])
        res = {"to_mesh": self.call(bpy.ops.splat.convert_form, form="MESH")}
        res["mesh_type"] = bpy.context.view_layer.objects.active.type
        res["mesh_export"] = self.export("converted.ply")
        res["to_native"] = self.call(bpy.ops.splat.convert_form, form="NATIVE")
        res["native_export"] = self.export("reconverted.ply")
        res["prune"] = self.call(bpy.ops.splat.prune, by="OPACITY", threshold=0.5, measure=False)
        res["pruned_export"] = self.export("pruned.ply")
        self.bpy.data.objects.remove(bpy.context.view_layer.objects.active)
        self.blender_import("src3.ply")
        command = self.module("splat_addon.command")
        res["command"] = command.execute(["export", str(self.out / "command.ply"), "--frames", "1"])
        return res

    def bind(self):
        """Bind to Armature on a cloud Blender's PLY importer made, posed: the bind's weights and the
        bones' deform matrices are saved for the linear-blend reference."""
        bpy = self.bpy
        obj = self.blender_import("src3.ply")
        arm = self.two_bone_armature("Rig")
        self.select([obj], active=arm)
        res = {"bind": self.call(bpy.ops.splat.bind_armature, max_influences=2)}
        res["rest_export"] = self.export("bound_rest.ply")
        bone = arm.pose.bones["Upper"]
        bone.rotation_mode = "XYZ"
        bone.rotation_euler = (0.6, 0.0, 0.2)
        bpy.context.view_layer.update()
        self.select([obj])
        res["posed_export"] = self.export("bound_posed.ply")
        names = ["Lower", "Upper"]
        weights = np.zeros((len(obj.data.points), 2), np.float32)
        for j, name in enumerate(names):
            obj.data.attributes[f"splat_weight:{name}"].data.foreach_get("value", weights[:, j])
        bones = [arm.pose.bones[n] for n in names]
        deform = np.stack(
            [
                np.array(arm.matrix_world @ b.matrix @ b.bone.matrix_local.inverted() @ arm.matrix_world.inverted())
                for b in bones
            ]
        )
        self.save("bind", weights=weights, deform=deform)
        return res

    def collisions(self):
        """Two clouds Blender imported, overlapping, then set 100 apart: the exact contact test on both."""
        bpy = self.bpy
        collide = self.module("splat_addon.rig.collide")
        a, b = self.blender_import("other.ply"), self.blender_import("collide.ply")
        res = {"near": collide.check_collisions(bpy.context, a, b, [1], write_attribute=False).as_dict()}
        res["op"] = self.call(
            bpy.ops.splat.check_collisions,
            object_a=a.name,
            object_b=b.name,
            use_scene_range=False,
            frame_start=1,
            frame_end=1,
        )
        b.location = (100.0, 0.0, 0.0)
        bpy.context.view_layer.update()
        res["far"] = collide.check_collisions(bpy.context, a, b, [1], write_attribute=False).as_dict()
        res["defaults"] = {"sigma": collide.DEFAULT_SIGMA, "min_opacity": collide.DEFAULT_MIN_OPACITY}
        return res


if __name__ == "__main__":
    worker_main(NativeWorker)
