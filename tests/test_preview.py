"""The Rendered viewport's picture without Blender (core/preview.py): the camera of an OpenGL view
against the projection written out, the flat-shaded mesh layer against ray-plane intersections, the
composite against the float64 reference, and the progressive renderer's schedule with a fake clock
and renderer."""

import threading
import time

import numpy as np
import pytest
from helpers import random_cloud
from reference_render import reference_render

from splatwright.core.camera import Camera, opengl_camera_to_world
from splatwright.core.preview import Progressive, Triangles, camera_from_opengl, mesh_layer, preview_image, scaled

STEP = 1.0 / 255.0


def opengl(camera, near=0.1, far=100.0):
    """The OpenGL view and projection matrices of a core camera, written out from their textbook form."""
    view = np.linalg.inv(opengl_camera_to_world(camera.world_to_camera))
    w, h = camera.width, camera.height
    # the view volume's sides at distance 1 (perspective) or in world units (orthographic)
    left, right = -camera.cx / camera.fx, (w - camera.cx) / camera.fx
    top, bottom = camera.cy / camera.fy, -(h - camera.cy) / camera.fy
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = 2 / (right - left), 2 / (top - bottom)
    if camera.is_orthographic:
        p[0, 3], p[1, 3] = -(right + left) / (right - left), -(top + bottom) / (top - bottom)
        p[2, 2], p[2, 3], p[3, 3] = -2 / (far - near), -(far + near) / (far - near), 1.0
    else:
        p[0, 2], p[1, 2] = (right + left) / (right - left), (top + bottom) / (top - bottom)
        p[2, 2], p[2, 3], p[3, 2] = -(far + near) / (far - near), -2 * far * near / (far - near), -1.0
    return view, p


def clip_to_pixels(view, projection, points, width, height):
    """Pixel coordinates (x right, y down) of world points through OpenGL's pipeline."""
    clip = np.c_[points, np.ones(len(points))] @ (projection @ view).T
    ndc = clip[:, :3] / clip[:, 3:]
    return np.stack([(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height], axis=1)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Camera(80, 60, 70.0, 72.0, 35.0, 33.0, Camera.look_at((1, 2, -3), (0, 0, 1)).world_to_camera),
        lambda: Camera.look_at_ortho((2, 1, -4), (0, 0, 0), ortho_scale=3.0, width=50, height=70),
    ],
    ids=["perspective-shifted", "orthographic"],
)
def test_camera_of_an_opengl_view_projects_as_opengl_does(make):
    cam = make()
    view, projection = opengl(cam, near=0.5, far=50.0)
    got = camera_from_opengl(view, projection, cam.width, cam.height)
    points = np.random.default_rng(0).normal(0, 1, (50, 3))
    pixels, _ = got.project(points)
    np.testing.assert_allclose(pixels, clip_to_pixels(view, projection, points, cam.width, cam.height), atol=1e-9)
    if not cam.is_orthographic:
        assert got.near == pytest.approx(0.5) and got.far == pytest.approx(50.0)
    assert got.projection == cam.projection


def test_orthographic_view_with_a_clip_range_behind_the_eye_moves_back_keeping_the_picture():
    cam = Camera.look_at_ortho((0, 0, -2), (0, 0, 0), ortho_scale=2.0, width=30, height=30)
    view, projection = opengl(cam, near=-10.0, far=10.0)
    got = camera_from_opengl(view, projection, 30, 30)
    assert got.near > 0 and got.far == pytest.approx(got.near + 20.0)
    # the moved eye sees what the view sees: the same pixels, every splat in front of it
    cloud = random_cloud(80, sh_degree=0, seed=3, spread=0.5)
    points = cloud.positions.astype(np.float64)
    np.testing.assert_allclose(got.project(points)[0], clip_to_pixels(view, projection, points, 30, 30), atol=1e-9)
    assert (got.project(points)[1] > got.near).all()


def test_scaled_camera_keeps_the_view():
    cam = Camera(80, 60, 70.0, 72.0, 35.0, 33.0, Camera.look_at((1, 2, -3), (0, 0, 1)).world_to_camera)
    small = scaled(cam, 0.25)
    assert (small.width, small.height) == (20, 15)
    points = np.random.default_rng(1).normal(0, 1, (20, 3))
    np.testing.assert_allclose(small.project(points)[0] * 4, cam.project(points)[0], atol=1e-9)


def plane_and_box():
    """A floor (z = 0, two triangles) and a tilted square in front of it, with flat colours."""
    floor = np.array([[[-3, -3, 0], [3, -3, 0], [3, 3, 0]], [[-3, -3, 0], [3, 3, 0], [-3, 3, 0]]], float)
    square = np.array(
        [
            [[-0.5, -0.5, 0.5], [0.5, -0.5, 0.9], [0.5, 0.5, 0.9]],
            [[-0.5, -0.5, 0.5], [0.5, 0.5, 0.9], [-0.5, 0.5, 0.5]],
        ],
        float,
    )
    return Triangles(np.concatenate([floor, square]), np.array([[0.5, 0.5, 0.5]] * 2 + [[0.9, 0.2, 0.1]] * 2))


