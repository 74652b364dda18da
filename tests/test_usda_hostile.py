"""Hostile and malformed OpenUSD text layers read without OpenUSD (io/usd's text stage
implementation): nesting, size and malformed values give a SplatFileError naming the file, in memory
linear in the file; what both readers accept reads as usd-core reads it."""

import contextlib
import time
import tracemalloc
import warnings

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.io import SplatFileError, usd
from splatwright.io.usd import stages
from splatwright.io.usd.usda_parse import MAX_DEPTH

POSITIONS = "point3f[] positions = [(1, 2, 3), (-4, 5, 0.5)]"


def splat(name="S", body="", specifier="def", meta="", inner=""):
    """A splat prim's text: two particles, `body` added to its properties, `inner` to its children."""
    head = f'{specifier} ParticleField3DGaussianSplat "{name}"' + (f" (\n    {meta}\n)" if meta else "")
    return f"{head}\n{{\n    {POSITIONS}\n    {body}\n{inner}\n}}\n"


def layer(tmp_path, *prims, name="hostile.usda"):
    path = tmp_path / name
    path.write_text('#usda 1.0\n(\n    metersPerUnit = 1\n    upAxis = "Y"\n)\n\n' + "\n".join(prims))
    return str(path)


@contextlib.contextmanager
def using(impl):
    old = stages.active
    stages.active = impl
    try:
        yield
    finally:
        stages.active = old


def read_with(impl, path, **options):
    """[(prim path, cloud)] as `impl` reads the stage, or the SplatFileError it raises."""
    with using(impl), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return [(p.path, p.cloud) for p in usd.read_stage(path, **options)]
        except SplatFileError as exc:
            return exc


def assert_refused(path, *words):
    """The text reader refuses the layer with a SplatFileError naming the file and `words`."""
    got = read_with(stages.TEXT, path)
    assert isinstance(got, SplatFileError), got
    assert got.path == path
    for word in words:
        assert word in got.problem, got.problem


def assert_read_as_pxr(path, **options):
    expected, got = read_with(stages.PXR, path, **options), read_with(stages.TEXT, path, **options)
    if isinstance(expected, SplatFileError):
        assert isinstance(got, SplatFileError), f"pxr refuses ({expected}), the text reader does not"
        return
    assert not isinstance(got, SplatFileError), got
    assert [p for p, _ in got] == [p for p, _ in expected]
    for (_, a), (_, b) in zip(got, expected):
        for field in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=2e-6, atol=2e-6, err_msg=field)
        assert a.antialiased == b.antialiased
        assert a.extras.keys() == b.extras.keys()
        for key in a.extras:
            assert a.extras[key].dtype == b.extras[key].dtype
            np.testing.assert_array_equal(a.extras[key], b.extras[key])
    return got


# nesting --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 2000])
def test_deeply_nested_lists_are_refused_by_their_limit(tmp_path, depth):
    path = layer(tmp_path, splat(body=f"custom string[] deep = {'[' * depth}1{']' * depth}"))
    assert_refused(path, str(MAX_DEPTH), "deep")


def test_deeply_nested_dictionaries_are_refused_by_their_limit(tmp_path):
    depth = 2000
    data = "dictionary d = {\n" * depth + "}\n" * depth
    path = layer(tmp_path, splat(body=f"custom float x = 1 (\n customData = {{\n{data}}}\n)"))
    assert_refused(path, str(MAX_DEPTH), "deep")


def test_deeply_nested_prims_are_refused_by_their_limit(tmp_path):
    depth = 1000
    prims = "".join(f'def Xform "P{i}"\n{{\n' for i in range(depth)) + splat() + "}\n" * depth
    path = layer(tmp_path, prims)
    assert_refused(path, str(MAX_DEPTH), "deep")


