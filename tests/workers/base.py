"""The worker half of the headless Blender tests: a Python process with `bpy` and nothing of ours
installed. It installs the extension zip into a fresh user repository (BLENDER_USER_RESOURCES, set by
the test before bpy is imported), runs one worker class's steps, each on a cleared scene, and writes
what each returned, or its traceback, to results.json. tests/blender_session.py starts it and reads
the results back.

Worker modules (tests/workers/*.py) import only the standard library, NumPy and this module at their
top, and bpy and the installed extension (self.module(...)) inside their steps, because they run in
every Blender of the version matrix, whose Python has neither pytest nor splatwright.
"""

import contextlib
import importlib
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

MODULE = "bl_ext.user_default.splatwright"  # the extension's package once installed


def random_cloud_arrays(n, sh_degree=3, seed=0, spread=1.0):
    """The fields of a random anisotropic cloud with every field populated and non-unit quaternions
    (tests/helpers.random_cloud wraps them in a SplatCloud)."""
    rng = np.random.default_rng(seed)
    k = (sh_degree + 1) ** 2
    return dict(
        positions=rng.normal(0, spread, (n, 3)),
        rotations=rng.normal(0, 1, (n, 4)) * rng.uniform(0.5, 2.0, (n, 1)),
        log_scales=rng.uniform(-4, -1, (n, 3)),
        opacity_logits=rng.normal(0, 2, n),
        sh=rng.normal(0, 0.3, (n, k, 3)),
    )


class BlenderWorker:
    """Runs the step methods named in `steps`, each on a cleared scene, and records into
    self.results[step] what it returned (or the traceback on failure)."""

    steps = ()  # names of step methods, in the order they run
    keep_objects = ("Camera", "Light")  # what clear_scene leaves of the startup scene
    orphan_kinds = ("meshes", "armatures", "materials", "images", "collections", "actions")
    inventory_kinds = ("objects", "meshes", "materials", "node_groups", "collections")

    def __init__(self, work, zip_path):
        import bpy

        self.bpy, self.work, self.zip = bpy, Path(work), zip_path
        self.out = self.work / "out"
        self.out.mkdir(exist_ok=True)
        self.results, self.seconds = {}, {}

    def run(self):
        for name in self.steps:
            self.clear_scene()
            start = time.perf_counter()
            try:
                self.results[name] = getattr(self, name)() or {}
            except Exception:
                self.results[name] = {"worker_error": traceback.format_exc()}
            self.seconds[name] = round(time.perf_counter() - start, 2)
        self.results["_seconds"] = self.seconds  # where a worker's time goes
        (self.work / "results.json").write_text(json.dumps(self.results, indent=1))

    def clear_scene(self):
        """Remove what earlier steps made: objects but `keep_objects`, then unused data of `orphan_kinds`;
        back to the default frame range at frame 1."""
        bpy = self.bpy
        for obj in list(bpy.data.objects):
            if obj.name not in self.keep_objects:
                bpy.data.objects.remove(obj)
        for kind in self.orphan_kinds:
            collection = getattr(bpy.data, kind)
            for item in list(collection):
                if item.users == 0:
                    collection.remove(item)
        scene = bpy.context.scene
        scene.frame_start, scene.frame_end, scene.frame_step = 1, 250, 1
        scene.frame_set(1)

    def install_extension(self):
        """Install the zip into the user repository and enable it, as Install from Disk does."""
        self.bpy.ops.extensions.package_install_files(
            filepath=str(self.zip), repo="user_default", enable_on_install=True
        )

    def module(self, name):
        """A module of the installed extension, e.g. "splat_addon.data" or "core.render"."""
        return importlib.import_module(f"{MODULE}.{name}")

    def menu_entries(self, menu):
        """How many draw functions the extension has added to `menu` (a bpy.types menu name)."""
        funcs = getattr(getattr(self.bpy.types, menu).draw, "_draw_funcs", [])
        return sum(1 for f in funcs if f.__module__.startswith(MODULE))

    def call(self, op, **kw):
        """Run an operator; ERROR reports raise RuntimeError in background mode: return the message."""
        try:
            return {"result": sorted(op(**kw)), "error": None}
        except RuntimeError as exc:
            return {"result": ["CANCELLED"], "error": str(exc)}

    def select(self, objects, active=None):
        """Select exactly `objects`; the active object is `active`, else the first of them (or none)."""
        for obj in self.bpy.context.view_layer.objects:
            obj.select_set(obj in objects)
        self.bpy.context.view_layer.objects.active = active if active is not None else (objects[0] if objects else None)

    def inventory(self):
        """Names of the data a failed operator must leave as it was, and the selection."""
        bpy = self.bpy
        inv = {k: sorted(x.name for x in getattr(bpy.data, k)) for k in self.inventory_kinds}
        inv["selected"] = sorted(o.name for o in bpy.context.selected_objects)
        return inv

    @staticmethod
    def image_format(settings, file_format, **values):
        """Set a render's image format (and other image settings) as this Blender wants it: from 5.0
        the media type comes first."""
        if hasattr(settings, "media_type"):
            settings.media_type = "MULTI_LAYER_IMAGE" if file_format == "OPEN_EXR_MULTILAYER" else "IMAGE"
        settings.file_format = file_format
        for name, value in values.items():
            setattr(settings, name, value)

    def world_map(self, pixels, name="Map"):
        """An Environment Texture of `pixels` (H, W, 4) float32, rows from the bottom, on the scene
        world's Background Color: (the texture node, its image), for the caller to remove."""
        bpy = self.bpy
        height, width = pixels.shape[:2]
        image = bpy.data.images.new(name, width, height, float_buffer=True)
        image.pixels.foreach_set(np.ascontiguousarray(pixels, np.float32).ravel())
        tree = bpy.context.scene.world.node_tree
        background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
        texture = tree.nodes.new("ShaderNodeTexEnvironment")
        texture.image = image
        tree.links.new(texture.outputs["Color"], background.inputs["Color"])
        return texture, image

    def two_bone_armature(self, name, location=(0.0, 0.0, 0.0)):
        """An armature object `name` at `location` in the scene: bone Lower from (0,0,0) to (0,0,1),
        Upper connected above it to (0,0,2)."""
        bpy = self.bpy
        arm = bpy.data.objects.new(name, bpy.data.armatures.new(name))
        bpy.context.scene.collection.objects.link(arm)
        arm.location = location
        self.select([arm])
        bpy.ops.object.mode_set(mode="EDIT")
        lower = arm.data.edit_bones.new("Lower")
        lower.head, lower.tail = (0, 0, 0), (0, 0, 1)
        upper = arm.data.edit_bones.new("Upper")
        upper.head, upper.tail, upper.parent, upper.use_connect = (0, 0, 1), (0, 0, 2), lower, True
        bpy.ops.object.mode_set(mode="OBJECT")
        return arm

    def group_matrix(self, obj, names):
        """(V, len(names)) weights read one vertex at a time through VertexGroup.weight."""
        out = np.zeros((len(obj.data.vertices), len(names)))
        for j, name in enumerate(names):
            group = obj.vertex_groups.get(name)
            for i in range(len(out)) if group is not None else ():
                with contextlib.suppress(RuntimeError):  # not in the group
                    out[i, j] = group.weight(i)
        return out

    def weight_matrix(self, obj, names):
        """(splats, len(names)) bone weights of a splat object in either form: a mesh's vertex groups
        (group_matrix), a native point cloud's FLOAT attributes splat_weight:<name>, or <name> itself
        (the binding-strength mask), 0 where there is none."""
        if obj.type != "POINTCLOUD":
            return self.group_matrix(obj, names)
        attributes = obj.data.attributes
        out = np.zeros((len(obj.data.points), len(names)))
        for j, name in enumerate(names):
            attr = attributes.get("splat_weight:" + name) or attributes.get(name)
            if attr is not None:
                column = np.empty(len(out), np.float32)
                attr.data.foreach_get("value", column)
                out[:, j] = column
        return out

    def save(self, name, **arrays):
        np.savez(self.out / f"{name}.npz", **arrays)

    def random_cloud(self, n, sh_degree=3, seed=0, spread=1.0):
        """random_cloud_arrays as a SplatCloud of the installed extension."""
        return self.module("core").SplatCloud(**random_cloud_arrays(n, sh_degree, seed, spread))


