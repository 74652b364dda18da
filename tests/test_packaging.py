"""The repository as a Blender extension (Blender's own blender_ext.py validates and builds it) and
as a Python package (no bpy where it is not needed; console script and `python -m`)."""

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO_ROOT, first_renders, package_tool, random_cloud, run_blender_ext

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


# The platforms Blender ships for, and the Pythons whose numba/llvmlite wheels each zip holds: the
# pinned numba and llvmlite publish no macOS x86_64 wheels and Windows arm64 ones for 3.13 alone.
PLATFORM_PYTHONS = {
    "windows-x64": {"cp311", "cp313"},
    "windows-arm64": {"cp313"},
    "macos-arm64": {"cp311", "cp313"},
    "macos-x64": {"cp311", "cp313"},
    "linux-x64": {"cp311", "cp313"},
}
UPLOAD_LIMIT = 300e6  # bytes extensions.blender.org takes in one upload (since May 2024)
PLATFORM_TAGS = {  # what a wheel's platform tag must look like in each zip
    "windows-x64": ("win_amd64",),
    "windows-arm64": ("win_arm64",),
    "macos-arm64": ("macosx_", "_arm64"),
    "macos-x64": ("macosx_", "_x86_64"),
    "linux-x64": ("manylinux_", "_x86_64"),
}


def test_one_zip_per_platform_named_as_blender_names_them(platform_zips):
    manifest = tomllib.loads((REPO_ROOT / "blender_manifest.toml").read_text())
    assert set(manifest["platforms"]) == set(PLATFORM_PYTHONS)
    assert {p: z.name for p, z in platform_zips.items()} == {
        p: f"splatwright-{manifest['version']}-{p.replace('-', '_')}.zip" for p in PLATFORM_PYTHONS
    }


@pytest.mark.parametrize("platform", sorted(PLATFORM_PYTHONS))
def test_each_platform_zip_holds_its_own_wheels_and_nothing_else(platform_zips, platform):
    path = platform_zips[platform]
    names = zipfile.ZipFile(path).namelist()
    wheels = [n for n in names if n.endswith(".whl")]
    tool = package_tool()
    pythons = {tool.wheel_tags(w)[2] for w in wheels}
    assert pythons == PLATFORM_PYTHONS[platform]
    for wheel in wheels:
        dist, version, python, tag = tool.wheel_tags(wheel)
        assert tag.startswith(PLATFORM_TAGS[platform][0]) and tag.endswith(PLATFORM_TAGS[platform][-1]), wheel
    by_python = {py: sorted(tool.wheel_tags(w)[0] for w in wheels if tool.wheel_tags(w)[2] == py) for py in pythons}
    assert all(dists == ["llvmlite", "numba"] for dists in by_python.values()), by_python
    assert tool.check_zip(path, platform) == []  # the manifest's wheels, its platform alone, no dev files
    assert path.stat().st_size < UPLOAD_LIMIT
    top = {n.split("/")[0] for n in names}
    assert not top & {"tests", "bench", "docs", "tools", "dist", ".venv", ".git", "run", "pyproject.toml"}
    assert [n for n in names if n.endswith(".md")] == ["README.md"]
    built = tomllib.loads(zipfile.ZipFile(path).read("blender_manifest.toml").decode())["build"]["generated"]
    assert built["platforms"] == [platform] and sorted(Path(w).name for w in built["wheels"]) == sorted(
        Path(w).name for w in wheels
    )
    done = run_blender_ext("validate", path)
    assert done.returncode == 0, done.stdout + done.stderr


def _without_wheels(zip_path, out):
    """A copy of `zip_path` with no numba/llvmlite wheels (as the macos-x64 zip, but installable
    here): the installed extension's kernels cannot load, so it renders on the NumPy path."""
    with zipfile.ZipFile(zip_path) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as target:
        for info in source.infolist():
            data = source.read(info)
            if info.filename.endswith(".whl"):
                continue
            if info.filename == "blender_manifest.toml":
                text = data.decode()  # the listed wheels dropped; the generated list left empty
                generated = text.index("[build.generated]")
                drop = lambda m: "wheels = []\n" if m.start() > generated else ""  # noqa: E731
                data = re.sub(r"^wheels = \[[^\]]*\]\n", drop, text, flags=re.M).encode()
            target.writestr(info, data)
    return out


