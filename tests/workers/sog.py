"""Worker: SOG in Blender, whose Python has no Pillow (see tests/test_blender_sog.py): the extension's
WebP codec on the test's images, SOG files read (through io and through the import operator) and
written (through io and through the export operator) with it, and a damaged image refused."""

import warnings

import numpy as np

from workers.base import BlenderWorker, splat_total, worker_main

FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh")
READS = {"bundle": "a.sog", "loose": "loose/meta.json", "streamed": "scene/lod-meta.json"}
# what the exports step writes (under out/) -> the cloud it wrote, saved as <name>.npz
EXPORTS = {
    "io_bundle": ("io.sog", "io_cloud"),
    "io_loose": ("io/meta.json", "io_cloud"),
    "operator_bundle": ("back.sog", "exported"),
    "operator_loose": ("back/meta.json", "exported"),
}


class SogWorker(BlenderWorker):
    steps = ("codec", "reads", "exports", "refusals")

    def __init__(self, work, zip_path):
        super().__init__(work, zip_path)
        self.install_extension()

    def codec(self):
        """Every codec/*.webp decoded by the registered codec, saved as codec.npz; every image of
        encode.npz encoded through io.image, as out/encoded/<name>.webp; which codecs the registry hands
        out, and that unregister() takes Blender's away and register() brings it back."""
        image, webp = self.module("io.image"), self.module("splat_addon.files.webp")
        decoded = {path.stem: webp.decode(path.read_bytes()) for path in sorted((self.work / "codec").glob("*.webp"))}
        self.save("codec", **decoded)
        (self.out / "encoded").mkdir()
        for name, pixels in np.load(self.work / "encode.npz").items():
            (self.out / "encoded" / f"{name}.webp").write_bytes(image.encode_webp("x.sog", pixels))
        encoder = image.webp_codec("encode")
        res = {"decoder": image.webp_codec("decode").name, "encoder": encoder.name, "exact": encoder.exact}
        webp.unregister()
        res["decoder_unregistered"] = image.webp_codec("decode")
        webp.register()
        res["decoder_again"] = image.webp_codec("decode").name
        return res

    def reads(self):
        """Each SOG of READS read by io.read_splats (saved as read_<key>.npz) and imported by the
        operator (its object's splats saved as object_<key>.npz)."""
        io, data = self.module("io"), self.module("splat_addon.data")
        res = {}
        for key, name in READS.items():
            cloud = io.read_splats(self.work / name)
            self.save(f"read_{key}", **{field: getattr(cloud, field) for field in FIELDS})
            before = set(self.bpy.data.objects)
            outcome = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / name))
            made = [o for o in self.bpy.data.objects if o not in before]
            res[key] = {**outcome, "objects": len(made), "count": sum(splat_total(o) for o in made)}
            if len(made) == 1:
                cloud = data.object_cloud(made[0])
                matrix = [list(row) for row in made[0].matrix_world]
                self.save(f"object_{key}", matrix=matrix, **{field: getattr(cloud, field) for field in FIELDS})
        return res

    def exports(self):
        """a.sog read by io.read_splats and written by io.write_splats (the warnings each gave), and
        imported by the operator and exported by it with the default axes; each cloud written saved
        (see EXPORTS), the export operator's as scene_cloud gives it."""
        io, files = self.module("io"), self.module("splat_addon.files.import_export")
        cloud = io.read_splats(self.work / "a.sog")
        self.save("io_cloud", **{field: getattr(cloud, field) for field in FIELDS})
        res = {}
        for key in ("io_bundle", "io_loose"):
            target = self.out / EXPORTS[key][0]
            target.parent.mkdir(exist_ok=True)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                io.write_splats(target, cloud)
            res[key] = [f"{w.category.__name__}: {w.message}" for w in caught]
        before = set(self.bpy.data.objects)
        outcome = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / "a.sog"))
        made = [o for o in self.bpy.data.objects if o not in before]
        res["import"] = {**outcome, "objects": len(made)}
        self.select(made)
        objects = files.export_objects(self.bpy.context, True)
        exported = files.scene_cloud(self.bpy.context, objects, files.export_conversion())
        self.save("exported", **{field: getattr(exported, field) for field in FIELDS})
        for key in ("operator_bundle", "operator_loose"):
            target = self.out / EXPORTS[key][0]
            target.parent.mkdir(exist_ok=True)
            res[key] = self.call(self.bpy.ops.splat.export_file, filepath=str(target), selected_only=True)
        return res

    def refusals(self):
        """The import of a bundle with a damaged image."""
        before = set(self.bpy.data.objects)
        res = {"damaged": self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / "damaged.sog"))}
        res["damaged"]["objects"] = len(set(self.bpy.data.objects) - before)
        return res


if __name__ == "__main__":
    worker_main(SogWorker)
