"""The text stage implementation against usd-core over generated layers: for every layer a seeded
generator writes (transform ops of every kind, order and value type, inverted, reset, time-sampled;
def, over and class prims, active or not, reordered; value types and their literals; samples of
quaternions), both read the same splats at each time, or both refuse the layer."""

import numpy as np
import pytest
from test_usda_hostile import assert_read_as_pxr

THREE_AXES = ["rotateXYZ", "rotateXZY", "rotateYXZ", "rotateYZX", "rotateZXY", "rotateZYX"]
ONE_AXIS = ["rotateX", "rotateY", "rotateZ", "translateX", "translateY", "translateZ", "scaleX", "scaleY", "scaleZ"]
TIMES = (None, 0, 0.5, 1.75, 2, 3)


def number(x):
    return repr(float(x))


def tuple_text(values):
    return "(" + ", ".join(number(v) for v in values) + ")"


def array_text(rows):
    return "[" + ", ".join(tuple_text(r) if np.ndim(r) else number(r) for r in rows) + "]"


class Layers:
    """Random layers of splat prims under transformed parents, drawn from one seeded generator."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)

    def pick(self, *options):
        return options[self.rng.integers(len(options))]

    def chance(self, p):
        return self.rng.random() < p

    def attribute(self, type_name, name, values, uniform=False):
        """`values` (one, or two samples at times 0 and 2) as a declaration."""
        prefix = "uniform " if uniform else ""
        if len(values) == 1:
            return f"{prefix}{type_name} {name} = {values[0]}"
        return f"{prefix}{type_name} {name}.timeSamples = {{ 0: {values[0]}, 2: {values[1]} }}"

    def samples(self, make):
        return [make()] if self.chance(0.6) else [make(), make()]

    def quaternion(self):
        q = self.rng.normal(size=4)
        return q / np.linalg.norm(q) if self.chance(0.8) else q * 2  # non-unit ones too

    def op(self, taken):
        """(declaration, name in xformOpOrder) of one transform op."""
        kind = self.pick("translate", "scale", "orient", "transform", "three", "one")
        rng = self.rng
        if kind in ("translate", "scale"):
            type_name = self.pick("double3", "float3", "half3")
            low = 0.5 if kind == "scale" else -3
            text = self.samples(lambda: tuple_text(rng.uniform(low, 3, 3).round(3)))
        elif kind == "orient":
            type_name = self.pick("quatf", "quatd", "quath")
            text = self.samples(lambda: tuple_text(self.quaternion()))
        elif kind == "transform":
            type_name, kind = "matrix4d", "transform"

            def matrix():
                m = np.eye(4)
                m[:3] = rng.normal(size=(3, 4))
                return "(" + ", ".join(tuple_text(r) for r in m.T) + ")"

            text = self.samples(matrix)
        elif kind == "three":
            type_name, kind = self.pick("float3", "double3", "half3"), self.pick(*THREE_AXES)
            text = self.samples(lambda: tuple_text(rng.uniform(-200, 200, 3).round(2)))
        else:
            type_name, kind = self.pick("double", "float", "half"), self.pick(*ONE_AXIS)
            low = 0.5 if kind.startswith("scale") else -120
            text = self.samples(lambda: number(rng.uniform(low, 3 if kind.startswith("scale") else 120)))
        name = f"xformOp:{kind}"
        if name in taken:
            name += f":n{len(taken)}"
        taken.add(name)
        if self.chance(0.01):  # a value of the wrong type: both refuse
            type_name = "int3" if type_name.endswith("3") else "float2"
            text = ["(1, 2, 3)" if type_name == "int3" else "(1, 2)"]
        inverted = self.chance(0.25) and not kind.startswith("scale") and type_name != "matrix4d"
        return self.attribute(type_name, name, text), ("!invert!" if inverted else "") + name

    def transform(self):
        ops, order, taken = [], [], set()
        for _ in range(self.rng.integers(0, 4)):
            declaration, name = self.op(taken)
            ops.append(declaration)
            order.append(name)
        if self.chance(0.1):
            order.insert(0, "!resetXformStack!")
        if not order:
            return []
        return ops + ["uniform token[] xformOpOrder = [" + ", ".join(f'"{n}"' for n in order) + "]"]

    def splat_values(self):
        rng, n = self.rng, int(self.rng.integers(1, 4))
        lines = [
            self.attribute(
                self.pick("point3f[]", "float3[]"),
                "positions",
                self.samples(lambda: array_text(rng.normal(size=(n, 3)))),
            ),
            self.attribute(
                self.pick("quatf[]", "quath[]") if self.chance(0.8) else "quatd[]",
                self.pick("orientations", "orientationsh"),
                self.samples(lambda: array_text([self.quaternion() for _ in range(n)])),
            ),
            self.attribute("float3[]", "scales", self.samples(lambda: array_text(rng.uniform(0.01, 1, (n, 3))))),
            self.attribute(
                self.pick("float[]", "half[]"),
                self.pick("opacities", "opacitiesh"),
                self.samples(lambda: array_text(rng.uniform(0, 1, n))),
            ),
        ]
        if self.chance(0.5):
            lines.append(f"custom bool splatwright:antialiased = {self.pick('true', 'false', '0', '1', '2.5')}")
        extra = self.pick("uchar[]", "int[]", "float[]", "bool[]", "double[]", "int64[]")
        values = {"bool[]": lambda: self.pick("true", "false", "0", "1")}.get(extra, lambda: str(rng.integers(0, 200)))
        listed = ", ".join(values() for _ in range(n))
        lines.append(f'{extra} primvars:extra = [{listed}] (\n interpolation = "vertex"\n)')
        if self.chance(0.01):  # a value OpenUSD refuses: both refuse
            lines.append(self.pick("uchar primvars:bad = 300", "int primvars:bad = 4294967296"))
        return lines

    def blender_points(self):
        """Blender's splat points: positions, rotations (w, x, y, z) and scales as vertex primvars."""
        rng, n = self.rng, int(self.rng.integers(1, 4))
        vertex, rotation = ' (\n interpolation = "vertex"\n)', self.pick("quatf[]", "float4[]")
        return [
            self.attribute("point3f[]", "points", self.samples(lambda: array_text(rng.normal(size=(n, 3))))),
            f"{rotation} primvars:rotation{vertex}",  # its metadata, then its values
            self.attribute(
                rotation, "primvars:rotation", self.samples(lambda: array_text([self.quaternion() for _ in range(n)]))
            ),
            f"float3[] primvars:scale = {array_text(rng.uniform(0.01, 1, (n, 3)))}{vertex}",
            f"float4[] primvars:radiance:base = {array_text(rng.uniform(0, 1, (n, 4)))}{vertex}",
        ]

    def prim(self, name, depth):
        specifier = "def" if self.chance(0.85) else self.pick("over", "class")
        splat = self.pick("ParticleField3DGaussianSplat", "Points") if depth > 0 and self.chance(0.75) else None
        type_name = splat or self.pick("Xform", "Xform", "Scope", "")
        meta = f" (\n    active = {self.pick('true', 'false', '0', '1')}\n)" if self.chance(0.15) else ""
        values = {"Points": self.blender_points, None: list}.get(splat, self.splat_values)
        body = self.transform() + values()
        count = int(self.rng.integers(1, 4)) if depth < 2 else 0
        children = [self.prim(f"{name}_{i}", depth + 1) for i in range(count)]
        if count > 1 and self.chance(0.3):  # an order naming some of the children
            listed = ", ".join(f'"{name}_{i}"' for i in self.rng.permutation(count)[: self.rng.integers(1, count + 1)])
            body.append(f"reorder nameChildren = [{listed}]")
        typed = f"{type_name} " if type_name else ""
        return f'{specifier} {typed}"{name}"{meta}\n{{\n' + "\n".join(body + children) + "\n}\n"

    def layer(self):
        up, units = self.pick("Y", "Z"), self.pick("1", "0.01", "2.5")
        prims = [self.prim(f"R{i}", 0) for i in range(self.rng.integers(1, 3))]
        return f'#usda 1.0\n(\n    metersPerUnit = {units}\n    upAxis = "{up}"\n)\n\n' + "\n".join(prims)


@pytest.mark.parametrize("seed", range(40))
def test_the_text_reader_reads_generated_layers_as_pxr_does(tmp_path, seed):
    layers = Layers(seed)
    path = tmp_path / f"generated_{seed}.usda"
    path.write_text(layers.layer())
    for time in TIMES:
        assert_read_as_pxr(str(path), time=time, nonfinite="keep")
