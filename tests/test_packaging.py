"""The repository as a Blender extension (Blender's own blender_ext.py validates and builds it) and
as a Python package (no bpy where it is not needed; console script and `python -m`)."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

from helpers import REPO_ROOT, run_blender_ext

from splatwright.core.scenes import seed_cube
from splatwright.io import write_splats


def run_python(code, cwd):
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, cwd=cwd, timeout=120
    )


def test_blender_ext_offers_validate_and_build():
    top = run_blender_ext("--help")
    assert top.returncode == 0, top.stderr
    assert "validate" in top.stdout and "build" in top.stdout
    build = run_blender_ext("build", "--help")
    assert build.returncode == 0 and "--source-dir" in build.stdout and "--output-filepath" in build.stdout
    validate = run_blender_ext("validate", "--help")
    assert validate.returncode == 0 and "SOURCE_PATH" in validate.stdout


def test_manifest_validates():
    done = run_blender_ext("validate", REPO_ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Success" in done.stdout


def test_built_zip_validates_and_leaves_out_dev_files(extension_zip):
    done = run_blender_ext("validate", extension_zip)
    assert done.returncode == 0, done.stdout + done.stderr
    names = zipfile.ZipFile(extension_zip).namelist()
    for needed in ("blender_manifest.toml", "__init__.py", "cli.py", "core/splats.py", "io/ply.py", "io/common.py"):
        assert needed in names
    top = {n.split("/")[0] for n in names}
    assert not top & {"tests", "bench", "docs", ".ci", ".venv", ".git", "run", "pyproject.toml", "out", "build"}
    assert not [n for n in names if "__pycache__" in n or ".egg-info" in n or "/." in "/" + n]


def test_core_and_io_work_without_bpy(tmp_path):
    """In a fresh interpreter where bpy cannot even be imported, the NumPy side reads and writes PLY
    and never touches bpy (or pxr, which core must not need)."""
    done = run_python(
        """
        import sys

        class NoBpy:
            def find_spec(self, name, path=None, target=None):
                if name == "bpy" or name.startswith("bpy."):
                    raise ImportError("bpy is blocked in this test")
                return None
        sys.meta_path.insert(0, NoBpy())

        import splatwright.core
        assert "pxr" not in sys.modules, "splatwright.core imported pxr"
        import splatwright.io
        from splatwright.core.scenes import seed_cube
        from splatwright.io import read_splats, write_splats
        write_splats("cube.ply", seed_cube())
        cloud = read_splats("cube.ply")
        assert len(cloud) == 1000, len(cloud)
        bad = sorted(m for m in sys.modules if m == "bpy" or m.startswith(("bpy.", "splatwright.splat_addon")))
        assert not bad, bad
        print("ok")
    """,
        cwd=tmp_path,
    )
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stdout + done.stderr


def test_console_script_and_python_dash_m(tmp_path):
    script = shutil.which("splatwright", path=str(Path(sys.executable).parent)) or shutil.which("splatwright")
    assert script, "the splatwright console script is not installed"
    env = dict(os.environ, PYTHONPATH="")
    write_splats(tmp_path / "cube.ply", seed_cube())
    for command in ([script], [sys.executable, "-m", "splatwright"]):
        done = subprocess.run([*command, "--help"], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
        assert done.returncode == 0, done.stderr
        assert "info" in done.stdout and "convert" in done.stdout and "demo" in done.stdout
        info = subprocess.run(
            [*command, "info", "cube.ply", "--json"], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120
        )
        assert info.returncode == 0, info.stderr
        assert json.loads(info.stdout)["count"] == 1000


def test_installed_extension_renders_with_its_bundled_numba(extension_zip, tmp_path):
    """Blender installs the numba/llvmlite wheels the manifest bundles for its Python; the installed
    extension's compiled kernels load from them and cache outside the extension's folder, where the
    same extension installed into another folder finds them compiled. (Blender puts the wheels' folder
    first on sys.path; the bpy module appends it after this venv, which has numba too, so the child
    moves it first.)"""
    names = zipfile.ZipFile(extension_zip).namelist()
    assert any(n.startswith("wheels/numba-") and "cp311" in n for n in names)
    compiled = []
    for user in ("user", "user_again"):
        env = {
            **os.environ,
            "BLENDER_USER_RESOURCES": str(tmp_path / user),
            "SPLATWRIGHT_CACHE_DIR": str(tmp_path / "cache"),
        }
        done = subprocess.run(
            [
                sys.executable,
                "-c",
                textwrap.dedent(f"""
            import importlib, sys, bpy
            import numpy as np
            bpy.ops.extensions.package_install_files(filepath={str(extension_zip)!r}, repo="user_default",
                                                     enable_on_install=True)
            sys.path.sort(key=lambda p: ".local" not in p)
            render = importlib.import_module("bl_ext.user_default.splatwright.core.render")
            import numba
            print(render.backend_status())          # loads the kernels (from the cache, if there)
            print(numba.__file__)
            kernels = importlib.import_module("bl_ext.user_default.splatwright.core.render_kernels")
            geometry = importlib.import_module("bl_ext.user_default.splatwright.core.geometry")
            geometry.polar_rotation(np.eye(3)[None])
            kernels = [*vars(kernels).values(), geometry._polar_loop]
            print(sum(len(f.stats.cache_misses) for f in kernels if hasattr(f, "stats")))
        """),
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
        status, numba_file, misses = done.stdout.strip().splitlines()[-3:]
        assert status == "compiled"
        assert str(tmp_path / user) in numba_file and ".local" in numba_file  # the bundled wheel
        compiled.append(int(misses))
    assert list((tmp_path / "cache").rglob("render_kernels.*.nbi"))
    assert compiled[0] > 0 and compiled[1] == 0  # compiled by the first install only
    # the same source imported as splatwright (pip) has kernels of its own beside the extension's
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            textwrap.dedent("""
        import numpy as np
        from splatwright.core import geometry
        r = geometry.polar_rotation(np.diag([2.0, 1.0, -1.0])[None])
        print(np.abs(r[0] - np.diag([1.0, 1.0, -1.0])).max(), len(geometry._polar_loop.stats.cache_misses))
    """),
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "SPLATWRIGHT_CACHE_DIR": str(tmp_path / "cache")},
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    error, misses = done.stdout.split()
    assert float(error) < 1e-12 and int(misses) == 1
