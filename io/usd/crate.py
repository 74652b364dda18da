"""Crate (.usdc) files checked against their own sizes before OpenUSD's crate reader opens them.

OpenUSD sizes its buffers by the counts a crate file states: one flipped bit in a count makes it
allocate gigabytes, read past the file, or abort the process. `check_crate_bytes` refuses a file whose
table of contents, section counts, compressed block sizes, or the element counts of the arrays,
vectors and dictionaries its FIELDS section points to, cannot fit in the bytes the file holds. The
FIELDS value representations are compressed; they are decoded here by a small LZ4 block decoder
that never produces more than the section says it holds (OpenUSD's TfFastCompression framing).
"""

import struct

import numpy as np

from ..common import SplatFileError

CRATE_EXPANSION = 256  # the most an element count may exceed its section's bytes by (LZ4 tops 255:1)
CRATE_INT_EXPANSION = 1024  # compressed integers: 2 code bits per int, then LZ4 (255:1)
# Non-inlined value types that start with a u64 count, and the fewest bytes each element takes:
# Dictionary (string index + value offset), PathVector, TokenVector, VariantSelectionMap,
# DoubleVector, LayerOffsetVector, StringVector (crateDataTypes.h).
CRATE_COUNTED = {31: 12, 40: 4, 41: 4, 45: 8, 48: 8, 49: 16, 50: 4}
# Bytes per element of uncompressed arrays by crate type (bool .. Vec4i, TimeCode); others take >= 1.
CRATE_ELEMENT = {
    1: 1,
    2: 1,
    3: 4,
    4: 4,
    5: 8,
    6: 8,
    7: 2,
    8: 4,
    9: 8,
    10: 4,
    11: 4,
    12: 4,
    13: 32,
    14: 72,
    15: 128,
    16: 32,
    17: 16,
    18: 8,
    19: 16,
    20: 8,
    21: 4,
    22: 8,
    23: 24,
    24: 12,
    25: 6,
    26: 12,
    27: 32,
    28: 16,
    29: 8,
    30: 16,
    56: 8,
}


class _CrateError(Exception):
    pass


def check_crate_bytes(path, data, where=""):
    """Refuse the crate layer `data` (its bytes; layer_check.py maps them, from a file or a .usdz)
    if its structure cannot fit in them: the table of contents and every section's counts and
    compressed sizes, and the element count of every array, vector and dictionary the FIELDS
    section points to (a flipped bit in one makes OpenUSD allocate gigabytes, read past the file,
    or abort the process). `where` prefixes the problem ("layer x.usdc: ") for a composed layer."""
    try:
        _check_crate_bytes(path, data)
    except SplatFileError as exc:  # a ValueError too: caught first
        if not where:
            raise
        raise SplatFileError(path, where + exc.problem) from None
    except struct.error:
        raise SplatFileError(path, f"{where}crate header or table of contents is truncated") from None
    except (_CrateError, ValueError, IndexError) as exc:
        raise SplatFileError(path, f"{where}crate file is corrupt: {exc}") from None


def _check_crate_bytes(path, data):
    size = len(data)
    major, minor = data[8], data[9]
    toc = struct.unpack_from("<q", data, 16)[0]
    sections = struct.unpack_from("<Q", data, toc)[0] if 88 <= toc <= size - 8 else None
    if sections is None or sections > (size - toc - 8) // 32:
        raise SplatFileError(path, "crate table of contents lies outside the file (truncated or corrupt?)")
    found = {}
    for i in range(sections):
        name, start, length = struct.unpack_from("<16sqq", data, toc + 8 + 32 * i)
        name = name.split(b"\0", 1)[0].decode("latin-1")
        if start < 0 or length < 8 or start + length > size:
            raise SplatFileError(path, f"crate section {name!r} lies outside the file (truncated or corrupt?)")
        count = struct.unpack_from("<Q", data, start)[0]
        if count > CRATE_EXPANSION * length:
            raise SplatFileError(path, f"crate section {name!r} claims {count} entries in {length} bytes (corrupt?)")
        found[name] = (start, length, count)
    if (major, minor) < (0, 4):  # before 0.4.0 sections were not compressed: counts checked above
        return
    sizes = {"TOKENS": 2, "FIELDS": 0, "FIELDSETS": 1, "PATHS": 0, "SPECS": 3}
    for name, (start, length, count) in found.items():
        end, at = start + length, start + 8
        if name == "TOKENS":
            raw, packed = struct.unpack_from("<QQ", data, at)
            if at + 16 + packed > end or raw > 255 * packed + 16 or count > raw:
                raise _CrateError(
                    f"TOKENS claims {count} tokens in {raw} bytes packed in {packed}, in a {length}-byte section"
                )
        elif name == "PATHS":
            encoded = struct.unpack_from("<Q", data, at)[0]
            if encoded > CRATE_INT_EXPANSION * length:
                raise _CrateError(f"PATHS claims {encoded} encoded paths in {length} bytes")
            _skip_packed(data, at + 8, end, 3, name)
        elif name == "FIELDS":
            at = _skip_packed(data, at, end, 1, name)
            packed = struct.unpack_from("<Q", data, at)[0]
            if at + 8 + packed > end:
                raise _CrateError(f"FIELDS value representations ({packed} bytes) run past the section")
            reps = _fast_decompress(data[at + 8 : at + 8 + packed], 8 * count)
            if len(reps) != 8 * count:
                raise _CrateError(f"FIELDS holds {len(reps) // 8} value representations, not {count}")
            _check_values(data, reps, toc, (major, minor) >= (0, 7))
        elif name in sizes:
            _skip_packed(data, at, end, sizes[name], name)