def test_deeply_nested_prims_read_as_pxr_reads_them(tmp_path):
    depth = MAX_DEPTH // 4
    ops = '    double3 xformOp:translate = (0.5, 0, 0)\n    uniform token[] xformOpOrder = ["xformOp:translate"]\n'
    prims = "".join(f'def Xform "P{i}"\n{{\n{ops}' for i in range(depth)) + splat() + "}\n" * depth
    got = assert_read_as_pxr(layer(tmp_path, prims))
    assert got[0][0].count("/") == depth + 1
    assert got[0][1].positions[0, 0] == pytest.approx(1 + 0.5 * depth)


def test_prims_of_any_depth_are_written_and_refused_past_the_limit_on_reading(tmp_path):
    deep = "/" + "/".join(["P"] * 1500)
    path = str(tmp_path / "deep.usda")
    with using(stages.TEXT):
        usd.write_stage(path, {deep: random_cloud(3, 0, seed=1), "/Near/S": random_cloud(2, 0, seed=2)})
    assert_refused(path, str(MAX_DEPTH), "deep")
    assert open(path).read().count("{") >= 1500


@pytest.mark.parametrize("name", ["/".join(["a"] * 3000), "a.b", "1a", "a b", ""])
def test_prim_names_that_are_no_identifiers_are_refused(tmp_path, name):
    path = layer(tmp_path, splat(name=name))
    assert isinstance(read_with(stages.PXR, path), SplatFileError)
    assert_refused(path, "not a valid prim name")


def test_relationships_orders_and_comments_read_as_pxr_reads_them(tmp_path):
    body = (
        "rel material:binding = </Looks/M>  // a comment\n"
        "    rel proxyPrim = [</A>, </B>]\n"
        '    reorder nameChildren = ["B", "A"]\n'
        "    /* a block\n comment */\n"
        "    custom string note = '''one\ntwo''' # and another"
    )
    got = assert_read_as_pxr(layer(tmp_path, splat(body=body, inner=splat("A") + splat("B"))))
    assert [p for p, _ in got] == ["/S", "/S/B", "/S/A"]


@pytest.mark.parametrize("order", [["D", "B"], ["C", "A"], ["B", "X", "A"], ["D"], ["D", "A", "D"], []])
def test_children_are_reordered_as_pxr_reorders_them(tmp_path, order):
    listed = ", ".join(f'"{name}"' for name in order)
    children = "".join(splat(name) for name in "ABCD")
    assert_read_as_pxr(layer(tmp_path, splat(body=f"reorder nameChildren = [{listed}]", inner=children)))


def test_unicode_prim_names_read_as_pxr_reads_them(tmp_path):
    got = assert_read_as_pxr(layer(tmp_path, splat(name="Éclair_2")))
    assert got[0][0] == "/Éclair_2"


