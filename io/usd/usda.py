"""OpenUSD text layers without OpenUSD: the layer model the text stage implementation (text_stages.py)
authors and reads, and its text as OpenUSD itself writes it.

A Layer holds typed prims, attributes with default values, time samples and metadata, and layer
metadata; `Layer.text` writes it in OpenUSD's own syntax, `Layer.save` to a .usda or (a zip of that
layer, see usdz.py) a .usdz. usda_parse.read_layer reads the same subset back from any .usda.
Composition (sublayers, references, payloads, inherits, specializes, variants) needs OpenUSD to
resolve and is refused by name, as are binary (crate) layers.

Numeric arrays are written (and parsed) in bulk by NumPy: writing costs about 1 us per number,
reading a quarter of that. Prims, attributes and primvars answer the few pxr calls the readers make
(GetAttribute, Get, HasAuthoredValue, GetTimeSamples, PrimvarsAPI ...), so one reader serves both
implementations; like pxr, arrays of quaternions come back in Vt's memory order (x, y, z, w) although
the text writes them w first.
"""

import io as _io
import os
import re
from dataclasses import dataclass, field

import numpy as np

from ...core.geometry import quaternions_to_matrices
from ..common import SplatFileError
from .schema import is_quaternion
from .usdz import write_usdz

HEADER = "#usda 1.0"
COMPOSITION = ("subLayers", "references", "payload", "inherits", "specializes", "variantSets", "variants")

# scalar type -> NumPy dtype (bools are written 0 and 1)
SCALARS = {
    "bool": np.bool_,
    "uchar": np.uint8,
    "int": np.int32,
    "uint": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "half": np.float16,
    "float": np.float32,
    "double": np.float64,
    "timecode": np.float64,
}
FLOATS = {"h": np.float16, "f": np.float32, "d": np.float64}
VECTOR = re.compile(
    r"(half|float|double|int)([234])|(point|normal|vector|color)3([hfd])|texCoord([23])([hfd])"
    r"|quat([hfd])|matrix([234])d"
)


def element(type_name):
    """(NumPy dtype, numbers per element) of a numeric USD type ("float3[]" -> float32, 3), or None."""
    base = type_name[:-2] if type_name.endswith("[]") else type_name
    if base in SCALARS:
        return np.dtype(SCALARS[base]), 1
    m = VECTOR.fullmatch(base)
    if m is None:
        return None
    scalar, n, _, role, tex_n, tex_t, quat, matrix = m.groups()
    if scalar:
        return np.dtype(SCALARS[scalar]), int(n)
    if role:
        return np.dtype(FLOATS[role]), 3
    if tex_n:
        return np.dtype(FLOATS[tex_t]), int(tex_n)
    if quat:
        return np.dtype(FLOATS[quat]), 4
    return np.dtype(np.float64), int(matrix) ** 2


# the layer model ----------------------------------------------------------------------------------


@dataclass
class Attribute:
    """One attribute: its default value and time samples as NumPy arrays (or Python scalars,
    strings, lists of strings), and its metadata. Quaternions are held in Vt's memory order
    (x, y, z, w), as pxr hands them out."""

    name: str
    type_name: str
    uniform: bool = False
    custom: bool = False
    default: object = None
    samples: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    # authoring
    def Set(self, value, time=None):
        if time is None:
            self.default = value
        else:
            self.samples[float(time)] = value

    # the pxr calls the readers make
    def __bool__(self):
        return True

    def GetName(self):
        return self.name

    def GetTypeName(self):
        return self.type_name

    def HasAuthoredValue(self):
        return self.default is not None or bool(self.samples)

    def GetTimeSamples(self):
        return sorted(self.samples)

    def GetCustomDataByKey(self, key):
        value = self.metadata.get("customData", {})
        for part in key.split(":"):
            value = value.get(part) if isinstance(value, dict) else None
        return value

    def Get(self, time=None):
        """The value at `time` as OpenUSD resolves it: time samples over the default, held before
        the first and after the last, linear between samples of the same shape; time=None asks for
        the earliest sample (the default when there are none)."""
        if not self.samples:
            return self.default
        times = self.GetTimeSamples()
        t = times[0] if time is None else float(time)
        i = int(np.searchsorted(times, t, side="right"))
        if i == 0 or times[i - 1] == t or i == len(times):
            return self.samples[times[max(i - 1, 0)]]
        a, b = self.samples[times[i - 1]], self.samples[times[i]]
        if isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.shape == b.shape and a.dtype.kind == "f":
            w = (t - times[i - 1]) / (times[i] - times[i - 1])
            return (a + (b - a) * w).astype(a.dtype)
        return a


