"""XGRIDS LCC2 (`.lcc2`, as XGRIDS's white paper describes version 0.0.3, and the older field
names), read only.

The `.lcc2` file is JSON: a tree of nodes under `root`, whose `splatFiles` lists the chunk files
(relative to the `.lcc2`'s folder; `splatType` says ".sog" bundles, the default, or ".spz"):
    {"totalLevels": L, "splatType": ".sog", "root": {"splatFiles": [...],
        "data": {"env": {"name": i}} (optional: environment splats, e.g. the sky),
        "child": [node, ...] or {"0": node, ...}}}
    node: {"data": {"3dgs": {"name": file index, "start": first splat, "count": splats}},
           "child": ...}
A node at depth d (the root's children at 1) holds its region at level L - d: the leaves hold the
finest level, 0. Older files name the fields `lod_level`, `total_splats`, `lod_3dgs_info` and
`root.files` (chunk names without their ".sog"). The scene is Z up: it is read turned into the PLY's
axes by a quarter turn about X, as splat-transform reads it (SPZ chunks' values taken as stored, in
the scene's axes, not SPZ's own). Chunks are read by io/sog.py and
io/spz.py through io.policy.referenced_file, as streamed SOG's units are (io/sog_streamed.py).
"""

import functools
import os
from collections.abc import Sequence

import numpy as np

from ..core import SplatCloud
from . import sog, spz
from .common import SplatFileError, apply_nonfinite_policy, check_nonfinite_policy, warn_notes
from .sog_streamed import Units, chosen_levels, level_cloud, read_index, whole_number

# SPZ chunks hold the scene's values as they are (not SPZ's RUB axes): read unturned, as splat-transform
# reads them
CHUNK_READERS = {".sog": {".sog": sog.read}, ".spz": {".spz": functools.partial(spz.read, axes=None)}}
# LCC2's Z-up scene axes -> the PLY's (y down, z forward): a quarter turn about X
TO_PLY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def read(
    path: str | os.PathLike,
    levels: str | int | Sequence[int] = "finest",
    environment: bool = True,
    allow_outside: bool = False,
    nonfinite: str = "raise",
) -> SplatCloud:
    """Read an LCC2 scene into one SplatCloud; `levels`, `environment` and `allow_outside` as for
    streamed SOG (sog_streamed.read): "finest" (level 0), "all", a level or a list of them."""
    check_nonfinite_policy(nonfinite)
    meta = _meta(path, read_index(path, ".lcc2"))
    root, total = meta["root"], meta["totalLevels"]
    kind = meta.get("splatType", ".sog")
    if not isinstance(kind, str) or kind not in CHUNK_READERS:
        raise SplatFileError(path, f"splatType '{kind}'; this reader takes .sog and .spz chunks")
    data = root.get("data") or {}
    env = data.get("env") if isinstance(data, dict) else None
    env_file = env.get("name") if isinstance(env, dict) else None
    units = Units(path, root["splatFiles"], allow_outside, CHUNK_READERS[kind], f"a {kind} file")
    refs = _references(path, root, total, env_file)
    clouds = [level_cloud(path, units, refs.get(level, [])) for level in chosen_levels(path, levels, total)]
    if environment and env_file is not None:
        if not whole_number(env_file) or env_file >= len(units.names):
            raise SplatFileError(path, f"the environment names no file of its {len(units.names)}")
        clouds.append(units.read(env_file, "environment"))
    warn_notes(path, units.notes)
    cloud = SplatCloud.concatenate(clouds) if clouds else SplatCloud.empty()
    with np.errstate(invalid="ignore", over="ignore"):
        cloud = cloud.transformed(TO_PLY)
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


def _meta(path, meta):
    """The index with the older field names mapped to the current ones, its essentials checked."""
    if all(k in meta for k in ("total_splats", "lod_3dgs_info", "lod_level")):
        meta["totalLevels"] = meta["lod_level"]
        root = meta.get("root")
        if isinstance(root, dict) and isinstance(root.get("files"), list):
            names = [f.lstrip("/") if isinstance(f, str) else f for f in root["files"]]
            root["splatFiles"] = [f if not isinstance(f, str) or f.endswith(".sog") else f + ".sog" for f in names]
    if not whole_number(meta.get("totalLevels")) or meta["totalLevels"] == 0:
        raise SplatFileError(path, ".lcc2: totalLevels must be a positive whole number")
    root = meta.get("root")
    if not isinstance(root, dict) or not isinstance(root.get("splatFiles"), list):
        raise SplatFileError(path, ".lcc2: root must be an object listing its splatFiles")
    return meta


def _children(path, node):
    children = node.get("child") or []
    children = list(children.values()) if isinstance(children, dict) else children
    if not isinstance(children, list) or not all(isinstance(c, dict) for c in children):
        raise SplatFileError(path, ".lcc2: a node's child must be a list or an object of nodes")
    return children


def _references(path, root, total, env_file):
    """{level: [(file, start, count)]} of every node below the root (walked without recursion)."""
    refs = {}
    files = len(root["splatFiles"])
    stack = [(child, 1) for child in _children(path, root)]
    while stack:
        node, depth = stack.pop()
        stack.extend((child, depth + 1) for child in _children(path, node))
        data = node.get("data") or {}
        ref = data.get("3dgs") if isinstance(data, dict) else None
        if ref is None or (isinstance(ref, dict) and ref.get("name") == env_file):
            continue
        if not isinstance(ref, dict):
            raise SplatFileError(path, f".lcc2: a node's 3dgs data must be an object, not {ref!r}")
        if depth > total:
            raise SplatFileError(path, f".lcc2: a node {depth} deep holds splats, below its {total} levels")
        file, start, count = (ref.get(k, 0 if k == "start" else None) for k in ("name", "start", "count"))
        if not (whole_number(file) and whole_number(start) and whole_number(count)) or file >= files:
            raise SplatFileError(
                path,
                f".lcc2: the reference {ref} needs a file index below {files} and a whole-number start and count",
            )
        refs.setdefault(total - depth, []).append((file, start, count))
    return refs