# size -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "literal",
    [
        '"' + "a" * (4 << 20) + '"',
        '"' + "\\n" * (2 << 20) + '"',
        '"""' + "a\n" * (2 << 20) + '"""',
        "'" + "\\'" * (2 << 20) + "'",
    ],
    ids=["plain", "escapes", "triple", "single"],
)
def test_big_string_literals_cost_memory_linear_in_the_file(tmp_path, literal):
    path = layer(tmp_path, splat(body=f"custom string note = {literal}"))
    size = len(literal)
    tracemalloc.start()
    try:
        got = read_with(stages.TEXT, path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert not isinstance(got, SplatFileError), got
    assert peak < 8 * size, f"{peak / size:.1f} bytes per byte of the string"


def _bombs():
    """Layers just under 1 MB built to make a parser slow or greedy."""
    n = 1 << 20
    yield "comments", "#" + "\n#" * (n // 2) + "\n" + splat()
    yield "open brackets", splat(body="custom float[] x = " + "[" * (n // 2))
    yield "open strings", splat(body='custom string s = "' + 'a"\n"' * (n // 4))
    yield "unclosed triple", splat(body='custom string s = """' + "a" * n)
    yield "open tuples", splat(body="custom float3 x = " + "(" * (n // 2))
    yield "many prims", "".join(f'def "P{i}"\n{{\n}}\n' for i in range(n // 16)) + splat()
    yield "big array", splat(body="custom float[] x = [" + "1," * (n // 2) + "]")
    yield "tuples", splat(body="custom float3[] x = [" + "(1,2,3)," * (n // 8) + "]")
    yield "words", splat(body="custom token[] x = [" + '"a",' * (n // 4) + "]")
    many_ops = '    double3 xformOp:translate = (0.001, 0, 0)\n    uniform token[] xformOpOrder = ["' + (
        '", "'.join(["xformOp:translate"] * (n // 40))
    )
    children = "".join(splat(f"K{i}") for i in range(500))
    yield "ops over many prims", 'def Xform "P"\n{\n' + many_ops + '"]\n' + children + "}\n"
    yield "dictionaries", splat(body="custom float x = 1 (\n customData = {" + 'string a = "b"\n' * (n // 16) + "}\n)")


@pytest.mark.parametrize("name", [name for name, _ in _bombs()])
def test_small_layers_read_or_refused_in_bounded_time_and_memory(tmp_path, name):
    path = layer(tmp_path, dict(_bombs())[name])
    tracemalloc.start()  # which slows the reading about threefold: the bound on time allows for it
    start = time.perf_counter()
    try:
        read_with(stages.TEXT, path)
        seconds, peak = time.perf_counter() - start, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert seconds < 30 and peak < 256 << 20, (seconds, peak)


# values read as pxr reads them ------------------------------------------------------------------------


@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
def test_three_axis_rotations_take_x_y_z_angles_in_the_named_order(tmp_path, order):
    ops = f'float3 xformOp:rotate{order} = (90, 0, 0)\n    uniform token[] xformOpOrder = ["xformOp:rotate{order}"]'
    assert_read_as_pxr(layer(tmp_path, splat(body=ops)), unmarked="stage")
    ops = f'float3 xformOp:rotate{order} = (30, -50, 70)\n    uniform token[] xformOpOrder = ["xformOp:rotate{order}"]'
    assert_read_as_pxr(layer(tmp_path, splat(body=ops)), unmarked="stage")


@pytest.mark.parametrize("op", ["rotateX", "rotateY", "rotateZ", "translateX", "translateY", "translateZ", "scaleZ"])
def test_one_axis_ops_read_as_pxr_reads_them(tmp_path, op):
    for invert in ("", "!invert!") if not op.startswith("scale") else ("",):
        ops = f'half xformOp:{op} = 70\n    uniform token[] xformOpOrder = ["{invert}xformOp:{op}"]'
        assert_read_as_pxr(layer(tmp_path, splat(body=ops)), unmarked="stage")


def test_indexed_primvars_read_as_pxr_reads_them(tmp_path):
    body = (
        'float[] primvars:w = [0.5, 7] (\n interpolation = "vertex"\n)\n    int[] primvars:w:indices = [1, 0]\n'
        '    token[] primvars:t = ["a", "b"] (\n interpolation = "vertex"\n)\n    int[] primvars:t:indices = [1, 1]'
    )
    got = assert_read_as_pxr(layer(tmp_path, splat(body=body)))
    np.testing.assert_array_equal(got[0][1].extras["w"], [7, 0.5])


@pytest.mark.parametrize(
    "value", ["false", "true", "0", "1", "0.0", "2", '"false"', '"true"', "FALSE", "truE", "yes", '"no"', '"1"', "on"]
)
def test_bool_literals_read_as_pxr_reads_them(tmp_path, value):
    got = assert_read_as_pxr(layer(tmp_path, splat(body=f"custom bool splatwright:antialiased = {value}")))
    if value != "on":  # which OpenUSD refuses
        assert got[0][1].antialiased == (value.strip('"').lower() in ("true", "1", "2", "yes"))


def test_quaternion_samples_are_slerped_as_pxr_does(tmp_path):
    rng = np.random.default_rng(4)
    lines = []
    for kind in ("quatf", "quatd", "quath"):
        q = rng.normal(size=(2, 2, 4))
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        q[1, 1] = -q[0, 1] + 1e-4  # nearly opposite: the shorter way round
        samples = ", ".join(
            f"{t}: [{', '.join('(' + ', '.join(map(repr, e)) + ')' for e in v)}]" for t, v in zip((1, 3), q.tolist())
        )
        lines.append(f"{kind}[] orientations.timeSamples = {{ {samples} }}")
    angles = "xformOp:orient.timeSamples = { 1: (0.6, 0, 0.8, 0), 3: (0, 1, 0, 0) }"
    for body in lines:
        for orient in ("quatf", "quatd", "quath"):
            ops = f'{orient} {angles}\n    uniform token[] xformOpOrder = ["xformOp:orient"]'
            path = layer(tmp_path, splat(body=f"{body}\n    {ops}"))
            for t in (1, 1.25, 2.5, 3):
                got = assert_read_as_pxr(path, time=t)
                if t == 2.5:  # not a linear blend: the quaternion's norm stays 1
                    np.testing.assert_allclose(np.linalg.norm(got[0][1].rotations, axis=1), 1, rtol=2e-3)


def test_scalar_and_vector_samples_are_blended_as_pxr_does(tmp_path):
    body = (
        "float[] opacities.timeSamples = { 0: [0.25, 0.5], 4: [0.75, 1] }\n"
        "    half3[] scalesh.timeSamples = { 0: [(1, 2, 3), (4, 5, 6)], 4: [(2, 2, 2), (0.5, 0.25, 8)] }\n"
        "    double xformOp:rotateY.timeSamples = { 0: 10, 4: 50 }\n"
        "    double3 xformOp:translate.timeSamples = { 0: (1, 2, 3), 4: (5, 6, -7) }\n"
        '    uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateY"]'
    )
    path = layer(tmp_path, splat(body=body))
    for t in (0, 0.3, 1, 3.7, 4, 9):
        assert_read_as_pxr(path, time=t)


def test_classes_overs_and_inactive_prims_are_skipped_as_pxr_skips_them(tmp_path):
    path = layer(
        tmp_path,
        splat("Kept", inner=splat("Child")),
        splat("Abstract", specifier="class", inner=splat("UnderClass")),
        splat("Over", specifier="over", inner=splat("UnderOver")),
        splat("Off", meta="active = false", inner=splat("UnderOff")),
        splat("Zero", meta="active = 0"),
        splat("On", meta="active = true"),
    )
    got = assert_read_as_pxr(path)
    assert [p for p, _ in got] == ["/Kept", "/Kept/Child", "/On"]


@pytest.mark.parametrize(
    "body",
    [
        "point3f[] positionsh = [(1, 2), (3, 4), (5, 6)]",
        "custom float3[] splatwright:logScales = [(1, 2, 3), 4, 5, 6]",
        "custom float3[] splatwright:logScales = [(1, 2, 3) (4, 5, 6)]",
        "custom float3[] splatwright:logScales = [1(, 2, 3), (4, 5, 6)]",
        'uchar[] primvars:label = [1, 300] (\n interpolation = "vertex"\n)',
        "uchar primvars:label = 300",
        "uniform int radiance:sphericalHarmonicsDegree = 4294967296",
        "int primvars:n = 4294967296",
        'int[] primvars:n = [4294967296, 1] (\n interpolation = "vertex"\n)',
        "uniform int radiance:sphericalHarmonicsDegree = +1",
        "uniform int radiance:sphericalHarmonicsDegree = nan",
        'int[] primvars:n = [1, 2, 1e10] (\n interpolation = "vertex"\n)',
        'uint64[] primvars:n = [18446744073709551616, 1] (\n interpolation = "vertex"\n)',
        "float[] opacities = [1 2]",
        "float[] opacities = [1,,2]",
        "float[] opacities = [(1), 2]",
        'float[] opacities.timeSamples = { 0: [1, 1] } (\n interpolation = "vertex"\n)',
        "float[] opacities = [1, 1]\n    half[] opacities.timeSamples = { 0: [1, 1] }",
        "float3[] scales = [(1, 2, 3, 4), (1, 2, 3, 4)]",
        "float3 xformOp:translate = (1, 2)",
        'float3 xformOp:translate = "abc"',
        "matrix4d xformOp:transform = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0))",
        "custom token note = 1",
    ],
)
def test_values_pxr_refuses_are_refused_by_name(tmp_path, body):
    path = layer(tmp_path, splat(body=body))
    assert isinstance(read_with(stages.PXR, path), SplatFileError)
    assert_refused(path)


@pytest.mark.parametrize(
    "body",
    [
        'uchar[] primvars:label = [255, 0.5, 255.9] (\n interpolation = "vertex"\n)',
        'int[] primvars:n = [-2147483648, 2147483647.9] (\n interpolation = "vertex"\n)',
        'uint64[] primvars:n = [18446744073709551615, 1.8e19] (\n interpolation = "vertex"\n)',
        'int64[] primvars:n = [-9223372036854775808, 9223372036854775807] (\n interpolation = "vertex"\n)',
        'bool[] primvars:b = [true, 0, 2, 0.5] (\n interpolation = "vertex"\n)',
        "float[] opacities = [0.5, 1e-50,]",
        "float3[] scales = [(1, 2, 3,), (.5, 5., 1E1)]",
        "half[] opacitiesh = [0.1, 1e-10]",
        "float[] opacities = [1e300, -inf] (\n doc = 'x'\n)",
        "quath[] orientationsh = [(1, 0, 0, 0), # the first\n (0, 0.6, 0.8, 0) /* the second */]",
        'doublE[] primvars:extra = [72, 30] (\n interpolation = "vertex"\n)',
        "float[] opacities = [0.5, // a note\n 1e-3,]",
    ],
)
def test_values_pxr_accepts_read_as_pxr_reads_them(tmp_path, body):
    assert_read_as_pxr(layer(tmp_path, splat(body=body)), nonfinite="keep")


# malformed values: the project's own error ---------------------------------------------------------


@pytest.mark.parametrize(
    "body, words",
    [
        ('float[] primvars:w = [1, 2] (\n elementSize = "abc"\n interpolation = "vertex"\n)', ["elementSize"]),
        (
            'float[] primvars:w = [1, 2] (\n interpolation = "vertex"\n)\n    float[] primvars:w:indices = [0.5, 1]',
            ["indices"],
        ),
        (
            'float[] primvars:w = [1, 2] (\n interpolation = "vertex"\n)\n    int[] primvars:w:indices = [0, 7]',
            ["indices"],
        ),
        (
            "matrix4d xformOp:transform = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 0, 0), (0, 0, 0, 1))\n"
            '    uniform token[] xformOpOrder = ["!invert!xformOp:transform"]',
            ["singular"],
        ),
        ('float xformOp:translate = 3\n    uniform token[] xformOpOrder = ["xformOp:translate"]', ["translate"]),
        ('float3 xformOp:rotateX = (1, 2, 3)\n    uniform token[] xformOpOrder = ["xformOp:rotateX"]', ["rotateX"]),
        ('double4 xformOp:orient = (1, 0, 0, 0)\n    uniform token[] xformOpOrder = ["xformOp:orient"]', ["orient"]),
        ('float3 xformOp:foo = (1, 2, 3)\n    uniform token[] xformOpOrder = ["xformOp:foo"]', ["foo"]),
        ('double xformOp:scaleY = 2\n    uniform token[] xformOpOrder = ["!invert!xformOp:scaleY"]', ["negating"]),
        ('float3 xformOp:translate = (1, 2, 3)\n    uniform token[] xformOpOrder = "xformOp:translate"', []),
        ("float[] opacities.timeSamples = { 0: [1, 1], nan: [0, 0] }", ["time sample at nan"]),
        ("float[] opacities.timeSamples = { 0: [1, 1], -inf: [0, 0] }", ["time sample at -inf"]),
    ],
)
def test_malformed_values_are_the_projects_own_error(tmp_path, body, words):
    path = layer(tmp_path, splat(body=body))
    assert_refused(path, *words)
