"""The main job: everything Splatwright does, on the built-in demo scene, into one folder."""

import time
from pathlib import Path

from .core.scenes import seed_cube
from .io import write_splats


def run_demo(out_dir, progress=None):
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    cloud = seed_cube()
    path = out / "seed_cube.ply"
    write_splats(path, cloud)
    if progress:
        progress(1, 1, "seed cube")
    print(f"wrote {len(cloud)} splats to {path} in {time.perf_counter() - start:.2f} s")
    print(f"outputs: {out.resolve()}")
    return 0
