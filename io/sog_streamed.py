"""PlayCanvas streamed SOG (`lod-meta.json`, as splat-transform 3.x writes it), read only.

lod-meta.json names SOG units (`filenames`: `<level>_<n>/meta.json` folders or `.sog` bundles, relative
to its folder) and a spatial tree whose leaves say, per level of detail, which splats of which unit
they hold:
    {"version": 1, "lodLevels": L, "counts": [splats per level], "filenames": [...],
     "environment": "env/meta.json" (optional: splats shown at every level, e.g. the sky),
     "tree": {"children": [node, ...]} or {"lods": {"<level>": {"file": i, "offset": o, "count": c}}}}
Level 0 is the finest (the full capture), higher levels are ever coarser stand-ins for it. `version`
and `counts` may be absent (files written before splat-transform stamped them).

Every unit is read by io/sog.py; the names it reads go through io.policy.referenced_file (regular
files under the lod-meta.json's folder only, unless allow_outside). Units must be SOG (meta.json or
.sog), never another lod-meta.json, so references cannot loop.
"""

import json
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..core import SplatCloud
from . import sog
from .common import SplatFileError, SplatFileWarning, apply_nonfinite_policy, check_nonfinite_policy
from .policy import referenced_file

# A lod-meta.json beyond this is refused unparsed: real ones hold a few hundred bytes per chunk (16 MiB:
# some 40,000 chunks, 20 billion splats at splat-transform's default chunk size), and Python's parse of
# one costs about 30 times its size in memory.
MAX_META_BYTES = 16 << 20


def read(
    path: str | os.PathLike,
    levels: str | int | Sequence[int] = "finest",
    environment: bool = True,
    allow_outside: bool = False,
    nonfinite: str = "raise",
) -> SplatCloud:
    """Read a streamed SOG into one SplatCloud.

    `levels`: "finest" (level 0, the full capture), "all" (every level, finest first, as one cloud:
    the coarse levels duplicate the fine one), a level number (negative counts from the coarsest) or
    a list of them. `environment`: add the environment splats, if the file has them."""
    check_nonfinite_policy(nonfinite)
    meta = _meta(path)
    refs = _references(path, meta)
    chosen = chosen_levels(path, levels, meta["lodLevels"])
    units = Units(path, meta["filenames"], allow_outside)
    clouds = [level_cloud(path, units, refs.get(level, [])) for level in chosen]
    if environment and meta.get("environment") is not None:
        clouds.append(units.read(meta["environment"], "environment"))
    for note in units.notes:
        warnings.warn(f"{path}: {note}", SplatFileWarning, stacklevel=2)
    cloud = SplatCloud.concatenate(clouds) if clouds else SplatCloud.empty()
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


