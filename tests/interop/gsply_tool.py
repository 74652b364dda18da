"""PyPI gsply on .npz arrays (3DGS PLY values: means, log scales, w-first quats, logits, sh0, shN).

python gsply_tool.py write-spz in.npz out.spz VERSION
python gsply_tool.py write-compressed in.npz out.compressed.ply
python gsply_tool.py read-spz|read-ply|read-sog in out.npz
python gsply_tool.py time-spz in.npz out.spz REPEAT [VERSION]   (the median of REPEAT writes
                                                                 after one untimed, in seconds)
"""

import statistics
import sys
import time

import gsply
import numpy as np
from gsply import spz


def data_from(path):
    with np.load(path) as a:
        return gsply.GSData(
            means=a["means"],
            scales=a["scales"],
            quats=a["quats"],
            opacities=a["opacities"],
            sh0=a["sh0"],
            shN=a["shN"] if a["shN"].size else None,
        )


def save(data, path):
    n = len(data.means)
    shn = np.zeros((n, 0, 3), np.float32) if data.shN is None else np.asarray(data.shN).reshape(n, -1, 3)
    np.savez(
        path, means=data.means, scales=data.scales, quats=data.quats, opacities=data.opacities, sh0=data.sh0, shN=shn
    )


verb, args = sys.argv[1], sys.argv[2:]
if verb == "write-spz":
    spz.write_spz(args[1], data_from(args[0]), version=int(args[2]))
elif verb == "write-compressed":
    gsply.plywrite(args[1], data_from(args[0]), compressed=True)
elif verb == "time-spz":
    data, times = data_from(args[0]), []
    for _ in range(int(args[2]) + 1):
        start = time.perf_counter()
        spz.write_spz(args[1], data, version=int(args[3]) if len(args) > 3 else 3)
        times.append(time.perf_counter() - start)
    print(statistics.median(times[1:]))
elif verb == "read-spz":
    save(spz.read_spz(args[0]), args[1])
elif verb == "read-ply":
    save(gsply.plyread(args[0]), args[1])
elif verb == "read-sog":
    save(gsply.sogread(args[0]), args[1])
else:
    raise SystemExit(f"unknown verb {verb}")
