"""The PLY header, for every PLY reader (io/ply.py, io/compressed_ply.py): its scalar types,
formats and elements, and the column order of a 3DGS file's SH properties."""

import re
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .common import SplatFileError

# PLY scalar type names (both spellings of the spec) -> NumPy type codes, and back for writing.
PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
TYPE_NAMES = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}
FORMATS = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}
ANTIALIASED_COMMENT = "antialiased"  # the header comment's first word for splats made for that mode
MAX_HEADER = 1 << 20


@dataclass
class Element:
    name: str
    count: int
    properties: list  # (name, type code) or (name, ("list", count code, item code))

    @property
    def has_lists(self):
        return any(isinstance(t, tuple) for _, t in self.properties)

    def dtype(self, order):
        return np.dtype([(name, order + code) for name, code in self.properties])


def read_header(path, f):
    """(format, elements, header length in bytes, antialiased) from an open file; antialiased: a
    'comment antialiased' line says the splats were made for antialiased rendering (see io.ply's _layout)."""
    head = f.read(MAX_HEADER)
    if not re.match(rb"ply[ \t]*\r?\n", head):
        raise SplatFileError(path, "not a PLY file (it does not start with a 'ply' line)")
    end = re.search(rb"\nend_header[ \t]*\r?\n", head)
    if end is None:
        raise SplatFileError(path, "PLY header has no 'end_header' line (truncated file?)")
    try:
        lines = head[: end.start()].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise SplatFileError(path, "PLY header is not ASCII text") from None
    fmt, elements, antialiased = None, [], False
    for number, line in enumerate(lines, start=2):
        words = line.split()
        if words[:2] == ["comment", ANTIALIASED_COMMENT]:
            antialiased = True
        if not words or words[0] in ("comment", "obj_info"):
            continue
        where = f"PLY header line {number} '{line.strip()}'"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in FORMATS or words[2] != "1.0":
                raise SplatFileError(
                    path,
                    f"{where}: unsupported format (expected ascii, "
                    "binary_little_endian or binary_big_endian, version 1.0)",
                )
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise SplatFileError(path, f"{where}: expected 'element NAME COUNT'")
            elements.append(Element(words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise SplatFileError(path, f"{where}: property before any element")
            elements[-1].properties.append(_parse_property(path, where, words))
        else:
            raise SplatFileError(path, f"{where}: unknown keyword '{words[0]}'")
    if fmt is None:
        raise SplatFileError(path, "PLY header has no 'format' line")
    for element in elements:  # counted once each: a 1 MiB header holds 45,000 properties
        dupes = sorted(n for n, times in Counter(name for name, _ in element.properties).items() if times > 1)
        if dupes:
            raise SplatFileError(path, f"{element.name} element repeats properties {dupes}")
    return fmt, elements, end.end(), antialiased


def _parse_property(path, where, words):
    if len(words) == 5 and words[1] == "list":
        types = words[2:4]
        if all(t in PLY_TYPES for t in types):
            return words[4], ("list", PLY_TYPES[types[0]], PLY_TYPES[types[1]])
    elif len(words) == 3 and words[1] in PLY_TYPES:
        return words[2], PLY_TYPES[words[1]]
    raise SplatFileError(
        path,
        f"{where}: expected 'property TYPE NAME' or 'property list TYPE TYPE NAME' "
        f"with TYPE one of {', '.join(sorted(set(TYPE_NAMES.values())))}",
    )


def sh_order(k):
    """Column permutation from the file's f_dc_0..2, f_rest_* (channel-major) to the cloud's
    (K, 3) coefficient-major SH: sh.reshape(N, 3K) = file_columns[:, sh_order(k)]."""
    j, c = np.meshgrid(np.arange(1, k), np.arange(3), indexing="ij")  # coefficient j, channel c
    return np.concatenate([[0, 1, 2], 3 + c.ravel() * (k - 1) + (j.ravel() - 1)])
