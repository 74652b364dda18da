"""Worker: Blender 5.3's own importers (PLY, SPZ, OpenUSD) beside Splatwright's, on the files Splatwright
writes, and Blender's imports written back through Splatwright (see tests/test_blender_peer.py).

Each import is saved as it stands in Blender: the point attributes as stored and the object's world
matrix; the test makes world-space splats of them."""

import warnings

import numpy as np

from workers.base import BlenderWorker, point_attributes, worker_main

DEGREES = (0, 3, 4)
USD_EXTENSIONS = (".usda", ".usdc", ".usdz")
HALF_USD = "d3_half.usdc"  # written with half floats (use_half)
MATERIAL_FILES = ("material.ply", "material.glb")  # a material and extras, for Blender's own importers
# An object transform given on Blender's side before export: a turn with a stretch along the object's
# own axes (shear-free), so the SH turn with the rotation alone.
MOVE = {"location": (0.25, -1.5, 2.0), "rotation_euler": (0.4, -0.9, 1.3), "scale": (1.0, 2.5, 0.5)}


def spz_names(degree):
    """The SPZ files written of a degree: v3 holds up to degree 3, v4 up to 4."""
    return [f"d{degree}_v{version}.spz" for version in (3, 4) if degree <= 3 or version == 4]


def peer_files():
    """Every file written for the comparison of importers, in the order the worker imports them."""
    names = []
    for degree in DEGREES:
        names += [f"d{degree}.ply", *spz_names(degree), *(f"d{degree}{ext}" for ext in USD_EXTENSIONS)]
    return [*names, HALF_USD]


def blender_importer(name):
    """Blender's own import operator for a file name."""
    return {"ply": "ply_import", "spz": "spz_import"}.get(name.rsplit(".", 1)[-1], "usd_import")


