"""Mesh to splats within a memory budget: the prediction holds what the operating system measures,
a budget that binds keeps the best splats it reached and says so, one too small is refused before
anything is allocated, and the default is a share of the memory free."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import REPO_ROOT, skip_platform

from splatwright.core import memory
from splatwright.core.mesh_refine import conversion_bytes, splats_within
from splatwright.core.mesh_to_splats import mesh_to_splats

STRIPED_CYLINDER = """
import numpy as np
from splatwright.core.mesh import Material

def striped_cylinder(sections=64, rings=16):
    # A cup-like wall with hard-edged vertical stripes: refinement keeps asking for more splats.
    a = np.linspace(0, 2 * np.pi, sections + 1)[:-1]
    z = np.linspace(0, 1, rings + 1)
    ring = np.stack([0.5 * np.cos(a), 0.5 * np.sin(a)], 1)
    vertices = np.concatenate([np.column_stack([ring, np.full(sections, h)]) for h in z])
    i, j = np.meshgrid(np.arange(rings), np.arange(sections), indexing="ij")
    a0, a1 = i * sections + j, i * sections + (j + 1) % sections
    b0, b1 = a0 + sections, a1 + sections
    faces = np.concatenate([np.stack([a0, a1, b1], -1), np.stack([a0, b1, b0], -1)]).reshape(-1, 3)
    u = np.arctan2(vertices[:, 1], vertices[:, 0]) / (2 * np.pi) + 0.5
    uv = np.stack([u, vertices[:, 2]], 1)[faces]
    uv[..., 0] = np.where(uv[..., 0] - uv[..., 0].min(1, keepdims=True) > 0.5, uv[..., 0] - 1, uv[..., 0])
    texture = np.full((64, 512, 3), 230, np.uint8)
    for k in range(0, 512, 32):
        texture[:, k : k + 12] = (200, 30, 30)
    return vertices, faces, uv, Material(texture=texture)
"""

MEASURED = (
    STRIPED_CYLINDER
    + """
import json, sys
from splatwright.core.mesh_to_splats import mesh_to_splats

def status(key):  # bytes of this process from Linux's /proc/self/status (kB there)
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(key + ":"))

v, f, uv, material = striped_cylinder()
appearance = dict(corner_uvs=uv, face_materials=np.zeros(len(f), int), materials=[material])
mesh_to_splats(v, f, **appearance, max_splats=2000, view_size=32, view_count=1)  # kernels compiled, imports done
with open("/proc/self/clear_refs", "w") as clear:
    clear.write("5")  # the peak (VmHWM) starts again from what is resident now
before = status("VmRSS")
info = {}
cloud = mesh_to_splats(v, f, **appearance, view_size=96, memory_budget=int(sys.argv[1]), info=info)
grew = status("VmHWM") - before
print(json.dumps({"splats": len(cloud), "grew": grew, "faces": len(f), "psnr": info["psnr"],
                  "cap": info["memory_cap"], "limit": info["limit"]}))
"""
)


def test_a_conversion_stays_within_its_memory_budget(tmp_path):
    """Refinement of a striped wall asks for more splats (33k unbounded); under a 180 MiB budget it
    stops at the 18k splats the budget holds, keeps the best it reached, says why, and the process's
    peak resident memory (the operating system's count, not the model's) grew by less than the budget."""
    if not os.path.exists("/proc/self/clear_refs"):
        skip_platform("the peak resident memory cannot be reset here (Linux's /proc/self/clear_refs)")
    budget = 180 << 20
    done = subprocess.run(
        [sys.executable, "-c", MEASURED, str(budget)], capture_output=True, text=True, timeout=900, cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    cap = splats_within(budget, got["faces"], 12 * 96 * 96)
    assert got["cap"] == cap and 0.9 * cap <= got["splats"] <= cap
    assert "memory budget (180.0 MiB)" in got["limit"] and np.isfinite(got["psnr"]) and got["psnr"] > 15
    assert 0 < got["grew"] <= budget
    # the model errs on the safe side, but not absurdly: the prediction is at most 4x what was used
    assert conversion_bytes(got["splats"], got["faces"], 12 * 96 * 96) <= 4 * got["grew"] + (64 << 20)


def test_a_budget_too_small_for_the_views_is_refused_before_any_splat(monkeypatch):
    import splatwright.core.mesh_sampling as sampling

    def no_splats(*args, **kwargs):
        raise AssertionError("splats were placed")

    monkeypatch.setattr("splatwright.core.mesh_refine.unplaced_splats", no_splats)
    monkeypatch.setattr(sampling, "unplaced_splats", no_splats)
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    with pytest.raises(ValueError, match=r"memory budget \(70.0 MiB\) cannot hold this conversion.*views"):
        mesh_to_splats(vertices, np.array([[0, 1, 2]]), view_size=512, memory_budget=70 << 20)
    with pytest.raises(ValueError, match="at least 64 MiB"):
        mesh_to_splats(vertices, np.array([[0, 1, 2]]), max_splats=10, memory_budget=1 << 20)


def test_a_budget_caps_a_splat_budget_and_says_so():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    budget = 80 << 20
    info = {}
    cloud = mesh_to_splats(vertices, faces, max_splats=10**7, calibrate=False, memory_budget=budget, info=info)
    cap = splats_within(budget, 2, 0)
    assert info["memory_cap"] == cap and abs(len(cloud) - cap) < 0.02 * cap
    from splatwright.core.mesh_refine import summary

    assert summary(info) == f"the memory budget (80.0 MiB) held it to {cap} splats"


def test_the_default_budget_is_half_the_memory_free():
    if not memory.available_memory():
        pytest.skip("not on this platform: the free memory cannot be told")
    with open("/proc/meminfo") as meminfo:
        free = next(int(line.split()[1]) * 1024 for line in meminfo if line.startswith("MemAvailable:"))
    assert abs(memory.default_budget() - free / 2) < 0.05 * free


def test_the_command_takes_a_budget_and_tells_the_size_before_writing(tmp_path):
    obj = tmp_path / "quad.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    out = tmp_path / "quad.ply"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "splatwright",
            "mesh2splats",
            str(obj),
            str(out),
            "--max-splats",
            "10000000",
            "--no-calibrate",
            "--memory-budget",
            "80M",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO_ROOT.parent,
    )
    assert done.returncode == 0, done.stderr
    cap = splats_within(80 << 20, 2, 0)
    writing = next(line for line in done.stdout.splitlines() if line.startswith("writing "))
    count, size = int(writing.split()[1]), float(writing.split("about ")[1].split(" MiB")[0]) * 2**20
    assert abs(count - cap) < 0.02 * cap and "memory budget (80.0 MiB)" in done.stdout
    assert abs(out.stat().st_size - size) < 0.01 * size
    bad = subprocess.run(
        [sys.executable, "-m", "splatwright", "mesh2splats", str(obj), str(out), "--memory-budget", "lots"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO_ROOT.parent,
    )
    assert bad.returncode == 2 and "expected a size such as 4G" in bad.stderr


def test_a_budget_that_did_not_bind_is_not_reported():
    from splatwright.core.mesh_refine import summary

    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    info = {}
    mesh_to_splats(vertices, np.array([[0, 1, 2], [0, 2, 3]]), target_psnr=20, view_size=32, view_count=1, info=info)
    assert info["reached"] and info["memory_budget"] > 0
    assert info["memory_cap"] is None and "memory budget" not in summary(info)
