"""PLY read/write speed for a 1M-splat degree-3 cloud against raw np.fromfile / tofile of the very
same bytes (the floor any PLY reader or writer could reach) and, for writing, against gsply (a peer
writer timed in the same process: from the GSData it read, its fastest case, and from arrays as we
write from a SplatCloud), with the error each buys (none: both directions are exact). Our files
carry the reference layout's zero normals, 5% more bytes than gsply's. Our write ends with an fsync
before its rename (the file is on the disk before it replaces the old one), so the write rows are
given once more against baselines followed by the same fsync."""

import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from common import Row, fresh_file, machine, paired, print_rows  # noqa: E402
from helpers import random_cloud  # noqa: E402

from splatwright.io import ply  # noqa: E402


def _max_error(a, b):
    return max(
        float(np.abs(getattr(a, f).astype(np.float64) - getattr(b, f)).max())
        for f in ("positions", "rotations", "log_scales", "opacity_logits", "sh")
    )


def run(quick=False):
    n = 100_000 if quick else 1_000_000
    repeat = 3 if quick else 7
    cloud = random_cloud(n, sh_degree=3, seed=0)
    tmp = Path(tempfile.mkdtemp(prefix="splatwright-bench-ply-"))
    try:
        path = tmp / "cloud.ply"
        ply.write(path, cloud)
        raw = np.fromfile(path, np.uint8)
        size = f"{len(raw) / 2**20:.0f} MiB"

        read_base, read_ours = paired(lambda: np.fromfile(path, np.uint8), lambda: ply.read(path), repeat)
        back = ply.read(path)
        write_base, write_ours = paired(
            fresh_file(tmp / "raw.bin", raw.tofile), fresh_file(tmp / "out.ply", lambda p: ply.write(p, back)), repeat
        )
        durable_base, durable_ours = paired(
            fresh_file(tmp / "raw.bin", lambda p: (raw.tofile(p), _fsync(p))),
            fresh_file(tmp / "out.ply", lambda p: ply.write(p, back)),
            repeat,
        )
        same_bytes = (tmp / "out.ply").read_bytes() == path.read_bytes()
        written_error = _max_error(ply.read(tmp / "out.ply"), cloud)
        gsply_rows = _against_gsply(tmp, path, back, repeat)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    case = f"{n:,} splats, SH degree 3, {size}"
    return [
        Row(
            "ply",
            f"read {case}",
            read_ours,
            read_base,
            error={"max_abs_error": _max_error(back, cloud)},
            extra={
                "baseline": "np.fromfile",
                "slowdown": f"{read_ours.median / read_base.median:.2f}x",
                "threads": ply.WORKERS,
            },
        ),
        Row(
            "ply",
            f"write {case}",
            write_ours,
            write_base,
            error={"max_abs_error": written_error},
            extra={
                "baseline": "ndarray.tofile",
                "bytes_identical": same_bytes,
                "slowdown": f"{write_ours.median / write_base.median:.2f}x",
                "threads": ply.WORKERS,
            },
        ),
        Row(
            "ply",
            f"write {case}, against tofile then fsync (as ours ends)",
            durable_ours,
            durable_base,
            error={"max_abs_error": written_error},
            extra={
                "baseline": "ndarray.tofile + os.fsync",
                "slowdown": f"{durable_ours.median / durable_base.median:.2f}x",
                "threads": ply.WORKERS,
            },
        ),
    ] + gsply_rows


def _fsync(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _against_gsply(tmp, path, cloud, repeat):
    """Our write against gsply's (target: at least as fast), both timed in this process. Ours ends
    with an fsync before its rename (io.common.atomic_write: the file is on the disk before it
    replaces the old one), which makes a large write as slow as the disk; gsply's does not, so
    the last row gives gsply the same fsync."""
    import gsply

    data = gsply.plyread(str(path))
    arrays = dict(
        scales=cloud.log_scales,
        quats=cloud.rotations,
        opacities=cloud.opacity_logits,
        sh0=np.ascontiguousarray(cloud.sh[:, 0]),
        shN=np.ascontiguousarray(cloud.sh[:, 1:]),
    )
    rows = []
    for label, theirs in [
        ("its GSData (zero-copy)", lambda p: gsply.plywrite(str(p), data)),
        ("arrays", lambda p: gsply.plywrite(str(p), cloud.positions, **arrays)),
        ("its GSData, then fsync as ours does", lambda p: (gsply.plywrite(str(p), data), _fsync(p))),
    ]:
        base, ours = paired(
            fresh_file(tmp / "gsply.ply", theirs), fresh_file(tmp / "ours.ply", lambda p: ply.write(p, cloud)), repeat
        )
        check = gsply.plyread(str(tmp / "ours.ply"))  # gsply reads what we wrote
        error = float(np.abs(np.asarray(check.means) - cloud.positions).max())
        rows.append(
            Row(
                "ply",
                f"write {len(cloud):,} splats SH 3 against gsply {gsply.__version__} from {label}",
                ours,
                base,
                error={"max_abs_error": error},
                extra={"baseline": f"gsply.plywrite from {label}", "target": ">= 1x"},
            )
        )
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
