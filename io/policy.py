"""Where readers may open files: only where the user pointed.

A file that names other files (an OBJ its MTL libraries, an MTL its textures, an OpenUSD layer its
sublayers, references and payloads) is a request to read them, made by whoever wrote the file. A
reader follows such a name only when it stays inside the folder the user's file is in (or, for a
.usdz, inside that package), after `..` and symbolic links are followed: absolute paths, `../`
escapes and names that only the working directory would make sense of are refused. The refusal
is the same text whether or not the named file exists, so a hostile file cannot probe the disk.

Limits on what a header may make a reader decode (image pixels, SPZ payloads) live here too.
"""

import os
import re
import stat
from pathlib import Path, PurePosixPath

from .common import SplatFileError

# A texture bigger than this is refused from its header, before decoding: 8192 x 8192 RGBA8 is
# 256 MiB; the largest textures of captured or sold models are 8K (16K would be 4 GiB decoded).
MAX_IMAGE_PIXELS = 8192 * 8192
# A text layer the NumPy reader parses (OpenUSD without pxr) may hold at most this many bytes: about
# 100M numbers, which take it half a minute and several GiB.
MAX_TEXT_LAYER_BYTES = 1 << 30
# An SPZ payload may decompress to at most this many bytes (about 66M splats of SH degree 3, 214M
# of degree 0), and to at most SPZ_MAX_RATIO times its compressed size once past SPZ_RATIO_FLOOR:
# real SPZ payloads (quantised positions, colours, rotations) deflate 1.2-3x, never 64x.
SPZ_MAX_BYTES = 4 << 30
SPZ_MAX_RATIO = 64
SPZ_RATIO_FLOOR = 64 << 20
# Payloads are decompressed in pieces of this size, counting bytes as they come.
STREAM_PIECE = 16 << 20

_DRIVE = re.compile(r"^[A-Za-z]:|^//")  # Windows drive letters and UNC shares (after \ -> /)


def outside_message(reference, where):
    """The one message for a name that leaves the allowed folder: it never says whether the file exists."""
    return f"'{reference}' is outside {where}; only files in it and below are read"


def inside(root, base, reference):
    """The path `reference` names, taken relative to the folder `base`, if it stays inside the folder
    `root` once `..` and symbolic links are followed; None when it is empty, absolute (a drive or
    share on Windows too) or leaves `root`. The file itself is not looked at."""
    text = str(reference).strip().strip('"').replace("\\", "/")
    if not text or text.startswith("/") or _DRIVE.match(text):
        return None
    candidate = (Path(base) / text).resolve()
    return candidate if within(root, candidate) else None


def referenced_file(owner, reference, roots, base=None, allow_outside=False, what="file"):
    """The one reading policy for every name a file makes (glTF URIs, OpenUSD layers, URDF meshes,
    textures, SOG images): the regular file that `reference` names, relative to the folder `base`
    (default: the folder of `owner`, the file that names it). It must lie under one of `roots` once
    `..` and symbolic links are followed, unless `allow_outside`; FIFOs, devices, sockets and folders
    are refused before they are opened (a FIFO would hang the read, /dev/zero never ends). Refused,
    missing and special files all raise the same SplatFileError, so a hostile file cannot learn
    whether a path exists. `reference` is a plain path: decode URIs (percent escapes, file://)
    first."""
    base = Path(owner).parent if base is None else Path(base)
    roots = [Path(r) for r in ([roots] if isinstance(roots, str | os.PathLike) else roots)]
    text = str(reference).strip().replace("\\", "/")
    if allow_outside:
        candidate = (base / text).resolve() if text else None
    else:
        candidate = next((c for r in roots if (c := inside(r, base, text)) is not None), None)
    try:
        regular = candidate is not None and stat.S_ISREG(os.stat(candidate).st_mode)
    except (OSError, ValueError):
        regular = False
    if not regular:
        where = " or ".join(f"'{r}'" for r in roots) or "the file's folder"
        raise SplatFileError(
            owner,
            f"{what} '{reference}' is not a readable file under {where} (only regular files there are read; "
            "allow_outside lifts the folder rule)",
        )
    return candidate


def within(root, path):
    """Whether `path` lies in the folder `root` or below once `..` and symbolic links are followed."""
    root, path = Path(root).resolve(), Path(path).resolve()
    return path == root or path.is_relative_to(root)


def inside_package(package, reference):
    """Whether `reference` ("pkg.usdz[inner]", as OpenUSD writes a packaged path) lies in the package
    `package`: the same archive, and an inner path without absolute or `..` parts."""
    match = re.fullmatch(r"(.*?)\[(.*)\]", str(reference))
    if not match or Path(match.group(1)).resolve() != Path(package).resolve():
        return False
    inner = PurePosixPath(match.group(2).replace("\\", "/").split("[", 1)[0])
    return not inner.is_absolute() and ".." not in inner.parts and not _DRIVE.match(str(inner))
