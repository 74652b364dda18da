"""Cameras: look-at and field-of-view conventions (closed forms), OpenGL/Blender axes, and Blender
lens settings checked against Blender's own projection (bpy in a subprocess)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from splatwright.core.camera import (
    Camera,
    blender_intrinsics,
    blender_lens,
    frame_points,
    opengl_camera_to_world,
    spread_along,
    world_to_camera_from_opengl,
)


def rigid(m):
    r = m[:3, :3]
    return np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)


def test_look_at_centres_the_target_and_keeps_world_up_up():
    eye, target = np.array([1.8, 1.2, 4.5]), np.array([0.0, 0.0, 3.0])
    cam = Camera.look_at(eye, target, fov_deg=60, width=640, height=480)
    assert rigid(cam.world_to_camera)
    np.testing.assert_allclose(cam.center, eye, atol=1e-12)
    px, z = cam.project(np.stack([target, target + [0, 0.1, 0], target - [0, 0.1, 0]]))
    np.testing.assert_allclose(px[0], [320, 240], atol=1e-9)
    np.testing.assert_allclose(z[0], np.linalg.norm(target - eye), rtol=1e-12)
    assert px[1, 1] < 240 < px[2, 1]  # higher in the world = nearer row 0 (the top)
    np.testing.assert_allclose(cam.forward, (target - eye) / np.linalg.norm(target - eye), atol=1e-12)


def test_horizontal_field_of_view_reaches_the_image_edges():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), fov_deg=70, width=300, height=100)
    half = math.tan(math.radians(35)) * 5
    px, _ = cam.project(np.array([[half, 0, 0], [-half, 0, 0], [0, half, 0]]))
    np.testing.assert_allclose(px[0], [300, 50], atol=1e-9)  # world +x appears right
    np.testing.assert_allclose(px[1], [0, 50], atol=1e-9)
    np.testing.assert_allclose(px[2], [150, 50 - 150], atol=1e-9)  # square pixels: fy = fx
    assert cam.fov_x_deg == pytest.approx(70)


def test_orthographic_scale_is_the_visible_width_and_depth_does_not_shrink():
    cam = Camera.look_at_ortho((0, 0, 5), (0, 0, 0), ortho_scale=4.0, width=200, height=100)
    px, z = cam.project(np.array([[2.0, 0, 0], [-2.0, 1.0, -7.0], [0, 0, 3.0]]))
    np.testing.assert_allclose(px, [[200, 50], [0, 0], [100, 50]], atol=1e-9)
    np.testing.assert_allclose(z, [5, 12, 2], atol=1e-12)


def test_look_at_straight_down_still_gives_a_rigid_camera():
    cam = Camera.look_at((0, 10, 0), (0, 0, 0), up=(0, 1, 0))
    assert rigid(cam.world_to_camera)
    px, _ = cam.project(np.zeros((1, 3)))
    np.testing.assert_allclose(px[0], [256, 256], atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"fov_deg": 0}, "fov_deg"),
        ({"fov_deg": 180}, "fov_deg"),
        ({"width": 0}, "width"),
        ({"eye": (0, 0, 0)}, "same point"),
        ({"eye": (np.nan, 0, 1)}, "finite"),
        ({"near": -1}, "near"),
    ],
)
def test_bad_cameras_are_refused_with_the_reason(kwargs, message):
    args = {"eye": (0, 0, 1), "target": (0, 0, 0)} | kwargs
    with pytest.raises(ValueError, match=message):
        Camera.look_at(**args)


def test_non_rigid_world_to_camera_is_refused():
    m = np.eye(4)
    m[0, 0] = 2.0
    with pytest.raises(ValueError, match="rigid"):
        Camera(64, 64, 50, 50, 32, 32, m)


def test_opengl_axes_round_trip_and_match_the_blender_convention():
    # A Blender camera at (0, 0, 5) with identity rotation looks down -Z with +Y up.
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, 5]
    w2c = world_to_camera_from_opengl(c2w)
    p = w2c[:3, :3] @ np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]).T + w2c[:3, 3:4]
    np.testing.assert_allclose(p.T, [[0, 0, 5], [1, 0, 5], [0, -1, 5]], atol=1e-12)
    cam = Camera.look_at((1, 2, 3), (-1, 0.5, 0), fov_deg=40)
    np.testing.assert_allclose(
        world_to_camera_from_opengl(opengl_camera_to_world(cam.world_to_camera)), cam.world_to_camera, atol=1e-12
    )
    scaled = opengl_camera_to_world(cam.world_to_camera) @ np.diag([2.0, 0.5, 3.0, 1.0])
    np.testing.assert_allclose(world_to_camera_from_opengl(scaled), cam.world_to_camera, atol=1e-12)


def test_blender_intrinsics_closed_forms():
    k = blender_intrinsics(1920, 1080, lens=50, sensor_width=36)
    assert k["fx"] == pytest.approx(50 / 36 * 1920) and k["fy"] == pytest.approx(k["fx"])
    assert (k["cx"], k["cy"]) == (960, 540)
    portrait = blender_intrinsics(1080, 1920, lens=50, sensor_width=36)  # AUTO fits the long side
    assert portrait["fy"] == pytest.approx(50 / 36 * 1920)
    shifted = blender_intrinsics(1000, 500, shift_x=0.1, shift_y=0.2)
    assert (shifted["cx"], shifted["cy"]) == (pytest.approx(500 - 100), pytest.approx(250 + 200))
    ortho = blender_intrinsics(800, 600, type="ORTHO", ortho_scale=4.0)
    assert ortho["fx"] == pytest.approx(200) and ortho["projection"] == "orthographic"
    with pytest.raises(ValueError, match="PANO"):
        blender_intrinsics(10, 10, type="PANO")


@pytest.mark.parametrize(
    "camera",
    [
        Camera(640, 360, 700.0, 700.0, 320.0, 180.0),
        Camera(300, 500, 420.0, 610.0, 171.5, 262.0),  # shifted, non-square pixels
        Camera(200, 100, 90.0, 45.0, 100.0, 55.0, projection="orthographic"),
        Camera(200, 100, 30.0, 45.0, 90.0, 50.0, projection="orthographic"),
    ],
)
def test_blender_lens_gives_the_camera_back(camera):
    """blender_lens inverts blender_intrinsics: a Blender camera with those settings sees as the camera does."""
    lens = blender_lens(camera)
    assert lens["pixel_aspect_x"] >= 1 and lens["pixel_aspect_y"] >= 1
    k = blender_intrinsics(camera.width, camera.height, **lens)
    np.testing.assert_allclose(
        [k["fx"], k["fy"], k["cx"], k["cy"]], [camera.fx, camera.fy, camera.cx, camera.cy], rtol=1e-12
    )
    assert k["projection"] == camera.projection


def orbit(degrees, distance=4.0, fov_deg=40.0):
    """Cameras on a circle around the origin at these angles (degrees), looking at it."""
    rad = np.radians(degrees)
    return [Camera.look_at(distance * np.array([np.cos(a), 0.0, np.sin(a)]), np.zeros(3), fov_deg=fov_deg) for a in rad]


def turns(cams):
    """Degrees between consecutive cameras' directions from the origin."""
    d = np.array([c.center / np.linalg.norm(c.center) for c in cams])
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", d[:-1], d[1:]), -1, 1)))


