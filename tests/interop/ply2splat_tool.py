"""PyPI ply2splat (a Rust converter) turning a 3DGS PLY into antimatter15 .splat, in file order:
python ply2splat_tool.py in.ply out.splat"""

import sys

import ply2splat

ply2splat.convert(sys.argv[1], sys.argv[2], sort=False)
