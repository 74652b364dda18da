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

NPM_PACKAGES = [
    "@playcanvas/splat-transform@3.10.2",
    "@adobe/spz@0.2.3",
    "spz-js@1.2.5",
    "@gltf-transform/core@4.5.1",
]
PYPI_TOOLS = {
    "gsply": ["gsply[spz,sogs]==0.4.6"],
    "nvidia": ["usd-convert-gsplat[usd]==0.1.15"],
    "ply2splat": ["ply2splat==0.6.0"],
    "plyfile": ["plyfile==1.1.5"],
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
    """The npm prefix holding splat-transform, @adobe/spz, spz-js and glTF Transform (installed once)."""
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


def node(driver, *args, cwd=None):
    """Run one of our node drivers (tests/interop/*.mjs) against the npm packages (relative paths
    from `cwd`)."""
    npm_prefix()
    return run(["node", DRIVERS / driver, *args], cwd=cwd)


def batch(*jobs):
    """Several jobs for one run of a driver (each a [verb, arguments...] list): one process start."""
    return [word for job in jobs for word in ["+", *job]][1:]


def batch_in(folders, *jobs):
    """The same jobs for each of `folders` (a "{}" in a word stands for the folder), as one batch."""
    return batch(*[[str(word).replace("{}", folder) for word in job] for folder in folders for job in jobs])


def python(tool, driver, *args, cwd=None):
    """Run one of our Python drivers (tests/interop/*.py), or `-m module`, in a tool's own environment
    (relative paths from `cwd`)."""
    script = [driver] if driver == "-m" else [DRIVERS / driver]
    return run([python_tool(tool), *script, *args], cwd=cwd)


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


def niantic_arrays(cloud):
    """A cloud as Niantic's GaussianCloud (@adobe/spz, and spz-js after it): the model's axes, xyzw
    quaternions, SH coefficient-major with the channel fastest."""
    n, k = len(cloud), cloud.sh.shape[1]
    return dict(
        numPoints=n,
        shDegree=cloud.sh_degree,
        positions=cloud.positions,
        scales=cloud.log_scales,
        rotations=cloud.rotations[:, [1, 2, 3, 0]],
        alphas=cloud.opacity_logits,
        colors=cloud.sh[:, 0],
        sh=cloud.sh[:, 1:].reshape(n, 3 * (k - 1)),
    )


def cloud_from_niantic(a):
    n, k = int(a["numPoints"]), (int(a["shDegree"]) + 1) ** 2
    xyzw = np.asarray(a["rotations"], np.float32).reshape(n, 4)
    sh = np.concatenate([np.reshape(a["colors"], (n, 1, 3)), np.reshape(a["sh"], (n, k - 1, 3))], axis=1)
    return SplatCloud(
        np.reshape(a["positions"], (n, 3)),
        xyzw[:, [3, 0, 1, 2]],
        np.reshape(a["scales"], (n, 3)),
        np.reshape(a["alphas"], n),
        sh,
    )


def ply_properties(cloud):
    """A cloud as the 3DGS PLY's vertex properties by name (f_rest channel-major), positions as
    doubles (exact: every float32 is one): what a general PLY library is given to write."""
    n, k = len(cloud), cloud.sh.shape[1]
    rest = cloud.sh[:, 1:].transpose(0, 2, 1).reshape(n, 3 * (k - 1))
    columns = {name: cloud.positions[:, i].astype(np.float64) for i, name in enumerate("xyz")}
    columns |= {f"f_dc_{c}": cloud.sh[:, 0, c] for c in range(3)}
    columns |= {f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])}
    columns["opacity"] = cloud.opacity_logits
    columns |= {f"scale_{i}": cloud.log_scales[:, i] for i in range(3)}
    columns |= {f"rot_{i}": cloud.rotations[:, i] for i in range(4)}
    return columns


def cloud_from_ply_properties(a):
    """The cloud a 3DGS PLY's vertex properties (by name) stand for."""
    stack = lambda names: np.column_stack([a[n] for n in names]).astype(np.float32)  # noqa: E731
    rest = sorted((n for n in a if n.startswith("f_rest_")), key=lambda n: int(n[7:]))
    n = len(a["x"])
    sh_rest = stack(rest).reshape(n, 3, len(rest) // 3).transpose(0, 2, 1) if rest else np.zeros((n, 0, 3), np.float32)
    sh = np.concatenate([stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :], sh_rest], axis=1)
    return SplatCloud(
        stack("xyz"),
        stack([f"rot_{i}" for i in range(4)]),
        stack([f"scale_{i}" for i in range(3)]),
        np.asarray(a["opacity"], np.float32),
        sh,
    )


def cloud_from_arrays(a):
    sh = np.concatenate([a["sh0"][:, None, :], a["shN"].reshape(len(a["sh0"]), -1, 3)], axis=1)
    return SplatCloud(a["means"], a["quats"], a["scales"], a["opacities"], sh)


def matched(got, want):
    """`got` in `want`'s order, each splat of `want` paired with the splat of `got` nearest its centre
    (tools reorder splats when they write: splat-transform and spz-js into Morton order). The pairing
    must be one to one; a wrong pair shows in the fields compared after it."""
    assert len(got) == len(want), f"{len(got)} splats for {len(want)}"
    a, b = got.positions.astype(np.float64), want.positions.astype(np.float64)
    order = np.concatenate(
        [((b[i : i + 1024, None, :] - a[None, :, :]) ** 2).sum(axis=2).argmin(axis=1) for i in range(0, len(b), 1024)]
    ).astype(int)
    assert len(np.unique(order)) == len(want), "splats do not pair up one to one"
    return got[order]


def assert_same_splats(got, want, position=1e-6, scale=1e-5, opacity=1e-4, sh=1e-5, angle_deg=0.01):
    """The same splats in any order (paired by `matched`), every field within the given absolute
    tolerances: centres, log-scales, opacities (1e-4 by default for the ends, which tools clamp
    differently: 0, 1e-7, sigmoid(-10)), SH coefficients, and rotations (the angle between them).
    The defaults are float32 round-off: two decodings of one file; a format's quantisation is passed
    in by the caller."""
    assert got.sh_degree == want.sh_degree, (got.sh_degree, want.sh_degree)
    got = matched(got, want)
    np.testing.assert_allclose(got.positions, want.positions, rtol=1e-6, atol=position, err_msg="positions")
    np.testing.assert_allclose(got.log_scales, want.log_scales, rtol=0, atol=scale, err_msg="log_scales")
    np.testing.assert_allclose(got.opacities, want.opacities, rtol=0, atol=opacity, err_msg="opacities")
    np.testing.assert_allclose(got.sh, want.sh, rtol=0, atol=sh, err_msg="sh")
    cos = np.abs((got.unit_rotations * want.unit_rotations).sum(axis=1))
    assert np.degrees(2 * np.arccos(np.clip(cos, 0, 1))).max() <= angle_deg, "rotations"
