"""The Blender side of tests/test_blender_normals.py: Estimate Normals on splat objects of both forms
(run in each Blender of the version matrix; see workers/base.py). The splats and the expected
normals are built here from closed forms; the test checks what the operator stored."""

import json

import numpy as np

from workers.base import BlenderWorker, worker_main

SPHERE = 600
ROUND = 37  # splats of the sphere made round (equal scales): their normals are not to be trusted
SHEET = 15  # a SHEET x SHEET grid of flat splats
CAMERA_AT = (0.4, -4.0, 1.5)  # looking at the sheet's centre
SHEET_AT = (0.2, 0.3, 0.1)
MATRIX = dict(location=(0.3, -0.2, 0.5), rotation_euler=(0.4, -0.3, 0.8), scale=(1.0, 1.3, 0.8))


def frames_from_axes(normal, rng):
    """(N,3,3) rotation matrices whose third column is `normal` (N,3) unit, first column random."""
    t1 = np.cross(normal, rng.normal(size=normal.shape))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return np.stack([t1, np.cross(normal, t1), normal], axis=2)


def sphere_arrays(seed=5):
    """Flat splats tiling a unit sphere (object space), each axis along the radius with a random sign,
    the last ROUND of them round; returns the cloud's fields and the outward normals."""
    rng = np.random.default_rng(seed)
    i = np.arange(SPHERE) + 0.5
    z = 1 - 2 * i / SPHERE
    ring = np.sqrt(1 - z**2)
    angle = np.pi * (3 - np.sqrt(5)) * i
    radial = np.column_stack([ring * np.cos(angle), ring * np.sin(angle), z])
    sign = np.where(rng.uniform(size=SPHERE) < 0.5, -1.0, 1.0)[:, None]
    sigma = 0.9 * np.sqrt(4 * np.pi / SPHERE)
    scales = np.tile([sigma, sigma, 0.02 * sigma], (SPHERE, 1))
    scales[-ROUND:] = sigma
    return frames_from_axes(sign * radial, rng), radial, radial, scales


def sheet_arrays(seed=6):
    """A square sheet of flat splats through SHEET_AT, facing CAMERA_AT, axes of random sign."""
    rng = np.random.default_rng(seed)
    facing = np.asarray(CAMERA_AT) - SHEET_AT
    facing /= np.linalg.norm(facing)
    u = np.cross(facing, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(facing, u)
    g = np.linspace(-0.6, 0.6, SHEET)
    a, b = (x.ravel() for x in np.meshgrid(g, g))
    positions = np.asarray(SHEET_AT) + a[:, None] * u + b[:, None] * v
    sign = np.where(rng.uniform(size=len(a)) < 0.5, -1.0, 1.0)[:, None]
    rot = frames_from_axes(sign * np.tile(facing, (len(a), 1)), rng)
    step = g[1] - g[0]
    return rot, positions, np.tile(facing, (len(a), 1)), np.tile([step, step, 0.02 * step], (len(a), 1))


class Worker(BlenderWorker):
    steps = ("install", "sphere_mesh", "sphere_native", "sheet_mesh", "sheet_native", "refusals")
    keep_objects = ()
    orphan_kinds = ("meshes", "cameras", "materials")

    def install(self):
        self.install_extension()
        return {"operator": hasattr(self.bpy.ops.splat, "estimate_normals")}

    def make(self, name, arrays, form, positions=None):
        rot, radial, _, scales = arrays
        core = self.module("core")
        q = core.geometry.matrices_to_quaternions(rot)
        positions = radial if positions is None else positions
        cloud = core.SplatCloud.from_activated(positions, q, scales, np.full(len(q), 0.99))
        data = self.module("splat_addon.data")
        obj, _ = data.new_splat_object(cloud, name, self.bpy.context.scene.collection, form=form)
        return obj

    def estimate(self, obj, orient):
        self.select([obj])
        res = self.call(self.bpy.ops.splat.estimate_normals, orient=orient)
        res["report"] = json.loads(obj.get("splatwright_normals_report", "null"))
        extras = self.module("splat_addon.data").object_cloud(obj).extras
        normals = np.stack([extras[k] for k in ("nx", "ny", "nz")], 1) if "nx" in extras else np.zeros((0, 3))
        return res, normals

    def sphere(self, form):
        """No camera in the scene: both orientations point away from the centre; the object is moved,
        turned and stretched, so the normals go to world and back."""
        data = self.module("splat_addon.data")
        if form == "NATIVE" and not data.native_supported():
            return {"skipped": True}
        arrays = sphere_arrays()
        obj = self.make("Sphere", arrays, form)
        for key, value in MATRIX.items():
            setattr(obj, key, value)
        self.bpy.context.view_layer.update()
        res = {}
        for orient in ("CAMERAS", "CENTRE"):
            res[orient], normals = self.estimate(obj, orient)
            self.save(f"sphere_{form}_{orient}", normals=normals, outward=arrays[2])
        res["exported_extras"] = sorted(data.object_cloud(obj).extras)
        return res

    def camera(self, name="Cam", offset=(0.0, 0.0, 0.0)):
        bpy = self.bpy
        cam = bpy.data.objects.new(name, bpy.data.cameras.new(name))
        bpy.context.scene.collection.objects.link(cam)
        cam.location = np.asarray(CAMERA_AT) + offset
        direction = np.asarray(SHEET_AT) - cam.location
        cam.rotation_euler = _track(direction)
        bpy.context.view_layer.update()
        return cam

    def sheet(self, form):
        """One camera in front of a flat sheet: with Cameras every normal faces it."""
        data = self.module("splat_addon.data")
        if form == "NATIVE" and not data.native_supported():
            return {"skipped": True}
        arrays = sheet_arrays()
        obj = self.make("Sheet", arrays, form, positions=arrays[1])
        self.camera()
        res = {}
        res["CAMERAS"], normals = self.estimate(obj, "CAMERAS")
        self.save(f"sheet_{form}", normals=normals, facing=arrays[2])
        for k in range(4):  # more cameras than the operator is allowed: thinned to two
            self.camera(f"Cam{k}", offset=(0.3 * k - 0.5, 0.0, 0.2 * k))
        self.select([obj])
        res["thinned"] = self.call(self.bpy.ops.splat.estimate_normals, orient="CAMERAS", max_cameras=2)
        res["thinned"]["report"] = json.loads(obj["splatwright_normals_report"])
        return res

    def sphere_mesh(self):
        return self.sphere("MESH")

    def sphere_native(self):
        return self.sphere("NATIVE")

    def sheet_mesh(self):
        return self.sheet("MESH")

    def sheet_native(self):
        return self.sheet("NATIVE")

    def refusals(self):
        """A splat with NaN log-scales: an error report, no normals written."""
        arrays = sphere_arrays()
        obj = self.make("Broken", arrays, "MESH")
        data = self.module("splat_addon.data")
        cloud = data.object_cloud(obj)
        cloud.log_scales[4] = np.nan
        data.update_splats(obj, cloud)
        res, normals = self.estimate(obj, "CENTRE")
        return {"broken": res, "normals_written": len(normals)}


def _track(direction):
    """Euler XYZ (radians) turning a camera (looking down its -Z, +Y up) to look along `direction`."""
    import mathutils

    return tuple(mathutils.Vector(tuple(float(x) for x in direction)).to_track_quat("-Z", "Y").to_euler())


if __name__ == "__main__":
    worker_main(Worker)
