"""Test helpers shared by several test modules (tests/ is on sys.path)."""

import functools
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from workers.base import random_cloud_arrays

from splatwright.core import SplatCloud

REPO_ROOT = Path(__file__).resolve().parents[1]


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


def fetch_wheels():
    """Download the wheels the manifest bundles into wheels/ (kept there, git-ignored), as Blender's
    manual describes: `pip download --no-deps --only-binary=:all: --python-version V --platform P`.
    Skips the calling test with one line when PyPI cannot be reached."""
    manifest = tomllib.loads((REPO_ROOT / "blender_manifest.toml").read_text())
    for entry in manifest.get("wheels", []):
        path = REPO_ROOT / entry
        if path.exists():
            continue
        name, version, python = path.name.split("-")[:3]
        platform = path.stem.split("-")[-1].split(".")[-1]
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "--no-deps",
                "--only-binary=:all:",
                "--python-version",
                f"{python[2]}.{python[3:]}",
                "--platform",
                platform,
                "-d",
                str(path.parent),
                f"{name}=={version}",
            ],
            capture_output=True,
            text=True,
        )
        if not path.exists():
            if "Could not fetch" in done.stdout + done.stderr or "NewConnectionError" in done.stderr:
                pytest.skip(f"cannot reach PyPI to fetch the bundled wheel {path.name}")
            raise RuntimeError(f"pip download of {path.name} failed:\n{done.stdout}\n{done.stderr}")


def build_extension_zip(out_dir):
    """Build the Blender extension zip from the repository with `blender_ext.py build` (its bundled
    wheels fetched first); returns its path."""
    fetch_wheels()
    manifest = tomllib.loads((REPO_ROOT / "blender_manifest.toml").read_text())
    out = Path(out_dir) / f"{manifest['id']}-{manifest['version']}.zip"
    done = run_blender_ext("build", "--source-dir", REPO_ROOT, "--output-filepath", out)
    if done.returncode != 0 or not out.is_file():
        raise RuntimeError(f"blender_ext.py build failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return out


# independent references (textbook formulas in float64, none of the code under test) ------------------

PLATFORM_SKIP = "not on this platform: "  # CI fails any other skip (conftest.py)


def skip_platform(reason):
    """Skip for what this platform or Blender version cannot do (CI lets only these pass)."""
    pytest.skip(PLATFORM_SKIP + reason)


def read(path):
    """A splat file read through splatwright.io (each reader is tested against its format elsewhere)."""
    from splatwright.io import read_splats

    return read_splats(path)


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
