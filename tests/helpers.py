"""Test helpers shared by several test modules (tests/ is on sys.path)."""

import functools
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from workers.base import random_cloud_arrays

from splatwright.core import SplatCloud, jit

REPO_ROOT = Path(__file__).resolve().parents[1]

needs_numba = pytest.mark.skipif(
    importlib.util.find_spec("numba") is None or not jit.enabled(),
    reason="numba is not installed, or compiled kernels are turned off",
)


def random_cloud(n, sh_degree=3, seed=0, spread=1.0):
    """A random anisotropic cloud with every field populated and non-unit quaternions (the same
    values a Blender worker's random_cloud makes)."""
    return SplatCloud(**random_cloud_arrays(n, sh_degree, seed, spread))


@functools.cache
def blender_ext_script():
    """Blender's own extension tool, blender_ext.py, from the bpy module (looked up in a child
    process so the test process does not import bpy)."""
    scripts = (
        subprocess.run(
            [sys.executable, "-c", "import bpy; print(bpy.utils.system_resource('SCRIPTS'))"],
            capture_output=True,
            text=True,
            check=True,
        )
        .stdout.strip()
        .splitlines()[-1]
    )
    return Path(scripts) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"


def run_blender_ext(*args):
    """Run blender_ext.py with this Python; returns the CompletedProcess (text output)."""
    return subprocess.run(
        [sys.executable, str(blender_ext_script()), *map(str, args)], capture_output=True, text=True, timeout=300
    )