def read_index(path, what="lod-meta.json"):
    """The JSON object of an index file (`what` names its kind), read within MAX_META_BYTES."""
    try:
        with open(path, "rb") as f:
            text = f.read(MAX_META_BYTES + 1)
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None
    if len(text) > MAX_META_BYTES:
        raise SplatFileError(path, f"{what} beyond {MAX_META_BYTES >> 20} MiB is refused")
    try:
        meta = json.loads(text)
    except RecursionError:
        raise SplatFileError(path, f"{what} nests too deeply to be a level-of-detail tree") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise SplatFileError(path, f"{what} is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise SplatFileError(path, f"{what} must hold an object")
    return meta


def _meta(path):
    meta = read_index(path)
    if meta.get("version", 1) != 1:
        raise SplatFileError(path, f"streamed SOG version {meta.get('version')}; this reader takes version 1")
    if not whole_number(meta.get("lodLevels")) or meta["lodLevels"] == 0:
        raise SplatFileError(path, "lod-meta.json: lodLevels must be a positive whole number")
    names = meta.get("filenames")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise SplatFileError(path, "lod-meta.json: filenames must be a list of file names")
    if not isinstance(meta.get("tree"), dict):
        raise SplatFileError(path, "lod-meta.json: tree must be an object")
    if meta.get("environment") is not None and not isinstance(meta["environment"], str):
        raise SplatFileError(path, "lod-meta.json: environment must be a file name")
    return meta


def whole_number(value):
    """Whether a JSON value is a whole number from 0 to 2^53 (JSON's exact integers; not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 1 << 53


def _references(path, meta):
    """{level: [(file, offset, count)]} from every leaf of the tree (walked without recursion),
    checked against the level and file counts and, where given, `counts`."""
    levels, files = meta["lodLevels"], len(meta["filenames"])
    refs = {}
    stack = [meta["tree"]]
    while stack:
        node = stack.pop()
        children, lods = node.get("children", []), node.get("lods", {})
        if not isinstance(children, list) or not isinstance(lods, dict):
            raise SplatFileError(path, "lod-meta.json: a tree node's children must be a list and its lods an object")
        if not all(isinstance(child, dict) for child in children):
            raise SplatFileError(path, "lod-meta.json: a tree node's children must be objects")
        stack.extend(children)
        for key, ref in lods.items():
            level = int(key) if key.isascii() and key.isdigit() else -1
            if not isinstance(ref, dict) or not 0 <= level < levels:
                raise SplatFileError(path, f"lod-meta.json: level '{key}' of a tree node is not one of its {levels}")
            file, offset, count = (ref.get(k) for k in ("file", "offset", "count"))
            if not (whole_number(file) and whole_number(offset) and whole_number(count)) or file >= files:
                raise SplatFileError(
                    path,
                    f"lod-meta.json: the level {level} reference {ref} needs a file index below {files} and a "
                    "whole-number offset and count",
                )
            refs.setdefault(level, []).append((file, offset, count))
    counts = meta.get("counts")
    if counts is not None:
        found = [sum(c for _, _, c in refs.get(level, [])) for level in range(levels)]
        if counts != found:
            raise SplatFileError(path, f"lod-meta.json claims {counts} splats per level, its tree holds {found}")
    return refs


def chosen_levels(path, levels, count):
    if levels == "finest":
        return [0]
    if levels == "all":
        return list(range(count))
    wanted = [levels] if isinstance(levels, int) else list(levels)
    if not all(isinstance(level, int) and not isinstance(level, bool) for level in wanted):
        raise ValueError(f"levels must be 'finest', 'all', a level number or a list of them, got {levels!r}")
    outside = [level for level in wanted if not -count <= level < count]
    if outside:
        raise SplatFileError(path, f"has {count} levels of detail (0 the finest); level {outside[0]} asked for")
    return [level % count for level in wanted]


def level_cloud(path, units, refs):
    """One level's splats: each unit's referenced runs, by file then offset (one selection per unit,
    however many leaves share it)."""
    pieces = []
    by_file = {}
    for file, offset, count in refs:
        by_file.setdefault(file, []).append((offset, count))
    for file in sorted(by_file):
        unit = units.read(file)
        offsets, counts = np.array(sorted(by_file[file]), np.int64).T
        ends = offsets + counts
        bad = np.flatnonzero((ends > len(unit)) | (offsets < np.maximum.accumulate(np.r_[0, ends[:-1]])))
        if len(bad):
            raise SplatFileError(
                path,
                f"lod-meta.json: splats {offsets[bad[0]]} to {ends[bad[0]]} of '{units.names[file]}' overlap "
                f"another reference or lie beyond its {len(unit)} splats",
            )
        starts = np.repeat(offsets - (np.cumsum(counts) - counts), counts)
        pieces.append(unit[starts + np.arange(len(starts))])
    return SplatCloud.concatenate(pieces) if pieces else SplatCloud.empty()


# a streamed SOG's units: name ending -> reader (never another lod-meta.json)
SOG_UNITS = {"meta.json": sog.read, ".sog": sog.read}


class Units:
    """The units (chunk files) a tree of levels names, each read once, by the one reading policy;
    `readers` maps the name endings allowed to their readers (lcc2 uses this too)."""

    def __init__(self, path, names, allow_outside, readers=None, kind="a SOG (meta.json or .sog)"):
        self.path, self.names, self.allow_outside = path, names, allow_outside
        self.readers, self.kind = readers or SOG_UNITS, kind
        self.clouds = {}
        self.notes = []

    def read(self, key, what="SOG unit"):
        """The cloud of unit `key` (an index into filenames, or a name)."""
        if key not in self.clouds:
            name = self.names[key] if isinstance(key, int) else key
            lower = name.lower() if isinstance(name, str) else ""
            reader = next((r for end, r in self.readers.items() if lower.endswith(end)), None)
            if reader is None or lower.endswith("lod-meta.json"):
                raise SplatFileError(self.path, f"{what} '{name}' is not {self.kind}")
            unit = referenced_file(
                self.path, name, [Path(self.path).parent], allow_outside=self.allow_outside, what=what
            )
            self.clouds[key] = self._read_unit(reader, unit)
        return self.clouds[key]

    def _read_unit(self, reader, unit):
        """Read a unit keeping non-finite splats (the whole cloud is judged once, at the end, so
        references keep their offsets); its other warnings are passed on."""
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cloud = reader(unit, nonfinite="keep")
        self.notes += [str(w.message) for w in caught if "non-finite" not in str(w.message)]
        return cloud
