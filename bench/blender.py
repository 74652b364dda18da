"""Blender import/export of a 1M-splat degree-3 PLY: our operators against the per-splat approach of
the ReshotAI gaussian-splatting-blender-addon (reimplemented here from its description).

Ours: splat.import_file / splat.export_file (file read, NumPy, foreach_set/foreach_get on float32
buffers, display modifier set up). Baseline import: the same parsed columns stacked as float64, a
Python loop turning every quaternion into Euler angles with mathutils, mesh.from_pydata on a Python
list of centres and float64 foreach_set for its attributes. Baseline export: a Python loop reading
every splat's attributes element by element, rows built as tuples, then written. The baselines are
timed on a subset and scaled linearly (they are linear in the splat count), as the row notes say.
Error: max abs difference between the source file's arrays and those of the file written back.

A second import row sets ours against Blender's own `wm.ply_import` of the same file (raw vertex
attributes only, no splat layout), timed alternately in the same run.
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import Row, Timing, paired, print_rows, timeit  # noqa: E402

from splatwright.core import SplatCloud  # noqa: E402
from splatwright.io import read_splats, write_splats  # noqa: E402

TOPIC = "blender"


def make_cloud(n, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    return SplatCloud(
        rng.normal(0, 2, (n, 3)),
        rng.normal(size=(n, 4)),
        rng.uniform(-5, -1, (n, 3)),
        rng.normal(0, 2, n),
        rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)),
    )


def max_abs_error(a, b):
    fields = ("positions", "rotations", "log_scales", "opacity_logits", "sh")
    return max(float(np.abs(getattr(a, f).astype(np.float64) - getattr(b, f)).max(initial=0.0)) for f in fields)


# ours ----------------------------------------------------------------------------------------------


def _remove(bpy, obj):
    mesh = obj.data
    bpy.data.objects.remove(obj)
    bpy.data.meshes.remove(mesh)


def _against_blender_import(bpy, src, repeat):
    """(Blender's wm.ply_import, our import) of the same file, timed alternately (see common.paired)."""
    made = []

    def importer(op):
        def run():
            while made:  # one imported object alive at a time
                _remove(bpy, made.pop())
            op(filepath=str(src))
            made.append(bpy.context.active_object)

        return run

    timings = paired(importer(bpy.ops.wm.ply_import), importer(bpy.ops.splat.import_file), repeat)
    while made:
        _remove(bpy, made.pop())
    return timings


def _ours(bpy, src, out, repeat):
    made = []

    def do_import():
        if made:  # keep one object alive at a time (removal: ~20 ms at 1M)
            _remove(bpy, made.pop())
        bpy.ops.splat.import_file(filepath=str(src))
        made.append(bpy.context.active_object)

    t_import = timeit(do_import, repeat=repeat)
    t_export = timeit(lambda: bpy.ops.splat.export_file(filepath=str(out), selected_only=True), repeat=repeat)
    obj = made[0]
    t_display = timeit(lambda: (obj.update_tag(), bpy.context.view_layer.update()), repeat=repeat)
    _remove(bpy, obj)
    return t_import, t_export, t_display


# baseline: per-splat loops -------------------------------------------------------------------------


def baseline_import(bpy, path):
    import mathutils

    cloud = read_splats(path)  # parsing itself is not what differs; use the same reader
    n, k = len(cloud), cloud.sh.shape[1]
    xyz = np.stack([cloud.positions[:, i].astype(np.float64) for i in range(3)], axis=1)
    log_opacity = cloud.opacity_logits.astype(np.float64)[:, None]
    opacity = 1 / (1 + np.exp(-log_opacity))
    log_scales = np.stack([cloud.log_scales[:, i].astype(np.float64) for i in range(3)], axis=1)
    quats = np.stack([cloud.rotations[:, i].astype(np.float64) for i in range(4)], axis=1)
    euler = np.zeros((n, 3))
    for i in range(n):  # the per-splat loop
        e = mathutils.Quaternion(quats[i].tolist()).to_euler()
        euler[i] = (e.x, e.y, e.z)
    mesh = bpy.data.meshes.new("baseline")
    mesh.from_pydata(xyz.tolist(), [], [])
    mesh.update()

    def put(name, kind, values):
        attr = mesh.attributes.new(name, kind, "POINT")
        attr.data.foreach_set("value" if kind == "FLOAT" else "vector", values.flatten())

    put("log_opacity", "FLOAT", log_opacity)
    put("opacity", "FLOAT", opacity)
    put("scale", "FLOAT_VECTOR", np.exp(log_scales))
    put("logscale", "FLOAT_VECTOR", log_scales)
    for j in range(k):
        put(f"sh{j}", "FLOAT_VECTOR", cloud.sh[:, j, :].astype(np.float64))
    put("quatxyz", "FLOAT_VECTOR", quats[:, :3])
    put("quatw", "FLOAT", quats[:, 3])
    put("rot_euler", "FLOAT_VECTOR", euler)
    obj = bpy.data.objects.new("baseline", mesh)
    bpy.context.collection.objects.link(obj)
    return obj


def baseline_export(obj, path, k):
    mesh = obj.data
    n = len(mesh.vertices)
    pos, logop = mesh.attributes["position"], mesh.attributes["log_opacity"]
    logscale, sh = mesh.attributes["logscale"], [mesh.attributes[f"sh{j}"] for j in range(k)]
    qxyz, qw = mesh.attributes["quatxyz"], mesh.attributes["quatw"]
    xyz, opac, scale, rot = np.zeros((n, 3)), np.zeros((n, 1)), np.zeros((n, 3)), np.zeros((n, 4))
    dc, rest = np.zeros((n, 3)), np.zeros((n, 3 * (k - 1)))
    for i in range(n):  # the per-splat loop
        xyz[i] = pos.data[i].vector.to_tuple()
        opac[i] = logop.data[i].value
        scale[i] = logscale.data[i].vector.to_tuple()
        dc[i] = sh[0].data[i].vector.to_tuple()
        for j in range(1, k):
            rest[i, j - 1 :: k - 1] = sh[j].data[i].vector.to_tuple()
        rot[i] = (*qxyz.data[i].vector.to_tuple(), qw.data[i].value)
    columns = np.concatenate([xyz, np.zeros((n, 3)), dc, rest, opac, scale, rot], axis=1)
    rows = np.empty(n, np.dtype([(f"c{i}", "<f4") for i in range(columns.shape[1])]))
    rows[:] = list(map(tuple, columns))
    names = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest.shape[1])]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names] + ["end_header\n"]
    with open(path, "wb") as f:
        f.write("\n".join(header).encode("ascii"))
        rows.tofile(f)


