"""The Blender side of tests/test_blender_material.py: the material extras (albedo, normals,
roughness, metallic) on splat objects of both forms, read back, exported through a stretched world
matrix, and made by Mesh to Splats' "Material for Relighting" from Principled BSDF materials (run in
each Blender of the version matrix; see workers/base.py)."""

import numpy as np

from workers.base import BlenderWorker, worker_main

COUNT = 300
# A moved, turned, unevenly scaled and mirrored object: its normals go through the inverse transpose.
MATRIX = dict(location=(0.3, -0.2, 0.5), rotation_euler=(0.4, -0.3, 0.8), scale=(1.0, 1.7, -0.6))
# The converted quad's two materials: Principled BSDF values (unlinked), and one whose Roughness
# is linked to a node (read as the default) and whose Metallic is not.
FIRST = dict(base=(0.2, 0.35, 0.6), roughness=0.25, metallic=0.9)
SECOND = dict(base=(0.7, 0.1, 0.05), metallic=0.15)


def material_arrays(seed=3):
    """Albedo (N,3), unit normals (N,3), roughness and metallic (N,) of random values."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(COUNT, 3))
    return dict(
        albedo=rng.uniform(0, 1, (COUNT, 3)),
        normals=normals / np.linalg.norm(normals, axis=1, keepdims=True),
        roughness=rng.uniform(0, 1, COUNT),
        metallic=rng.uniform(0, 1, COUNT),
    )


class Worker(BlenderWorker):
    steps = ("install", "forms_mesh", "forms_native", "convert", "smooth", "join_mesh", "join_native")
    keep_objects = ()
    orphan_kinds = ("meshes", "materials", "pointclouds")

    def install(self):
        self.install_extension()
        return {}

    def material_extras(self, cloud):
        material = self.module("core.material")
        return dict(
            albedo=material.albedo(cloud),
            normals=material.normals(cloud),
            roughness=material.roughness(cloud),
            metallic=material.metallic(cloud),
        )

    def forms(self, form):
        """A cloud with a material as an object of `form`: its own cloud read back, and the cloud
        the scene evaluates through the object's stretched, mirrored world matrix."""
        data = self.module("splat_addon.data")
        if form == "NATIVE" and not data.native_supported():
            return {"skipped": True}
        material = self.module("core.material")
        arrays = material_arrays()
        cloud = material.with_material(self.random_cloud(COUNT, 1, seed=4), **arrays)
        obj, skipped = data.new_splat_object(cloud, "Lit", self.bpy.context.scene.collection, form=form)
        for key, value in MATRIX.items():
            setattr(obj, key, value)
        self.bpy.context.view_layer.update()
        own = data.object_cloud(obj)
        world = data.evaluated_cloud(obj, self.bpy.context.evaluated_depsgraph_get())
        self.save(
            f"forms_{form}",
            matrix=np.array(obj.matrix_world, np.float64),
            **{f"own_{k}": v for k, v in self.material_extras(own).items()},
            **{f"world_{k}": v for k, v in self.material_extras(world).items()},
            **{f"source_{k}": v for k, v in arrays.items()},
        )
        return {"skipped_extras": list(skipped), "type": obj.type, "extras": sorted(own.extras)}

    def forms_mesh(self):
        return self.forms("MESH")

    def forms_native(self):
        return self.forms("NATIVE")

    def principled(self, name, values, link_roughness=False):
        bpy = self.bpy
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*values["base"], 1.0)
        bsdf.inputs["Metallic"].default_value = values["metallic"]
        if link_roughness:
            bsdf.inputs["Roughness"].default_value = 0.05  # not what is read: a node feeds it
            value = mat.node_tree.nodes.new("ShaderNodeValue")
            value.outputs[0].default_value = 0.9
            mat.node_tree.links.new(value.outputs[0], bsdf.inputs["Roughness"])
        else:
            bsdf.inputs["Roughness"].default_value = values["roughness"]
        return mat

    def convert(self):
        """Mesh to Splats with Material for Relighting on a two-material quad (two triangles, one
        material each), the object moved and turned: the splats stay in object space."""
        bpy = self.bpy
        mesh = bpy.data.meshes.new("Quad")
        mesh.from_pydata([(0, 0, 0), (1, 0, 0), (1, 1, 0.5), (0, 1, 0)], [], [(0, 1, 2), (0, 2, 3)])
        mesh.materials.append(self.principled("First", FIRST))
        mesh.materials.append(self.principled("Second", SECOND, link_roughness=True))
        mesh.polygons[1].material_index = 1
        obj = bpy.data.objects.new("Quad", mesh)
        bpy.context.scene.collection.objects.link(obj)
        obj.location, obj.rotation_euler = (1.0, 2.0, 0.0), (0.3, 0.0, 0.5)
        bpy.context.view_layer.update()  # the view layer learns of the new object (selectable)
        self.select([obj])
        res = self.call(bpy.ops.splat.from_mesh, mode="BUDGET", max_splats=800, calibrate=False, use_material=True)
        if res["result"] != ["FINISHED"]:
            return res
        made = bpy.data.objects["Quad_splats"]
        cloud = self.module("splat_addon.data").object_cloud(made)
        corners = np.array([v.co for v in mesh.vertices], np.float64)
        self.save(
            "convert",
            source_triangle=cloud.extras["source_triangle"],
            polygon_vertices=np.array([list(p.vertices) for p in mesh.polygons]),
            corners=corners,
            **self.material_extras(cloud),
        )
        self.select([obj])
        plain = self.call(bpy.ops.splat.from_mesh, mode="BUDGET", max_splats=200, calibrate=False)
        plain_extras = sorted(
            self.module("splat_addon.data").object_cloud(bpy.context.view_layer.objects.active).extras
        )
        return {**res, "name": made.name, "plain": plain, "plain_extras": plain_extras}

    def smooth(self):
        """A smooth-shaded UV sphere converted with its material: Blender's corner normals of each
        loop triangle saved beside the splats' normals and barycentric coordinates."""
        bpy = self.bpy
        bpy.ops.mesh.primitive_uv_sphere_add(segments=24, ring_count=12, radius=1.0)
        obj = bpy.context.active_object
        bpy.ops.object.shade_smooth()
        bpy.context.view_layer.update()
        self.select([obj])
        res = self.call(bpy.ops.splat.from_mesh, mode="BUDGET", max_splats=1500, calibrate=False, use_material=True)
        if res["result"] != ["FINISHED"]:
            return res
        cloud = self.module("splat_addon.data").object_cloud(bpy.data.objects[obj.name + "_splats"])
        mesh = obj.data
        mesh.calc_loop_triangles()
        loops = np.array([list(t.loops) for t in mesh.loop_triangles])
        corner = np.array([list(mesh.corner_normals[i].vector) for i in range(len(mesh.loops))], np.float64)
        self.save(
            "smooth",
            normals=self.material_extras(cloud)["normals"],
            source_triangle=cloud.extras["source_triangle"],
            barycentric=cloud.extras["barycentric"],
            positions=cloud.positions,
            corner_normals=corner[loops],
        )
        return res

    def join(self, form):
        """Two material clouds of `form`, the second stretched and mirrored, joined into the first
        (Join Splats); then the first's own stretch applied (Apply Splat Transform)."""
        bpy, data = self.bpy, self.module("splat_addon.data")
        if form == "NATIVE" and not data.native_supported():
            return {"skipped": True}
        material = self.module("core.material")
        a_arrays, b_arrays = material_arrays(3), material_arrays(8)
        a = material.with_material(self.random_cloud(COUNT, 0, seed=4), **a_arrays)
        b = material.with_material(self.random_cloud(COUNT, 0, seed=9), **b_arrays)
        collection = bpy.context.scene.collection
        target, _ = data.new_splat_object(a, "A", collection, form=form)
        other, _ = data.new_splat_object(b, "B", collection, form=form)
        target.location, target.scale = (0.5, 0.0, 0.0), (1.5, 1.0, 0.8)
        for key, value in MATRIX.items():
            setattr(other, key, value)
        bpy.context.view_layer.update()
        to_target = np.linalg.inv(np.array(target.matrix_world)) @ np.array(other.matrix_world)
        target_matrix = np.array(target.matrix_world, np.float64)
        self.select([target, other], active=target)
        joined = self.call(bpy.ops.splat.join)
        after_join = self.material_extras(data.object_cloud(target))
        self.select([target])
        applied = self.call(bpy.ops.splat.apply_transform)
        after_apply = self.material_extras(data.object_cloud(target))
        self.save(
            f"join_{form}",
            to_target=to_target,
            target_matrix=target_matrix,
            a_normals=a_arrays["normals"],
            b_normals=b_arrays["normals"],
            b_albedo=b_arrays["albedo"],
            **{f"join_{k}": v for k, v in after_join.items()},
            **{f"apply_{k}": v for k, v in after_apply.items()},
        )
        return {"join": joined, "apply": applied}

    def join_mesh(self):
        return self.join("MESH")

    def join_native(self):
        return self.join("NATIVE")


if __name__ == "__main__":
    worker_main(Worker)
