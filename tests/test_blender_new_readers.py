"""The Blender extension imports the read-only formats through read_splats: .ksplat (a file of the
layout tests/test_new_readers.py writes and splat-transform reads), LCC2 of SPZ chunks, and streamed
SOG, whose WebP images the extension decodes with Blender's own decoder (Blender's Python has no
Pillow; tests/test_blender_sog.py compares SOG splats read there with Pillow's)."""

import json

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import random_cloud

from splatwright.io import read_splats, write_splats

pytestmark = [pytest.mark.blender, pytest.mark.slow]


def _write_inputs(work):
    from test_new_readers import ksplat_cloud, write_ksplat, write_lcc2

    write_ksplat(work / "a.ksplat", ksplat_cloud(n=120, degree=2, seed=60), level=1, sections=2)
    (work / "lcc2").mkdir()
    write_lcc2(work / "lcc2", kind=".spz")  # SPZ chunks: no WebP, so Blender's Python reads them
    unit = work / "scene" / "0_0" / "meta.json"
    unit.parent.mkdir(parents=True)
    write_splats(unit, random_cloud(30, sh_degree=0, seed=61))
    meta = {"version": 1, "lodLevels": 1, "counts": [30], "filenames": ["0_0/meta.json"],
            "tree": {"lods": {"0": {"file": 0, "offset": 0, "count": 30}}}}  # fmt: skip
    (work / "scene" / "lod-meta.json").write_text(json.dumps(meta))


blender = blender_fixture("workers.new_readers", _write_inputs)


def test_import_dialog_offers_the_read_only_formats_and_export_does_not(blender):
    globs = blender.step("dialogs")
    assert {"*.ksplat", "*lod-meta.json", "*.lcc2", "*.ply", "*.sog"} <= set(globs["import"].split(";"))
    exported = set(globs["export"].split(";"))
    assert "*.ply" in exported and not {"*.ksplat", "*lod-meta.json", "*.lcc2"} & exported


def test_ksplat_imports_and_exports_back_as_read(blender):
    res = blender.step("imports")["ksplat"]
    assert res["result"] == ["FINISHED"] and res["objects"] == 1 and res["count"] == 120, res
    assert res["export"]["result"] == ["FINISHED"], res["export"]
    want = read_splats(blender.work / "a.ksplat")
    got = read_splats(blender.out / "a_back.ply")
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-5)
    np.testing.assert_allclose(got.log_scales, want.log_scales, atol=1e-5)
    np.testing.assert_allclose(got.sh, want.sh, atol=1e-4)
    cos = np.abs((got.unit_rotations * want.unit_rotations).sum(axis=1))
    assert cos.min() > 1 - 1e-6


def test_lcc2_of_spz_chunks_imports_as_read(blender):
    res = blender.step("imports")["lcc2"]
    assert res["result"] == ["FINISHED"] and res["objects"] == 1 and res["count"] == 70, res
    want = read_splats(blender.work / "lcc2" / "scene.lcc2")
    got = read_splats(blender.out / "lcc2_back.ply")
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-5)
    np.testing.assert_allclose(got.sh, want.sh, atol=1e-4)


def test_streamed_sog_imports_without_pillow(blender):
    res = blender.step("imports")["streamed"]
    assert res["result"] == ["FINISHED"] and res["objects"] == 1 and res["count"] == 30, res