def test_spread_along_puts_views_where_the_view_changes():
    # Still for 50 frames, then a quarter turn over 50: one view where it stands, three along the turn
    # (each turn counts twice, around the centre and of the forward axis).
    path = orbit([0.0] * 50 + list(np.linspace(0.0, 90.0, 51)[1:]))
    picked = spread_along(path, 4, np.zeros(3))
    np.testing.assert_allclose(turns([path[i] for i in picked]), 30.0, atol=1.8)  # a frame is 1.8 degrees
    assert picked[0] < 50
    frames = np.round(np.linspace(0, len(path) - 1, 4)).astype(int)  # by frames: two the same
    assert turns([path[i] for i in frames]).min() == 0.0


def test_spread_along_closed_forms():
    steady = orbit(np.linspace(0.0, 120.0, 121))  # a steady turn: even in frames
    np.testing.assert_array_equal(spread_along(steady, 5, np.zeros(3)), [0, 30, 60, 90, 120])
    still = orbit([10.0] * 20)
    np.testing.assert_array_equal(spread_along(still, 6, np.zeros(3)), [0])
    np.testing.assert_array_equal(spread_along(still[:3] + orbit([50.0]), 1, np.zeros(3)), [0])
    assert len(spread_along([], 4, np.zeros(3))) == 0
    np.testing.assert_array_equal(spread_along(orbit([0.0, 5.0, 10.0]), 8, np.zeros(3)), [0, 1, 2])
    # A dolly in from 8 to 1 (no turn): views evenly spaced in the log of the distance, 8, 4, 2, 1.
    dolly = [Camera.look_at([0.0, 0.0, d], np.zeros(3)) for d in np.geomspace(8.0, 1.0, 301)]
    picked = spread_along(dolly, 4, np.zeros(3))
    np.testing.assert_allclose([dolly[i].center[2] for i in picked], [8.0, 4.0, 2.0, 1.0], rtol=0.01)
    # A zoom from 20 to 80 degrees standing still counts as the log of its focal length ratio.
    zoom = [Camera.look_at([0.0, 0.0, 3.0], np.zeros(3), fov_deg=f) for f in np.linspace(20.0, 80.0, 200)]
    fx = np.array([zoom[i].fx for i in spread_along(zoom, 3, np.zeros(3))])
    np.testing.assert_allclose(np.diff(np.log(fx)), np.log(fx[-1] / fx[0]) / 2, rtol=0.02)


