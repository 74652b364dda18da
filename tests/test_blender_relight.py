"""Relighting in Blender, headless in every Blender of the version matrix.

The lights the engine reads are checked against values computed here by hand from the settings the
worker gave each light (Blender's XYZ Euler, the light's -Z as its direction, Cycles' reading of
power, exposure and Normalize).
"""

import math

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import euler_matrix
from workers.relight import COLORS, EXPOSURE, INSTANCE_OFFSET, LIGHTS, ORIGIN

pytestmark = [pytest.mark.blender, pytest.mark.slow]

blender = blender_fixture("workers.relight")


def expected_light(name, kind, location, rotation, scale, settings, exposure, normalize):
    """The core Light fields of one light, from its settings (float64, written out per kind)."""
    r = euler_matrix(rotation) @ np.diag(scale)
    out = {
        "kind": kind.lower(),
        "color": COLORS.get(name, (1.0, 1.0, 1.0)),
        "position": np.subtract(location, ORIGIN),
        "direction": -r[:, 2] / np.linalg.norm(r[:, 2]),
        "cast_shadow": settings.get("use_shadow", True),
    }
    power = settings["energy"] * (2.0**EXPOSURE if exposure and name == "Sun" else 1.0)
    if kind == "SUN":
        out["angle"] = settings["angle"]
    elif kind == "AREA":
        out["shape"] = settings["shape"]
        out["size_x"] = settings["size"] * scale[0]
        out["size_y"] = settings.get("size_y", settings["size"]) * scale[1]
        out["x_axis"] = r[:, 0] / np.linalg.norm(r[:, 0])
        if name == "Disk" and not normalize:  # power per square metre of the disk
            power *= math.pi / 4 * out["size_x"] * out["size_y"]
    else:
        out["radius"] = settings.get("shadow_soft_size", 0.25)
    if kind == "SPOT":
        out["spot_size"], out["spot_blend"] = settings["spot_size"], settings["spot_blend"]
    out["power"] = power
    return out


def test_scene_lights_are_read_with_blender_axes_and_cycles_units(blender):
    res = blender.step("lights")
    got = {f["name"]: f for f in res["fields"] if f["name"] != "Lamp"}
    assert sorted(got) == sorted(LIGHTS)
    for name, spec in LIGHTS.items():
        want = expected_light(name, *spec, exposure=res["exposure"], normalize=not res["normalize"])
        assert sorted(got[name]) == sorted(["name", *want]), name
        for key, value in want.items():
            if isinstance(value, str | bool):
                assert got[name][key] == value, (name, key)
            else:
                np.testing.assert_allclose(got[name][key], value, rtol=1e-6, atol=1e-6, err_msg=f"{name}.{key}")
    # the instanced lamp and its own collection object: one light, at the instance's place
    lamps = [f for f in res["fields"] if f["name"] == "Lamp"]
    assert len(lamps) == 1
    np.testing.assert_allclose(lamps[0]["position"], np.add((0.0, 0.0, 1.0), INSTANCE_OFFSET) - ORIGIN, atol=1e-6)


def test_scene_lights_make_core_lights(blender):
    made = blender.step("lights")["scene_lights"]
    if isinstance(made, str):
        pytest.fail(f"core.lights could not take the fields: {made}")
    assert sorted(m["kind"] for m in made) == sorted(["area", "area", "point", "point", "spot", "sun"])
