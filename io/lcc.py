"""XGRIDS LCC (`.lcc`, the first generation, as XGRIDS's LCC white paper lays it out), read only.

The `.lcc` file (any name, often meta.lcc) is JSON describing binary files beside it, whose names are
fixed (lower case, as splat-transform opens them, or capitalised, as the white paper writes them):
    meta.lcc         {"totalLevel": L, "fileType": "Portable" (colour only) | "Quality" (+ SH),
                      "splats": [per level], "attributes": [{"name": "scale", "min": [3], "max": [3]},
                      {"name": "shcoef", ...}, {"name": "envscale", ...}, {"name": "envshcoef", ...}]}
    index.bin        one entry per unit (a cell of the ground grid): uint32 cell, then per level
                     (finest, 0, first) uint32 splat count, uint64 byte offset into data.bin, uint32
                     byte size; all little-endian
    data.bin         32 bytes a splat: float32 x y z, uint8 r g b opacity, uint16 linear scales
                     (between the scale attribute's min and max), uint32 rotation (three 10-bit
                     components and the 2-bit index of the largest, rebuilt), uint16 normal (unused)
    shcoef.bin       ("Quality" only) 64 bytes a splat at twice its data.bin offset: fifteen uint32
                     SH coefficients, 11/10/11 bits of r/g/b between the shcoef attribute's min, max
    environment.bin  (optional) the environment, e.g. the sky: a data.bin record followed, for
                     "Quality", by its shcoef record; ranges from envscale and envshcoef
A level is its units' splats in index order, as splat-transform reads them; an entry's byte size is
not used (its count of 32-byte records is). The scene's global
offset, shift and scale are not applied (splat-transform does not either). Like LCC2, the scene is
Z up: it is read turned into the PLY's axes by a quarter turn about X. Every file goes through
io.policy.referenced_file; every run the index names is checked against the files' sizes, and runs
of the levels read may not overlap, before anything is allocated.
"""

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..core import SplatCloud
from ..core import sh as shmod
from ..core.splats import logit
from .common import SplatFileError, apply_nonfinite_policy, check_nonfinite_policy
from .lcc2 import TO_PLY
from .policy import referenced_file
from .sog_streamed import chosen_levels, read_index, whole_number

RECORD = np.dtype(
    [("position", "<f4", 3), ("rgba", "u1", 4), ("scale", "<u2", 3), ("rotation", "<u4"), ("normal", "<u2", 3)]
)
SH_RECORD = np.dtype(("<u4", 16))  # fifteen coefficients and one unused word
MAX_LEVELS = 64  # real scenes have up to about ten; the index entry grows 16 bytes a level
MAX_INDEX_BYTES = 256 << 20  # 16M units of ten levels: far beyond any captured scene
SQRT_HALF = np.sqrt(0.5)


def read(
    path: str | os.PathLike,
    levels: str | int | Sequence[int] = "finest",
    environment: bool = True,
    allow_outside: bool = False,
    nonfinite: str = "raise",
) -> SplatCloud:
    """Read an LCC scene into one SplatCloud: `levels` "finest" (level 0), "all", a level or a list
    of them; `environment` adds environment.bin's splats when there is one; `allow_outside` follows
    the binary files (symbolic links) outside the `.lcc`'s folder."""
    check_nonfinite_policy(nonfinite)
    meta = read_index(path, ".lcc")
    total = meta.get("totalLevel")
    if not whole_number(total) or not 0 < total <= MAX_LEVELS:
        raise SplatFileError(path, f".lcc: totalLevel must be a whole number from 1 to {MAX_LEVELS}")
    with_sh = _has_sh(path, meta)
    ranges = _ranges(path, meta, with_sh)
    files = _Files(path, allow_outside)
    entries = _index(path, files.read_all("index.bin", MAX_INDEX_BYTES), total)
    chosen = chosen_levels(path, levels, total)
    runs = _runs(path, entries, chosen, files.size("data.bin"), files.size("shcoef.bin") if with_sh else None)
    clouds = [_level(files, level_runs, ranges["scale"], ranges.get("shcoef"), with_sh) for level_runs in runs]
    if environment and files.exists("environment.bin"):
        clouds.append(_environment(path, files, ranges, with_sh))
    degree = 3 if with_sh else 0
    cloud = SplatCloud.concatenate(clouds) if any(len(c) for c in clouds) else SplatCloud.empty(degree)
    with np.errstate(invalid="ignore", over="ignore"):
        cloud = cloud.transformed(TO_PLY)
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


