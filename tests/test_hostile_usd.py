"""Hostile OpenUSD files read through pxr: what a stage may compose, and what OpenUSD may parse.

Every layer a stage opens (sublayers, references, payloads, value clips and their manifests and
templates, in any layer and variant) must lie in the stage's folder or package, be a regular file,
and pass the byte checks (io/usd/layer_check.py) before OpenUSD parses it: a FIFO would hang the
read, and 100k nested parentheses abort the process. The cases that would hang or abort run the
command line in a child process with a timeout, so this suite cannot hang.
"""

import os
import re
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from helpers import random_cloud, skip_platform

from splatwright.io import SplatFileError, usd
from splatwright.io.usd.layer_check import MAX_NESTING, nesting

INSIDE, OUTSIDE = random_cloud(6, sh_degree=0, seed=1), random_cloud(6, sh_degree=0, seed=2)
CLIP_TIMES = "double2[] active = [(0, 0)]\n            double2[] times = [(0, 0), (1, 1)]"


def splat_layer(path, cloud, frames=False):
    """A layer holding one splat prim /Splats (animated at times 0 and 1 if frames: clips serve
    time samples)."""
    if frames:
        usd.write_frames(path, [cloud, cloud], times=[0, 1])
    else:
        usd.write(path, cloud)
    return path


def clip_stage(model, clips, name="stage.usda"):
    """model/<name>: the splat prim of INSIDE without positions, which come from its value clips
    (`clips`: the entries of the clip set "default")."""
    text = splat_layer(model / "base.usda", INSIDE).read_text()
    text = re.sub(r" *point3f\[\] positions = .*\n", "", text)
    metadata = (
        "(\n    clips = {\n        dictionary default = {\n            "
        + clips
        + '\n            string primPath = "/Splats"\n        }\n    }\n)\n'
    )
    text = text.replace(
        'def ParticleField3DGaussianSplat "Splats"\n', 'def ParticleField3DGaussianSplat "Splats" ' + metadata
    )
    (model / name).write_text(text)
    return model / name


def folders(tmp_path):
    """tmp/model (the stage's folder) and tmp/outside, each with a clip of its cloud."""
    model, outside = tmp_path / "model", tmp_path / "outside"
    model.mkdir()
    outside.mkdir()
    for folder, cloud in ((model, INSIDE), (outside, OUTSIDE)):
        splat_layer(folder / "clip.usda", cloud, frames=True)
        for i in range(2):
            splat_layer(folder / f"clip.{i}.usda", cloud, frames=True)
    return model, outside


CLIP_KINDS = {
    "assetPaths": f"asset[] assetPaths = [@{{0}}clip.usda@]\n            {CLIP_TIMES}",
    "template": 'string templateAssetPath = "{0}clip.#.usda"\n            double templateStartTime = 0\n'
    "            double templateEndTime = 1\n            double templateStride = 1",
}


# value clips -------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", CLIP_KINDS)
def test_value_clips_from_outside_the_folder_are_refused(tmp_path, kind):
    model, outside = folders(tmp_path)
    inside = clip_stage(model, CLIP_KINDS[kind].format("./"))
    np.testing.assert_array_equal(usd.read(inside).positions, usd.read(model / "clip.usda").positions)
    stage = clip_stage(model, CLIP_KINDS[kind].format("../outside/"))
    outside_positions = usd.read(outside / "clip.usda").positions
    # the clips are what the prim's positions come from: allowed, they come back
    np.testing.assert_array_equal(usd.read(stage, allow_outside=True).positions, outside_positions)
    with pytest.raises(
        SplatFileError, match=r"stage.usda: refers to a layer: '../outside/clip.*' is outside the stage's folder"
    ):
        usd.read(stage)
    (outside / "clip.usda").unlink()
    for i in range(2):
        (outside / f"clip.{i}.usda").unlink()
    with pytest.raises(SplatFileError, match=r"stage.usda: refers to a layer: '../outside/clip.*' is outside"):
        usd.read(stage)  # the same words whether it exists or not


