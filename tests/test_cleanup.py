"""Clean-up and grading (core.cleanup, core.economy.change_report) against independent references:
crop by ray parity in float64, one splat at a time; grading checked on renders (grade the splats and
render = grade the render, to float32 round-off) and on the SH colour formula."""

import math

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud, cleanup, economy
from splatwright.core.camera import Camera
from splatwright.core.render import render
from splatwright.core.sh import evaluate


def box_mesh(lo, hi):
    """A closed box (12 triangles, outward winding) from corner lo to corner hi."""
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return v, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def torus(r_major=1.0, r_minor=0.35, nu=24, nv=12):
    u, v = np.meshgrid(
        np.linspace(0, 2 * np.pi, nu, endpoint=False), np.linspace(0, 2 * np.pi, nv, endpoint=False), indexing="ij"
    )
    verts = np.stack(
        [(r_major + r_minor * np.cos(v)) * np.cos(u), (r_major + r_minor * np.cos(v)) * np.sin(u), r_minor * np.sin(v)],
        -1,
    ).reshape(-1, 3)
    faces = []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, ((i + 1) % nu) * nv + j
            c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
            faces += [(a, b, c), (a, c, d)]
    return verts, np.array(faces)


def parity_inside(point, verts, faces, direction=(0.5773, 0.5774, 0.5775)):
    """Ray parity for one point, crossing each triangle by Moller-Trumbore, in float64."""
    d = np.array(direction)
    a, b, c = (np.asarray(verts, np.float64)[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    s = point - a
    q = np.cross(s, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.einsum("ij,ij->i", s, p) / det
        v = q @ d / det
        t = np.einsum("ij,ij->i", e2, q) / det
    hits = (np.abs(det) >= 1e-14) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hits.sum() % 2 == 1


# crop -----------------------------------------------------------------------------------------------


def test_inside_mesh_equals_ray_parity_on_a_torus():
    verts, faces = torus()
    points = np.random.default_rng(0).uniform(-1.5, 1.5, (300, 3)) * [1, 1, 0.4]
    expected = np.array([parity_inside(p, verts, faces) for p in points])
    np.testing.assert_array_equal(cleanup.inside_mesh(points, verts, faces), expected)
    assert 30 < expected.sum() < 270
    # the winding number ignores which way the faces turn
    np.testing.assert_array_equal(cleanup.inside_mesh(points, verts, faces[:, ::-1]), expected)


def test_inside_box_equals_the_mesh_of_the_same_box():
    rng = np.random.default_rng(1)
    angle = 0.7
    turn = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    matrix = np.eye(4)
    matrix[:3, :3] = turn @ np.diag([0.5, 1.0, 2.0])
    matrix[:3, 3] = [0.3, -0.2, 0.1]
    points = rng.uniform(-2.5, 2.5, (2000, 3))
    verts, faces = box_mesh(-np.ones(3), np.ones(3))
    world = verts @ matrix[:3, :3].T + matrix[:3, 3]
    np.testing.assert_array_equal(cleanup.inside_box(points, matrix), cleanup.inside_mesh(points, world, faces))
    local = (points - matrix[:3, 3]) @ np.linalg.inv(matrix[:3, :3]).T
    np.testing.assert_array_equal(cleanup.inside_box(points, matrix), (np.abs(local) <= 1).all(axis=1))


def test_bad_crop_volumes_are_refused_by_name():
    with pytest.raises(cleanup.CleanupError, match="no faces"):
        cleanup.inside_mesh(np.zeros((3, 3)), np.zeros((4, 3)), np.zeros((0, 3), int))
    with pytest.raises(cleanup.CleanupError, match="zero size"):
        cleanup.inside_box(np.zeros((3, 3)), np.diag([1.0, 0.0, 1.0, 1.0]))


def test_size_mask_keeps_splats_between_the_sizes():
    cloud = random_cloud(500, seed=3)
    largest = np.exp(cloud.log_scales.astype(np.float64)).max(axis=1)
    keep = cleanup.size_mask(cloud, 0.05, 0.2, scale=2.0)
    np.testing.assert_array_equal(keep, (2 * largest >= 0.05) & (2 * largest <= 0.2))
    assert 0 < keep.sum() < len(cloud)
    with pytest.raises(cleanup.CleanupError):
        cleanup.size_mask(cloud, 0.3, 0.1)


# grading --------------------------------------------------------------------------------------------

GRADES = [
    dict(exposure=0.5),
    dict(saturation=0.3),
    dict(hue=0.8),
    dict(white=(1.0, 0.8, 0.6)),
    dict(exposure=-0.4, saturation=1.4, hue=-0.5, white=(0.9, 1.0, 1.1)),
]


def test_grade_matrix_parts():
    white = np.array([1.0, 0.8, 0.6])
    m = cleanup.grade_matrix(white=white)
    np.testing.assert_allclose(m @ white, np.full(3, cleanup.LUMA @ white))  # white -> its grey
    grey = np.full(3, 0.4)
    np.testing.assert_allclose(cleanup.grade_matrix(saturation=0.2, hue=1.1) @ grey, grey)
    hue = cleanup.grade_matrix(hue=2 * np.pi / 3)
    np.testing.assert_allclose(hue @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)  # a third of a turn: r -> g
    np.testing.assert_allclose(cleanup.grade_matrix(exposure=1.0), 2 * np.eye(3))
    with pytest.raises(cleanup.CleanupError, match="white"):
        cleanup.grade_matrix(white=(1.0, 0.0, 1.0))


@pytest.mark.parametrize("grade", GRADES)
def test_graded_sh_show_graded_colours_from_every_direction(grade):
    cloud = random_cloud(200, sh_degree=3, seed=5)
    m = cleanup.grade_matrix(**grade)
    graded = cleanup.graded(cloud, m)
    d = np.random.default_rng(6).normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    raw = 0.5 + evaluate(cloud.sh.astype(np.float64), d)
    raw_graded = 0.5 + evaluate(graded.sh.astype(np.float64), d)
    np.testing.assert_allclose(raw_graded, raw @ m.T, atol=2e-6)


@pytest.mark.parametrize("grade", GRADES)
def test_grading_then_rendering_equals_grading_the_render(grade):
    """Colours kept away from 0 (the renderer's clamp), a transparent render: blending is linear, so
    the graded splats render to M C (C premultiplied colour), to float32 round-off."""
    rng = np.random.default_rng(7)
    n = 400
    colors = rng.uniform(0.35, 0.65, (n, 3))
    sh = np.zeros((n, 16, 3))
    sh[:, 0] = (colors - 0.5) / 0.28209479177387814
    sh[:, 1:] = rng.normal(0, 0.01, (n, 15, 3))
    cloud = SplatCloud(
        positions=rng.normal(0, 0.5, (n, 3)),
        rotations=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(-3.5, -2.0, (n, 3)),
        opacity_logits=rng.normal(0, 1, n),
        sh=sh,
    )
    camera = Camera.look_at([0, 0, -4], [0, 0, 0], up=[0, -1, 0], fov_deg=40, width=96, height=96)
    m = cleanup.grade_matrix(**grade)
    before = render(cloud, camera, background=None)
    after = render(cleanup.graded(cloud, m), camera, background=None)
    expected = before.color.astype(np.float64) @ m.T
    assert before.alpha.max() > 0.9
    np.testing.assert_allclose(after.color, expected, rtol=0, atol=2e-5)
    np.testing.assert_array_equal(after.alpha, before.alpha)


# what a change costs ---------------------------------------------------------------------------------


def test_change_report_counts_and_measures():
    cloud = random_cloud(300, sh_degree=3, seed=8)
    same = economy.change_report(cloud, cloud)
    assert same["psnr"] == math.inf and same["max_abs"] == 0.0 and same["views"] == 6
    keep = economy.opacity_mask(cloud, 0.5)
    smaller = cloud[keep].with_sh_degree(1)
    r = economy.change_report(cloud, smaller)
    assert (r["splats_before"], r["splats_after"]) == (300, int(keep.sum()))
    assert (r["bytes_before"], r["bytes_after"]) == (300 * 4 * 62, int(keep.sum()) * 4 * 26)
    views = economy.orbit_views(economy.cloud_points(cloud), 6, 96, phase=0.5)
    assert r["psnr"] == pytest.approx(economy.image_error(cloud, smaller, views).psnr)
    assert 5 < r["psnr"] < 60
    assert "splats" in economy.describe_change(r) and "PSNR" in economy.describe_change(r)
