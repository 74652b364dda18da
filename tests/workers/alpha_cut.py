"""The Blender side of tests/test_blender_alpha_cut.py: Mesh to Splats on a leaf quad whose
Principled BSDF takes its Alpha from the leaf image (an alpha clip of Math nodes, or the image's
Alpha directly), and the alpha mode read from each of the node setups artists and Blender's glTF
importer build (run in each Blender of the version matrix; see workers/base.py)."""

import numpy as np

from workers.base import BlenderWorker, worker_main

TEXTURE = 64  # texels a side of the leaf image
CUTOFF = 0.4
# node setup -> the (alpha_mode, alpha_cutoff) core.mesh.Material must get
SETUPS = {
    "gltf": ("MASK", CUTOFF),  # 1 - (alpha < c), as Blender's glTF importer builds MASK
    "greater": ("MASK", CUTOFF),  # alpha > c
    "round": ("MASK", 0.5),
    "direct": ("BLEND", 0.5),  # Cycles mixes with transparency by the alpha
    "clip": ("MASK", CUTOFF),  # direct, blend_method CLIP (where the attribute exists)
    "colour": ("OPAQUE", 0.5),  # Alpha fed by the image's colour, not its alpha
    "unlinked": ("OPAQUE", 0.5),
}


class Worker(BlenderWorker):
    steps = ("install", "modes", "convert")
    keep_objects = ()

    def install(self):
        self.install_extension()
        return {}

    def leaf_image(self):
        bpy = self.bpy
        leaf = self.module("core.mesh_corpus").leaf_texture(TEXTURE)
        img = bpy.data.images.new("Leaf", TEXTURE, TEXTURE, alpha=True)
        img.pixels.foreach_set((leaf[::-1].astype(np.float32) / 255).ravel())  # Blender's row 0 is the bottom
        return img, leaf

    def material(self, name, setup, img):
        """A Principled BSDF material whose Base Color is the image's Color and whose Alpha is fed
        as `setup` says."""
        bpy = self.bpy
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        nodes, links = mat.node_tree.nodes, mat.node_tree.links
        bsdf = next(n for n in nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        tex = nodes.new("ShaderNodeTexImage")
        tex.image = img
        links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
        alpha = bsdf.inputs["Alpha"]

        def math(operation, first, second):
            node = nodes.new("ShaderNodeMath")
            node.operation = operation
            for socket, value in zip(node.inputs, (first, second)):
                if isinstance(value, float):
                    socket.default_value = value
                else:
                    links.new(value, socket)
            return node.outputs[0]

        if setup == "gltf":
            links.new(math("SUBTRACT", 1.0, math("LESS_THAN", tex.outputs["Alpha"], CUTOFF)), alpha)
        elif setup == "greater":
            links.new(math("GREATER_THAN", tex.outputs["Alpha"], CUTOFF), alpha)
        elif setup == "round":
            links.new(math("ROUND", tex.outputs["Alpha"], 0.0), alpha)
        elif setup in ("direct", "clip"):
            links.new(tex.outputs["Alpha"], alpha)
            if setup == "clip":
                mat.blend_method, mat.alpha_threshold = "CLIP", CUTOFF
        elif setup == "colour":
            links.new(tex.outputs["Color"], alpha)
        return mat, bsdf, tex

    def modes(self):
        """The (alpha_mode, alpha_cutoff) read from each setup."""
        reading = self.module("splat_addon.convert.mesh_reading")
        img, _ = self.leaf_image()
        out = {}
        for setup in SETUPS:
            if setup == "clip" and not hasattr(self.bpy.types.Material, "blend_method"):
                continue
            mat, bsdf, tex = self.material(setup, setup, img)
            mode, cutoff = reading.alpha_mode(mat, bsdf, tex)
            appearance = reading.material_appearance(mat, lambda message: None)
            out[setup] = [mode, round(cutoff, 6), appearance.material.alpha_mode]
        return out

    def convert(self):
        """A unit leaf quad (UVs 0..1) with the glTF importer's alpha clip, and the same quad
        with its Alpha unlinked, both converted to a budget: the splats' source points and the
        image as the test reads it."""
        bpy = self.bpy
        img, leaf = self.leaf_image()
        counts = {}
        for setup in ("gltf", "unlinked"):
            mesh = bpy.data.meshes.new(f"Leaf_{setup}")
            mesh.from_pydata([(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)], [], [(0, 1, 2, 3)])
            uv = mesh.uv_layers.new(name="UVMap")
            for loop, coords in zip(mesh.loops, [(0, 0), (1, 0), (1, 1), (0, 1)]):
                uv.data[loop.index].uv = coords
            mesh.materials.append(self.material(f"leaf_{setup}", setup, img)[0])
            obj = bpy.data.objects.new(f"Leaf_{setup}", mesh)
            bpy.context.scene.collection.objects.link(obj)
            bpy.context.view_layer.update()
            self.select([obj])
            res = self.call(bpy.ops.splat.from_mesh, mode="BUDGET", max_splats=3000, calibrate=False)
            if res["result"] != ["FINISHED"]:
                return res
            cloud = self.module("splat_addon.data").object_cloud(bpy.data.objects[f"Leaf_{setup}_splats"])
            counts[setup] = len(cloud)
            self.save(f"convert_{setup}", positions=cloud.positions, leaf=leaf)
        held = np.empty(TEXTURE * TEXTURE * 4, np.float32)
        img.pixels.foreach_get(held)
        counts["alpha_held"] = float(held[3::4].mean())  # the image keeps its alpha
        return {"result": ["FINISHED"], "counts": counts}


if __name__ == "__main__":
    worker_main(Worker)