def _package_tool():
    """tools/package.py, which fetches the bundled wheels and builds the platform zips (`./run package`)."""
    spec = importlib.util.spec_from_file_location("splatwright_package_tool", REPO_ROOT / "tools" / "package.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


package_tool = functools.cache(_package_tool)


def fetch_wheels():
    """Download the wheels the manifest bundles into wheels/ (kept there, git-ignored) as `./run
    package` does; skips the calling test with one line when PyPI cannot be reached."""
    tool = package_tool()
    try:
        tool.fetch_wheels(quiet=True)
    except tool.NoNetwork as exc:
        pytest.skip(str(exc))


def build_extension_zips(out_dir):
    """Every platform's zip, built into out_dir as `./run package` builds them (Blender's split build,
    its wheels fetched first); {Blender platform: path}."""
    fetch_wheels()
    return package_tool().build(out_dir)


def build_extension_zip(out_dir):
    """The linux-x64 zip of the split build (the Blender matrix runs on Linux x86_64), built into
    out_dir; returns its path."""
    return build_extension_zips(out_dir)["linux-x64"]


def first_renders(python, zip_path, ply, work, renders=2, size=(320, 240), cache=None, env=None):
    """Install `zip_path` into a fresh user folder of the bpy-only `python` and F12-render `ply` with
    the Splatwright engine `renders` times (tests/workers/first_render.py); its results.json, with
    the first render's pixels as "pixels". `cache` is the kernel cache folder (default: a new one in
    `work`, empty: a first render after install)."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    job = {"zip": str(zip_path), "ply": str(ply), "work": str(work), "renders": renders, "size": list(size)}
    (work / "job.json").write_text(json.dumps(job))
    child_env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    child_env.update(BLENDER_USER_RESOURCES=str(work / "user"), SPLATWRIGHT_CACHE_DIR=str(cache or work / "cache"))
    child_env.update(env or {})
    script = Path(__file__).resolve().parent / "workers" / "first_render.py"
    done = subprocess.run(
        [str(python), str(script), str(work / "job.json")], env=child_env, capture_output=True, text=True, timeout=900
    )
    shutil.rmtree(work / "user", ignore_errors=True)  # the installed extension, ~300 MB with its wheels
    log = f"exit {done.returncode}\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    if not (work / "results.json").exists():
        raise RuntimeError(f"the first-render child wrote no results:\n{log}")
    results = json.loads((work / "results.json").read_text())
    if "error" in results:
        raise RuntimeError(f"the first-render child failed:\n{results['error']}\n{log}")
    results["pixels"] = np.load(work / "render.npy")
    return results


# independent references (textbook formulas in float64, none of the code under test) ------------------

PLATFORM_SKIP = "not on this platform: "  # CI fails any other skip (conftest.py)


def skip_platform(reason):
    """Skip for what this platform or Blender version cannot do (CI lets only these pass)."""
    pytest.skip(PLATFORM_SKIP + reason)


def read(path):
    """A splat file read through splatwright.io (each reader is tested against its format elsewhere)."""
    from splatwright.io import read_splats

    return read_splats(path)


def euler_matrix(euler):
    """Blender's XYZ Euler rotation: R = Rz Ry Rx."""
    x, y, z = euler
    rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return rz @ ry @ rx


def quat_matrices(q):
    """Rotation matrices of (w, x, y, z) quaternions of any length, float64."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def rebuilt_rotation_bound(unit, rebuilt, half_step):
    """The largest turn a quaternion stored as three components (each to within `half_step`) and one
    rebuilt from the unit norm can come back with, per splat: `unit` (N, 4), `rebuilt` (N,) the index
    of the rebuilt component (SPZ v2: w; smallest-three: the largest). The stored part moves by at most
    dv = sqrt(3) half_step and the rebuilt one by dw, most where it is small; the quaternion then moves
    by a chord e <= hypot(dv, dw), its direction by arcsin(e) and the rotation by twice that."""
    q = np.asarray(unit, np.float64)
    w = np.abs(q[np.arange(len(q)), rebuilt])
    v, dv = np.sqrt(np.maximum(1 - w * w, 0)), np.sqrt(3) * half_step
    dw = np.maximum(np.sqrt(1 - np.maximum(v - dv, 0) ** 2) - w, w - np.sqrt(np.maximum(1 - (v + dv) ** 2, 0)))
    return 2 * np.arcsin(np.minimum(np.hypot(dv, dw), 1.0)) + 1e-6


def covariances(rotations, log_scales):
    """Float64 R S S^T R^T straight from stored quaternions and log-scales."""
    rs = quat_matrices(rotations) * np.exp(np.asarray(log_scales, np.float64))[:, None, :]
    return rs @ rs.transpose(0, 2, 1)


def cloud_covariances(cloud):
    return covariances(cloud.rotations, cloud.log_scales)


def psnr(a, b):
    """Peak signal-to-noise ratio in dB of images with values in 0..1."""
    return 10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def srgb_to_linear(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


# comparing clouds ------------------------------------------------------------------------------------


def assert_clouds_equal(a, b):
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def check_transformed(source, result, matrix, sh_rotation=None):
    """`result` is `source` under the affine `matrix`: centres, covariances L Sigma L^T and (when the
    linear part is a rotation times a uniform scale, `sh_rotation`) the colour seen from every side."""
    from splatwright.core import sh as shmod

    lin, t = matrix[:3, :3], matrix[:3, 3]
    np.testing.assert_allclose(result.positions, source.positions.astype(np.float64) @ lin.T + t, atol=2e-5, rtol=1e-5)
    expected = lin @ cloud_covariances(source) @ lin.T
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
    assert (
        np.abs(cloud_covariances(result) - expected).max(initial=0) <= 0
        or np.max(np.abs(cloud_covariances(result) - expected) / scale) < 2e-5
    )
    np.testing.assert_allclose(result.opacity_logits, source.opacity_logits, rtol=0, atol=0)
    if sh_rotation is not None:
        dirs = np.random.default_rng(9).normal(size=(len(source), 3))
        np.testing.assert_allclose(
            shmod.colors(result.sh, dirs @ sh_rotation.T), shmod.colors(source.sh, dirs), atol=2e-5
        )


def format_errors(a, b):
    """Largest differences a format can make: centres, covariances (relative), opacity, colours."""
    from splatwright.core import sh as shmod

    dirs = np.random.default_rng(8).normal(size=(len(a), 3))
    cov_a, cov_b = cloud_covariances(a), cloud_covariances(b)
    degree = min(a.sh_degree, b.sh_degree)
    return {
        "positions": np.abs(a.positions - b.positions).max(),
        "covariance": np.max(np.abs(cov_a - cov_b).max(axis=(1, 2)) / np.abs(cov_b).max(axis=(1, 2))),
        "opacity": np.abs(a.opacities - b.opacities).max(),
        "colour": np.abs(
            shmod.colors(a.with_sh_degree(degree).sh, dirs) - shmod.colors(b.with_sh_degree(degree).sh, dirs)
        ).max(),
    }
