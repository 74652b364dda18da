"""The pytest half of the headless Blender tests (tests/test_blender_*.py), and their version matrix.

Each test module names a worker module (tests/workers/*.py) and gets, through `blender_fixture`, one
Session per Blender version of tests/blender_envs.py: the worker runs in a child process of that
version's bpy-only Python, with BLENDER_USER_RESOURCES pointing at a fresh folder, installs the
extension zip there as a user does, runs its steps and writes results.json. Every test of the module
runs once per version (its id ends in the version, e.g. [4.2]); a version whose Python this machine
lacks is skipped with one line that says so.
"""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import blender_envs

TESTS = Path(__file__).resolve().parent
from workers.base import MODULE  # noqa: F401  (the test modules import it from here)


class Session:
    """The worker's results and output folder, seen from the tests, and the Blender version it ran."""

    def __init__(self, work, results, log, version):
        self.work, self.out, self.results, self.log = work, work / "out", results, log
        self.version = version
        self.version_tuple = tuple(int(x) for x in version.split("."))

    def step(self, name):
        res = self.results.get(name)
        if res is None:
            pytest.fail(f"worker did not reach step {name}:\n{self.log}")
        if "worker_error" in res:
            pytest.fail(f"worker step {name} failed:\n{res['worker_error']}")
        return res

    def npz(self, name):
        return dict(np.load(self.out / f"{name}.npz"))


def run_worker(worker, work, zip_path, version=blender_envs.PRIMARY):
    """Run the worker module `worker` ("workers.addon") on `work` (its inputs already written there) in
    Blender `version`'s bpy-only Python, with a user resource folder of its own, so the zip installs
    into a fresh repository; returns its Session. Skips when this machine cannot run that version."""
    try:
        python = blender_envs.python_of(version)
    except blender_envs.Unavailable as exc:
        pytest.skip(str(exc))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(BLENDER_USER_RESOURCES=str(work / "user"), PYTHONPATH=str(TESTS))
    proc = subprocess.run([python, "-m", worker, str(work), str(zip_path)], cwd=work, env=env,
                          capture_output=True, text=True, timeout=900)
    log = f"Blender {version}, exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}"
    results_file = work / "results.json"
    if not results_file.exists():
        pytest.fail(f"Blender worker wrote no results:\n{log}")
    return Session(work, json.loads(results_file.read_text()), log, version)


def blender_fixture(worker, write_inputs=None):
    """The module-scoped fixture `blender` of a test module: one Session per Blender version, its
    worker module run on a fresh folder that `write_inputs(folder)` (if given) filled first."""
    @pytest.fixture(scope="module", params=list(blender_envs.VERSIONS))
    def blender(request, tmp_path_factory, extension_zip):
        work = tmp_path_factory.mktemp(f"{worker.rsplit('.', 1)[-1]}_{request.param}")
        if write_inputs is not None:
            write_inputs(work)
        return run_worker(worker, work, extension_zip, request.param)
    return blender
