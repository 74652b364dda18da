"""Worker: the axes an SPZ is read and written in, and where imported splats stand, in Blender 5.3 next
to its own PLY and SPZ importers (see tests/test_blender_spz_axes.py)."""

import numpy as np

from workers.base import BlenderWorker, point_attributes, worker_main


class SpzAxesWorker(BlenderWorker):
    steps = ("placement", "spz_axes_import", "spz_axes_export")

    def __init__(self, work, zip_path):
        super().__init__(work, zip_path)
        self.install_extension()

    def imported(self, name, how):
        """The object made of work/`name`: by Blender's importer ("blender"), or by Splatwright's with
        a placement ("UPRIGHT", "BLENDER") and its other import settings."""
        bpy = self.bpy
        before = set(bpy.data.objects)
        path = str(self.work / name)
        if how == "blender":
            getattr(bpy.ops.wm, f"{name.rsplit('.', 1)[1]}_import")(filepath=path)
        else:
            options = {"placement": how} if isinstance(how, str) else dict(how)
            bpy.ops.splat.import_file(filepath=path, **options)
        (obj,) = set(bpy.data.objects) - before
        return obj

    def record(self, tag, obj):
        """Save the object's native attributes (object space) and world matrix as `tag`; its landing."""
        arrays = {name.replace(":", "_"): values for name, values in point_attributes(obj.data).items()}
        self.save(tag, matrix=np.array(obj.matrix_world, dtype=np.float64), **arrays)
        return obj.data.get("splatwright_landing")

    def placement(self):
        """The same files opened by Blender's importers and by Splatwright's with each placement; the
        clouds placed as Blender's are exported with the default settings."""
        landing = {}
        for name in ("src.spz", "src.ply"):
            stem = name.replace(".", "_")
            for how in ("blender", "UPRIGHT", "BLENDER"):
                obj = self.imported(name, how)
                landing[f"{stem}_{how}"] = self.record(f"{stem}_{how}", obj)
                if how == "BLENDER":
                    self.select([obj])
                    self.bpy.ops.splat.export_file(filepath=str(self.out / f"{stem}_as_blender.ply"))
                self.bpy.data.objects.remove(obj)
            # Blender's importers have no Forward/Up: as they place it, whatever those say
            obj = self.imported(name, {"placement": "BLENDER", "axis_forward": "Y", "axis_up": "Z"})
            landing[f"{stem}_BLENDER_axes"] = self.record(f"{stem}_BLENDER_axes", obj)
            self.bpy.data.objects.remove(obj)
        return {"landing": landing}

    def spz_axes_import(self):
        """An SPZ holding PLY's axes without a record, read as asked, and one whose record says RDF."""
        cases = {
            "wild_rdf": ("wild.spz", {"spz_axes": "RDF"}),
            "wild_auto": ("wild.spz", {}),
            "tagged_auto": ("tagged.spz", {}),
            "plain": ("plain.ply", {}),
        }
        for tag, (name, options) in cases.items():
            obj = self.imported(name, options)
            self.record(tag, obj)
            self.bpy.data.objects.remove(obj)
        self.record("tagged_blender", self.imported("tagged.spz", "blender"))
        self.record("tagged3_blender", self.imported("tagged3.spz", "blender"))
        return {}

    def spz_axes_export(self):
        """One cloud exported as SPZ in each axes (the dialog's SPZ Axes), v3 and v4."""
        obj = self.imported("plain.ply", {})
        self.select([obj])
        res = {}
        for axes in ("RUB", "RDF"):
            for version in ("3", "4"):
                name = f"export_{axes}_{version}.spz"
                res[name] = self.call(
                    self.bpy.ops.splat.export_file, filepath=str(self.out / name), spz_axes=axes, spz_version=version
                )
        return res


if __name__ == "__main__":
    worker_main(SpzAxesWorker)
