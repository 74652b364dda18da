"""The first renders after installing the extension zip, as a user meets them: a fresh Blender (a
bpy-only Python of tests/blender_envs.py, no numba but the zip's), the linux-x64 zip of `./run
package` just installed, an empty kernel cache (SPLATWRIGHT_CACHE_DIR), then F12 with the Splatwright
engine twice (tests/workers/first_render.py). The first render compiles the kernels into the cache;
the second, in the same session, reuses them. A second fresh Blender with the now filled cache shows
a later session's first render (kernels loaded from the cache, not compiled).

Scene: 100k random SH-3 splats (20k with --quick) imported from a PLY by the extension's importer,
640x480 (320x240). Wall seconds of one run each; the install time is in the extra column.
"""

import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(1, str(ROOT / "tests"))
from common import Row, Timing, print_rows  # noqa: E402

from splatwright.io import write_splats  # noqa: E402

TOPIC = "first_render"
BLENDERS = ("5.0", "5.3")  # Python 3.11 and 3.13: each compiles with its own bundled numba


def run(quick=False):
    import blender_envs
    from helpers import build_extension_zip, first_renders, random_cloud

    n, size = (20_000, (320, 240)) if quick else (100_000, (640, 480))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        zip_path = build_extension_zip(tmp / "dist")
        ply = tmp / "cloud.ply"
        write_splats(ply, random_cloud(n, spread=0.5))
        for version in BLENDERS:
            python = blender_envs.python_of(version)
            cache = tmp / f"cache-{version}"
            fresh = first_renders(python, zip_path, ply, tmp / f"fresh-{version}", 2, size, cache)
            later = first_renders(python, zip_path, ply, tmp / f"later-{version}", 1, size, cache)
            extra = {"backend": fresh["backend"], "install s": round(fresh["install_s"], 2)}
            cases = [
                ("first render after install (compiles)", fresh["render_s"][0]),
                ("second render, same session", fresh["render_s"][1]),
                ("first render of a later session (cached kernels)", later["render_s"][0]),
            ]
            for case, seconds in cases:
                rows.append(Row(TOPIC, f"Blender {version}: {case}", Timing(seconds, 0.0, 1), extra=extra))
    return rows


if __name__ == "__main__":
    print_rows(run(quick="--quick" in sys.argv))
