"""PyPI plyfile (a general PLY library, nothing splat-specific) on .npz arrays of vertex properties:

python plyfile_tool.py read in.ply out.npz           (every vertex property by name, in file order,
                                                      and the file's format as "format")
python plyfile_tool.py write in.npz out.ply FORMAT   (the arrays as vertex properties, in their order;
                                                      FORMAT ascii, binary_little_endian or
                                                      binary_big_endian)
Several jobs run in one process when separated by "+".
"""

import sys

import numpy as np
from plyfile import PlyData, PlyElement

BYTE_ORDER = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}


def read(source, out):
    ply = PlyData.read(source)
    vertex = ply["vertex"]
    arrays = {p.name: np.asarray(vertex[p.name]) for p in vertex.properties}
    fmt = "ascii" if ply.text else {"<": "binary_little_endian", ">": "binary_big_endian"}[ply.byte_order]
    np.savez(out, format=fmt, names=[p.name for p in vertex.properties], **arrays)


def write(source, out, fmt):
    with np.load(source) as a:
        names = list(a.files)
        table = np.empty(len(a[names[0]]), dtype=[(n, a[n].dtype.newbyteorder(BYTE_ORDER[fmt])) for n in names])
        for n in names:
            table[n] = a[n]
    PlyData([PlyElement.describe(table, "vertex")], text=fmt == "ascii", byte_order=BYTE_ORDER[fmt]).write(out)


VERBS = {"read": read, "write": write}
args = sys.argv[1:]
while args:
    end = args.index("+") if "+" in args else len(args)
    verb, *rest = args[:end]
    args = args[end + 1 :]
    VERBS[verb](*rest)
