"""bench/relight_accuracy.py's own pieces: the lights it gives Cycles and render_lit light the mesh as
stated (closed-form irradiance at its centre), the Blender light matrix points the light where the
core Light points, and the error shares add up over the masks they name."""

import importlib.util
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from splatwright.core.lights import irradiance
from splatwright.core.mesh_corpus import striped_cylinder

BENCH = Path(__file__).resolve().parent.parent / "bench"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_relight_accuracy", BENCH / "relight_accuracy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_lights_give_the_stated_irradiance_at_the_centre(bench):
    mesh = striped_cylinder(16, 4)
    centre, radius = bench.bounds(mesh)
    lights = bench.scene_lights(mesh)
    assert set(lights) == {"point", "spot", "sun", "area"}
    for kind, light in lights.items():
        if kind == "sun":
            towards = -light.direction
        else:
            towards = (light.position - centre) / np.linalg.norm(light.position - centre)
            assert np.linalg.norm(light.position - centre) == pytest.approx(3 * radius)
        e = irradiance(light, centre[None], towards[None])[0, 0]
        # point, spot (on its axis: cone factor 1) and sun exactly; the area light's P / (pi d^2) holds
        # for a small light: its 0.6 R x 0.4 R rectangle at 3 R gives about 1% less
        tolerance = 0.02 if kind == "area" else 1e-9
        assert e == pytest.approx(bench.IRRADIANCE, rel=tolerance), kind
        assert 30 <= math.degrees(math.asin(towards[1])) <= 60, kind


def test_spot_cone_edge_crosses_the_mesh(bench):
    mesh = striped_cylinder(16, 4)
    centre, radius = bench.bounds(mesh)
    spot = bench.scene_lights(mesh)["spot"]
    half = spot.spot_size / 2
    # the bounding sphere seen from the spot subtends asin(1/3): wider than the cone's half-angle
    assert half < math.asin(1 / 3) < 2 * half


def test_light_matrix_points_like_the_core_light(bench):
    mesh = striped_cylinder(16, 4)
    for light in bench.scene_lights(mesh).values():
        spec = bench.light_spec(light)
        m = bench._light_matrix(spec)
        rotation = m[:3, :3]
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(-rotation[:, 2], light.direction, atol=1e-12)
        np.testing.assert_allclose(m[:3, 3], light.position, atol=1e-12)
        if light.kind == "area":
            np.testing.assert_allclose(rotation[:, 0], light.x_axis, atol=1e-12)


def test_error_shares_split_the_error_by_mask(bench):
    ref = np.zeros((4, 4, 3))
    color = np.zeros((4, 4, 3))
    color[0, 0] = 0.1  # in a penumbra
    color[3, 3] = 0.2  # in full shadow
    shadow = np.zeros((4, 4))
    shadow[0, 0], shadow[3, 3] = 0.5, 1.0
    frame = SimpleNamespace(color=color, shadow=shadow, specular=np.zeros((4, 4, 3)), diffuse=np.ones((4, 4, 3)))
    shares = bench.error_shares([frame], [ref])
    assert shares["penumbra"] == pytest.approx(0.01 / 0.05)
    assert shares["full shadow"] == pytest.approx(0.04 / 0.05)
    assert shares["highlight"] == 0.0