def test_a_clip_manifest_from_outside_the_folder_is_refused(tmp_path):
    model, outside = folders(tmp_path)
    (outside / "manifest.usda").write_text('#usda 1.0\nover "Splats"\n{\n    point3f[] positions\n}\n')
    clips = CLIP_KINDS["assetPaths"].format("./") + "\n            asset manifestAssetPath = @{0}manifest.usda@"
    (model / "manifest.usda").write_text((outside / "manifest.usda").read_text())
    np.testing.assert_array_equal(
        usd.read(clip_stage(model, clips.format("./"))).positions, usd.read(model / "clip.usda").positions
    )
    with pytest.raises(SplatFileError, match="stage.usda: refers to a layer: '../outside/manifest.usda' is outside"):
        usd.read(clip_stage(model, clips.format("../outside/")))


def test_value_clips_in_sublayers_references_and_variants_are_checked(tmp_path):
    model, _ = folders(tmp_path)
    (model / "deep").mkdir()
    clip_stage(model / "deep", CLIP_KINDS["assetPaths"].format("../../outside/"), "mid.usda")
    arcs = {
        "sublayer": "#usda 1.0\n(\n    subLayers = [@deep/mid.usda@]\n)\n",
        "reference": '#usda 1.0\ndef "W" (\n    prepend references = @deep/mid.usda@</Splats>\n)\n{\n}\n',
    }
    for kind, text in arcs.items():
        (model / f"{kind}.usda").write_text(text)
        with pytest.raises(
            SplatFileError, match=r"usda: layer .*mid.usda refers to a layer: '../../outside/clip.usda'"
        ):
            usd.read(model / f"{kind}.usda")
    variant = (
        '#usda 1.0\ndef "W" (\n    variants = { string look = "far" }\n    prepend variantSets = "look"\n)\n'
        '{\n    variantSet "look" = {\n        "far" (\n            clips = { dictionary default = {\n'
        "                asset[] assetPaths = [@../outside/clip.usda@]\n"
        '                string primPath = "/Splats"\n            } }\n        ) {\n        }\n    }\n}\n'
    )
    (model / "variant.usda").write_text(variant)
    with pytest.raises(SplatFileError, match="variant.usda: refers to a layer: '../outside/clip.usda' is outside"):
        usd.read(model / "variant.usda")


@pytest.mark.parametrize("kind", CLIP_KINDS)
def test_value_clips_leave_a_package_only_when_allowed(tmp_path, kind):
    model, _ = folders(tmp_path)
    for prefix in ("./", "sub/", "../", "sub/../../"):
        stage = clip_stage(model, CLIP_KINDS[kind].format(prefix))
        with zipfile.ZipFile(model / "clips.usdz", "w", zipfile.ZIP_STORED) as z:
            z.writestr("stage.usda", stage.read_text())
            for name in ("clip.usda", "clip.0.usda", "clip.1.usda"):  # beside the package too
                z.write(model / name, (prefix if prefix == "sub/" else "") + name)
        if ".." in prefix:
            with pytest.raises(
                SplatFileError, match=f"clips.usdz: refers to a layer: '{prefix}clip.*' is outside the stage's package"
            ):
                usd.read(model / "clips.usdz")
        else:
            got = usd.read(model / "clips.usdz")
            np.testing.assert_array_equal(got.positions, usd.read(model / "clip.usda").positions)


def test_layers_named_by_expressions_are_refused(tmp_path):
    model, _ = folders(tmp_path)
    (model / "expr.usda").write_text(
        '#usda 1.0\n(\n    expressionVariables = { string X = "../outside/clip" }\n'
        '    subLayers = [@`"${X}.usda"`@]\n)\n'
    )
    with pytest.raises(SplatFileError, match="expr.usda: names a layer by an expression"):
        usd.read(model / "expr.usda")


def test_the_open_stage_uses_only_checked_layers(tmp_path, monkeypatch):
    """The backstop: a layer the walk did not check, found among the stage's used layers, is refused."""
    from splatwright.io.usd import pxr_stages

    model, _ = folders(tmp_path)
    stage = clip_stage(model, CLIP_KINDS["assetPaths"].format("./"))
    monkeypatch.setattr(pxr_stages._LayerWalk, "_clips", lambda *args: iter(()))
    with pytest.raises(
        SplatFileError, match=r"stage.usda: the stage composes a layer that was not checked .*clip.usda"
    ):
        usd.read(stage)


# nesting depth: the scan against a character-by-character reference ----------------------------