def test_spread_along_adds_views_where_the_path_needs_them():
    # A quarter turn counts pi (around and of the forward axis): views at most 0.5 apart need 8.
    turn = orbit(np.linspace(0.0, 90.0, 91))
    picked = spread_along(turn, 2, np.zeros(3), spacing=0.5)
    np.testing.assert_allclose(turns([turn[i] for i in picked]), 90.0 / 7, atol=1.0)
    assert len(spread_along(turn, 2, np.zeros(3), spacing=0.5, most=5)) == 5
    assert len(spread_along(turn, 12, np.zeros(3), spacing=0.5)) == 12  # never fewer than asked
    assert len(spread_along(orbit([0.0, 45.0]), 2, np.zeros(3), spacing=0.01)) == 2  # only the cameras there are


def test_frame_points_sees_every_point():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(500, 3)) * [3, 1, 0.2] + [100, -5, 7]
    for cam in (frame_points(pts, 320, 200, fov_deg=50), frame_points(pts, 200, 320, ortho_scale=0)):
        px, z = cam.project(pts)
        assert (z > cam.near).all()
        assert (px >= 0).all() and (px[:, 0] <= cam.width).all() and (px[:, 1] <= cam.height).all()


BPY_SCRIPT = r"""
import json, sys
import bpy, bpy_extras.object_utils as ou
from mathutils import Vector, Euler
scene = bpy.context.scene
data = bpy.data.cameras.new("cam")
cam = bpy.data.objects.new("cam", data)
scene.collection.objects.link(cam)
out = []
for c in json.loads(sys.stdin.read()):
    scene.render.resolution_x, scene.render.resolution_y = c["width"], c["height"]
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = c["pixel_aspect"]
    data.type, data.lens, data.sensor_fit = c["type"], c["lens"], c["sensor_fit"]
    data.sensor_width, data.sensor_height = c["sensor"]
    data.shift_x, data.shift_y = c["shift"]
    data.ortho_scale = c["ortho_scale"]
    cam.location, cam.rotation_euler, cam.scale = c["location"], Euler(c["rotation"]), c["scale"]
    bpy.context.view_layer.update()
    out.append({"matrix_world": [list(r) for r in cam.matrix_world],
                "ndc": [list(ou.world_to_camera_view(scene, cam, Vector(p))) for p in c["points"]]})
print("RESULT" + json.dumps(out))
"""


