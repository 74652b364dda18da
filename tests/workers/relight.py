"""The Blender side of tests/test_blender_relight.py (run in each Blender of the version matrix; see
workers/base.py): the scene's lights as the engine reads them, relit splats rendered with their
Diffuse, Specular and Shadow passes, a splat sphere's shadow on a mesh floor, and the demo rig
converted with its material, relit and rendered over two frames."""

import numpy as np

from workers.base import BlenderWorker, worker_main

ORIGIN = (0.5, -0.25, 0.0)  # the engine's frame: world shifted by -ORIGIN
# name -> (type, location, rotation (Euler XYZ), scale, settings)
LIGHTS = {
    "Point": ("POINT", (1.0, 2.0, 3.0), (0.3, 0.0, 0.0), (1.0, 1.0, 1.0), dict(energy=100.0, shadow_soft_size=0.3)),
    "Spot": (
        "SPOT",
        (-1.0, 0.5, 2.0),
        (0.3, 0.2, 0.1),
        (1.0, 1.0, 1.0),
        dict(energy=200.0, spot_size=0.8, spot_blend=0.2, shadow_soft_size=0.05, use_shadow=False),
    ),
    "Sun": ("SUN", (0.0, 0.0, 5.0), (0.4, -0.5, 1.0), (1.0, 1.0, 1.0), dict(energy=3.0, angle=0.1)),
    "Area": (
        "AREA",
        (0.0, -2.0, 1.0),
        (1.2, 0.0, 0.3),
        (2.0, 3.0, 1.0),
        dict(energy=50.0, shape="RECTANGLE", size=2.0, size_y=0.5),
    ),
    "Disk": ("AREA", (2.0, 0.0, 1.0), (0.0, 0.7, 0.0), (0.5, 0.5, 0.5), dict(energy=10.0, shape="DISK", size=1.0)),
}
COLORS = {"Point": (1.0, 0.5, 0.25), "Spot": (0.2, 0.4, 1.0)}
INSTANCE_OFFSET = (5.0, 0.0, 0.0)  # a collection instance of the point light, moved by this
EXPOSURE = 1.0  # Blender 4.5+? set where the light has it: power x 2


class Worker(BlenderWorker):
    steps = ("install", "lights")
    keep_objects = ("Camera",)
    orphan_kinds = ("meshes", "materials", "actions", "lights", "collections")

    def install(self):
        self.install_extension()
        return {}

    def add_light(self, name, kind, location, rotation, scale, settings, collection=None):
        bpy = self.bpy
        data = bpy.data.lights.new(name, kind)
        for key, value in settings.items():
            setattr(data, key, value)
        data.color = COLORS.get(name, (1.0, 1.0, 1.0))
        obj = bpy.data.objects.new(name, data)
        (collection or bpy.context.scene.collection).objects.link(obj)
        obj.location, obj.rotation_euler, obj.scale = location, rotation, scale
        return obj

    def lights(self):
        """Every kind of light, one with exposure where Blender has it, one with Normalize off
        where it has that, and a collection instance: the engine's Light fields of each."""
        bpy = self.bpy
        scene = bpy.context.scene
        for obj in [o for o in scene.objects if o.type == "LIGHT"]:
            bpy.data.objects.remove(obj)
        for name, spec in LIGHTS.items():
            self.add_light(name, *spec)
        has_exposure = hasattr(bpy.data.lights["Point"], "exposure")
        if has_exposure:
            bpy.data.lights["Sun"].exposure = EXPOSURE
        has_normalize = hasattr(bpy.data.lights["Disk"], "normalize")
        if has_normalize:
            bpy.data.lights["Disk"].normalize = False
        group = bpy.data.collections.new("Lamps")
        self.add_light("Lamp", "POINT", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), dict(energy=5.0), group)
        holder = bpy.data.objects.new("Holder", None)
        holder.instance_type, holder.instance_collection = "COLLECTION", group
        holder.location = INSTANCE_OFFSET
        scene.collection.objects.link(holder)
        bpy.context.view_layer.update()
        lights = self.module("splat_addon.render.lights")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        fields = []
        for inst in depsgraph.object_instances:
            if inst.object.type == "LIGHT":
                matrix = np.array(inst.matrix_world, dtype=np.float64)
                record = lights.light_fields(inst.object.data, matrix, np.array(ORIGIN))
                record = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in record.items()}
                fields.append({"name": inst.object.name, **record})
        made = []
        try:  # the core's Light, where core/lights.py takes these fields
            made = [
                {"kind": light.kind, "position": np.asarray(light.position).tolist(), "power": float(light.power)}
                for light in lights.scene_lights(depsgraph, np.array(ORIGIN))
            ]
        except ImportError as exc:
            made = str(exc)
        return {"fields": fields, "exposure": has_exposure, "normalize": has_normalize, "scene_lights": made}


if __name__ == "__main__":
    worker_main(Worker)
