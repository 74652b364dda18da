"""Reading OpenUSD text layers without OpenUSD: a .usda file (or a .usdz whose first file is one)
into a usda.Layer, over the subset of the grammar usda.py describes (tokens: usda_tokens.py; typed
values as OpenUSD reads them, numeric arrays in bulk: usda_values.py). A layer bigger than
policy.MAX_TEXT_LAYER_BYTES is refused before it is read; composition and crate layers are refused
by name.

The parser keeps its own stacks rather than recursing, and prims, lists and dictionaries nested
more than MAX_DEPTH deep are refused, so no text can exhaust Python's stack; memory stays a few
times the size of the text.
"""

import io as _io
import math
import os
import re
import zipfile

from ..common import SplatFileError
from ..policy import MAX_TEXT_LAYER_BYTES
from .usda import COMPOSITION, Layer, element
from .usda_tokens import ASSET, NUMBER, PATH, STRING, WORD, Asset, Tokens, Word, shown
from .usda_values import BadValue, Unregistered, numeric_array, scalar, typed, typed_list

MAX_DEPTH = 256  # prims in prims, lists in lists, dictionaries in dictionaries
SPECIFIERS = ("def", "over", "class")
QUALIFIERS = ("custom", "uniform", "varying", "config")
LIST_OPS = ("add", "delete", "prepend", "append", "reorder")
# metadata the readers use, typed as OpenUSD types them
TYPED_METADATA = {"elementSize": "int", "active": "bool", "instanceable": "bool", "hidden": "bool"}
TEXT_METADATA = ("interpolation", "kind", "upAxis", "defaultPrim")


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
    del data
    if not text.startswith("#usda"):
        raise SplatFileError(path, "not an OpenUSD text layer (it does not start with '#usda')")
    layer = Layer(os.fspath(path))
    try:
        _Parser(path, text, layer).parse()
    except MemoryError:
        raise SplatFileError(path, "its values need more memory than this machine has") from None
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


_PRIM_NAME = re.compile(r"[^\W\d]\w*+")