def _has_sh(path, meta):
    """Whether the scene has SH: "Quality" yes, "Portable" no, other or none: when it names shcoef."""
    kind = meta.get("fileType")
    if kind in ("Quality", "Portable"):
        return kind == "Quality"
    attributes = meta.get("attributes")
    return isinstance(attributes, list) and any(isinstance(a, dict) and a.get("name") == "shcoef" for a in attributes)


def _ranges(path, meta, with_sh):
    """{attribute: (min, max)} of the quantised attributes, each three finite numbers; the
    environment's fall back to the scene's."""
    attributes = meta.get("attributes")
    if not isinstance(attributes, list) or not all(isinstance(a, dict) for a in attributes):
        raise SplatFileError(path, ".lcc: attributes must be a list of objects")
    named = {a.get("name"): a for a in attributes if isinstance(a.get("name"), str)}
    needed = ["scale", "shcoef"] if with_sh else ["scale"]
    ranges = {}
    for name in needed + ["envscale", "envshcoef"]:
        if name not in named:
            if name in needed:
                raise SplatFileError(path, f".lcc: the attributes give no '{name}' range")
            continue
        bounds = [named[name].get(k) for k in ("min", "max")]
        if not all(_three_numbers(b) for b in bounds):
            raise SplatFileError(path, f".lcc: the '{name}' attribute's min and max must be three finite numbers")
        ranges[name] = tuple(np.array(b, np.float64) for b in bounds)
    ranges.setdefault("envscale", ranges["scale"])
    if with_sh:
        ranges.setdefault("envshcoef", ranges["shcoef"])
    return ranges


def _three_numbers(value):
    return (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(float(v)) for v in value)
    )


class _Files:
    """The binary files beside the `.lcc`, by the policy, under either spelling of their names."""

    def __init__(self, path, allow_outside):
        self.path, self.folder, self.allow_outside = path, Path(path).parent, allow_outside

    def _name(self, name):
        capitalised = name.capitalize()
        if not os.path.lexists(self.folder / name) and os.path.lexists(self.folder / capitalised):
            return capitalised
        return name

    def exists(self, name):
        return os.path.lexists(self.folder / self._name(name))

    def resolved(self, name):
        return referenced_file(
            self.path, self._name(name), [self.folder], allow_outside=self.allow_outside, what="LCC data file"
        )

    def size(self, name):
        return os.stat(self.resolved(name)).st_size

    def read_all(self, name, limit):
        file = self.resolved(name)
        size = os.stat(file).st_size
        if size > limit:
            raise SplatFileError(self.path, f"{self._name(name)} beyond {limit >> 20} MiB is refused")
        return self.read(name, [(0, size)], size)

    def read(self, name, runs, total):
        """The bytes of (offset, length) runs, one after another; `total` is their checked sum."""
        out = bytearray(total)
        at = 0
        try:
            with open(self.resolved(name), "rb") as f:
                for offset, length in runs:
                    f.seek(offset)
                    got = f.readinto(memoryview(out)[at : at + length])
                    if got != length:
                        raise SplatFileError(self.path, f"{self._name(name)} ends inside the splats it should hold")
                    at += length
        except OSError as exc:
            raise SplatFileError(self.path, f"cannot read {self._name(name)}: {exc.strerror or exc}") from None
        return bytes(out)


def _index(path, data, total):
    """index.bin's entries: a structured array of (cell, per level (count, offset, size))."""
    entry = np.dtype([("cell", "<u4"), ("levels", [("count", "<u4"), ("offset", "<u8"), ("size", "<u4")], total)])
    if len(data) % entry.itemsize:
        raise SplatFileError(
            path, f"index.bin's {len(data)} bytes are not whole entries of {entry.itemsize} ({total} levels)"
        )
    return np.frombuffer(data, entry)


