"""Worker: SOG in Blender, whose Python has no Pillow (see tests/test_blender_sog.py): the extension's
WebP decoder on the test's images, SOG files read (through io and through the import operator) with
it, and what stays refused: export to SOG, a damaged image."""

from workers.base import BlenderWorker, splat_total, worker_main

FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh")
READS = {"bundle": "a.sog", "loose": "loose/meta.json", "streamed": "scene/lod-meta.json"}


class SogWorker(BlenderWorker):
    steps = ("codec", "reads", "refusals")

    def __init__(self, work, zip_path):
        super().__init__(work, zip_path)
        self.install_extension()

    def codec(self):
        """Every codec/*.webp decoded by the registered codec, saved as codec.npz; which codecs the
        registry hands out, and that unregister() takes Blender's away and register() brings it back."""
        image, webp = self.module("io.image"), self.module("splat_addon.files.webp")
        decoded = {path.stem: webp.decode(path.read_bytes()) for path in sorted((self.work / "codec").glob("*.webp"))}
        self.save("codec", **decoded)
        res = {"decoder": image.webp_codec("decode").name, "encoder": image.webp_codec("encode")}
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

    def refusals(self):
        """Export to SOG (no exact encoder here) and the import of a bundle with a damaged image."""
        before = set(self.bpy.data.objects)
        res = {"damaged": self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / "damaged.sog"))}
        res["damaged"]["objects"] = len(set(self.bpy.data.objects) - before)
        outcome = self.call(self.bpy.ops.splat.import_file, filepath=str(self.work / "a.sog"))
        self.select([o for o in self.bpy.data.objects if o not in before])
        target = self.out / "back.sog"
        res["export"] = {
            "import": outcome,
            **self.call(self.bpy.ops.splat.export_file, filepath=str(target), selected_only=True),
            "written": target.exists() or any(self.out.glob("back.sog*")),
        }
        return res


if __name__ == "__main__":
    worker_main(SogWorker)
