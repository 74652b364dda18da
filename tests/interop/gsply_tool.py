"""PyPI gsply on .npz arrays (3DGS PLY values: means, log scales, w-first quats, logits, sh0, shN).

python gsply_tool.py write-spz in.npz out.spz VERSION
python gsply_tool.py write-ply|write-compressed in.npz out.ply
python gsply_tool.py read-spz|read-ply|read-sog in out.npz
python gsply_tool.py time-spz in.npz out.spz REPEAT [VERSION]   (the median of REPEAT writes
                                                                 after one untimed, in seconds)
Several jobs run in one process when separated by "+".
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


def time_spz(source, out, repeat, version=3):
    data, times = data_from(source), []
    for _ in range(int(repeat) + 1):
        start = time.perf_counter()
        spz.write_spz(out, data, version=int(version))
        times.append(time.perf_counter() - start)
    print(statistics.median(times[1:]))


VERBS = {
    "write-spz": lambda source, out, version: spz.write_spz(out, data_from(source), version=int(version)),
    "write-ply": lambda source, out: gsply.plywrite(out, data_from(source)),
    "write-compressed": lambda source, out: gsply.plywrite(out, data_from(source), compressed=True),
    "time-spz": time_spz,
    "read-spz": lambda source, out: save(spz.read_spz(source), out),
    "read-ply": lambda source, out: save(gsply.plyread(source), out),
    "read-sog": lambda source, out: save(gsply.sogread(source), out),
}
args = sys.argv[1:]
while args:
    end = args.index("+") if "+" in args else len(args)
    verb, *rest = args[:end]
    args = args[end + 1 :]
    VERBS[verb](*rest)