# Blender attribute type -> (foreach_get property, components, NumPy dtype)
POINT_TYPES = {
    "FLOAT": ("value", 1, np.float32),
    "INT": ("value", 1, np.int32),
    "FLOAT2": ("vector", 2, np.float32),
    "FLOAT_VECTOR": ("vector", 3, np.float32),
    "QUATERNION": ("value", 4, np.float32),
    "FLOAT_COLOR": ("color", 4, np.float32),
    "FLOAT4": ("vector", 4, np.float32),
}


def splat_total(obj):
    """How many splats a splat object holds in either form: a mesh's vertices, a point cloud's points."""
    return len(obj.data.points) if obj.type == "POINTCLOUD" else len(obj.data.vertices)


def point_attributes(geometry):
    """{name: (points, components) array} of a mesh's or point cloud's visible point attributes of
    POINT_TYPES, as Blender stores them (foreach_get)."""
    out = {}
    for attr in geometry.attributes:
        if attr.domain == "POINT" and attr.data_type in POINT_TYPES and not attr.name.startswith("."):
            prop, width, dtype = POINT_TYPES[attr.data_type]
            values = np.empty(len(attr.data) * width, dtype)
            attr.data.foreach_get(prop, values)
            out[attr.name] = values.reshape(-1, width)
    return out


def point_attribute(geometry, name):
    """One point attribute of POINT_TYPES by name, hidden ones too, as a (points, components) array."""
    attr = geometry.attributes[name]
    prop, width, dtype = POINT_TYPES[attr.data_type]
    values = np.empty(len(attr.data) * width, dtype)
    attr.data.foreach_get(prop, values)
    return values.reshape(-1, width)


def worker_main(worker_class):
    """A worker module run as a script: `python -m workers.x WORK ZIP` runs its worker."""
    worker_class(sys.argv[1], sys.argv[2]).run()
