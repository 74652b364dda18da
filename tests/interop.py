"""The peer tools the interop tests run, installed from their registries on first use.

Each tool lives in its own environment under `.cache/interop/` (gitignored): npm packages in one
prefix, each PyPI tool in its own virtual environment, so their dependencies (NumPy 2, numba, ...)
never meet ours. An install that fails because the registry cannot be reached skips the test with
one line saying so; any other failure fails it. Drivers that speak to the tools are in
tests/interop/ and exchange plain arrays (.npz) with the tests.
"""

import functools
import json
import os
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from splatwright.core import SplatCloud

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / ".cache" / "interop"
DRIVERS = Path(__file__).resolve().parent / "interop"

NPM_PACKAGES = ["@playcanvas/splat-transform@2.7.1", "@adobe/spz@0.2.3", "@gltf-transform/core@4.5.1"]
PYPI_TOOLS = {
    "gsply": ["gsply[spz,sogs]==0.4.6"],
    "nvidia": ["usd-convert-gsplat[usd]==0.1.15"],
    "ply2splat": ["ply2splat==0.6.0"],
}
REGISTRIES = {"npm": "https://registry.npmjs.org/", "pypi": "https://pypi.org/simple/pip/"}


def _reachable(registry):
    try:
        with urllib.request.urlopen(REGISTRIES[registry], timeout=15):
            return True
    except Exception:  # noqa: BLE001 - any failure to connect means unreachable
        return False


def _install(registry, what, command, done_marker):
    """Run an install command once (a marker file records success)."""
    if done_marker.exists():
        return
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=900)
    except subprocess.TimeoutExpired:
        result = None
    if result is None or result.returncode:
        if not _reachable(registry):
            pytest.skip(f"{registry} registry unreachable: cannot install {what}")
        detail = "timed out" if result is None else (result.stderr or result.stdout)[-2000:]
        pytest.fail(f"installing {what} failed: {detail}")
    done_marker.write_text(json.dumps(command))


@functools.cache
def npm_prefix():
    """The npm prefix holding splat-transform, @adobe/spz and glTF Transform (installed once)."""
    if not (shutil.which("node") and shutil.which("npm")):
        pytest.skip("node and npm are needed for the npm peer tools")
    prefix = CACHE / "npm"
    prefix.mkdir(parents=True, exist_ok=True)
    marker = prefix / (".installed-" + "_".join(p.replace("/", "+") for p in NPM_PACKAGES))
    _install(
        "npm",
        ", ".join(NPM_PACKAGES),
        ["npm", "install", "--prefix", str(prefix), "--no-audit", "--no-fund", "--no-save", *NPM_PACKAGES],
        marker,
    )
    return prefix


@functools.cache
def python_tool(name):
    """The Python executable of the virtual environment holding PyPI tool `name` (installed once)."""
    env = CACHE / f"venv-{name}"
    marker = env / (".installed-" + "_".join(PYPI_TOOLS[name]).replace("/", "+"))
    python = env / "bin" / "python"
    if not marker.exists():
        if not python.exists():
            subprocess.run([sys.executable, "-m", "venv", "--clear", str(env)], check=True, capture_output=True)
        _install(
            "pypi",
            " ".join(PYPI_TOOLS[name]),
            [str(python), "-m", "pip", "install", "--disable-pip-version-check", "-q", *PYPI_TOOLS[name]],
            marker,
        )
    return python


def run(command, timeout=300, cwd=None):
    """Run a tool; a failure shows its output."""
    done = subprocess.run(
        [str(c) for c in command],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        env={**os.environ, "INTEROP_NODE_MODULES": str(CACHE / "npm" / "node_modules")},
    )
    assert done.returncode == 0, (
        f"{command[0]} failed ({done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    )
    return done.stdout


def splat_transform(*args):
    """Run PlayCanvas splat-transform (CPU only, overwriting outputs)."""
    cli = npm_prefix() / "node_modules" / ".bin" / "splat-transform"
    return run([cli, "-q", "-w", *args])


def node(driver, *args):
    """Run one of our node drivers (tests/interop/*.mjs) against the npm packages."""
    npm_prefix()
    return run(["node", DRIVERS / driver, *args])


def python(tool, driver, *args):
    """Run one of our Python drivers (tests/interop/*.py), or `-m module`, in a tool's own environment."""
    script = [driver] if driver == "-m" else [DRIVERS / driver]
    return run([python_tool(tool), *script, *args])


# the arrays the drivers exchange: the model's fields, in the tool's own conventions ------------------


def save_arrays(path, **arrays):
    np.savez(path, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})


def load_arrays(path):
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def save_json(path, **arrays):
    """Arrays as JSON lists (exact for float32: every float32 is a double) for the node drivers."""
    Path(path).write_text(json.dumps({k: np.asarray(v).tolist() for k, v in arrays.items()}))


def load_json(path):
    return {k: np.asarray(v) if isinstance(v, list) else v for k, v in json.loads(Path(path).read_text()).items()}


def ply_arrays(cloud):
    """A cloud as 3DGS PLY values: means, log scales, w-first quaternions, logits, DC, higher SH
    (N, K-1, 3) coefficient-major."""
    return {
        "means": cloud.positions,
        "scales": cloud.log_scales,
        "quats": cloud.rotations,
        "opacities": cloud.opacity_logits,
        "sh0": cloud.sh[:, 0],
        "shN": cloud.sh[:, 1:],
    }


def cloud_from_arrays(a):
    sh = np.concatenate([a["sh0"][:, None, :], a["shN"].reshape(len(a["sh0"]), -1, 3)], axis=1)
    return SplatCloud(a["means"], a["quats"], a["scales"], a["opacities"], sh)


def matched(got, want):
    """`got` reordered to `want`'s order by nearest centre (tools that sort splats, e.g. into
    Morton order); every splat must find a distinct partner."""
    d = ((got.positions[None, :, :].astype(np.float64) - want.positions[:, None, :]) ** 2).sum(axis=2)
    order = np.argmin(d, axis=1)
    assert len(np.unique(order)) == len(want), "splats do not pair up one to one"
    return got[order]