class _Missing:
    """What GetAttribute returns for an attribute the prim does not have (falsy, as in pxr)."""

    def __bool__(self):
        return False


@dataclass
class Prim:
    path: str
    type_name: str = ""
    specifier: str = "def"
    attributes: dict = field(default_factory=dict)
    children: list = field(default_factory=list)
    metadata: dict = field(default_factory=dict)
    layer: "Layer" = None

    def attribute(self, name, type_name, uniform=False, custom=False):
        """The attribute `name`, created with this type when new."""
        if name not in self.attributes:
            self.attributes[name] = Attribute(name, type_name, uniform, custom)
        return self.attributes[name]

    # the pxr calls the readers make
    def GetPath(self):
        return self.path

    def GetTypeName(self):
        return self.type_name

    def GetAttribute(self, name):
        return self.attributes.get(name) or _Missing()

    def GetAttributes(self):
        return list(self.attributes.values())

    def GetStage(self):
        return self.layer

    def local_matrix(self, time):
        """4x4 (column vectors) of the prim's own transform ops, and whether it resets the parents'."""
        order = self.GetAttribute("xformOpOrder")
        names = list(order.Get() or []) if order else []
        m, reset = np.eye(4), False
        for name in names:
            if name == "!resetXformStack!":
                m, reset = np.eye(4), True
                continue
            invert = name.startswith("!invert!")
            op_name = name[len("!invert!") :] if invert else name
            attr = self.GetAttribute(op_name)
            if not attr or not attr.HasAuthoredValue():
                raise SplatFileError(self.layer.identifier, f"{self.path}: transform op {op_name} has no value")
            op = _op_matrix(self.layer.identifier, self.path, op_name, attr.Get(time))
            m = m @ (np.linalg.inv(op) if invert else op)
        return m, reset

    def world_matrix(self, time):
        local, reset = self.local_matrix(time)
        parent = self.layer.prim_at(self.path.rsplit("/", 1)[0]) if self.path.count("/") > 1 else None
        return local if reset or parent is None else parent.world_matrix(time) @ local


def _op_matrix(path, prim_path, name, value):
    """4x4 (column vectors) of one transform op, OpenUSD's conventions (angles in degrees; an
    xformOp:rotateXYZ turns about X first)."""
    kind = name.split(":")[1] if name.count(":") >= 1 else ""
    m = np.eye(4)
    value = np.asarray(value, np.float64)
    if not np.isfinite(value).all():  # a NaN quaternion would normalise to the identity
        raise SplatFileError(path, f"{prim_path}: its transform ops {name} hold NaN or Inf")
    if kind == "transform":
        return value.reshape(4, 4).T  # USD matrices act on row vectors
    if kind == "translate":
        m[:3, 3] = value.reshape(3)
    elif kind == "scale":
        m[:3, :3] = np.diag(np.broadcast_to(value.reshape(-1), 3))
    elif kind == "orient":
        x, y, z, w = value.reshape(4)  # Vt order (see Attribute)
        m[:3, :3] = quaternions_to_matrices(np.array([[w, x, y, z]]))[0]
    elif kind in ("rotateX", "rotateY", "rotateZ"):
        m[:3, :3] = _rotation(kind[-1], float(value))
    elif re.fullmatch("rotate[XYZ]{3}", kind):
        for axis, angle in zip(kind[-3:], value.reshape(3)):
            m[:3, :3] = _rotation(axis, float(angle)) @ m[:3, :3]
    else:
        raise SplatFileError(path, f"{prim_path}: transform op {name} cannot be read without OpenUSD's Python module")
    return m