def reference_nesting(text):
    """The deepest bracket nesting of usda text outside strings, asset paths and comments, read one
    character at a time as OpenUSD's grammar does (a stray closer counts from zero again)."""
    depth = deepest = i = 0
    n = len(text)
    while i < n:
        for opener, closer, multiline, escapes in (
            ("'''", "'''", True, True), ("'", "'", False, True), ('"""', '"""', True, True),
            ('"', '"', False, True), ("@@@", "@@@", False, False), ("@", "@", False, False),
            ("#", "\n", False, False), ("//", "\n", False, False), ("/*", "*/", True, False),
        ):  # fmt: skip
            if text.startswith(opener, i):
                j = i + len(opener)
                while (
                    j < n and not text.startswith(closer, j) and (multiline or text[j] not in "\r\n" or closer == "\n")
                ):
                    if escapes and text[j] == "\\" and j + 1 < n and (multiline or text[j + 1] not in "\r\n"):
                        j += 1
                    elif opener == "@@@" and text.startswith("\\@@@", j):
                        j += 3
                    j += 1
                if closer == "\n" or text.startswith(closer, j):
                    i = j + (0 if closer == "\n" else len(closer))
                    if opener == "@@@":
                        i += min(2, len(text[i:]) - len(text[i:].lstrip("@")))
                    break
        else:
            c = text[i]
            depth = depth + 1 if c in "([{" else max(0, depth - 1) if c in ")]}" else depth
            deepest = max(deepest, depth)
            i += 1
    return deepest


def test_nesting_matches_a_character_by_character_reference():
    rng = np.random.default_rng(7)
    pieces = list("([{)]}") * 6 + ["'", '"', "'''", '"""', "@", "@@@", "#", "//", "/*", "*/", "\\", "\n", "x", " "]
    for _ in range(2000):
        text = "".join(rng.choice(pieces, size=rng.integers(0, 60)))
        assert nesting(text.encode(), limit=10**9)[0] == reference_nesting(text), repr(text)


def test_nesting_ignores_strings_and_comments_and_counts_across_chunks(monkeypatch):
    from splatwright.io.usd import layer_check

    text = 'string doc = "(((("  # ((((\n/* [[[[ */ x = @(((@ ((( ]]] )))'
    assert nesting(text.encode())[0] == 3
    monkeypatch.setattr(layer_check, "_CHUNK", 7)  # depth and skipped spans carried from chunk to chunk
    deep = b"#usda 1.0\n" + b'"(("' + b"(" * 40 + b"''')))'''" + b")" * 40
    assert nesting(deep)[0] == 40
    assert nesting(deep, limit=20) == (21, deep.index(b"(" * 21) + 20)


def nested_dictionaries(depth):
    """A valid layer whose brackets nest exactly `depth` deep: metadata parentheses, then braces."""
    body = "dictionary d = {\n" * (depth - 2) + "int x = 1\n" + "}\n" * (depth - 2)
    return f'#usda 1.0\ndef "A" (\n    customData = {{\n{body}}}\n)\n{{\n}}\n'


def test_nesting_up_to_the_limit_reads_and_past_it_is_refused(tmp_path):
    from pxr import Sdf

    model, _ = folders(tmp_path)
    text = splat_layer(model / "s.usda", INSIDE).read_text()
    for depth in (MAX_NESTING, MAX_NESTING + 1):
        (model / "deep.usda").write_text(nested_dictionaries(depth))
        assert nesting((model / "deep.usda").read_bytes())[0] == depth
        assert Sdf.Layer.OpenAsAnonymous(str(model / "deep.usda")) is not None  # OpenUSD parses both
        (model / "stage.usda").write_text(text.replace(")\n", "    subLayers = [@./deep.usda@]\n)\n", 1))
        if depth == MAX_NESTING:
            np.testing.assert_array_equal(
                usd.read(model / "stage.usda").positions, usd.read(model / "s.usda").positions
            )
        else:
            with pytest.raises(
                SplatFileError, match=f"stage.usda: layer deep.usda: brackets nest more than {MAX_NESTING} deep"
            ):
                usd.read(model / "stage.usda")