def _skip_packed(data, at, end, blocks, name):
    """The offset after `blocks` compressed blocks (u64 size + bytes) that must end by `end`."""
    for _ in range(blocks):
        packed = struct.unpack_from("<Q", data, at)[0]
        at += 8 + packed
        if at > end:
            raise _CrateError(f"a compressed block of {name} ({packed} bytes) runs past the section")
    return at


def _check_values(data, reps, data_end, wide_counts):
    """Every non-inlined array, vector and dictionary must hold its count in the bytes before the TOC."""
    values = np.frombuffer(reps, "<u8")
    outside = (values >> 62) & 1 == 0  # not inlined: the payload is a file offset
    offsets = values & ((1 << 48) - 1)
    kinds = (values >> 48) & 0xFF
    arrays = (values >> 63) == 1
    counted = outside & (arrays | np.isin(kinds, list(CRATE_COUNTED)))
    for value, offset, kind, is_array in zip(
        values[counted].tolist(), offsets[counted].tolist(), kinds[counted].tolist(), arrays[counted].tolist()
    ):
        width = 8 if wide_counts or not is_array else 4
        if offset == 0 and is_array:  # an empty array
            continue
        if offset < 88 or offset + width > data_end:
            raise _CrateError(f"a value of type {kind} lies outside the data (offset {offset})")
        count = struct.unpack_from("<Q" if width == 8 else "<I", data, offset)[0]
        room = data_end - offset - width
        if is_array and (value >> 61) & 1:  # compressed: integers, or a lookup table
            fits = count <= CRATE_INT_EXPANSION * room + 16
        else:
            fits = count * (CRATE_ELEMENT.get(kind, 1) if is_array else CRATE_COUNTED[kind]) <= room
        if not fits:
            raise _CrateError(
                f"{'an array' if is_array else 'a value'} of type {kind} at byte {offset} claims "
                f"{count} elements, more than the {room} bytes after it can hold"
            )


def _fast_decompress(src, limit):
    """OpenUSD's TfFastCompression: a chunk count byte (0: one LZ4 block), then sized LZ4 blocks."""
    if not len(src):
        raise _CrateError("an empty compressed block")
    chunks = src[0]
    if chunks == 0:
        return _lz4_block(src[1:], limit)
    out, at = bytearray(), 1
    for _ in range(chunks):
        size = struct.unpack_from("<i", src, at)[0]
        if size < 0 or at + 4 + size > len(src):
            raise _CrateError("a compressed chunk runs past its block")
        out += _lz4_block(src[at + 4 : at + 4 + size], limit - len(out))
        at += 4 + size
    return bytes(out)


def _lz4_block(src, limit):
    """One LZ4 block, refusing to produce more than `limit` bytes (only small sections are decoded)."""
    out, i, n = bytearray(), 0, len(src)
    while i < n:
        token = src[i]
        i += 1
        literals, i = _lz4_length(src, i, token >> 4)
        if len(out) + literals > limit or i + literals > n:
            raise _CrateError("compressed data expands past its stated size")
        out += src[i : i + literals]
        i += literals
        if i >= n:
            break
        offset = src[i] | src[i + 1] << 8
        match, i = _lz4_length(src, i + 2, token & 15)
        match += 4
        if not 0 < offset <= len(out) or len(out) + match > limit:
            raise _CrateError("compressed data refers outside itself")
        start = len(out) - offset
        while match > 0:  # overlapping copies repeat the pattern
            piece = out[start : start + min(match, offset)]
            out += piece
            start += len(piece)
            match -= len(piece)
    return bytes(out)


def _lz4_length(src, i, length):
    if length == 15:
        while True:
            more = src[i]
            i += 1
            length += more
            if more != 255:
                break
    return length, i