def test_a_zip_whose_kernels_cannot_load_renders_the_same_image(extension_zip, tmp_path):
    """The F12 render of a fresh Blender (a bpy-only Python: no numba but the zip's) with the linux-x64
    zip installed runs the compiled kernels; the same extension without its wheels takes the NumPy path
    and gives the same image."""
    import blender_envs

    from splatwright.core import jit

    try:
        python = blender_envs.python_of(blender_envs.PRIMARY)
    except blender_envs.Unavailable as exc:
        pytest.skip(str(exc))
    ply = tmp_path / "cloud.ply"
    write_splats(ply, random_cloud(3000, spread=0.5))
    no_wheels = _without_wheels(extension_zip, tmp_path / "no_wheels.zip")
    assert not [n for n in zipfile.ZipFile(no_wheels).namelist() if n.endswith(".whl")]
    cache = jit.cache_dir()  # the user's kernel cache, which the Blender workers fill too
    compiled = first_renders(python, extension_zip, ply, tmp_path / "compiled", renders=1, cache=cache)
    numpy_path = first_renders(python, no_wheels, ply, tmp_path / "numpy", renders=1, cache=cache)
    assert compiled["backend"] == "compiled" and ".local" in compiled["numba"]
    assert numpy_path["backend"].startswith("unavailable") and numpy_path["numba"] is None
    assert numpy_path["pixels"][..., 3].max() > 0.5
    np.testing.assert_allclose(numpy_path["pixels"], compiled["pixels"], rtol=0, atol=2e-5)


def _bundled_versions(platform_tail):
    """{distribution: version} of the wheels the manifest bundles whose platform tag ends so."""
    tool = package_tool()
    wheels = tomllib.loads((REPO_ROOT / "blender_manifest.toml").read_text())["wheels"]
    return {tool.wheel_tags(w)[0]: tool.wheel_tags(w)[1] for w in wheels if w.endswith(platform_tail + ".whl")}


KERNEL_CHECK = """
import json, sys
import numpy as np
import numba
from kernels import missing_kernels
from splatwright.core import render, scenes
from splatwright.core.camera import Camera

cloud = scenes.seed_cube(points_per_edge=12, sigma=0.06, opacity=0.3)
camera = Camera.look_at((1.2, 0.8, 0.5), (0.0, 0.0, 3.0), width=96, height=80)
compiled = render.render(cloud, camera, backend="compiled")
numpy_path = render.render(cloud, camera, backend="numpy")
print(json.dumps({
    "numba": numba.__version__, "numpy": np.__version__, "missing": missing_kernels(),
    "alpha": float(compiled.alpha.max()),
    "difference": float(np.abs(compiled.color - numpy_path.color).max()),
}))
"""


@pytest.mark.parametrize("python, numpy_version", [("3.11", "1.26.4"), ("3.13", "2.3.5")])
def test_the_macos_x64_zips_numba_compiles_every_kernel(python, numpy_version, tmp_path):
    """The macOS x86_64 zip bundles an older numba than the other zips: the last that publishes
    wheels for it. macOS cannot run here, so that numba's Linux wheels stand in, in an environment of
    their own with the NumPy of Blender 4.2-5.0 (1.26) and the newest that numba accepts (2.3): every
    kernel compiles, and renders the NumPy path's image."""
    import blender_envs

    versions = _bundled_versions("macosx_10_15_x86_64")
    assert set(versions) == {"numba", "llvmlite"} and versions["numba"] != "0.68.1"
    requirements = [f"numpy=={numpy_version}", *(f"{d}=={v}" for d, v in sorted(versions.items()))]
    name = f"numba-{versions['numba']}-py{python}"
    try:
        interpreter = blender_envs.make_env(name, python, requirements, f"numba {versions['numba']}")
    except blender_envs.Unavailable as exc:
        pytest.skip(str(exc))
    (tmp_path / "splatwright").symlink_to(REPO_ROOT, target_is_directory=True)
    done = subprocess.run(
        [interpreter, "-c", KERNEL_CHECK],
        capture_output=True,
        text=True,
        timeout=900,
        env={
            **os.environ,
            "PYTHONPATH": f"{tmp_path}{os.pathsep}{REPO_ROOT / 'tests'}",
            "SPLATWRIGHT_CACHE_DIR": str(tmp_path / "cache"),
        },
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert (result["numba"], result["numpy"]) == (versions["numba"], numpy_version)
    assert result["missing"] == []
    assert result["alpha"] > 0.5 and result["difference"] < 2e-5


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