class PeerWorker(BlenderWorker):
    steps = ("imports", "round_trips", "moved", "blender_usd", "material")

    def __init__(self, work, zip_path):
        super().__init__(work, zip_path)
        self.install_extension()

    def new_objects(self, run):
        """The objects `run()` adds to the file, and what it returned (the operator's outcome)."""
        before = set(self.bpy.data.objects)
        outcome = run()
        return [o for o in self.bpy.data.objects if o not in before], outcome

    def blender_import(self, name):
        if name.endswith(".glb"):
            op = self.bpy.ops.import_scene.gltf
            return self.new_objects(lambda: self.call(op, filepath=str(self.work / name)))
        op = getattr(self.bpy.ops.wm, blender_importer(name))
        return self.new_objects(lambda: self.call(op, filepath=str(self.work / name)))

    def splatwright_import(self, name):
        return self.new_objects(lambda: self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name)))

    def describe(self, objects, outcome, key):
        """What an import made, its point cloud's attributes saved as `key` (with its world matrix)."""
        clouds = [o for o in objects if o.type == "POINTCLOUD"]
        res = {
            **outcome,
            "objects": sorted(o.type for o in objects),
            "data_type": [getattr(o.data, "type", None) for o in clouds],
            "names": [o.name for o in clouds],
        }
        if len(clouds) == 1:
            obj = clouds[0]
            res["attributes"] = {a.name: a.data_type for a in obj.data.attributes if not a.name.startswith(".")}
            self.save(key, matrix_world=np.array(obj.matrix_world), **point_attributes(obj.data))
        for obj in objects:
            self.bpy.data.objects.remove(obj)
        return res

    def imports(self):
        """Every file of peer_files opened by Blender's importer and by Splatwright's."""
        res = {}
        for name in peer_files():
            res[name] = {
                "blender": self.describe(*self.blender_import(name), f"blender_{name}"),
                "ours": self.describe(*self.splatwright_import(name), f"ours_{name}"),
            }
        return res

    def export(self, name, **kw):
        return self.call(self.bpy.ops.splat.export_file, filepath=str(self.out / name), **kw)

    def command_export(self, name, *options):
        """The `blender -b ... --command splatwright export` handler on the scene (frame 1 alone)."""
        command = self.module("splat_addon.command")
        return command.execute(["export", str(self.out / name), "--frames", "1", *options])

    def round_trips(self):
        """Each PLY and SPZ Blender imported, written back by Splatwright in its own format (SPZ at the
        source's version) by the Export operator and by the command."""
        res = {}
        for degree in DEGREES:
            for name in [f"d{degree}.ply", *spz_names(degree)]:
                objects, outcome = self.blender_import(name)
                if not objects:  # refused by Blender (the test says which and why)
                    res[name] = {"import": outcome}
                    continue
                (obj,) = objects
                stem, ext = name.rsplit(".", 1)
                version = ["--spz-version", stem[-1]] if ext == "spz" else []
                self.select([obj])
                res[name] = {
                    "import": outcome,
                    "export": self.export(f"back_{name}", **({"spz_version": stem[-1]} if version else {})),
                    "command": self.command_export(f"command_{name}", *version),
                }
                self.bpy.data.objects.remove(obj)
        for ext in USD_EXTENSIONS:  # written back as PLY: the splats Blender's USD importer placed
            (obj,), outcome = self.blender_import(f"d3{ext}")
            self.select([obj])
            res[f"d3{ext}"] = {"import": outcome, "export": self.export(f"back_d3_{ext[1:]}.ply")}
            self.bpy.data.objects.remove(obj)
        return res

    def moved(self):
        """The degree-3 PLY and v4 SPZ Blender imported, given MOVE, exported by Splatwright to PLY (no
        quantisation after the turn)."""
        res = {}
        for name in ("d3.ply", "d3_v4.spz"):
            (obj,), outcome = self.blender_import(name)
            for key, value in MOVE.items():
                setattr(obj, key, value)
            self.bpy.context.view_layer.update()
            self.select([obj])
            res[name] = {
                "import": outcome,
                "matrix_world": np.array(obj.matrix_world).tolist(),
                "export": self.export(f"moved_{name.replace('.', '_')}.ply"),
            }
            self.bpy.data.objects.remove(obj)
        return res

    def blender_usd(self):
        """Blender's own USD export of the degree-3 PLY it imported, and its USD import of that file."""
        (obj,), outcome = self.blender_import("d3.ply")
        self.select([obj])
        path = self.out / "blender_export.usda"
        res = {"import": outcome, "export": self.call(self.bpy.ops.wm.usd_export, filepath=str(path))}
        self.bpy.data.objects.remove(obj)
        made = self.new_objects(lambda: self.call(self.bpy.ops.wm.usd_import, filepath=str(path)))
        return {**res, "reimport": self.describe(*made, "blender_usd_reimport")}

    def material(self):
        """The files of MATERIAL_FILES opened by Blender's own importers: the extras Splatwright reads
        of the cloud (saved as `material_<file>`), Export to PLY, and the render engine's word on a
        Relight the cloud without normals cannot take."""
        data, relit = self.module("splat_addon.data"), self.module("splat_addon.render.relit")
        res = {}
        for name in MATERIAL_FILES:
            (obj,), outcome = self.blender_import(name)
            stem = name.replace(".", "_")
            cloud = data.object_cloud(obj)
            self.save(f"material_{stem}", **{k: np.asarray(v) for k, v in cloud.extras.items()})
            self.select([obj])
            res[name] = {
                "import": outcome,
                "type": getattr(obj.data, "type", None),
                "extras": {k: str(np.asarray(v).dtype) for k, v in cloud.extras.items()},
                "export": self.export(f"material_{stem}.ply"),
            }
            setattr(obj, self.module("splat_addon.render.lights").RELIGHT, True)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                relit._marked(obj, cloud)
            res[name]["warnings"] = [str(w.message) for w in caught]
            # Estimate Normals completes the material: the cloud is then relit, its albedo the file's
            res[name]["estimate"] = self.call(self.bpy.ops.splat.estimate_normals, orient="CENTRE")
            estimated = data.object_cloud(obj)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                marked = relit._marked(obj, estimated)
            res[name]["warnings_estimated"] = [str(w.message) for w in caught]
            self.save(f"material_{stem}_estimated", albedo=np.asarray(marked.extras["albedo"]))
            self.bpy.data.objects.remove(obj)
        return res


if __name__ == "__main__":
    worker_main(PeerWorker)
