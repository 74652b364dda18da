"""Splat file formats. `read_splats`/`write_splats` pick the format by extension; every other part
of Splatwright reads and writes through them."""

import importlib
import inspect
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..core.splats import SplatCloud
from .common import SplatFileError, SplatFileWarning, check_file

# extension -> module in this package exposing read(path) -> SplatCloud and (unless READ_ONLY)
# write(path, cloud, **options)
FORMATS = {
    ".ply": "ply",
    ".compressed.ply": "compressed_ply",
    ".usd": "usd",
    ".usda": "usd",
    ".usdc": "usd",
    ".usdz": "usd",
    ".spz": "spz",
    ".splat": "splat",
    ".sog": "sog",
    "meta.json": "sog",
    ".glb": "gltf",
    ".gltf": "gltf",
    ".ksplat": "ksplat",
    "lod-meta.json": "sog_streamed",
    ".lcc2": "lcc2",
    ".lcc": "lcc",
}

# formats Splatwright reads but does not write
READ_ONLY = {"ksplat", "sog_streamed", "lcc2", "lcc"}


# format module -> the extension a writer's file gets when only the format is named (OpenUSD: .usd,
# binary where OpenUSD's module is present, text where it is not)
DEFAULT_EXTENSIONS = {
    "ply": ".ply",
    "spz": ".spz",
    "splat": ".splat",
    "usd": ".usd",
    "compressed_ply": ".compressed.ply",
    "sog": ".sog",
    "gltf": ".glb",
}


def format_of(path: str | os.PathLike) -> str:
    """The format module name for a path (the longest known ending of its name wins, so
    x.compressed.ply is compressed PLY; a bare ".ply" is no name), or SplatFileError naming the
    unknown extension."""
    name = Path(path).name.lower()
    for ending in sorted(FORMATS, key=len, reverse=True):
        if name.endswith(ending) and (len(name) > len(ending) or not ending.startswith(".")):
            return FORMATS[ending]
    known = ", ".join(sorted(FORMATS))
    raise SplatFileError(path, f"unknown splat file extension '{Path(path).suffix.lower()}' (known: {known})")


def file_sizes(count: int, sh_degree: int, spz_version: int = 3, half: bool = False) -> dict[str, int]:
    """{format: bytes} a file of `count` splats of `sh_degree` takes, by each writer's own layout:
    "ply" and "splat" exactly (without extras), "spz" before compression (the file is smaller),
    "usd" the arrays a crate file holds (see usd.data_size)."""
    from . import ply, splat, spz, usd

    return {
        "ply": ply.file_size(count, sh_degree),
        "spz": spz.uncompressed_size(count, sh_degree, spz_version),
        "splat": splat.file_size(count, sh_degree),
        "usd": usd.data_size(count, sh_degree, half),
    }


def written_size(cloud: SplatCloud, fmt: str) -> int | None:
    """About how many bytes `cloud` takes written as `fmt` (file_sizes' estimate; PLY with the extras
    it keeps, such as a converted mesh's source triangles or a material), None for formats file_sizes
    cannot tell. What the command line and the Mesh to Splats operator show before or after writing."""
    size = file_sizes(len(cloud), cloud.sh_degree).get(fmt)
    if size is not None and fmt == "ply":
        size += sum(np.asarray(values).nbytes for values in cloud.extras.values())
    return size


def _module(path):
    return importlib.import_module(f".{format_of(path)}", __name__)


def read_splats(path: str | os.PathLike, **options: Any) -> SplatCloud:
    """Read a splat file of any known format into a SplatCloud.

    Every reader takes `nonfinite="raise"|"keep"|"drop"` (default raise) for splats holding NaN/Inf,
    and reports anything it could not read exactly as a SplatFileWarning. `allow_outside=True` lets
    the readers of files that name other files (OpenUSD layers, glTF buffers, SOG images) follow
    names outside the file's folder (io.policy); formats that name no other file take no notice."""
    check_file(path)
    read = _module(path).read
    if "allow_outside" in options and "allow_outside" not in inspect.signature(read).parameters:
        del options["allow_outside"]  # this format names no other file
    return read(path, **options)


# formats that record whether splats were made for antialiased rendering (SPZ's flag, a PLY comment,
# a custom OpenUSD attribute)
RECORDS_ANTIALIASED = {"ply", "spz", "usd"}


def write_splats(path: str | os.PathLike, cloud: SplatCloud, **options: Any) -> None:
    """Write a SplatCloud in the format its extension names; the file appears whole or not at all.
    A cloud made for antialiased rendering written where the format cannot say so gets a warning:
    readers of that file will render it classic, with fatter outlines."""
    if format_of(path) in READ_ONLY:
        writable = ", ".join(sorted(DEFAULT_EXTENSIONS.values()))
        raise SplatFileError(path, f"Splatwright reads this format but does not write it; write one of {writable}")
    if cloud.antialiased and format_of(path) not in RECORDS_ANTIALIASED:
        warnings.warn(
            f"{path}: this format cannot record that the splats were made for antialiased rendering; "
            "readers will render them classic (outlines about a pixel wider); PLY, SPZ and OpenUSD "
            "record it",
            SplatFileWarning,
            stacklevel=2,
        )
    return _module(path).write(path, cloud, **options)


__all__ = [
    "DEFAULT_EXTENSIONS",
    "FORMATS",
    "READ_ONLY",
    "RECORDS_ANTIALIASED",
    "SplatFileError",
    "SplatFileWarning",
    "file_sizes",
    "format_of",
    "read_splats",
    "write_splats",
]