@pytest.mark.blender
def test_blender_cameras_project_like_blender():
    """Our Camera.from_blender against bpy_extras' world_to_camera_view for sensor fits, shifts,
    pixel aspects, orthographic cameras and scaled camera objects."""
    pytest.importorskip("bpy")
    rng = np.random.default_rng(7)
    cases = [
        (640, 480, "PERSP", "AUTO", (1, 1)),
        (480, 640, "PERSP", "AUTO", (1, 1)),
        (640, 480, "PERSP", "VERTICAL", (1, 1)),
        (300, 500, "PERSP", "HORIZONTAL", (1, 1)),
        (640, 480, "ORTHO", "AUTO", (1, 1)),
        (400, 700, "ORTHO", "AUTO", (1, 1)),
        (640, 480, "PERSP", "AUTO", (2, 1)),
        (640, 480, "ORTHO", "VERTICAL", (1, 1.5)),
    ]
    configs = []
    for i, (w, h, kind, fit, aspect) in enumerate(cases):
        configs.append(
            {
                "width": w,
                "height": h,
                "type": kind,
                "sensor_fit": fit,
                "pixel_aspect": aspect,
                "lens": float(rng.uniform(20, 80)),
                "sensor": (36.0, 24.0),
                "shift": rng.uniform(-0.3, 0.3, 2).tolist(),
                "ortho_scale": float(rng.uniform(2, 8)),
                "location": rng.uniform(-3, 3, 3).tolist(),
                "rotation": rng.uniform(-3, 3, 3).tolist(),
                "scale": [1.0, 1.0, 1.0] if i % 2 == 0 else rng.uniform(0.5, 2, 3).tolist(),
                "points": rng.uniform(-10, 10, (30, 3)).tolist(),
            }
        )
    run = subprocess.run(
        [sys.executable, "-c", BPY_SCRIPT],
        input=json.dumps(configs),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).parent,
    )
    assert "RESULT" in run.stdout, run.stderr[-2000:]
    for c, got in zip(configs, json.loads(run.stdout.split("RESULT", 1)[1])):
        cam = Camera.from_blender(
            np.array(got["matrix_world"]),
            c["width"],
            c["height"],
            lens=c["lens"],
            sensor_width=c["sensor"][0],
            sensor_height=c["sensor"][1],
            sensor_fit=c["sensor_fit"],
            shift_x=c["shift"][0],
            shift_y=c["shift"][1],
            type=c["type"],
            ortho_scale=c["ortho_scale"],
            pixel_aspect_x=c["pixel_aspect"][0],
            pixel_aspect_y=c["pixel_aspect"][1],
        )
        px, z = cam.project(np.array(c["points"]))
        ndc = np.array(got["ndc"])
        front = z > 0.1
        assert front.sum() > 3
        ours = np.column_stack([px[:, 0] / c["width"], 1 - px[:, 1] / c["height"], z])[front]
        # mathutils works in float32: agree to its round-off
        np.testing.assert_allclose(ours, ndc[front], rtol=1e-5, atol=2e-5 * np.abs(ndc[front]).max())


def test_pixel_rays_look_through_the_pixels_and_their_solid_angles_tile_the_view():
    """A perspective camera's pixel rays project back onto their pixels' centres, and their solid
    angles sum to the view's closed form, 4 asin(a b / sqrt((1 + a^2)(1 + b^2))) for half-tangents a,
    b (the midpoint rule at 64 x 48 pixels: within 1e-4); an orthographic camera has none."""
    cam = Camera.look_at((1.0, -2.0, 0.5), (0.2, 0.3, 0.1), up=(0, 0, 1), fov_deg=70, width=64, height=48)
    rays, solid = cam.pixel_rays()
    assert rays.shape == (48, 64, 3) and solid.shape == (48, 64)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, rtol=1e-12)
    pixels, _ = cam.project(cam.center + rays.reshape(-1, 3))
    centres = np.stack(np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5), axis=-1).reshape(-1, 2)
    np.testing.assert_allclose(pixels, centres, atol=1e-9)
    a, b = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    whole = 4.0 * math.asin(a * b / math.sqrt((1 + a * a) * (1 + b * b)))
    assert abs(solid.sum() / whole - 1.0) < 1e-4
    with pytest.raises(ValueError, match="orthographic"):
        Camera.look_at_ortho((0, 0, 5), (0, 0, 0), ortho_scale=2.0).pixel_rays()