def _runs(path, entries, chosen, data_size, sh_size):
    """Per chosen level, the (offset, count) of its units' splats in data.bin, in index order; each
    run inside data.bin (and its SH inside shcoef.bin), no two runs of the levels read overlapping."""
    runs = []
    for level in chosen:
        units = entries["levels"][:, level]
        keep = units["count"] > 0
        runs.append(list(zip(units["offset"][keep].tolist(), units["count"][keep].tolist(), strict=True)))
    flat = sorted({run for level_runs in runs for run in level_runs})
    end = 0
    for offset, count in flat:
        if offset < end or offset + count * RECORD.itemsize > data_size:
            raise SplatFileError(
                path,
                f"index.bin: {count} splats at byte {offset} of data.bin overlap another run or lie beyond its "
                f"{data_size} bytes",
            )
        end = offset + count * RECORD.itemsize
        if sh_size is not None and 2 * end > sh_size:
            raise SplatFileError(path, f"shcoef.bin's {sh_size} bytes end before the SH of splats at byte {offset}")
    if len(flat) != sum(len(level_runs) for level_runs in runs):
        raise SplatFileError(path, "index.bin names one run of data.bin twice")
    return runs


def _level(files, runs, scale_range, sh_range, with_sh):
    """One level's splats: its runs read in index order and decoded."""
    count = sum(n for _, n in runs)
    data_runs = [(o, n * RECORD.itemsize) for o, n in runs]
    records = np.frombuffer(files.read("data.bin", data_runs, count * RECORD.itemsize), RECORD)
    sh = None
    if with_sh:
        sh_runs = [(2 * o, n * SH_RECORD.itemsize) for o, n in runs]
        sh = np.frombuffer(files.read("shcoef.bin", sh_runs, count * SH_RECORD.itemsize), SH_RECORD)
    return _decode(records, sh, scale_range, sh_range)


def _environment(path, files, ranges, with_sh):
    """environment.bin: records of data.bin's layout, each followed by its SH for "Quality"."""
    record = np.dtype([("base", RECORD), ("sh", SH_RECORD)]) if with_sh else np.dtype([("base", RECORD)])
    size = files.size("environment.bin")
    if size % record.itemsize:
        raise SplatFileError(path, f"environment.bin's {size} bytes are not whole splats of {record.itemsize}")
    data = np.frombuffer(files.read("environment.bin", [(0, size)], size), record)
    return _decode(data["base"], data["sh"] if with_sh else None, ranges["envscale"], ranges.get("envshcoef"))


def _decode(records, sh_words, scale_range, sh_range):
    """SplatCloud of data.bin records (and their SH words), in the scene's axes."""
    rgba = records["rgba"] / 255.0
    low, high = scale_range
    scales = low + (high - low) * (records["scale"] / 65535.0)
    degree = 3 if sh_words is not None else 0
    sh = np.zeros((len(records), shmod.num_coeffs(degree), 3))
    sh[:, 0] = shmod.rgb_to_dc(rgba[:, :3])
    if sh_words is not None:
        words = sh_words[:, :15]
        low, high = sh_range
        for channel, (shift, bits) in enumerate(((0, 11), (11, 10), (21, 11))):
            fraction = ((words >> shift) & ((1 << bits) - 1)) / ((1 << bits) - 1)
            sh[:, 1:, channel] = low[channel] + (high[channel] - low[channel]) * fraction
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(scales)
    return SplatCloud(records["position"], _rotations(records["rotation"]), log_scales, logit(rgba[:, 3]), sh)


def _rotations(packed):
    """w, x, y, z of the packed quaternions: three components of x, y, z, w in order, the one at the
    2-bit index (the largest) rebuilt non-negative from them."""
    shifts = np.array([0, 10, 20], np.uint32)
    three = ((packed[:, None] >> shifts) & 1023) / 1023.0 * (2 * SQRT_HALF) - SQRT_HALF
    rebuilt = np.sqrt(1.0 - np.minimum(1.0, (three**2).sum(axis=1)))
    largest = (packed >> 30).astype(np.int64)[:, None]
    slots = np.arange(4)[None, :]
    source = np.where(slots < largest, slots, np.where(slots == largest, 3, slots - 1))
    xyzw = np.take_along_axis(np.column_stack([three, rebuilt]), source, axis=1)
    return xyzw[:, [3, 0, 1, 2]]