def test_brackets_in_strings_and_comments_do_not_count(tmp_path):
    text = splat_layer(tmp_path / "s.usda", INSIDE).read_text()
    noisy = text.replace(")\n", f'    doc = """{"(" * 1000}"""\n)\n# {"[" * 1000}\n', 1)
    (tmp_path / "noisy.usda").write_text(noisy)
    np.testing.assert_array_equal(usd.read(tmp_path / "noisy.usda").positions, usd.read(tmp_path / "s.usda").positions)


def test_a_text_layer_past_the_size_limit_is_refused_unread(tmp_path):
    from splatwright.io.policy import MAX_TEXT_LAYER_BYTES

    model, _ = folders(tmp_path)
    with open(model / "huge.usda", "wb") as f:  # sparse: no disk is used
        f.write(b"#usda 1.0\n")
        f.truncate(MAX_TEXT_LAYER_BYTES + 1)
    for path in (model / "huge.usda", stage_naming(model, "sublayer", "./huge.usda")):
        with pytest.raises(SplatFileError, match=f"a {MAX_TEXT_LAYER_BYTES + 1}-byte text layer, more than"):
            usd.read(path)


# the command line never hangs or aborts -----------------------------------------------------------

PEAK_LIMIT = 1 << 30  # bytes of resident memory the child may reach
# The child's own peak: Linux's VmHWM belongs to the process's memory since exec, while ru_maxrss
# also counts what the parent (this test run, often 1 GiB) held when it forked.
CHILD = (
    "import resource, runpy, sys\n"
    "sys.argv = ['splatwright', *sys.argv[1:]]\n"
    "def peak():\n"
    "    try:\n"
    "        with open('/proc/self/status') as f:\n"
    "            return next(int(l.split()[1]) * 1024 for l in f if l.startswith('VmHWM:'))\n"
    "    except OSError:\n"
    "        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024\n"
    "try:\n    runpy.run_module('splatwright', run_name='__main__')\n"
    "finally:\n    print('peak', peak(), file=sys.stderr)\n"
)
DEEP = {
    "(": "custom string[] x = " + "(" * 100_000 + '"a"' + ")" * 100_000,
    "[": "custom string[] x = " + "[" * 100_000 + "]" * 100_000,
    "{": "customData = " + "{ dictionary d = " * 50_000 + "{}" + "}" * 50_000,  # OpenUSD: a segfault
}


def deep_layer(path, bracket="("):
    """A text layer nesting 100k parentheses or brackets deep (200 KB; OpenUSD aborts or runs for
    minutes on the parentheses), or 50k braces (900 KB)."""
    if bracket == "{":
        path.write_text(f'#usda 1.0\ndef "A" (\n    {DEEP[bracket]}\n)\n{{\n}}\n')
    else:
        path.write_text(f'#usda 1.0\ndef "A"\n{{\n    {DEEP[bracket]}\n}}\n')
    return path


def stage_naming(model, arc, asset):
    """model/stage.usda naming `asset` by `arc`: a sublayer, reference, payload or value clip."""
    if arc == "clip":
        return clip_stage(model, f"asset[] assetPaths = [@{asset}@]\n            {CLIP_TIMES}")
    if arc == "sublayer":
        text = f"#usda 1.0\n(\n    subLayers = [@{asset}@]\n)\n"
    else:
        kind = "references" if arc == "reference" else "payload"
        text = f'#usda 1.0\ndef "P" (\n    prepend {kind} = @{asset}@\n)\n{{\n}}\n'
    (model / "stage.usda").write_text(text)
    return model / "stage.usda"