def _rotation(axis, degrees):
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    i, j = {"X": (1, 2), "Y": (2, 0), "Z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


class Layer:
    """One text layer: its metadata and prims."""

    def __init__(self, identifier=""):
        self.identifier = identifier
        self.metadata = {}
        self.root_prims = []
        self._by_path = {}

    def GetRootLayer(self):
        return self

    def define(self, path, type_name=""):
        """The prim at `path` (ancestors defined as Xform where missing), its type set."""
        prim = self._by_path.get(path)
        if prim is None:
            parent_path = path.rsplit("/", 1)[0]
            parent = self.define(parent_path, "Xform") if parent_path else None
            prim = Prim(path, type_name, layer=self)
            (parent.children if parent else self.root_prims).append(prim)
            self._by_path[path] = prim
        elif type_name and not prim.type_name:
            prim.type_name = type_name
        return prim

    def prim_at(self, path):
        return self._by_path.get(path)

    def GetPrimAtPath(self, path):
        return self._by_path.get(path) or _Missing()

    def traverse(self):
        """Every prim, parents before children."""
        stack = list(reversed(self.root_prims))
        while stack:
            prim = stack.pop()
            yield prim
            stack.extend(reversed(prim.children))

    # writing
    def save(self, path, package_name=None, usdz=None):
        """Write the layer to `path`: text, or with usdz (default: `path` ends in .usdz) a package
        of it named package_name (default: the stem of `path` + .usda)."""
        text = self.text()
        if path.lower().endswith(".usdz") if usdz is None else usdz:
            name = package_name or os.path.splitext(os.path.basename(path))[0] + ".usda"
            write_usdz(path, name, text.encode())
        else:
            with open(path, "w", encoding="utf-8", newline="\n") as f:
                f.write(text)

    def text(self):
        out = _io.StringIO()
        out.write(HEADER + "\n")
        if self.metadata:
            out.write("(\n")
            for key, value in sorted(self.metadata.items()):
                out.write(f"    {key} = {_scalar_text(value)}\n")
            out.write(")\n")
        for prim in self.root_prims:
            out.write("\n")
            _write_prim(out, prim, "")
        return out.getvalue()


def _write_prim(out, prim, indent):
    name = prim.path.rsplit("/", 1)[1]
    type_part = f"{prim.type_name} " if prim.type_name else ""
    out.write(f'{indent}{prim.specifier} {type_part}"{name}"\n{indent}{{\n')
    inner = indent + "    "
    for attr in prim.attributes.values():
        _write_attribute(out, attr, inner)
    for child in prim.children:
        out.write("\n")
        _write_prim(out, child, inner)
    out.write(f"{indent}}}\n")


def _write_attribute(out, attr, indent):
    head = ("custom " if attr.custom else "") + ("uniform " if attr.uniform else "") + f"{attr.type_name} {attr.name}"
    meta = _metadata_text(attr.metadata, indent)
    if attr.default is not None or not attr.samples or meta:  # metadata sits on the declaration
        value = f" = {value_text(attr.default, attr.type_name)}" if attr.default is not None else ""
        out.write(f"{indent}{head}{value}{meta}\n")
    if attr.samples:
        out.write(f"{indent}{head}.timeSamples = {{\n")
        for t, value in sorted(attr.samples.items()):
            out.write(f"{indent}    {_number_text(t)}: {value_text(value, attr.type_name)},\n")
        out.write(f"{indent}}}\n")


def _metadata_text(metadata, indent):
    if not metadata:
        return ""
    lines = [
        f"{indent}    {key} = {_meta_value_text(value, indent + '    ')}" for key, value in sorted(metadata.items())
    ]
    return " (\n" + "\n".join(lines) + f"\n{indent})"


def _meta_value_text(value, indent):
    if isinstance(value, dict):
        return _dictionary_text(value, indent)
    return _scalar_text(value)


def _dictionary_text(d, indent):
    lines = []
    for key, value in sorted(d.items()):
        if isinstance(value, dict):
            lines.append(f"{indent}    dictionary {key} = {_dictionary_text(value, indent + '    ')}")
        elif isinstance(value, str):
            lines.append(f"{indent}    string {key} = {_scalar_text(value)}")
        else:
            lines.append(f"{indent}    double {key} = {_scalar_text(value)}")
    return "{\n" + "\n".join(lines) + f"\n{indent}}}"


def _number_text(x):
    x = float(x)
    return str(int(x)) if x.is_integer() else repr(x)


def _scalar_text(value):
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return _number_text(value)


def value_text(value, type_name):
    """A value in USDA syntax: numeric arrays formatted by NumPy in bulk (shortest round-trip
    decimals), quaternions w first."""
    if type_name in ("token[]", "string[]"):
        return "[" + ", ".join(_scalar_text(v) for v in value) + "]"
    if isinstance(value, str) or np.ndim(value) == 0:
        return _scalar_text(value.item() if isinstance(value, np.generic) else value)
    values = np.asarray(value)
    if is_quaternion(type_name):
        values = values[..., [3, 0, 1, 2]]
    if values.dtype == bool:
        values = values.astype(np.uint8)
    if type_name.startswith("matrix"):
        rows = values.reshape(-1, values.shape[-1])
        return "( " + ", ".join("(" + ", ".join(r.astype(str).tolist()) + ")" for r in rows) + " )"
    words = values.astype(str).reshape(len(values), -1) if len(values) else np.zeros((0, 1), str)
    if not type_name.endswith("[]"):
        return "(" + ", ".join(words.reshape(-1).tolist()) + ")"
    if values.ndim == 1:
        return "[" + ", ".join(words.reshape(-1).tolist()) + "]"
    one = "(" + ", ".join(["%s"] * words.shape[1]) + ")"
    return "[" + ", ".join([one] * len(words)) % tuple(words.reshape(-1).tolist()) + "]"


# pxr-like views for the readers ----------------------------------------------------------------------


class Primvar:
    def __init__(self, attr, prim):
        self.attr, self.prim = attr, prim

    def __bool__(self):
        return True

    def GetAttr(self):
        return self.attr

    def GetPrimvarName(self):
        return self.attr.name[len("primvars:") :]

    def GetTypeName(self):
        return self.attr.type_name

    def GetInterpolation(self):
        return self.attr.metadata.get("interpolation", "constant")

    def GetElementSize(self):
        return int(self.attr.metadata.get("elementSize", 1))

    def HasAuthoredValue(self):
        return self.attr.HasAuthoredValue()

    def ComputeFlattened(self, time=None):
        value = self.attr.Get(time)
        indices = self.prim.GetAttribute(self.attr.name + ":indices")
        if value is None or not indices or not indices.HasAuthoredValue():
            return value
        index = np.asarray(indices.Get(time))
        if len(index) and (index.min() < 0 or index.max() >= len(value)):
            raise SplatFileError(
                self.prim.layer.identifier, f"{self.prim.path}: {self.attr.name}:indices point outside its values"
            )
        return np.asarray(value)[index]


class PrimvarsAPI:
    def __init__(self, prim):
        self.prim = prim

    def GetPrimvar(self, name):
        attr = self.prim.GetAttribute("primvars:" + name)
        return Primvar(attr, self.prim) if attr else attr

    def HasPrimvar(self, name):
        return bool(self.prim.GetAttribute("primvars:" + name))

    def GetPrimvarsWithAuthoredValues(self):
        return [
            Primvar(a, self.prim)
            for name, a in self.prim.attributes.items()
            if name.startswith("primvars:") and not name.endswith(":indices") and a.HasAuthoredValue()
        ]
