"""Layer bytes checked before OpenUSD parses them, for every layer a stage composes.

OpenUSD trusts what a layer says. Its crate reader sizes buffers by the counts a .usdc states
(crate.py checks them). Its text parser descends once per bracket: 100k nested parentheses in
200 KB abort the process (its stack runs out) and 10k take over a gigabyte and ten seconds (memory
grows with the square of the depth), before any error is reported. So a text layer is scanned here
first: brackets, parentheses and braces outside string literals, asset paths and comments may nest
at most MAX_NESTING deep, and it may hold at most policy.MAX_TEXT_LAYER_BYTES. The scan is NumPy
over the bytes (a regular expression finds the strings and comments, whose brackets do not count)
and copies no file: a layer is mapped, and a .usdz member is the slice of the package that
holds it (OpenUSD reads only stored members).
"""

import mmap
import os
import re
import struct

import numpy as np

from ..common import SplatFileError
from ..policy import MAX_TEXT_LAYER_BYTES
from .crate import check_crate_bytes

# Real layers nest one brace per ancestor prim and a few more for metadata, dictionaries and tuples
# in arrays: the deepest scene hierarchies (CAD assemblies) are tens of prims deep. 256 is far above
# them, and far below the depths at which OpenUSD's parser costs anything (a 256-deep value parses
# in a millisecond; memory grows with the square of the depth).
MAX_NESTING = 256
_CHUNK = 1 << 22  # bytes scanned at a time: the running depth of 4 MiB is a 16 MiB array

# What OpenUSD's text grammar reads as a string literal, an asset path or a comment (possessive, as
# its parser never backtracks into them): brackets inside these do not nest.
_SKIPPED = re.compile(
    rb"""
      '''(?:[^\\']|\\.|'(?!''))*+'''
    | '(?:[^\\'\r\n]|\\[^\r\n])*+'
    | \"\"\"(?:[^\\"]|\\.|"(?!""))*+\"\"\"
    | "(?:[^\\"\r\n]|\\[^\r\n])*+"
    | @@@(?:[^\\@\r\n]|\\@@@|\\|@(?!@@))*+@@@@{0,2}
    | @[^@\r\n]*+@
    | \#[^\r\n]*+
    | //[^\r\n]*+
    | /\*(?:[^*]|\*(?!/))*+\*/
    """,
    re.S | re.X,
)
_STEP = np.zeros(256, np.int8)
_STEP[list(b"([{")] = 1
_STEP[list(b")]}")] = -1


def check_layer(owner, identifier):
    """Refuse the layer `identifier` (a file, "pkg.usdz[inner]", or a .usdz itself for its first
    layer) before OpenUSD parses it: a crate layer whose counts its bytes cannot hold (crate.py), a
    text layer over policy.MAX_TEXT_LAYER_BYTES or nested deeper than MAX_NESTING, or a packaged
    layer that is compressed (OpenUSD reads only stored ones). `owner` names the file in errors."""
    outer, members = split_packaged(identifier)
    data, name = _mapped(outer), os.path.basename(outer)
    while bytes(data[:4]) == b"PK\x03\x04":  # a package: its named member, or its first
        data, inner = _member(owner, data, members.pop(0) if members else None)
        name += f"[{inner}]"
    where = "" if str(identifier) == os.path.abspath(owner) else f"layer {name}: "
    if bytes(data[:8]) == b"PXR-USDC":
        check_crate_bytes(owner, data, where)
    else:
        check_text(owner, data, where)


def split_packaged(identifier):
    """("pkg.usdz", ["a.usdz", "b.usda"]) for "pkg.usdz[a.usdz[b.usda]]", OpenUSD's nested
    package paths; (identifier, []) for a plain file."""
    outer, _, rest = str(identifier).partition("[")
    members = []
    while rest.endswith("]"):
        rest = rest[:-1]
        member, _, rest = rest.partition("[")
        members.append(member)
    return outer, members


def _mapped(path):
    """The bytes of the file at `path`, mapped (a view that lives as long as its last user)."""
    with open(path, "rb") as f:
        if not os.fstat(f.fileno()).st_size:
            return memoryview(b"")
        return memoryview(mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ))


def _member(owner, view, name):
    """(bytes, name) of the member `name` (None: the first) of the package in `view`, found as
    OpenUSD finds it (see _headers)."""
    for found, method, start, size in _headers(view):
        if name is None or found == name:
            if method != 0:
                raise SplatFileError(
                    owner, f"packaged layer {found!r} is compressed; a .usdz stores its layers uncompressed"
                )
            return view[start : start + size], found
    raise SplatFileError(owner, f"the package holds no layer {name!r}" if name else "the package holds no layer")