class _Parser:
    """The layer's prims, properties and values; each kind of nesting is kept on a stack of its own
    and refused beyond MAX_DEPTH."""

    def __init__(self, path, text, layer):
        first_line = text.find("\n")
        self.tokens = Tokens(path, text, len(text) if first_line < 0 else first_line)
        self.layer = layer
        self.child_orders = {}  # prim path -> the names its `reorder nameChildren` lists

    def fail(self, problem):
        self.tokens.fail(problem)

    def parse(self):
        t = self.tokens
        if t.at("("):
            self.layer.metadata = self.metadata("layer")
        open_prims = []
        while True:
            kind, tok, _ = t.peek()
            if tok is None:
                if open_prims:
                    self.fail(f"unexpected end of file, expected '}}' closing {open_prims[-1].path}")
                return
            if tok == "}" and open_prims:
                t.next()
                closed = open_prims.pop()
                if closed.path in self.child_orders:
                    closed.children = _reordered(closed.children, self.child_orders[closed.path])
            elif kind == WORD and tok in SPECIFIERS:
                if len(open_prims) >= MAX_DEPTH:
                    self.fail(f"prims nested more than {MAX_DEPTH} deep, the most this reader follows")
                open_prims.append(self.prim(open_prims[-1].path if open_prims else ""))
            elif open_prims:
                self.property(open_prims[-1])
            else:
                self.fail(f"expected a prim (def, over or class), found {shown(tok)}")

    def prim(self, parent):
        """A prim's header and metadata, up to the `{` opening its body."""
        t = self.tokens
        _, specifier = t.next()
        kind, tok = t.next()
        type_name = ""
        if kind == WORD:
            type_name = tok
            kind, tok = t.next()
        if kind != STRING:
            self.fail(f"expected the prim's name in quotes, found {shown(tok)}")
        name = t.string(tok)
        if not _PRIM_NAME.fullmatch(name):
            self.fail(f"{shown(name)} is not a valid prim name")
        path = f"{parent}/{name}"
        if self.layer.prim_at(path) is not None:
            self.fail(f"prim {path} is defined twice")
        prim = self.layer.define(path, type_name)
        prim.specifier = specifier
        if t.at("("):
            prim.metadata = self.metadata(path)
        t.next("{")
        return prim

    def metadata(self, owner):
        """{key: value} of a parenthesised metadata block; composition arcs refused."""
        t = self.tokens
        t.next("(")
        meta = {}
        while not t.at(")"):
            kind, tok = t.next()
            if kind == STRING:  # a doc string
                meta["doc"] = t.string(tok)
                continue
            if tok in LIST_OPS:
                kind, tok = t.next()
            if tok in COMPOSITION:
                self.fail(f"{owner} uses composition ({tok}), which needs OpenUSD's Python module to resolve")
            if kind != WORD:
                self.fail(f"expected metadata of {owner}, found {shown(tok)}")
            t.next("=")
            meta[tok] = self.dictionary() if t.at("{") else self.metadata_value(owner, tok, self.value())
            if t.at(";"):
                t.next()
        t.next(")")
        return meta

    def metadata_value(self, owner, key, value):
        """Metadata the readers use, checked as OpenUSD types it."""
        if key in TYPED_METADATA:
            type_name = TYPED_METADATA[key]
            try:
                return scalar(type_name, element(type_name)[0], value)
            except BadValue as exc:
                self.fail(f"{owner}: {key}: {exc}")
        if key in TEXT_METADATA and (not isinstance(value, str) or isinstance(value, Word)):
            self.fail(f"{owner}: {key} must be a string in quotes, found {shown(str(value))}")
        return value

    def property(self, prim):
        t = self.tokens
        qualifiers = set()
        kind, tok = t.next()
        while tok in QUALIFIERS or tok in LIST_OPS:
            qualifiers.add(tok)
            kind, tok = t.next()
        if "reorder" in qualifiers and tok in ("nameChildren", "properties"):
            t.next("=")
            order = self.value()
            if not isinstance(order, list) or not order or not all(_is_quoted(name) for name in order):
                self.fail(f"{prim.path}: reorder {tok} needs a list of names in quotes")
            if tok == "nameChildren":
                self.child_orders[prim.path] = order
            return
        if tok == "rel":
            _, name = t.next()
            if t.at("="):
                t.next()
                self.value()
            if t.at("("):
                self.metadata(f"{prim.path}.{name}")
            return
        if tok == "variantSet":
            self.fail(f"{prim.path} has a variant set, which needs OpenUSD's Python module to resolve")
        if kind != WORD:
            self.fail(f"expected a property of {prim.path}, found {shown(tok)}")
        type_name = tok
        kind, name = t.next()
        if kind != WORD:
            self.fail(f"expected an attribute name after {shown(type_name)}, found {shown(name)}")
        name, _, suffix = name.partition(".")
        if suffix not in ("", "timeSamples", "connect"):
            self.fail(f"{prim.path}.{name}: .{suffix} values cannot be read without OpenUSD's Python module")
        where = f"{prim.path}.{name}"
        known = prim.attributes.get(name)
        if known is not None and known.type_name != type_name:
            self.fail(f"{where} already has type {known.type_name!r}, so it cannot be a {type_name!r}")
        attr = prim.attribute(name, type_name, "uniform" in qualifiers, "custom" in qualifiers)
        if t.at("="):
            t.next()
            if suffix == "timeSamples":
                attr.samples = self.time_samples(where, type_name)
            elif suffix == "connect":
                self.value()
            else:
                attr.default = self.typed_value(where, type_name)
        if t.at("(") and suffix == "":  # OpenUSD takes metadata on a declaration only
            attr.metadata.update(self.metadata(where))

    def time_samples(self, where, type_name):
        t = self.tokens
        t.next("{")
        samples = {}
        while not t.at("}"):
            kind, tok = t.next()
            if kind != NUMBER:
                self.fail(f"{where}: expected a time code, found {shown(tok)}")
            if not math.isfinite(float(tok)):  # OpenUSD keeps such a sample but orders it nowhere
                self.fail(f"{where}: a time sample at {tok}")
            t.next(":")
            samples[float(tok)] = self.typed_value(where, type_name)
            if not t.at("}"):
                t.next(",")
        t.next("}")
        return samples

    def typed_value(self, where, type_name):
        """A value of `type_name` as OpenUSD reads it (see usda_values.py), or None (blocked)."""
        t = self.tokens
        if t.at("None"):
            t.next()
            return None
        spec = element(type_name)
        is_array = type_name.endswith("[]")
        try:
            if spec is not None and is_array and spec[0].kind != "b":
                return self.numeric_array(type_name, spec)
            value = self.value()
            if spec is None:
                return _text_value(type_name, value)
            if is_array:
                if not isinstance(value, list):
                    raise BadValue(f"a {type_name} needs a list in [ ], found {shown(str(value))}")
                return typed_list(type_name, spec, value)
            return typed(type_name, spec, value)
        except BadValue as exc:
            self.fail(f"{where}: {exc}")

    def numeric_array(self, type_name, spec):
        """A numeric array in bulk, or token by token where it holds comments."""
        t = self.tokens
        start = t.pos
        t.next("[")
        end = t.text.find("]", t.pos)
        if end < 0:
            self.fail(f"a {type_name} array is not closed")
        body = t.text[t.pos : end]
        if "#" in body or "/" in body:
            t.pos = start
            return typed_list(type_name, spec, self.value())
        values = numeric_array(type_name, spec, body)
        t.pos = end + 1
        return values

    def dictionary(self):
        """A dictionary's { type key = value ... } entries, dictionaries in it kept on a stack."""
        t = self.tokens
        t.next("{")
        root = {}
        stack = [root]
        while stack:
            if t.at("}"):
                t.next()
                stack.pop()
                continue
            _, type_name = t.next()
            kind, key = t.next()
            key = t.string(key) if kind == STRING else key
            t.next("=")
            if type_name != "dictionary":
                stack[-1][key] = self.value()
                continue
            if len(stack) >= MAX_DEPTH:
                self.fail(f"dictionaries nested more than {MAX_DEPTH} deep, the most this reader follows")
            t.next("{")
            stack[-1][key] = child = {}
            stack.append(child)
        return root

    def value(self):
        """A generic value: number, string, word, asset or prim path, tuple or list (nested)."""
        t = self.tokens
        stack = []  # (items, closing token) of the tuples and lists still open
        while True:
            if stack and t.at(stack[-1][1]):  # empty, or after a trailing comma
                item = self._close(stack)
            else:
                kind, tok = t.next()
                if tok in ("(", "[") and kind not in (STRING, PATH):
                    if len(stack) >= MAX_DEPTH:
                        self.fail(f"values nested more than {MAX_DEPTH} deep, the most this reader follows")
                    stack.append(([], ")" if tok == "(" else "]"))
                    continue
                item = self.atom(kind, tok)
            while stack:
                items, close = stack[-1]
                items.append(item)
                _, tok, end = t.peek()
                if tok == ",":
                    t.pos = end
                    break
                if tok != close:
                    self.fail(f"expected ',' or {close!r}, found {shown(tok or 'the end of the file')}")
                item = self._close(stack)
            else:
                return item

    def _close(self, stack):
        items, close = stack.pop()
        self.tokens.next(close)
        return tuple(items) if close == ")" else items

    def atom(self, kind, tok):
        if kind == STRING:
            return self.tokens.string(tok)
        if kind == NUMBER:
            if any(c in tok for c in ".eEin"):
                return float(tok)
            if len(tok) > 40:  # beyond every integer type (and Python's digit limit): as a double
                return float(tok)
            return int(tok)
        if kind == WORD:
            return Word(tok)
        if kind == ASSET:
            return Asset(tok[1:-1])
        if kind == PATH:
            return tok[1:-1]
        self.fail(f"unexpected {shown(tok)}")


