"""Reading OpenUSD text layers without OpenUSD: a .usda file (or a .usdz whose first file is one)
into a usda.Layer, by recursive descent over the subset of the grammar usda.py describes, numeric
arrays parsed in bulk by NumPy. A layer bigger than policy.MAX_TEXT_LAYER_BYTES is refused before it
is read; composition and crate layers are refused by name.
"""

import io as _io
import os
import re
import warnings
import zipfile

import numpy as np

from ..common import SplatFileError
from ..policy import MAX_TEXT_LAYER_BYTES
from .usda import COMPOSITION, Layer, element


def read_layer(path):
    """The Layer in a .usda/.usd text file or a .usdz package whose first file is text. A layer of
    more than policy.MAX_TEXT_LAYER_BYTES is refused before it is read."""
    with open(path, "rb") as f:
        _check_text_size(path, os.fstat(f.fileno()).st_size)
        data = f.read()
    if data.startswith(b"PK\x03\x04"):
        data = _usdz_root(path, data)
    if data.startswith(b"PXR-USDC"):
        raise SplatFileError(
            path,
            "a binary (crate) OpenUSD layer needs OpenUSD's Python module (pxr), which "
            "this Python lacks (Blender 4.4 and later bundle it); only text layers "
            "(.usda) can be read here",
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise SplatFileError(path, "it holds bytes that are not UTF-8 text") from None
    if not text.startswith("#usda"):
        raise SplatFileError(path, "not an OpenUSD text layer (it does not start with '#usda')")
    layer = Layer(os.fspath(path))
    _Parser(path, text, layer).parse()
    return layer


def _check_text_size(path, size):
    if size > MAX_TEXT_LAYER_BYTES:
        raise SplatFileError(
            path,
            f"a {size}-byte text layer, more than the {MAX_TEXT_LAYER_BYTES >> 20} MiB "
            "this reader parses without OpenUSD (write .usdc with pxr for bigger stages)",
        )


def _usdz_root(path, data):
    try:
        with zipfile.ZipFile(_io.BytesIO(data)) as z:
            names = z.namelist()
            if not names:
                raise SplatFileError(path, "the .usdz package is empty")
            if not names[0].lower().endswith((".usda", ".usd", ".usdc")):
                raise SplatFileError(path, f"the .usdz package's first file {names[0]!r} is not an OpenUSD layer")
            info = z.getinfo(names[0])
            if info.compress_type != zipfile.ZIP_STORED:  # the usdz rule; also no zip bomb
                raise SplatFileError(path, f"the .usdz package's {names[0]!r} is compressed; usdz files are stored")
            _check_text_size(path, info.file_size)
            return z.read(names[0])
    except (zipfile.BadZipFile, EOFError, OSError) as exc:
        raise SplatFileError(path, f"the .usdz package is damaged: {exc}") from None


TOKEN = re.compile(
    r'\s*(?:#[^\n]*\n\s*)*(?:("""(?:.|\n)*?"""|"(?:[^"\\\n]|\\.)*"|\'(?:[^\'\\\n]|\\.)*\')'
    r"|(@[^@]*@)|([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|-?inf\b|nan\b)"
    r"|([A-Za-z_][\w:.]*(?:\[\])?|![\w]+!)|(\S))"
)


class _Parser:
    """Recursive descent over the USDA grammar's subset named in the module notes."""

    def __init__(self, path, text, layer):
        self.path, self.text, self.layer, self.pos = path, text, layer, text.index("\n") if "\n" in text else len(text)

    def fail(self, problem):
        line = self.text.count("\n", 0, self.pos) + 1
        raise SplatFileError(self.path, f"line {line}: {problem}")

    def peek(self):
        m = TOKEN.match(self.text, self.pos)
        if m is None or m.lastindex is None:
            return None, None, self.pos
        return m.lastindex, m.group(m.lastindex), m.end()

    def next(self, expected=None):
        kind, tok, end = self.peek()
        if tok is None:
            self.fail(f"unexpected end of file{f', expected {expected!r}' if expected else ''}")
        if expected is not None and tok != expected:
            self.fail(f"expected {expected!r}, found {tok!r}")
        self.pos = end
        return kind, tok

    def at(self, tok):
        return self.peek()[1] == tok

    def parse(self):
        if self.at("("):
            self.layer.metadata = self.metadata("layer")
        while self.peek()[1] is not None:
            self.prim("")

    def metadata(self, owner):
        """{key: value} of a parenthesised metadata block; composition arcs refused."""
        self.next("(")
        meta = {}
        while not self.at(")"):
            kind, tok = self.next()
            if kind == 1:  # a doc string
                meta["doc"] = _string(tok)
                continue
            if tok in ("add", "delete", "prepend", "append", "reorder"):
                kind, tok = self.next()
            if tok in COMPOSITION:
                self.fail(f"{owner} uses composition ({tok}), which needs OpenUSD's Python module to resolve")
            self.next("=")
            meta[tok] = self.dictionary() if self.at("{") else self.value()
        self.next(")")
        return meta

    def prim(self, parent):
        kind, specifier = self.next()
        if specifier not in ("def", "over", "class"):
            self.fail(f"expected a prim (def, over or class), found {specifier!r}")
        kind, tok = self.next()
        type_name = ""
        if kind != 1:
            type_name = tok
            kind, tok = self.next()
        if kind != 1:
            self.fail(f"expected the prim's name in quotes, found {tok!r}")
        path = f"{parent}/{_string(tok)}"
        if self.layer.prim_at(path) is not None:
            self.fail(f"prim {path} is defined twice")
        prim = self.layer.define(path, type_name)
        prim.specifier = specifier
        if self.at("("):
            prim.metadata = self.metadata(path)
        self.next("{")
        while not self.at("}"):
            if self.peek()[1] in ("def", "over", "class"):
                self.prim(path)
            else:
                self.property(prim)
        self.next("}")

    def property(self, prim):
        qualifiers = set()
        kind, tok = self.next()
        while tok in ("custom", "uniform", "varying", "config"):
            qualifiers.add(tok)
            kind, tok = self.next()
        if tok == "rel":
            kind, name = self.next()
            if self.at("="):
                self.next()
                self.value()
            if self.at("("):
                self.metadata(f"{prim.path}.{name}")
            return
        if tok == "variantSet":
            self.fail(f"{prim.path} has a variant set, which needs OpenUSD's Python module to resolve")
        type_name = tok
        kind, name = self.next()
        if kind != 4:
            self.fail(f"expected an attribute name after {type_name!r}, found {name!r}")
        name, _, suffix = name.partition(".")
        if suffix not in ("", "timeSamples", "connect"):
            self.fail(f"{prim.path}.{name}: .{suffix} values cannot be read without OpenUSD's Python module")
        attr = prim.attribute(name, type_name, "uniform" in qualifiers, "custom" in qualifiers)
        if self.at("="):
            self.next()
            if suffix == "timeSamples":
                attr.samples = self.time_samples(type_name)
            elif suffix == "connect":
                self.value()
            else:
                attr.default = self.typed_value(type_name)
        if self.at("("):
            attr.metadata.update(self.metadata(f"{prim.path}.{name}"))

    def time_samples(self, type_name):
        self.next("{")
        samples = {}
        while not self.at("}"):
            kind, tok = self.next()
            if kind != 3:
                self.fail(f"expected a time code, found {tok!r}")
            self.next(":")
            samples[float(tok)] = self.typed_value(type_name)
            if self.at(","):
                self.next()
        self.next("}")
        return samples

    def typed_value(self, type_name):
        """A value of `type_name`: numeric arrays parsed in bulk, anything else generically."""
        spec = element(type_name)
        if self.at("None"):
            self.next()
            return None
        if spec is None or not self.at("["):
            value = self.value()
            if spec is not None and not isinstance(value, str):
                dtype, width = spec
                value = np.asarray(value, np.float64)
                if value.size != width:
                    self.fail(f"a {type_name} needs {width} numbers, found {value.size}")
                value = value.astype(dtype) if width > 1 else value.astype(dtype).item()
                if type_name.startswith("quat"):
                    value = value[[1, 2, 3, 0]]
            return value
        return self.numeric_array(type_name, *spec)

    def numeric_array(self, type_name, dtype, width):
        self.next("[")
        end = self.text.find("]", self.pos)
        if end < 0:
            self.fail(f"a {type_name} array is not closed")
        body = self.text[self.pos : end]
        if re.search(r"[^\d\s.,()eE+\-infa]", body):
            self.fail(f"a {type_name} array holds something other than numbers")
        parse = np.float64 if dtype.kind == "f" else np.int64
        with warnings.catch_warnings():
            warnings.simplefilter("error", DeprecationWarning)
            try:
                flat = (
                    np.fromstring(body.translate(_SEPARATORS), parse, sep=" ") if body.strip() else np.zeros(0, parse)
                )
            except (DeprecationWarning, ValueError):
                self.fail(f"a {type_name} array holds text that is not a number")
        if flat.size % width:
            self.fail(f"a {type_name} array has {flat.size} numbers, not a multiple of {width}")
        values = flat.astype(dtype).reshape((-1, width) if width > 1 else (-1,))
        if type_name.startswith("quat"):
            values = np.ascontiguousarray(values[:, [1, 2, 3, 0]])  # w first in text, x, y, z, w held
        self.pos = end + 1
        return values

    def dictionary(self):
        self.next("{")
        d = {}
        while not self.at("}"):
            kind, type_name = self.next()
            kind, key = self.next()
            key = _string(key) if kind == 1 else key
            self.next("=")
            d[key] = self.dictionary() if type_name == "dictionary" else self.value()
        self.next("}")
        return d

    def value(self):
        """A generic value: number, string, token, asset path, tuple or list (nested)."""
        kind, tok = self.next()
        if tok in ("(", "["):
            close = ")" if tok == "(" else "]"
            items = []
            while not self.at(close):
                items.append(self.value())
                if self.at(","):
                    self.next()
            self.next(close)
            return tuple(items) if tok == "(" else items
        if kind == 1:
            return _string(tok)
        if kind == 2:
            return tok[1:-1]
        if kind == 3:
            return float(tok) if any(c in tok for c in ".eEin") else int(tok)
        if kind == 4:
            return tok
        self.fail(f"unexpected {tok!r}")


_SEPARATORS = str.maketrans("(),", "   ")


def _string(tok):
    if tok.startswith('"""'):
        return tok[3:-3]
    return re.sub(r"\\(.)", r"\1", tok[1:-1])