def _headers(view):
    """(name, compression method, start, size) of each member of the package in `view`, read as
    OpenUSD reads a package: walking the local file headers from the start, each member sized by its
    own header. The central directory is not read, so its sizes cannot differ from the bytes
    OpenUSD parses."""
    at = 0
    while len(view) - at >= 30:
        signature, _, _, method, _, _, _, size, _, name_length, extra_length = struct.unpack_from(
            "<IHHHHHIIIHH", view, at
        )
        start = at + 30 + name_length + extra_length
        if signature != 0x04034B50 or start + size > len(view):
            return
        yield bytes(view[at + 30 : at + 30 + name_length]).decode("utf-8", "replace"), method, start, size
        at = start + size


def package_names(owner, package, members=()):
    """The names of the members of the package `package` (a file), or of the package nested in it
    at `members` ("a.usdz", ...)."""
    data = _mapped(package)
    for member in members:
        data = _member(owner, data, member)[0]
    return [name for name, *_ in _headers(data)]


def check_text(owner, data, where=""):
    """Refuse a text layer over policy.MAX_TEXT_LAYER_BYTES, or whose brackets, parentheses and
    braces (outside strings, asset paths and comments) nest deeper than MAX_NESTING."""
    if len(data) > MAX_TEXT_LAYER_BYTES:
        raise SplatFileError(
            owner,
            f"{where}a {len(data)}-byte text layer, more than the {MAX_TEXT_LAYER_BYTES >> 20} MiB read",
        )
    depth, at = nesting(data)
    if depth > MAX_NESTING:
        line = bytes(data[:at]).count(b"\n") + 1
        raise SplatFileError(
            owner,
            f"{where}brackets nest more than {MAX_NESTING} deep (at line {line}); "
            "no real layer does, and OpenUSD's parser cannot take it",
        )


def nesting(data, limit=MAX_NESTING):
    """(depth, offset): how deep brackets, parentheses and braces nest in `data` outside strings,
    asset paths and comments, and the byte where the depth first exceeds `limit` (else the end).
    A closing bracket without an opening one counts from zero again, so stray closers cannot hide
    openers that follow them."""
    codes = np.frombuffer(data, np.uint8)
    spans = _skipped(data, codes)
    level, lowest, deepest = 0, 0, 0
    for start in range(0, len(codes), _CHUNK):
        at, step = _brackets(codes[start : start + _CHUNK], spans, start)
        if not len(at):
            continue
        running = level + np.cumsum(step, dtype=np.int64)
        floor = np.minimum(np.minimum.accumulate(running), lowest)
        depth = running - floor
        over = np.flatnonzero(depth > limit)
        if len(over):
            return int(depth.max()), int(at[over[0]])
        deepest = max(deepest, int(depth.max()))
        level, lowest = int(running[-1]), int(floor[-1])
    return deepest, len(codes)


def _skipped(data, codes):
    """[start, end) of every string, asset path and comment, in order: the expression is tried only
    where one can begin (a quote, @, # or /), which NumPy finds far faster than the expression."""
    spans, end = [], 0
    for start in range(0, len(codes), _CHUNK):
        piece = codes[start : start + _CHUNK]
        hits = (piece == 0x27) | (piece == 0x22) | (piece == 0x40) | (piece == 0x23) | (piece == 0x2F)
        for at in (np.flatnonzero(hits) + start).tolist():
            if at >= end and (match := _SKIPPED.match(data, at)):
                spans.append(match.span())
                end = match.end()
    return np.array(spans, np.int64).reshape(-1, 2)


def _brackets(codes, spans, start):
    """(offsets, +1 or -1): the brackets among `codes` (the bytes from `start`) outside the skipped
    spans. Compared byte by byte: '(' and ')' are 0x28 and 0x29, '[' ']' '{' '}' 0x5B 0x5D 0x7B 0x7D."""
    folded = codes | 0x20
    at = np.flatnonzero(((codes & 0xFE) == 0x28) | (folded == 0x7B) | (folded == 0x7D))
    step = _STEP[codes[at]]
    at += start
    if len(spans):
        span = np.searchsorted(spans[:, 0], at, "right") - 1
        inside = (span >= 0) & (spans[np.maximum(span, 0), 1] > at)
        at, step = at[~inside], step[~inside]
    return at, step