def test_mesh_layer_depth_is_the_nearest_surface_at_each_pixel_centre():
    cam = Camera.look_at((2.0, -4.0, 3.0), (0.0, 0.0, 0.3), up=(0, 0, 1), fov_deg=50, width=64, height=48)
    layer = mesh_layer(plane_and_box(), cam)
    rows, cols = np.mgrid[0:48, 0:64]
    rays = np.stack([(cols + 0.5 - cam.cx) / cam.fx, (rows + 0.5 - cam.cy) / cam.fy, np.ones((48, 64))], -1)
    world = rays @ cam.rotation  # direction per unit camera depth
    eye = cam.center
    t_floor = -eye[2] / world[..., 2]  # camera depth where the ray meets z = 0
    hit = np.abs(eye[None, None, :2] + t_floor[..., None] * world[..., :2]).max(-1) < 3
    # the square's plane: z = 0.7 + 0.4 x, |x|, |y| <= 0.5
    t_sq = (0.7 + 0.4 * eye[0] - eye[2]) / (world[..., 2] - 0.4 * world[..., 0])
    at = eye[None, None] + t_sq[..., None] * world
    on_square = (np.abs(at[..., 0]) <= 0.5) & (np.abs(at[..., 1]) <= 0.5) & (t_sq > 0)
    want = np.where(on_square, t_sq, np.where(hit & (t_floor > 0), t_floor, np.inf))
    edge = np.abs(np.abs(at[..., :2]).max(-1) - 0.5) < 0.02  # pixel centres on the square's border
    keep = ~edge
    np.testing.assert_allclose(layer.depth[keep], want[keep], rtol=1e-9)
    assert (layer.alpha == np.isfinite(layer.depth)).all() and on_square.sum() > 30


def test_preview_composites_splats_with_the_mesh_layer_exactly():
    cam = Camera.look_at((2.0, -4.0, 3.0), (0.0, 0.0, 0.3), up=(0, 0, 1), fov_deg=50, width=64, height=48)
    cloud = random_cloud(300, sh_degree=1, seed=5, spread=0.5)
    cloud = cloud.replace(
        positions=cloud.positions + np.float32([0, 0, 0.5]),
        log_scales=np.random.default_rng(6).uniform(-3.5, -2.2, cloud.log_scales.shape).astype(np.float32),
    )
    meshes = plane_and_box()
    got = preview_image(cloud, meshes, cam, background=(0.1, 0.2, 0.3))
    layer = mesh_layer(meshes, cam)
    ref = reference_render(cloud, cam, background=(0.1, 0.2, 0.3), layer=(layer.color, layer.alpha, layer.depth))
    assert np.abs(got.color - ref["color"]).max() <= STEP
    assert ((ref["layer_t"] < 0.9) & (layer.alpha == 1)).sum() > 50  # splats in front of the meshes
    assert (
        np.abs(reference_render(cloud, cam, background=(0.1, 0.2, 0.3))["color"] - ref["color"]).max(-1) > 0.2
    ).sum() > 50


# progressive rendering -------------------------------------------------------------------------


class FakeRenderer:
    """Records (view, scale) of each render; a render takes `seconds` and looks for staleness."""

    def __init__(self, seconds=0.0):
        self.seconds, self.calls, self.lock = seconds, [], threading.Lock()

    def __call__(self, view, scale, check):
        with self.lock:
            self.calls.append((view, scale))
        end = time.monotonic() + self.seconds
        while time.monotonic() < end:
            check()
            time.sleep(0.002)
        check()
        return f"{view}@{scale}"


def wait_for(condition, timeout=5.0):
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError("timed out")
        time.sleep(0.005)


def test_a_still_view_gets_a_coarse_pass_then_the_full_picture():
    fake, ready = FakeRenderer(), threading.Event()
    prog = Progressive(fake, on_ready=ready.set, coarse=0.25, settle=0.05)
    try:
        assert prog.show("A") is None  # nothing yet: asking never waits
        wait_for(lambda: prog.frame is not None and prog.frame.scale == 1.0)
        assert fake.calls == [("A", 0.25), ("A", 1.0)]
        assert prog.show("A").image == "A@1.0" and ready.is_set()
        prog.refresh()  # the scene changed: coarse again, then full
        wait_for(lambda: len(fake.calls) == 4 and prog.frame.scale == 1.0)
        assert fake.calls[2:] == [("A", 0.25), ("A", 1.0)]
    finally:
        prog.stop()


def test_a_moving_view_gets_coarse_passes_only_and_never_waits():
    fake = FakeRenderer(seconds=0.02)
    prog = Progressive(fake, coarse=0.25, settle=0.3)
    try:
        for k in range(12):  # the view changes every 40 ms, faster than it settles
            start = time.monotonic()
            prog.show(f"V{k}")
            assert time.monotonic() - start < 0.01
            time.sleep(0.04)
        assert all(scale == 0.25 for _, scale in fake.calls)
        wait_for(lambda: prog.frame is not None and prog.frame.view == "V11" and prog.frame.scale == 1.0)
    finally:
        prog.stop()


def test_a_full_render_made_stale_by_a_new_view_is_given_up():
    fake = FakeRenderer(seconds=0.3)
    prog = Progressive(fake, coarse=0.25, settle=0.0)
    try:
        prog.show("A")
        wait_for(lambda: ("A", 1.0) in fake.calls)  # the full picture of A has begun
        prog.show("B")
        wait_for(lambda: prog.frame is not None and prog.frame.view == "B" and prog.frame.scale == 1.0)
        assert fake.calls[-2:] == [("B", 0.25), ("B", 1.0)]  # A's full picture never finished
    finally:
        prog.stop()


def test_a_failing_render_keeps_the_error_and_the_thread():
    calls = []

    def broken(view, scale, check):
        calls.append(view)
        if view == "bad":
            raise RuntimeError("no")
        return view

    prog = Progressive(broken, settle=0.0)
    try:
        prog.show("bad")
        wait_for(lambda: prog.error is not None)
        prog.show("good")
        wait_for(lambda: prog.frame is not None and prog.frame.image == "good")
        assert prog.error is None
    finally:
        prog.stop()