def _baseline(bpy, src, out, subset, scale, repeat):
    """Time the baseline on `subset` splats; returns scaled timings and its round-trip error."""
    made = []

    def do_import():
        if made:
            _remove(bpy, made.pop())
        made.append(baseline_import(bpy, src))

    t_import = timeit(do_import, repeat=repeat, warmup=0)
    k = read_splats(src).sh.shape[1]
    t_export = timeit(lambda: baseline_export(made[0], out, k), repeat=repeat, warmup=0)
    _remove(bpy, made[0])
    scaled = [Timing(t.median * scale, t.spread * scale, t.runs) for t in (t_import, t_export)]
    return scaled, max_abs_error(read_splats(src), read_splats(out))


# run -----------------------------------------------------------------------------------------------


def run(quick=False):
    import bpy

    from splatwright import splat_addon

    n = 100_000 if quick else 1_000_000
    subset = 10_000 if quick else 50_000
    repeat = 3 if quick else 5
    splat_addon.register()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            src, out, sub = tmp / "src.ply", tmp / "out.ply", tmp / "subset.ply"
            cloud = make_cloud(n)
            write_splats(src, cloud)
            write_splats(sub, cloud[:subset])
            t_import, t_export, t_display = _ours(bpy, src, out, repeat)
            t_blender, t_import_paired = _against_blender_import(bpy, src, repeat)
            ours_error = max_abs_error(read_splats(src), read_splats(out))
            (b_import, b_export), b_error = _baseline(bpy, sub, tmp / "b.ply", subset, n / subset, max(1, repeat - 2))
    finally:
        splat_addon.unregister()
    note = {"splats": n, "sh_degree": 3, "baseline_timed_on": subset, "baseline_scaled_by": round(n / subset, 1)}
    return [
        Row(
            TOPIC,
            "PLY -> Blender object (splat.import_file)",
            t_import,
            b_import,
            {"max_abs_roundtrip": ours_error, "baseline_max_abs_roundtrip": b_error},
            note,
        ),
        Row(
            TOPIC,
            "PLY -> Blender object, against Blender's own wm.ply_import",
            t_import_paired,
            t_blender,
            {"max_abs_roundtrip": ours_error},
            {**note, "baseline": "wm.ply_import (raw attributes)"},
        ),
        Row(
            TOPIC,
            "Blender object -> PLY (splat.export_file)",
            t_export,
            b_export,
            {"max_abs_roundtrip": ours_error, "baseline_max_abs_roundtrip": b_error},
            note,
        ),
        Row(TOPIC, "viewport display evaluation (geometry nodes)", t_display, None, {}, {"splats": n}),
    ]


if __name__ == "__main__":
    t0 = time.perf_counter()
    print_rows(run(quick="--quick" in sys.argv))
    print(f"{time.perf_counter() - t0:.0f} s")
