"""Blender's import against a file naming a file outside its folder: refused unless Allow Files
Outside is on (headless, the extension installed from its zip as in test_blender_addon.py)."""

import json

import pytest
from blender_session import blender_fixture
from helpers import random_cloud

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version: ~3 s


def _write_inputs(work):
    from splatwright.io import gltf

    (work / "model").mkdir()
    gltf.write(work / "model" / "v.gltf", random_cloud(5, sh_degree=0, seed=3))
    (work / "model" / "v.bin").rename(work / "v.bin")
    doc = json.loads((work / "model" / "v.gltf").read_text())
    doc["buffers"][0]["uri"] = "../v.bin"
    (work / "model" / "v.gltf").write_text(json.dumps(doc))


blender = blender_fixture("workers.hostile", _write_inputs)


def test_import_follows_names_outside_the_folder_only_when_allowed(blender):
    case = blender.step("outside")
    before = case["objects_after_refusal"]
    assert case["refused"]["result"] == ["CANCELLED"] and "../v.bin" in case["refused"]["error"]
    assert "v.gltf" in case["refused"]["error"] and "Traceback" not in case["refused"]["error"]
    assert case["allowed"] == {"result": ["FINISHED"], "error": None} and case["count"] == 5
    assert case["name"] == "Allow Files Outside" and case["default"] is False
    assert "a hostile file could then read any file on this machine" in case["description"]
    assert before == 2  # the startup camera and light: the refusal added nothing
