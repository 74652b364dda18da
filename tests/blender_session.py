"""The pytest half of the headless Blender tests (tests/test_blender_*.py), and their version matrix.

Each test module names a worker module (tests/workers/*.py) and gets, through `blender_fixture`, one
Session per Blender version of tests/blender_envs.py: the worker runs in a child process of that
version's bpy-only Python, with BLENDER_USER_RESOURCES pointing at a fresh folder, installs the
extension zip there as a user does, runs its steps and writes results.json. Every test of the module
runs once per version (its id ends in the version, e.g. [4.2]); a version whose Python this machine
lacks is skipped with one line that says so.

The workers do not wait for their tests: when collection ends, every (worker, version) the selected
tests need starts in a background pool (two at a time on two cores; SPLATWRIGHT_BLENDER_JOBS sets
it; versions of different Pythons in turn, see _pythons_in_turn), and the tests with Blender workers
are moved after the others, which run meanwhile.
"""

import inspect
import json
import os
import shutil
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import blender_envs
import numpy as np
import pytest

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
    proc = subprocess.run(  # faulthandler: a crash in Blender still prints each thread's Python stack
        [python, "-X", "faulthandler", "-m", worker, str(work), str(zip_path)],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    log = (
        f"Blender {version}, exit {proc.returncode}\n"
        f"--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}"
    )
    # The installed extension (its bundled compiler wheels unpacked) is about 300 MB a worker, and
    # the tests read only results.json and out/: 36 of them would fill a small CI disk.
    shutil.rmtree(work / "user", ignore_errors=True)
    results_file = work / "results.json"
    if not results_file.exists():
        pytest.fail(f"Blender worker wrote no results:\n{log}")
    return Session(work, json.loads(results_file.read_text()), log, version)


# every worker the collected tests need, run in the background --------------------------------------

_WORKERS = {}  # test file -> (worker module, write_inputs)
_POOL = None


def blender_fixture(worker, write_inputs=None, since=None):
    """The module-scoped fixture `blender` of a test module: one Session per Blender version (from
    `since`, a version label, when what it tests came with that version), its worker module run on a
    fresh folder that `write_inputs(folder)` (if given) filled first. The workers themselves start when
    collection ends (see WorkerPool); the fixture waits for its own."""
    _WORKERS[Path(inspect.stack()[1].filename).resolve()] = (worker, write_inputs)
    versions = [v for v in blender_envs.VERSIONS if since is None or _label(v) >= _label(since)]

    @pytest.fixture(scope="module", params=versions)
    def blender(request):
        return _POOL.session(worker, request.param)

    return blender


def _label(version):
    return tuple(int(x) for x in version.split("."))


class WorkerPool:
    """Runs the Blender workers of the collected tests, `width` at a time, while the tests that need no
    Blender run: each worker is a separate process that mostly waits for Blender, so the machine's
    cores stay busy. Sessions are handed out in the order the tests ask for them."""

    def __init__(self, jobs, base, zip_path, width):
        self.executor = ThreadPoolExecutor(max(1, width))
        self.futures = {}
        started = time.monotonic()
        for worker, version, write_inputs in jobs:
            work = base / f"{worker.rsplit('.', 1)[-1]}_{version}"
            work.mkdir(parents=True)
            if write_inputs is not None:
                write_inputs(work)
            self.futures[worker, version] = self.executor.submit(
                _run_or_reason, worker, work, zip_path, version, started
            )

    def session(self, worker, version):
        outcome = self.futures[worker, version].result()
        if isinstance(outcome, Session):
            return outcome
        kind, message = outcome
        (pytest.skip if kind == "skip" else pytest.fail)(message)

    def close(self):
        self.executor.shutdown(wait=False, cancel_futures=True)


_TIMES = {}  # (worker, version) -> (seconds it ran, seconds from the pool's start to its end)


def _run_or_reason(worker, work, zip_path, version, started):
    """run_worker in a pool thread: its Session, or ("skip" | "fail", why) for the tests to report."""
    begun = time.monotonic()
    try:
        return run_worker(worker, work, zip_path, version)
    except pytest.skip.Exception as exc:
        return "skip", str(exc)
    except BaseException as exc:  # noqa: BLE001 - reported by every test of that session
        return "fail", f"{type(exc).__name__}: {exc}"
    finally:
        _TIMES[worker, version] = (time.monotonic() - begun, time.monotonic() - started)


def worker_times(slowest=8):
    """Lines for the end of the test run: the Blender workers' total time and the slowest of them,
    so the suite's time budget shows where it goes."""
    if not _TIMES:
        return []
    ranked = sorted(_TIMES.items(), key=lambda item: -item[1][0])
    lines = [
        f"{len(_TIMES)} Blender workers: {sum(t for t, _ in _TIMES.values()):.0f} s in all, "
        f"the last done {max(end for _, end in _TIMES.values()):.0f} s after they started"
    ]
    lines += [f"{seconds:7.1f} s  {worker} [{version}]" for (worker, version), (seconds, _) in ranked[:slowest]]
    return lines


def blender_last(items):
    """Tests with a Blender worker after the others, so those run while the workers do."""
    items.sort(key=lambda item: Path(str(item.fspath)).resolve() in _WORKERS)


def start_workers(config, items):
    """Start every (worker, version) the selected tests use, in the order they will ask for them."""
    global _POOL
    jobs = []
    for item in items:
        entry = _WORKERS.get(Path(str(item.fspath)).resolve())
        callspec = getattr(item, "callspec", None)
        if entry is None or callspec is None or "blender" not in callspec.params:
            continue
        job = (entry[0], callspec.params["blender"], entry[1])
        if job[:2] not in [j[:2] for j in jobs]:
            jobs.append(job)
    if not jobs:
        return
    jobs = _pythons_in_turn(jobs)
    from helpers import build_extension_zip

    base = config._tmp_path_factory.mktemp("blender")  # pytest's own temporary folder
    zip_path = build_extension_zip(base)
    width = int(os.environ.get("SPLATWRIGHT_BLENDER_JOBS", min(2, os.cpu_count() or 1)))
    _POOL = WorkerPool(jobs, base, zip_path, width)


def _pythons_in_turn(jobs):
    """The jobs with versions of different Pythons taking turns, so that the workers running at once
    seldom compile the same kernels for the same Python: the first worker of each Python fills the
    kernel cache the later ones load (core/jit.py), instead of two compiling side by side."""
    queues = {}
    for job in jobs:
        queues.setdefault(blender_envs.VERSIONS[job[1]][0], []).append(job)
    turns = []
    while any(queues.values()):
        turns += [queue.pop(0) for queue in queues.values() if queue]
    return turns


def stop_workers():
    if _POOL is not None:
        _POOL.close()
