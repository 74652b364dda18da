"""The harness of the headless Blender tests (tests/test_blender_*.py).

Each of those files is also its own worker script: pytest runs it in a child process with
BLENDER_USER_RESOURCES pointing at a fresh folder (Blender reads it when bpy is imported, so the
pytest process never imports bpy). The worker installs the extension zip into that user repository,
runs the file's steps one after another and writes what each returned, or its traceback, to
results.json; the tests read it back through a Session.
"""

import importlib
import json
import os
import subprocess
import sys
import traceback
from pathlib import Path

import numpy as np
import pytest

MODULE = "bl_ext.user_default.splatwright"      # the extension's package once installed


# the worker (a separate Python process with bpy) ------------------------------------------------------

class BlenderWorker:
    """Runs the step methods named in `steps`, each on a cleared scene, and records into
    self.results[step] what it returned (or the traceback on failure)."""

    steps = ()                                  # names of step methods, in the order they run
    keep_objects = ("Camera", "Light")          # what clear_scene leaves of the startup scene
    orphan_kinds = ("meshes", "armatures", "materials", "images", "collections", "actions")
    inventory_kinds = ("objects", "meshes", "materials", "node_groups", "collections")

    def __init__(self, work, zip_path):
        import bpy
        self.bpy, self.work, self.zip = bpy, Path(work), zip_path
        self.out = self.work / "out"
        self.out.mkdir(exist_ok=True)
        self.results = {}

    def run(self):
        for name in self.steps:
            self.clear_scene()
            try:
                self.results[name] = getattr(self, name)() or {}
            except Exception:
                self.results[name] = {"worker_error": traceback.format_exc()}
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
        self.bpy.ops.extensions.package_install_files(filepath=str(self.zip), repo="user_default",
                                                      enable_on_install=True)

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

    def save(self, name, **arrays):
        np.savez(self.out / f"{name}.npz", **arrays)


def worker_main(worker_class):
    """A test file run as a script: `python test_x.py WORK ZIP` runs its worker."""
    worker_class(sys.argv[1], sys.argv[2]).run()


# the pytest side ------------------------------------------------------------------------------------

class Session:
    """The worker's results and output folder, seen from the tests."""

    def __init__(self, work, results, log):
        self.work, self.out, self.results, self.log = work, work / "out", results, log

    def step(self, name):
        res = self.results.get(name)
        if res is None:
            pytest.fail(f"worker did not reach step {name}:\n{self.log}")
        if "worker_error" in res:
            pytest.fail(f"worker step {name} failed:\n{res['worker_error']}")
        return res

    def npz(self, name):
        return dict(np.load(self.out / f"{name}.npz"))


def run_worker(script, work, zip_path):
    """Run the test file `script` as the worker on `work` (its inputs already written there), with a
    user resource folder of its own, so the zip installs into a fresh repository; returns its Session."""
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(work / "user")}
    proc = subprocess.run([sys.executable, str(script), str(work), str(zip_path)], env=env, capture_output=True,
                          text=True, timeout=600)
    log = f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}"
    results_file = work / "results.json"
    if not results_file.exists():
        pytest.fail(f"Blender worker wrote no results:\n{log}")
    return Session(work, json.loads(results_file.read_text()), log)