def _is_quoted(value):
    return isinstance(value, str) and not isinstance(value, (Word, Asset))


def _reordered(children, order):
    """The prims in the order `reorder nameChildren` gives, as Sdf applies one: each named prim
    takes the unnamed ones after it along, the named groups follow the order, and prims before the
    first named one stay first."""
    names = {child.path.rsplit("/", 1)[1] for child in children}
    named = [name for name in dict.fromkeys(order) if name in names]
    if not named:
        return children
    first, groups, current = [], {name: [] for name in named}, None
    for child in children:
        name = child.path.rsplit("/", 1)[1]
        if name in groups:
            current = name
        (groups[current] if current is not None else first).append(child)
    return first + [child for name in named for child in groups[name]]


def _text_value(type_name, value):
    """A value of a non-numeric type: strings and tokens in quotes, asset paths in @s (or quotes),
    arrays of them in [ ]; the value of a type OpenUSD does not know is kept as Unregistered."""
    base = type_name.removesuffix("[]")
    if base not in ("string", "token", "asset"):
        return value if base in ("opaque", "group", "pathExpression") else Unregistered(value)
    is_array = type_name.endswith("[]")
    if is_array != isinstance(value, list):
        raise BadValue(f"a {type_name} needs {'a list in [ ]' if is_array else 'one value'}, found {shown(str(value))}")
    for item in value if is_array else [value]:
        if not (_is_quoted(item) or (base == "asset" and isinstance(item, Asset))):
            needs = "a path in @s" if base == "asset" else "a string in quotes"
            raise BadValue(f"a {base} is {needs}, found {item!r:.60}")
    return value
