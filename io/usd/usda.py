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
the text writes them w first. They answer as pxr does: samples are interpolated as Usd interpolates
them (Gf's slerp for quaternions), transform ops give the matrices UsdGeomXformOp gives (through
GfRotation's quaternions, each op inverted as it inverts them, a value of a type it does not take
refused), and only Xformable ancestors' ops reach a prim's world transform.
"""

import bisect
import io as _io
import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

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
    r"(half|float|double|int)([234])|(point|normal|vector|color)3([hfd])|color4([hfd])|texCoord([23])([hfd])"
    r"|quat([hfd])|matrix([234])d|(frame)4d"
)


def element(type_name):
    """(NumPy dtype, numbers per element) of a numeric USD type ("float3[]" -> float32, 3), or None."""
    base = type_name[:-2] if type_name.endswith("[]") else type_name
    if base in SCALARS:
        return np.dtype(SCALARS[base]), 1
    m = VECTOR.fullmatch(base)
    if m is None:
        return None
    scalar, n, _, role, color4, tex_n, tex_t, quat, matrix, frame = m.groups()
    if scalar:
        return np.dtype(SCALARS[scalar]), int(n)
    if role:
        return np.dtype(FLOATS[role]), 3
    if color4:
        return np.dtype(FLOATS[color4]), 4
    if tex_n:
        return np.dtype(FLOATS[tex_t]), int(tex_n)
    if quat:
        return np.dtype(FLOATS[quat]), 4
    return np.dtype(np.float64), 16 if frame else int(matrix) ** 2


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
        return list(self._times())

    def _times(self):
        """The sample times in order, sorted once for as long as the samples stay the same."""
        key = (id(self.samples), len(self.samples))
        if getattr(self, "_sorted", (None, None))[0] != key:
            self._sorted = (key, sorted(self.samples))
        return self._sorted[1]

    def GetCustomDataByKey(self, key):
        value = self.metadata.get("customData", {})
        for part in key.split(":"):
            value = value.get(part) if isinstance(value, dict) else None
        return value

    def Get(self, time=None):
        """The value at `time` as OpenUSD resolves it: time samples over the default, held before
        the first and after the last, interpolated between samples (see _interpolated); time=None
        asks for the earliest sample (the default when there are none)."""
        if not self.samples:
            return self.default
        times = self._times()
        t = times[0] if time is None else float(time)
        i = bisect.bisect_right(times, t)
        if i == 0 or times[i - 1] == t or i == len(times):
            return self.samples[times[max(i - 1, 0)]]
        alpha = (t - times[i - 1]) / (times[i] - times[i - 1])
        return _interpolated(self.type_name, self.samples[times[i - 1]], self.samples[times[i]], alpha)


def _interpolated(type_name, a, b, alpha):
    """The value `alpha` of the way from sample a to sample b as OpenUSD interpolates it: quaternions
    slerped, other floating-point values and arrays of them blended (1 - alpha) a + alpha b,
    rounded where Gf's arithmetic rounds; anything else (integers, bools, text, arrays of different
    lengths, a blocked sample) held at a."""
    spec = element(type_name)
    if a is None or b is None or spec is None or spec[0].kind != "f":
        return a
    dtype = spec[0]
    if isinstance(a, float) and isinstance(b, float):  # one number: blended in double, rounded once
        return np.float64((1 - alpha) * a + alpha * b).astype(dtype).item()
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != dtype or b.dtype != dtype:
        return a
    if is_quaternion(type_name):
        return _slerp(alpha, a, b)
    wide_a, wide_b = a.astype(np.float64), b.astype(np.float64)
    if a.ndim == 1 and type_name.endswith("[]"):  # arrays of numbers: each blended in double
        return ((1 - alpha) * wide_a + alpha * wide_b).astype(dtype)
    return ((1 - alpha) * wide_a).astype(dtype) + (alpha * wide_b).astype(dtype)  # Gf vectors: per term


def _slerp(alpha, q0, q1):
    """GfSlerp of quaternions (..., 4) held x, y, z, w: the shorter arc, rotations within 1e-5 of
    each other blended linearly; computed in the quaternions' own precision as Gf computes (its
    dot products accumulate in float for half and float quaternions)."""
    dtype = q0.dtype
    acc = np.float64 if dtype == np.float64 else np.float32
    a, b = q0.astype(acc), q1.astype(acc)
    imaginary = ((a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]) + a[..., 2] * b[..., 2]).astype(dtype)
    cos = (imaginary.astype(acc) + a[..., 3] * b[..., 3]).astype(np.float64)
    flip = cos < 0
    cos = np.abs(cos)
    far = 1.0 - cos > 1e-5

    def narrow(x):
        return np.asarray(x).astype(dtype).astype(np.float64)

    with np.errstate(invalid="ignore", divide="ignore"):
        theta = narrow(np.arccos(np.minimum(cos, 1)))
        sin = narrow(np.sin(theta))
        s0 = narrow(np.where(far, np.sin((1 - alpha) * theta) / sin, 1 - alpha))
        s1 = narrow(np.where(far, np.sin(alpha * theta) / sin, alpha))
    s1 = np.where(flip, -s1, s1)
    return (q0 * s0[..., None]).astype(dtype) + (q1 * s1[..., None]).astype(dtype)


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
        m, reset, ops = np.eye(4), False, {}  # ops: each named op's matrix, made once
        for name in self._op_order():
            if name == "!resetXformStack!":
                m, reset = np.eye(4), True
                continue
            if name not in ops:
                op_name = name.removeprefix("!invert!")
                attr = self.GetAttribute(op_name)
                if not attr or not attr.HasAuthoredValue() or attr.Get(time) is None:
                    raise SplatFileError(self.layer.identifier, f"{self.path}: transform op {op_name} has no value")
                ops[name] = _op_matrix(self.layer.identifier, self.path, attr, time, name != op_name)
            m = m @ ops[name]
        return m, reset

    def _op_order(self):
        order = self.GetAttribute("xformOpOrder")
        names = order.Get() if order else None
        if names is None:
            return []
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise SplatFileError(
                self.layer.identifier, f"{self.path}: xformOpOrder holds {names!r:.60}, not a list of op names"
            )
        return names

    def world_matrix(self, time, known=None):
        """Its own ops, then each ancestor's that OpenUSD counts as Xformable, up to the root or a
        prim that resets the transform stack. `known`: {(prim path, time): (local matrix, reset)}
        kept between calls, so that the children of a prim with many ops do not redo them."""
        m, prim = np.eye(4), self
        known = {} if known is None else known
        while prim is not None:
            if prim is self or is_xformable(prim.type_name):
                key = (prim.path, time)
                if key not in known:
                    known[key] = prim.local_matrix(time)
                local, reset = known[key]
                m = local @ m
                if reset:
                    break
            prim = prim.parent()
        return m

    def parent(self):
        return self.layer.prim_at(self.path.rsplit("/", 1)[0]) if self.path.count("/") > 1 else None


XFORMABLE = {
    "Xform", "Mesh", "Points", "BasisCurves", "NurbsCurves", "HermiteCurves", "NurbsPatch", "TetMesh", "Capsule",
    "Capsule_1", "Cone", "Cube", "Cylinder", "Cylinder_1", "Sphere", "Plane", "Camera", "PointInstancer", "SkelRoot",
    "Skeleton", "Volume", "OpenVDBAsset", "Field3DAsset", "GenerativeProcedural",
}  # fmt: skip


def is_xformable(type_name):
    """Whether OpenUSD counts a prim of this type as Xformable (its transform ops apply to its
    children): Xform, the gprims, cameras, lights, volumes, skeletons, particle fields."""
    return type_name in XFORMABLE or type_name.endswith("Light") or type_name.startswith("ParticleField")


_ONE_AXIS = re.compile(r"(rotate|translate|scale)([XYZ])")
_THREE_AXES = ("rotateXYZ", "rotateXZY", "rotateYXZ", "rotateYZX", "rotateZXY", "rotateZYX")


def _op_kind(name):
    """(op, the value it takes: "scalar", "vec3", "quat" or "matrix"), or None for a name that is no
    transform op OpenUSD knows."""
    parts = name.split(":")
    op = parts[1] if len(parts) > 1 and parts[0] == "xformOp" else ""
    if op in ("translate", "scale") or op in _THREE_AXES:
        return op, "vec3"
    if _ONE_AXIS.fullmatch(op):
        return op, "scalar"
    return {"orient": (op, "quat"), "transform": (op, "matrix")}.get(op)


def _value_kind(type_name):
    spec = element(type_name)
    if type_name.endswith("[]") or spec is None or spec[0].kind != "f" or type_name == "timecode":
        return None
    if is_quaternion(type_name):
        return "quat"
    if type_name.startswith(("matrix4", "frame4")):
        return "matrix"
    return {1: "scalar", 3: "vec3"}.get(spec[1])


def _op_matrix(path, prim_path, attr, time, invert=False):
    """4x4 (column vectors) of one transform op (or its inverse) as UsdGeomXformOp computes it:
    angles in degrees, three of them always X, Y, Z whatever order the op's name applies them in
    (rotateZYX turns about Z first); inverses taken op by op (negated angles and translations,
    reciprocal scales, a matrix's inverse unless it is singular); a value of a type OpenUSD does not
    take for the op refused."""
    name = attr.name
    kind = _op_kind(name)
    if kind is None:
        raise SplatFileError(path, f"{prim_path}: {name} is not a transform op OpenUSD knows")
    op, takes = kind
    if _value_kind(attr.type_name) != takes:
        raise SplatFileError(path, f"{prim_path}: transform op {name} holds a {attr.type_name}, not a {takes} value")
    value = np.asarray(attr.Get(time), np.float64)
    if not np.isfinite(value).all():  # a NaN quaternion would normalise to the identity
        raise SplatFileError(path, f"{prim_path}: its transform ops {name} hold NaN or Inf")
    m = np.eye(4)
    if op == "transform":
        m = value.reshape(4, 4).T  # USD matrices act on row vectors
        if invert:
            if abs(np.linalg.det(m)) <= 1e-9:
                raise SplatFileError(path, f"{prim_path}: !invert!{name} cannot invert a singular transform")
            m = np.linalg.inv(m)
        return m
    if op == "orient":
        m[:3, :3] = _orient(value, invert)
        return m
    sign = -1.0 if invert else 1.0
    if op == "translate":
        m[:3, 3] = sign * value
    elif op == "scale":
        with np.errstate(divide="ignore"):
            m[:3, :3] = np.diag(1 / value if invert else value)
    elif op in _THREE_AXES:
        turns = {axis: _rotation(axis, sign * angle) for axis, angle in zip("XYZ", value)}
        order = op[-3:][::-1] if invert else op[-3:]
        for axis in order:
            m[:3, :3] = turns[axis] @ m[:3, :3]
    else:
        verb, axis = _ONE_AXIS.fullmatch(op).groups()
        i = "XYZ".index(axis)
        if verb == "scale" and invert:  # OpenUSD negates it (a mirror), where its inverse is 1 / scale
            raise SplatFileError(
                path, f"{prim_path}: !invert!{name}: OpenUSD inverts a one-axis scale by negating it, not as 1 / scale"
            )
        if verb == "rotate":
            m[:3, :3] = _rotation(axis, sign * float(value))
        elif verb == "translate":
            m[i, 3] = sign * value
        else:
            m[i, i] = value
    return m


def _orient(xyzw, invert=False):
    """The rotation of a quaternion as GfRotation reads one that may not be unit: the angle
    2 acos(w) (w clamped to [-1, 1]) about the direction of (x, y, z); none when that is ~0."""
    x, y, z, w = (float(v) for v in xyzw)
    length = math.sqrt(x * x + y * y + z * z)
    if length <= 1e-10:
        return np.eye(3)
    degrees = 2.0 * math.degrees(math.acos(min(max(w, -1.0), 1.0)))
    return _axis_rotation((x / length, y / length, z / length), -degrees if invert else degrees)


def _rotation(axis, degrees):
    return _axis_rotation(np.eye(3)["XYZ".index(axis)], degrees)


def _axis_rotation(axis, degrees):
    """3x3 (column vectors) turning `degrees` about the unit `axis`, through the quaternion as
    GfRotation makes it (so that a half turn is as inexact as OpenUSD's)."""
    half = degrees * (math.pi / 180.0) / 2.0
    r = math.cos(half)
    i, j, k = (float(a) * math.sin(half) for a in axis)
    rows = np.array(
        [
            [1.0 - 2.0 * (j * j + k * k), 2.0 * (i * j + k * r), 2.0 * (k * i - j * r)],
            [2.0 * (i * j - k * r), 1.0 - 2.0 * (k * k + i * i), 2.0 * (j * k + i * r)],
            [2.0 * (k * i + j * r), 2.0 * (j * k - i * r), 1.0 - 2.0 * (j * j + i * i)],
        ]
    )
    return rows.T  # Gf's matrices act on row vectors


class Layer:
    """One text layer: its metadata and prims."""

    def __init__(self, identifier=""):
        self.identifier = identifier
        self.metadata = {}
        self.root_prims = []
        self._by_path = {}
        self.read_matrices = {}  # local transforms the readers computed (reading edits nothing)

    def GetRootLayer(self):
        return self

    def define(self, path, type_name=""):
        """The prim at `path` (ancestors defined as Xform where missing), its type set."""
        parent_path, _, _ = path.rpartition("/")
        if path not in self._by_path and (not parent_path or parent_path in self._by_path):  # the usual case
            prim = Prim(path, type_name, layer=self)
            (self._by_path[parent_path].children if parent_path else self.root_prims).append(prim)
            self._by_path[path] = prim
            return prim
        missing = []
        at = path
        while at and at not in self._by_path:
            missing.append(at)
            at = at.rsplit("/", 1)[0]
        for i, new in enumerate(reversed(missing)):
            parent = self._by_path.get(new.rsplit("/", 1)[0])
            prim = Prim(new, type_name if i == len(missing) - 1 else "Xform", layer=self)
            (parent.children if parent else self.root_prims).append(prim)
            self._by_path[new] = prim
        prim = self._by_path[path]
        if type_name and not prim.type_name:
            prim.type_name = type_name
        return prim

    def prim_at(self, path):
        return self._by_path.get(path)

    def GetPrimAtPath(self, path):
        return self._by_path.get(path) or _Missing()

    def traverse(self, keep=None):
        """Every prim, parents before children; with `keep`, only prims keep(prim) is true of, and
        none under a prim it is false of (as Usd.PrimRange prunes)."""
        stack = list(reversed(self.root_prims))
        while stack:
            prim = stack.pop()
            if keep is None or keep(prim):
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
    """The prim and its descendants, each opened before its children and closed after them (a stack
    of what is left to write, so that any depth of prims can be written)."""
    todo = [(prim, indent)]
    while todo:
        prim, indent = todo.pop()
        if isinstance(prim, str):  # the closing brace of a prim whose children are written
            out.write(prim)
            continue
        name = prim.path.rsplit("/", 1)[1]
        type_part = f"{prim.type_name} " if prim.type_name else ""
        out.write(f'{indent}{prim.specifier} {type_part}"{name}"\n{indent}{{\n')
        inner = indent + "    "
        for attr in prim.attributes.values():
            _write_attribute(out, attr, inner)
        todo.append((f"{indent}}}\n", indent))
        for child in reversed(prim.children):
            todo.append((child, inner))
            todo.append(("\n", inner))


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
        size = self.attr.metadata.get("elementSize", 1)
        if not isinstance(size, int) or isinstance(size, bool):
            raise SplatFileError(
                self.prim.layer.identifier, f"{self.prim.path}: {self.attr.name}: elementSize {size!r} is not an int"
            )
        return size

    def HasAuthoredValue(self):
        return self.attr.HasAuthoredValue()

    def ComputeFlattened(self, time=None):
        value = self.attr.Get(time)
        indices = self.prim.GetAttribute(self.attr.name + ":indices")
        if value is None or not indices or not indices.HasAuthoredValue():
            return value
        index = indices.Get(time)
        if not indices.GetTypeName() == "int[]" or not isinstance(index, np.ndarray) or index.ndim != 1:
            raise SplatFileError(
                self.prim.layer.identifier,
                f"{self.prim.path}: {self.attr.name}:indices is a {indices.GetTypeName()}, not an int[]",
            )
        if np.ndim(value) == 0:
            raise SplatFileError(
                self.prim.layer.identifier, f"{self.prim.path}: {self.attr.name} is indexed but holds no array"
            )
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
