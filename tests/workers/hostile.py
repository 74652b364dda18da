"""The Blender side of tests/test_blender_hostile.py (run in each Blender of the version matrix; see
workers/base.py)."""

from workers.base import BlenderWorker, splat_total, worker_main


class Worker(BlenderWorker):
    steps = ("install", "outside")

    def install(self):
        self.install_extension()

    def outside(self):
        """Import a glTF whose buffer lies outside its folder: refused by default, read when allowed."""
        bpy = self.bpy
        path = str(self.work / "model" / "v.gltf")
        refused = self.call(bpy.ops.splat.import_file, filepath=path)
        objects = len(bpy.data.objects)
        allowed = self.call(bpy.ops.splat.import_file, filepath=path, allow_outside=True)
        option = bpy.ops.splat.import_file.get_rna_type().properties["allow_outside"]
        return {
            "refused": refused,
            "objects_after_refusal": objects,
            "allowed": allowed,
            "count": splat_total(bpy.context.active_object) if allowed["error"] is None else None,
            "name": option.name,
            "description": option.description,
            "default": option.default,
        }


if __name__ == "__main__":
    worker_main(Worker)