def hostile_case(tmp_path, case):
    """(file to read, problem expected in the message) for one hostile case."""
    model, _ = folders(tmp_path)
    kind, _, where = case.partition(":")
    if kind == "fifo":
        if not hasattr(os, "mkfifo"):
            skip_platform("no FIFOs on this platform")
        os.mkfifo(model / "pipe.usda")
        if where == "root":  # the command line names its own refusal
            return model / "pipe.usda", ""
        return stage_naming(model, where, "./pipe.usda"), "'./pipe.usda', which cannot be opened"
    if kind == "template-times":
        clips = (
            'string templateAssetPath = "./clip.#.usda"\n            double templateStartTime = 1e300\n'
            "            double templateEndTime = 1e300\n            double templateStride = 1"
        )
        return clip_stage(model, clips), "a clip template spans times"
    if kind == "usdz-headers":  # a local header 22 bytes short: OpenUSD reads by local headers only
        from test_io_fuzz import fuzz_cases

        valid, cases = fuzz_cases(tmp_path, "usdz")
        valid.write_bytes(dict(cases)["m3k3"])
        return valid, "crate table of contents lies outside the file"
    problem = f"brackets nest more than {MAX_NESTING} deep"
    if kind in ("(", "[", "{"):
        return deep_layer(model / "deep.usda", kind), problem
    if kind == "usd-text":
        return deep_layer(model / "deep.usd"), problem
    if kind == "usdz":
        deep_layer(model / "deep.usda")
        with zipfile.ZipFile(model / "deep.usdz", "w", zipfile.ZIP_STORED) as z:
            if where == "root":
                z.write(model / "deep.usda", "deep.usda")
            else:
                z.writestr("root.usda", "#usda 1.0\n(\n    subLayers = [@./inner/deep.usda@]\n)\n")
                z.write(model / "deep.usda", "inner/deep.usda")
        return model / "deep.usdz", problem
    deep_layer(model / "deep.usda")
    return stage_naming(model, kind, "./deep.usda"), "layer deep.usda: " + problem


CASES = [
    "(", "[", "{", "usd-text", "usdz:root", "usdz:sublayer",
    "sublayer", "reference", "payload", "clip",
    "fifo:root", "fifo:sublayer", "fifo:reference", "fifo:payload", "fifo:clip",
    "template-times",
    "usdz-headers",
]  # fmt: skip


def run_cli(*args, timeout=120):
    try:
        done = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"splatwright {' '.join(args)} still ran after {timeout} s")
    peak = re.search(r"^peak (\d+)$", done.stderr, re.M)
    return done.returncode, done.stderr, int(peak.group(1)) if peak else None


@pytest.mark.parametrize("case", CASES)
def test_the_cli_refuses_hostile_layers_without_hanging_or_aborting(tmp_path, case):
    path, problem = hostile_case(tmp_path, case)
    rc, err, peak = run_cli("info", str(path))
    assert rc == 1, err  # an abort is -6 (134 from a shell), a crash -11
    assert "Traceback" not in err
    assert f"splatwright info: error: {path}: " in err and problem in err, err
    assert peak is not None and peak < PEAK_LIMIT


def test_usd_read_refuses_a_fifo_without_opening_it(tmp_path):
    if not hasattr(os, "mkfifo"):
        skip_platform("no FIFOs on this platform")
    os.mkfifo(tmp_path / "pipe.usda")
    code = (
        "import sys\nfrom splatwright.io import usd\n"
        "try:\n    usd.read(sys.argv[1])\nexcept Exception as e:\n    print(e)"
    )
    try:
        done = subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / "pipe.usda")], capture_output=True, text=True, timeout=120
        )
    except subprocess.TimeoutExpired:
        pytest.fail("reading a FIFO hung")
    assert done.stdout.strip() == f"{tmp_path / 'pipe.usda'}: not a regular file (a FIFO, device or folder?)", done


@pytest.mark.parametrize("arc", ["sublayer", "clip"])
def test_a_layer_linked_to_a_device_is_refused_even_when_outside_is_allowed(tmp_path, arc):
    model, _ = folders(tmp_path)
    if not os.path.exists("/dev/zero"):
        skip_platform("no /dev/zero on this platform")
    (model / "zero.usda").symlink_to("/dev/zero")  # OpenUSD would read it for ever
    path = stage_naming(model, arc, "./zero.usda")
    rc, err, _ = run_cli("info", str(path))
    assert rc == 1 and "'./zero.usda' is outside the stage's folder" in err, err
    rc, err, _ = run_cli("info", "--allow-outside", str(path))
    assert rc == 1 and "'./zero.usda', which cannot be opened (missing, not a regular file" in err, err


@pytest.mark.parametrize("verb", ["convert", "render"])
def test_convert_and_render_refuse_them_too(tmp_path, verb):
    path, problem = hostile_case(tmp_path, "(")
    out = tmp_path / ("out.ply" if verb == "convert" else "out.png")
    rc, err, _ = run_cli(verb, str(path), str(out) if verb == "convert" else f"--output={out}")
    assert rc == 1 and "Traceback" not in err and f"{path}: {problem}" in err, err
    assert not out.exists()
