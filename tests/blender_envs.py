"""The Blender versions the extension is tested on, each a virtual environment holding only the `bpy`
module (headless Blender) and what its wheel depends on, as Blender's own Python has them: NumPy,
zstandard, and for 4.5+ Blender's bundled `pxr` inside the module. Nothing of ours is installed
there: the tests install the extension zip into each, as a user does.

Environments are made on first use and kept in .cache/blender/<version> (a stamp file records what
was installed, so a changed pin rebuilds them). Run as a script to make them all up front:

    python tests/blender_envs.py           one line per version: ready, built or skipped (and why)
"""

import glob
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / ".cache" / "blender"

# version label -> (Python minor version, pip requirements). NumPy is pinned where the bpy wheel leaves it
# open, to the version that Blender release bundles.
VERSIONS = {
    "4.2": ("3.11", ["bpy==4.2.23", "numpy==1.26.4"]),
    "4.5": ("3.11", ["bpy==4.5.15"]),
    "5.0": ("3.11", ["bpy==5.0.1"]),
    "5.1": ("3.13", ["bpy==5.1.2"]),
    "5.2": ("3.13", ["bpy==5.2.4"]),
    "5.3": ("3.13", ["bpy==5.3.0"]),
}
PRIMARY = "5.0"  # the version of the project's own environment (pyproject.toml's dev extra)


class Unavailable(Exception):
    """A version this machine cannot run: the Python it needs is missing. (A failed install is an
    error, not a reason to skip.)"""


def find_python(minor):
    """An interpreter of Python `minor` ("3.13"): this one, one on PATH, or one under pyenv; None if absent."""
    if f"{sys.version_info.major}.{sys.version_info.minor}" == minor:
        base = Path(sys._base_executable if hasattr(sys, "_base_executable") else sys.executable)
        return str(base)
    candidates = [shutil.which(f"python{minor}")]
    pyenv_root = os.environ.get("PYENV_ROOT", str(Path.home() / ".pyenv"))
    candidates += sorted(glob.glob(f"{pyenv_root}/versions/{minor}.*/bin/python{minor}"), reverse=True)
    candidates += [f"/usr/local/bin/python{minor}", f"/usr/bin/python{minor}"]
    for candidate in candidates:
        if candidate and os.access(candidate, os.X_OK):
            probe = subprocess.run(
                [candidate, "-c", "import sys, venv; print(sys.version_info[:2])"], capture_output=True, text=True
            )
            if probe.returncode == 0 and probe.stdout.strip() == str(tuple(map(int, minor.split(".")))):
                return candidate
    return None


def python_of(version):
    """The bpy-only environment's interpreter for `version`, made if needed; Unavailable says why not."""
    minor, requirements = VERSIONS[version]
    return make_env(version, minor, requirements, f"Blender {version}")


def make_env(name, minor, requirements, purpose):
    """The interpreter of the virtual environment .cache/blender/`name` of Python `minor` holding only
    `requirements`, made if needed (a stamp records what it holds); Unavailable if this machine lacks
    that Python, RuntimeError with the install log's tail if the install fails."""
    env = CACHE / name
    python = env / "bin" / "python"
    stamp = env / ".installed"
    want = " ".join(requirements)
    if python.exists() and stamp.exists() and stamp.read_text() == want:
        return str(python)
    base = find_python(minor)
    if base is None:
        raise Unavailable(f"{purpose} needs Python {minor}, which this machine lacks")
    shutil.rmtree(env, ignore_errors=True)
    env.parent.mkdir(parents=True, exist_ok=True)
    log = env.parent / f"{name}.log"
    with open(log, "w") as out:
        ok = (
            subprocess.run([base, "-m", "venv", str(env)], stdout=out, stderr=out).returncode == 0
            and subprocess.run(
                [str(python), "-m", "pip", "install", "--no-input", *requirements], stdout=out, stderr=out
            ).returncode
            == 0
        )
    if not ok:
        raise RuntimeError(f"installing {want} for {purpose} failed; the log is {log}:\n" + log.read_text()[-3000:])
    stamp.write_text(want)
    return str(python)


def prepare(versions=None):
    """Make every environment (two at a time: the installs are mostly downloads); returns
    {version: interpreter path or the Unavailable or RuntimeError that says why not}."""
    versions = list(versions or VERSIONS)

    def one(version):
        try:
            return python_of(version)
        except (Unavailable, RuntimeError) as exc:
            return exc

    with ThreadPoolExecutor(2) as pool:
        return dict(zip(versions, pool.map(one, versions)))


if __name__ == "__main__":
    for version, result in prepare().items():
        state = f"skipped: {result}" if isinstance(result, Exception) else f"ready ({result})"
        print(f"Blender {version}: {state}", flush=True)
