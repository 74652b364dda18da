"""Worker: the Blender import of the read-only formats, .ksplat, LCC2 and streamed SOG (see
tests/test_blender_new_readers.py): the dialogs' file filters, imports written back as PLY, and a
streamed SOG, whose WebP images the extension decodes with Blender's own decoder."""

from workers.base import BlenderWorker, splat_total, worker_main


class NewReadersWorker(BlenderWorker):
    steps = ("dialogs", "imports")

    def __init__(self, work, zip_path):
        super().__init__(work, zip_path)
        self.install_extension()

    def glob(self, op):
        return op.get_rna_type().properties["filter_glob"].default

    def dialogs(self):
        ops = self.bpy.ops.splat
        return {"import": self.glob(ops.import_file), "export": self.glob(ops.export_file)}

    def import_file(self, name):
        before = set(self.bpy.data.objects)
        outcome = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name))
        made = [o for o in self.bpy.data.objects if o not in before]
        return outcome, made

    def imports(self):
        outcome, made = self.import_file("a.ksplat")
        res = {"ksplat": {**outcome, "objects": len(made), "count": sum(splat_total(o) for o in made)}}
        self.select(made)
        res["ksplat"]["export"] = self.call(
            self.bpy.ops.splat.export_file, filepath=str(self.out / "a_back.ply"), selected_only=True
        )
        outcome, made = self.import_file("lcc2/scene.lcc2")
        res["lcc2"] = {**outcome, "objects": len(made), "count": sum(splat_total(o) for o in made)}
        self.select(made)
        self.call(self.bpy.ops.splat.export_file, filepath=str(self.out / "lcc2_back.ply"), selected_only=True)
        outcome, made = self.import_file("scene/lod-meta.json")
        res["streamed"] = {**outcome, "objects": len(made), "count": sum(splat_total(o) for o in made)}
        return res


if __name__ == "__main__":
    worker_main(NewReadersWorker)
