"""Estimate Normals in every Blender of the version matrix (the worker is tests/workers/normals.py):
the normals it stores on splat objects of both forms, against the closed-form normals the splats were
built with: outward on a sphere of flat splats (its object moved, turned and stretched), towards the
camera on a sheet seen by one; its report of round splats; and a refusal that writes nothing."""

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import skip_platform
from workers.normals import ROUND, SHEET, SPHERE

pytestmark = [pytest.mark.blender, pytest.mark.slow]

blender = blender_fixture("workers.normals")


def test_operator_is_registered(blender):
    assert blender.step("install")["operator"]


def _result(blender, step):
    res = blender.step(step)
    if res.get("skipped"):
        skip_platform(f"Blender {blender.version} makes no native splats from Python")
    return res


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_sphere_normals_point_outward_either_way(blender, form):
    res = _result(blender, f"sphere_{form.lower()}")
    for orient in ("CAMERAS", "CENTRE"):
        assert res[orient]["result"] == ["FINISHED"], res[orient]
        # No camera in the scene: Cameras falls back to the centre; the round splats are counted.
        assert res[orient]["report"] == {"splats": SPHERE, "too_round": ROUND, "cameras": 0, "orient": orient}
        d = blender.npz(f"sphere_{form}_{orient}")
        assert d["normals"].shape == (SPHERE, 3)
        np.testing.assert_allclose(np.linalg.norm(d["normals"], axis=1), 1.0, atol=1e-6)
        flat = slice(0, SPHERE - ROUND)  # a round splat has no normal to check
        assert np.einsum("ij,ij->i", d["normals"][flat], d["outward"][flat]).min() > 0.999
    assert {"nx", "ny", "nz"} <= set(res["exported_extras"])


@pytest.mark.parametrize("form", ["MESH", "NATIVE"])
def test_sheet_normals_face_the_camera(blender, form):
    both = _result(blender, f"sheet_{form.lower()}")
    res = both["CAMERAS"]
    assert res["result"] == ["FINISHED"], res
    # Five cameras in the scene, at most two used.
    assert both["thinned"]["result"] == ["FINISHED"] and both["thinned"]["report"]["cameras"] == 2
    assert res["report"] == {"splats": SHEET * SHEET, "too_round": 0, "cameras": 1, "orient": "CAMERAS"}
    d = blender.npz(f"sheet_{form}")
    assert np.einsum("ij,ij->i", d["normals"], d["facing"]).min() > 0.9999


def test_non_finite_splats_are_refused_and_nothing_is_written(blender):
    res = blender.step("refusals")
    assert res["broken"]["result"] == ["CANCELLED"]
    assert "non-finite log_scales" in res["broken"]["error"]
    assert res["normals_written"] == 0
