"""Build the Blender extension: one zip per platform of blender_manifest.toml, into dist/.

    ./run package              fetch the wheels the manifest lists (once; kept in wheels/), then build
    ./run package --out DIR    the zips go to DIR instead of dist/

The manifest is the one source: its `wheels` name numba and llvmlite by version, Python and platform tag,
and its `platforms` the zips. Missing wheels are fetched from PyPI with
`pip download --no-deps --only-binary=:all: --python-version V --platform TAG name==version`; Blender's
own `blender_ext.py build --split-platforms` (from the bpy module) then writes one zip per platform,
named as Blender names them (<id>-<version>-<platform>.zip), each holding only the wheels of its
platform. Each zip is checked after the build (check_zip) and its size printed.
"""

import argparse
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "blender_manifest.toml"
PYTHONS = ("cp311", "cp313")  # Blender 4.2-5.0 and 5.1+
# A wheel's platform tag -> the Blender platform it serves (blender_ext.py maps them the same way).
WHEEL_PLATFORMS = {"win_amd64": "windows-x64", "win_arm64": "windows-arm64", "x86_64": "linux-x64"}
DEV_TOP = {"tests", "bench", "docs", "tools", "dist", "out", "build", "run", "pyproject.toml"}


class NoNetwork(RuntimeError):
    """PyPI could not be reached to fetch a wheel."""


def manifest():
    return tomllib.loads(MANIFEST.read_text())


def wheel_tags(name):
    """(distribution, version, python tag, platform tag) of a wheel file name; the platform tag is the
    last of a compressed set (manylinux_2_27_x86_64.manylinux_2_28_x86_64 -> manylinux_2_28_x86_64)."""
    dist, version, python, _abi, platform = Path(name).stem.split("-")[:5]
    return dist, version, python, platform.split(".")[-1]


def blender_platform(wheel_name):
    """The Blender platform ("macos-arm64", "linux-x64", ...) a wheel file is built for."""
    platform = wheel_tags(wheel_name)[3]
    if platform.startswith("macosx_"):
        return "macos-" + ("x64" if platform.endswith("x86_64") else platform.rpartition("_")[2])
    for tail, blender in WHEEL_PLATFORMS.items():
        if platform.endswith(tail):
            return blender
    raise ValueError(f"no Blender platform for the wheel {wheel_name}")


def fetch_wheels(quiet=False):
    """Download every wheel the manifest lists that wheels/ lacks; raises NoNetwork when PyPI cannot
    be reached, RuntimeError when pip finds no such wheel."""
    for entry in manifest().get("wheels", []):
        path = ROOT / entry
        if path.exists():
            continue
        dist, version, python, platform = wheel_tags(path.name)
        if not quiet:
            print(f"fetching {path.name}", flush=True)
        command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
        command += ["--python-version", f"{python[2]}.{python[3:]}", "--platform", platform]
        command += ["-d", str(path.parent), f"{dist}=={version}"]
        done = subprocess.run(command, capture_output=True, text=True)
        if not path.exists():
            log = done.stdout + done.stderr
            if "Could not fetch" in log or "NewConnectionError" in log or "Network is unreachable" in log:
                raise NoNetwork(f"cannot reach PyPI to fetch the bundled wheel {path.name}")
            raise RuntimeError(f"pip download of {path.name} failed:\n{log}")


def blender_ext_script():
    """Blender's extension tool, blender_ext.py, from the bpy module (looked up in a child process, so
    this one need not import bpy)."""
    code = "import bpy; print(bpy.utils.system_resource('SCRIPTS'))"
    scripts = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return Path(scripts.stdout.strip().splitlines()[-1]) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"


def zip_names(out_dir):
    """{Blender platform: the zip blender_ext.py's split build writes for it into out_dir}."""
    data = manifest()
    stem = f"{data['id']}-{data['version']}"
    return {p: Path(out_dir) / f"{stem}-{p.replace('-', '_')}.zip" for p in data["platforms"]}


def build(out_dir):
    """Build one zip per platform into out_dir (the wheels fetched first); {platform: path}."""
    fetch_wheels()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, str(blender_ext_script()), "build", "--split-platforms"]
    command += ["--source-dir", str(ROOT), "--output-dir", str(out_dir)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    zips = zip_names(out_dir)
    if done.returncode != 0 or not all(p.is_file() for p in zips.values()):
        raise RuntimeError(f"blender_ext.py build failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return zips


def expected_wheels(platform):
    """The wheel file names the manifest lists for `platform`."""
    return sorted(Path(w).name for w in manifest().get("wheels", []) if blender_platform(w) == platform)


def check_zip(path, platform):
    """What is wrong with the zip built for `platform` (empty when nothing): its wheels must be exactly
    the manifest's for that platform, its manifest must name that platform alone, and nothing a user
    does not need (tests, bench, docs, tools, the wheel cache, caches) may be inside."""
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        built = tomllib.loads(archive.read("blender_manifest.toml").decode())
    problems = []
    wheels = sorted(Path(n).name for n in names if n.endswith(".whl"))
    if wheels != expected_wheels(platform):
        problems.append(f"wheels {wheels}, expected {expected_wheels(platform)}")
    if [n for n in names if n.endswith(".whl") and not n.startswith("wheels/")]:
        problems.append("a wheel outside wheels/")
    foreign = [w for w in wheels if blender_platform(w) != platform]
    if foreign:
        problems.append(f"wheels of other platforms: {foreign}")
    generated = built.get("build", {}).get("generated", {})
    if generated.get("platforms") != [platform]:
        problems.append(f"generated platforms {generated.get('platforms')}, expected [{platform!r}]")
    dev = sorted({n.split("/")[0] for n in names} & DEV_TOP)
    if dev:
        problems.append(f"development files: {dev}")
    junk = [n for n in names if "__pycache__" in n or ".egg-info" in n or "/." in "/" + n]
    if junk:
        problems.append(f"caches or hidden files: {junk[:5]}")
    docs = [n for n in names if n.endswith((".md", ".rst", ".txt")) and n != "README.md"]
    if docs:
        problems.append(f"documents beyond README.md: {docs[:5]}")
    return problems


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "dist"), help="folder for the zips (default: dist/)")
    args = parser.parse_args(argv)
    try:
        zips = build(args.out)
    except NoNetwork as exc:
        sys.exit(f"error: {exc}")
    failed = False
    for platform, path in zips.items():
        problems = check_zip(path, platform)
        pythons = sorted({wheel_tags(w)[2] for w in expected_wheels(platform)}) or ["none: NumPy path"]
        print(f"{path}  {path.stat().st_size / 1e6:6.1f} MB  wheels for {', '.join(pythons)}")
        for problem in problems:
            print(f"  error: {problem}")
        failed |= bool(problems)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
