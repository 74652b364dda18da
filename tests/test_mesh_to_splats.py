"""Mesh to splats: sampling statistics, coverage, colours, frames, extras, hard cases, the mesh
rasteriser against brute-force ray casting (and its compiled path against its NumPy one), and the
target-PSNR mode."""

import importlib.util
import math

import numpy as np
import pytest
from helpers import needs_numba

from splatwright.core import jit, mesh_render, scenes, sh
from splatwright.core.camera import Camera
from splatwright.core.mesh import Material, Mesh, Surface, decode_texture
from splatwright.core.mesh_refine import budget_ladder, default_views, summary
from splatwright.core.mesh_render import rasterize, render_mesh
from splatwright.core.mesh_to_splats import SOLID_OPACITY, WALL_SIGMAS, build_splats, mesh_to_splats
from splatwright.core.metrics import psnr
from splatwright.core.render import render

C0 = 0.28209479177387814


def srgb(linear):
    """IEC 61966-2-1 encoding, written out here independently of core.color."""
    c = np.clip(np.asarray(linear, np.float64), 0, 1)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def display_colors(cloud):
    return 0.5 + C0 * cloud.sh[:, 0].astype(np.float64)


def grid_plane(n, jitter=0.0, seed=0, size=1.0):
    """An n x n grid of quads in the z=0 plane, split into triangles, vertices jittered in-plane."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0, size, n + 1)
    x, y = np.meshgrid(xs, xs)
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    inner = (v[:, 0] > 0) & (v[:, 0] < size) & (v[:, 1] > 0) & (v[:, 1] < size)
    v[inner, :2] += rng.uniform(-jitter, jitter, (inner.sum(), 2)) * size / n
    i = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    return v, f


def uv_sphere(segments=16, rings=8):
    """A closed UV sphere (poles and seam share vertices) with per-corner UVs."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    v = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]])
    south = len(v) - 1
    idx = lambda r, s: 1 + r * segments + s % segments
    faces = [[0, idx(0, s + 1), idx(0, s)] for s in range(segments)]
    faces += [[idx(r, s), idx(r, s + 1), idx(r + 1, s + 1)] for r in range(rings - 2) for s in range(segments)]
    faces += [[idx(r, s), idx(r + 1, s + 1), idx(r + 1, s)] for r in range(rings - 2) for s in range(segments)]
    faces += [[south, idx(rings - 2, s), idx(rings - 2, s + 1)] for s in range(segments)]
    f = np.array(faces)
    uv = np.stack([np.arctan2(v[:, 2], v[:, 0]) / (2 * np.pi) % 1.0, 0.5 + 0.5 * v[:, 1]], -1)[f]
    return v.astype(np.float64), f, uv


# sampling ---------------------------------------------------------------------------------------


def test_counts_follow_area_within_one_splat_per_face():
    rng = np.random.default_rng(3)
    f = 400
    base = rng.normal(size=(f, 1, 3)) * 5
    tris = base + rng.normal(size=(f, 3, 3)) * np.exp(rng.uniform(-4, 0, (f, 1, 1)))
    v, faces = tris.reshape(-1, 3), np.arange(3 * f).reshape(f, 3)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    n = 20000
    cloud = mesh_to_splats(v, faces, max_splats=n, calibrate=False)
    counts = np.bincount(cloud.extras["source_triangle"], minlength=f)
    expected = n * area / area.sum()
    assert counts.sum() == n
    assert np.abs(counts - expected).max() < 1.0
    chi2 = ((counts - expected) ** 2 / np.maximum(expected, 1e-9))[expected > 1].sum()
    assert chi2 < 0.1 * (expected > 1).sum()  # far below the ~1 per face of independent sampling


def test_faces_smaller_than_a_splat_are_covered_evenly():
    v, f = grid_plane(100, jitter=0.3)  # 20000 faces, 0.1 splat each
    cloud = mesh_to_splats(v, f, max_splats=2000, calibrate=False)
    cells = np.floor(cloud.positions[:, :2].astype(np.float64) * 10).clip(0, 9).astype(int)
    per_cell = np.bincount(cells[:, 0] * 10 + cells[:, 1], minlength=100)
    # Independent coin flips would give a spread of sqrt(20) ~ 4.5 per cell and chi2/dof ~ 1.
    assert np.abs(per_cell - 20).max() <= 5
    assert ((per_cell - 20) ** 2 / 20).mean() < 0.5


def bisection_reference(gram, n):
    """One face's points for n splats, by plain recursion on lists: its pieces (uv corners) level by
    level, each halving across its longest edge in the face's metric `gram` (2x2), the first halves
    of a level before the second ones; and the pieces' areas."""
    level, points, areas = [(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), n)], [], []
    while level:
        firsts, seconds = [], []
        for corners, held in level:
            if held == 1:
                points.append(corners.mean(axis=0))
                areas.append(0.5 * abs(np.cross(corners[1] - corners[0], corners[2] - corners[0])))
                continue
            edges = [corners[(k + 2) % 3] - corners[(k + 1) % 3] for k in range(3)]
            k = int(np.argmax([e @ gram @ e for e in edges]))
            a, b, c = corners[(k + 1) % 3], corners[(k + 2) % 3], corners[k]
            middle = a + (held // 2) / held * (b - a)
            firsts.append((np.array([a, middle, c]), held // 2))
            seconds.append((np.array([middle, b, c]), held - held // 2))
        level = firsts + seconds
    return np.array(points), np.array(areas)


@pytest.mark.parametrize("compiled", [True, False])
def test_points_are_the_centroids_of_an_equal_area_bisection(compiled, monkeypatch):
    """bisection_samples against a plain recursion, on a jittered grid, a 1000:1 sliver and faces of
    0, 1, 2, 3 and up to 300 points; the compiled path (where numba loads) and NumPy's alike."""
    from splatwright.core import mesh_sampling as m2s

    if not compiled:
        monkeypatch.setattr(m2s, "_bisect_kernel", lambda: None)
    elif m2s._bisect_kernel() is None:
        pytest.skip("numba is not installed, or compiled kernels are turned off")
    v, f = grid_plane(4, jitter=0.3, seed=2)
    v = np.concatenate([v, [[0, 0, 1], [1, 0, 1], [0.5, 0.001, 1]]])
    f = np.concatenate([f, [[len(v) - 3, len(v) - 2, len(v) - 1]]])
    surface = Surface(v, f)
    counts = np.random.default_rng(5).integers(0, 300, len(f))
    counts[:4] = 0, 1, 2, 3
    counts[-1] = 250
    tri, bary = m2s.bisection_samples(surface, counts)
    np.testing.assert_array_equal(tri, np.repeat(np.arange(len(f)), counts))
    for face in np.flatnonzero(counts):
        e1, e2 = surface.edge1[face], surface.edge2[face]
        gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        points, areas = bisection_reference(gram, counts[face])
        np.testing.assert_allclose(bary[tri == face][:, 1:], points, rtol=0, atol=1e-12)
        np.testing.assert_allclose(areas, 0.5 / counts[face], rtol=1e-9)


@pytest.mark.skipif(
    importlib.util.find_spec("numba") is None or not jit.enabled(),
    reason="numba is not installed, or compiled kernels are turned off",
)
def test_compiled_bisection_is_numpys_bit_for_bit(monkeypatch):
    """Many runs' worth of points in one face, slivers and single points: the compiled twin gives
    NumPy's points in NumPy's order to the bit."""
    from splatwright.core import mesh_sampling as m2s

    v, f = grid_plane(30, jitter=0.45, seed=4)
    surface = Surface(tilted(v, seed=1), f)
    counts = np.random.default_rng(6).integers(0, 40, len(f))
    counts[7] = 3 * m2s.BISECT_CHUNK + 17
    compiled = m2s.bisection_samples(surface, counts)
    monkeypatch.setattr(m2s, "_bisect_kernel", lambda: None)
    for got, want in zip(compiled, m2s.bisection_samples(surface, counts)):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("jitter, aspect, least", [(0.3, 1, 0.99), (0.0, 8, 0.94)])
def test_plane_renders_closed_inside(jitter, aspect, least, mode):
    v, f = grid_plane(12, jitter=jitter)
    v[:, 1] /= aspect  # aspect > 1: sliver triangles
    cloud = mesh_to_splats(v, f, max_splats=6000 // aspect, calibrate=False, render_mode=mode)
    if mode == "antialiased":  # splats about a pixel across keep ~half their opacity there: ~1% less cover
        least -= 0.01
    # An orthographic view from above filling its height with the plane.
    cam = Camera.look_at_ortho(
        (0.5, 0.5 / aspect, 2.0), (0.5, 0.5 / aspect, 0.0), ortho_scale=1.0 / aspect, width=96, height=96
    )
    alpha = render(cloud, cam).alpha
    margin = int(np.ceil(3 * cloud.scales[:, 0].max() * cam.fx)) + 1
    inside = alpha[margin:-margin, margin:-margin]
    assert inside.size > 2000
    assert inside.mean() > 0.99 and inside.min() > least


def test_frames_are_flat_discs_along_the_face_normal():
    v, f, _ = uv_sphere(24, 12)  # closed, creases of 15 degrees: no outline edges
    cloud = mesh_to_splats(v, f, max_splats=3000, calibrate=False, thickness=0.01)
    tri = cloud.extras["source_triangle"]
    normal = np.cross(v[f[tri, 1]] - v[f[tri, 0]], v[f[tri, 2]] - v[f[tri, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    vals, vecs = np.linalg.eigh(cloud.covariances())
    assert np.abs(np.einsum("ij,ij->i", vecs[:, :, 0], normal)).min() > 1 - 1e-6
    np.testing.assert_allclose(np.sqrt(vals[:, 1]), np.sqrt(vals[:, 2]), rtol=1e-5)
    np.testing.assert_allclose(np.sqrt(vals[:, 0] / vals[:, 2]), 0.01, rtol=1e-4)
    assert cloud.sh_degree == 0
    np.testing.assert_allclose(cloud.opacities, SOLID_OPACITY, rtol=1e-6)  # a closed solid


def test_splats_are_opaque_where_nothing_behind_covers_for_them():
    """Solid parts get SOLID_OPACITY; an open sheet, a wall hiding another colour (the cup's orange
    outside over its blue inside) and the faces along it (the rim) OPAQUE; the same cup in one
    colour is solid throughout (made for classic rendering, opaque); an opacity asked for is given
    everywhere."""
    from splatwright.core.mesh_to_splats import OPAQUE

    def opacity_of(m, **kw):
        return mesh_to_splats(m.vertices, m.faces, **m.appearance(), max_splats=4000, calibrate=False, **kw).opacities

    sheet = mesh_to_splats(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], max_splats=500, calibrate=False
    )
    np.testing.assert_allclose(sheet.opacities, OPAQUE, rtol=1e-6)
    cup = scenes.thin_walled_cup()
    np.testing.assert_allclose(opacity_of(cup), OPAQUE, rtol=1e-6)
    one_colour = Mesh(cup.vertices, cup.faces, None, cup.face_materials, [cup.materials[0]] * 2)
    np.testing.assert_allclose(opacity_of(one_colour), SOLID_OPACITY, rtol=1e-6)
    np.testing.assert_allclose(opacity_of(cup, opacity=0.5), 0.5, rtol=1e-6)
    np.testing.assert_allclose(opacity_of(one_colour, render_mode="classic"), OPAQUE, rtol=1e-6)


def test_wall_contrast_is_the_far_sides_colour_difference():
    """wall_thickness' contrast: on the cup's walls the largest display channel difference of
    orange and blue; none where the far side is past the reach."""
    from splatwright.core.mesh import to_display
    from splatwright.core.mesh_to_splats import wall_thickness

    cup = scenes.thin_walled_cup()
    surface = Surface(cup.vertices, cup.faces, None, cup.face_materials, cup.materials)
    thickness, contrast = wall_thickness(surface, 0.02)
    colours = to_display(np.array([m.base_color for m in cup.materials], np.float64))
    walls = np.isfinite(thickness)
    assert walls.mean() > 0.7
    np.testing.assert_allclose(contrast[walls], np.abs(colours[0] - colours[1]).max(), rtol=1e-6)
    assert (contrast[~walls] == 0).all()


def test_splats_and_walls_are_the_same_on_any_number_of_cores(monkeypatch):
    """Points are dealt out to the cores in the same runs, and wall ties go to the same far side,
    whatever the cores: one conversion gives the same splats on a laptop and on a farm."""
    from splatwright.core import mesh_sampling as m2s
    from splatwright.core import parallel

    cup = scenes.thin_walled_cup()
    surface = Surface(cup.vertices, cup.faces, None, cup.face_materials, cup.materials)
    density = np.full(len(cup.faces), 5 * m2s.BISECT_CHUNK / surface.area.sum())  # several runs
    made = []
    for workers in (1, 2, 3):
        monkeypatch.setattr(parallel, "WORKERS", workers)
        monkeypatch.setattr(m2s, "WORKERS", workers)
        made.append((build_splats(surface, density), m2s.wall_thickness(surface, 0.02)))
    (cloud, walls), others = made[0], made[1:]
    assert len(cloud) > 4 * m2s.BISECT_CHUNK and np.isfinite(walls[0]).mean() > 0.7
    for other, other_walls in others:
        for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(other, name), getattr(cloud, name), err_msg=name)
        np.testing.assert_array_equal(other.extras["source_triangle"], cloud.extras["source_triangle"])
        for got, want in zip(other_walls, walls):
            np.testing.assert_array_equal(got, want)


def test_a_wall_hiding_its_own_colour_gets_a_lower_density_floor():
    """thin_wall_density: splats at most 1/WALL_SIGMAS of the wall where the far side would show
    another colour, 1/SAME_WALL_SIGMAS where it has the face's own."""
    from splatwright.core.mesh_to_splats import SAME_WALL_SIGMAS, thin_wall_density

    cup = scenes.thin_walled_cup()
    coarse = np.full(len(cup.faces), 1e5)  # splats far wider than the 5 mm wall
    floors = {}
    for name, mats in (("two", cup.materials), ("one", [cup.materials[0]] * 2)):
        surface = Surface(cup.vertices, cup.faces, None, cup.face_materials, mats)
        floor, thickness = thin_wall_density(surface, coarse, 0.8)
        walls = np.isfinite(thickness)
        assert walls.mean() > 0.7 and (floor[~walls] == 0).all()
        floors[name] = (floor[walls], thickness[walls])
    for name, sigmas in (("two", WALL_SIGMAS), ("one", SAME_WALL_SIGMAS)):
        floor, thickness = floors[name]
        np.testing.assert_allclose(floor, (sigmas * 0.8 / thickness) ** 2, rtol=1e-9)
    np.testing.assert_allclose(floors["two"][0] / floors["one"][0], (WALL_SIGMAS / SAME_WALL_SIGMAS) ** 2)


def test_discs_do_not_reach_past_outline_edges():
    rng = np.random.default_rng(5)
    tris = rng.normal(size=(40, 1, 3)) * 4 + rng.normal(size=(40, 3, 3))  # a soup: every edge is a boundary
    v, f = tris.reshape(-1, 3), np.arange(120).reshape(40, 3)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    cloud = mesh_to_splats(v, f, max_splats=4000, calibrate=False)
    sigma = 0.8 / np.sqrt(4000 / area.sum())
    tri = cloud.extras["source_triangle"]
    corners = tris[tri]
    p = cloud.positions.astype(np.float64)
    cov = cloud.covariances()
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    vals, vecs = np.linalg.eigh(cov)
    assert np.abs(np.einsum("ij,ij->i", vecs[:, :, 0], normal)).min() > 1 - 1e-6
    np.testing.assert_allclose(np.sqrt(vals[:, 0]), 0.01 * sigma, rtol=1e-4)
    assert (np.sqrt(vals[:, 2]) <= sigma * (1 + 1e-5)).all()
    for k in range(3):
        a, b = corners[:, (k + 1) % 3], corners[:, (k + 2) % 3]
        edge = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
        across = np.cross(normal, edge)
        distance = np.abs(np.einsum("ij,ij->i", p - a, across))
        spread = np.sqrt(np.einsum("ni,nij,nj->n", across, cov, across))
        assert (spread <= np.maximum(distance / 2, 0.05 * sigma) * (1 + 1e-3) + 1e-9).all()
    narrowed = np.sqrt(vals[:, 1]) < 0.9 * sigma
    assert 0.1 < narrowed.mean() < 0.9  # the splats near the edges, not all of them


def test_extras_reproduce_positions_from_the_triangles():
    v, f = grid_plane(4, jitter=0.3)
    v[:, 2] = np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1])
    v = v * 1e3 + np.array([1e6, -2e5, 3e4])
    cloud = mesh_to_splats(v, f, max_splats=5000, calibrate=False)
    tri, bary = cloud.extras["source_triangle"], cloud.extras["barycentric"].astype(np.float64)
    assert cloud.extras["source_triangle"].dtype == np.int32 and bary.shape == (5000, 3)
    assert (bary >= 0).all()
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=1e-6)
    expected = np.einsum("nk,nkc->nc", bary, v[f[tri]])
    # float32 storage: positions 1e6 from the origin are good to ~0.06 in the last bit.
    np.testing.assert_allclose(cloud.positions, expected, rtol=0, atol=0.2)
    np.testing.assert_array_equal(cloud.extras["normal_offset"], 0.0)


# colours --------------------------------------------------------------------------------------


def affine_texture(size=64):
    """Linear-light texture f(u, v) = a + b u + c v sampled at texel centres (bilinear-exact)."""
    j, i = np.meshgrid(np.arange(size), np.arange(size))
    u, v = (j + 0.5) / size, 1.0 - (i + 0.5) / size
    coeff = np.array([[0.1, 0.6, 0.2], [0.3, -0.2, 0.5], [0.2, 0.1, -0.1]])
    return (coeff[0] + u[..., None] * coeff[1] + v[..., None] * coeff[2]).astype(np.float32), coeff


def test_colours_follow_a_linear_texture_at_the_sampled_barycentrics():
    v, f = grid_plane(3, jitter=0.2)
    uv = 0.1 + 0.8 * v[f][:, :, :2]  # inside [0.1, 0.9]: no wrapping
    tex, coeff = affine_texture()
    cloud = mesh_to_splats(
        v, f, corner_uvs=uv, materials=[Material(texture=tex, texture_srgb=False)], max_splats=2000, calibrate=False
    )
    tri, bary = cloud.extras["source_triangle"], cloud.extras["barycentric"].astype(np.float64)
    at = np.einsum("nk,nkc->nc", bary, uv[tri])
    expected = coeff[0] + at[:, :1] * coeff[1] + at[:, 1:] * coeff[2]
    np.testing.assert_allclose(display_colors(cloud), srgb(expected), atol=2e-5)


def test_textures_of_every_integer_depth_decode_to_the_srgb_curve():
    """8- and 16-bit textures are decoded through a table of every value: each texel must still be
    the IEC 61966-2-1 curve of value / max (float64, written out here), grey and RGBA alike."""
    rng = np.random.default_rng(3)
    curve = lambda c: np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)  # noqa: E731
    for dtype, top in ((np.uint8, 255), (np.uint16, 65535), (np.int32, 2**31 - 1)):
        image = rng.integers(0, top, (13, 7, 4), dtype=np.int64, endpoint=True).astype(dtype)
        for channels, want in ((4, image[:, :, :3]), (1, image[:, :, :1].repeat(3, axis=2))):
            got = decode_texture(image[:, :, :channels])
            assert got.dtype == np.float32 and got.shape == (13, 7, 3) and got.flags.c_contiguous
            np.testing.assert_allclose(got, curve(want / top), rtol=1e-6, atol=1e-9)
            np.testing.assert_allclose(decode_texture(image[:, :, :channels], srgb=False), want / top, rtol=1e-6)


def test_srgb_texture_orientation_and_round_trip():
    # 8 x 8 blocks of 8 texels, each block its own 8-bit colour; row 0 of the image is v = 1.
    rng = np.random.default_rng(2)
    blocks = rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)
    tex = blocks.repeat(8, 0).repeat(8, 1)
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = v[f][:, :, :2]
    cloud = mesh_to_splats(v, f, corner_uvs=uv, materials=[Material(texture=tex)], max_splats=4000, calibrate=False)
    tri, bary = cloud.extras["source_triangle"], cloud.extras["barycentric"].astype(np.float64)
    at = np.einsum("nk,nkc->nc", bary, uv[tri])
    col, row = at[:, 0] * 64, (1 - at[:, 1]) * 64
    away = (np.abs(col / 8 - np.round(col / 8)) > 1.2 / 8) & (np.abs(row / 8 - np.round(row / 8)) > 1.2 / 8)
    assert away.sum() > 500
    want = blocks[(row[away] // 8).astype(int), (col[away] // 8).astype(int)] / 255.0
    np.testing.assert_allclose(display_colors(cloud)[away], want, atol=2e-5)


def test_corner_and_vertex_colours_and_base_colours():
    v, f = grid_plane(2)
    rng = np.random.default_rng(4)
    corner = rng.uniform(0, 1, (len(f), 3, 3))
    base = (0.21404114, 1.0, 0.5)  # linear 0.21404114 is sRGB 0.5
    cloud = mesh_to_splats(
        v, f, corner_colors=corner, materials=[Material(base_color=base)], max_splats=1000, calibrate=False
    )
    tri, bary = cloud.extras["source_triangle"], cloud.extras["barycentric"].astype(np.float64)
    expected = np.einsum("nk,nkc->nc", bary, corner[tri]) * np.array(base)
    np.testing.assert_allclose(display_colors(cloud), srgb(expected), atol=2e-5)
    vertex = rng.uniform(0, 1, (len(v), 3))
    cloud = mesh_to_splats(
        v, f, corner_colors=vertex, max_splats=1000, calibrate=False, materials=[Material(base_color=(1, 1, 1))]
    )
    tri, bary = cloud.extras["source_triangle"], cloud.extras["barycentric"].astype(np.float64)
    np.testing.assert_allclose(display_colors(cloud), srgb(np.einsum("nk,nkc->nc", bary, vertex[f[tri]])), atol=2e-5)
    plain = mesh_to_splats(v, f, materials=[Material(base_color=base)], max_splats=10, calibrate=False)
    np.testing.assert_allclose(display_colors(plain), np.tile([0.5, 1.0, 0.735356983], (10, 1)), atol=2e-5)


def test_face_materials_pick_the_material_and_unknown_ones_fall_back():
    v, f = grid_plane(2)
    mats = [Material(base_color=(1, 0, 0)), Material(base_color=(0, 0, 1))]
    fm = np.array([0, 1, 7, 1, 0, -1, 1, 0])
    info = {}
    cloud = mesh_to_splats(v, f, face_materials=fm, materials=mats, max_splats=800, calibrate=False, info=info)
    rgb = display_colors(cloud)
    want = np.where((fm[cloud.extras["source_triangle"]] == 1)[:, None], [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(rgb, want, atol=2e-5)
    assert info["repaired"] == {"faces with an unknown material (default used)": 2}


def test_view_dependent_material_projects_the_facing_blend_onto_sh():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2]])
    base, rim = np.array([0.05, 0.4, 0.8]), np.array([1.0, 0.6, 0.1])
    cloud = mesh_to_splats(v, f, materials=[Material(base_color=base, rim_color=rim)], max_splats=5, calibrate=False)
    assert cloud.sh_degree == 2
    # Independent least-squares fit of the target colour over many directions, same SH basis.
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    facing = (1 - np.abs(d[:, 2]))[:, None]
    target = srgb(base * (1 - facing) + rim * facing)
    y = sh.basis(d, 2)
    fit = np.linalg.lstsq(y, target - 0.5, rcond=None)[0]
    np.testing.assert_allclose(cloud.sh[0].astype(np.float64), fit, atol=5e-3)
    # Face on and edge on the colours come close to the blend's ends.
    face_on = cloud.colors(directions=np.array([[0, 0, 1.0]]))[0]
    edge_on = cloud.colors(directions=np.array([[1.0, 0, 0]]))[0]
    assert np.abs(face_on - srgb(base)).max() < 0.12 and np.abs(edge_on - srgb(rim)).max() < 0.2
    assert np.abs(face_on - srgb(base)).max() < np.abs(edge_on - srgb(base)).max()


# hard cases ----------------------------------------------------------------------------------


def test_degenerate_faces_are_skipped_and_reported_never_nan():
    v = np.array(
        [
            [0, 0, 0],
            [1, 0, 0],
            [0, 1, 0],
            [2, 0, 0],
            [np.nan, 0, 0],
            [0, 0, 1],
            [1e4, 1e4, 0],
            [1e4 + 1e-6, 1e4, 0],
            [1e4, 1e4 + 1e-6, 0],
        ],
        float,
    )
    f = np.array(
        [
            [0, 1, 2],  # fine
            [0, 1, 3],  # collinear: zero area
            [1, 1, 2],  # repeated vertex
            [4, 1, 2],  # NaN vertex
            [0, 1, 5],  # shares edge 0-1 with two other faces: non-manifold
            [0, 1, 5],  # duplicate face
            [6, 7, 8],
        ]
    )  # tiny, far from the origin
    info = {}
    cloud = mesh_to_splats(v, f, max_splats=3000, calibrate=False, info=info)
    assert len(cloud) == 3000 and not cloud.problems()
    for name in ("positions", "rotations", "log_scales", "opacity_logits", "sh"):
        assert np.isfinite(getattr(cloud, name)).all()
    used = set(np.unique(cloud.extras["source_triangle"]))
    assert used.isdisjoint({1, 2, 3}) and {0, 4, 5} <= used
    assert info["repaired"] == {"non-finite vertices": 1, "zero-area faces": 2}


@pytest.mark.parametrize("scale", [1e-6, 1e4])
def test_tiny_and_huge_meshes(scale):
    v, f = grid_plane(3, jitter=0.2)
    cloud = mesh_to_splats(v * scale, f, max_splats=2000, calibrate=False)
    assert not cloud.problems()
    spacing = scale / np.sqrt(2000)
    np.testing.assert_allclose(np.median(cloud.scales[:, 0]), 0.8 * spacing, rtol=0.05)


def test_bad_input_is_rejected_with_the_field_named():
    v, f = grid_plane(1)
    with pytest.raises(ValueError, match="no face with positive area"):
        mesh_to_splats(np.zeros((3, 3)), [[0, 1, 2]], max_splats=10, calibrate=False)
    with pytest.raises(ValueError, match="faces: face 1 refers to vertex 9"):
        mesh_to_splats(v, [[0, 1, 2], [0, 1, 9]], max_splats=10, calibrate=False)
    with pytest.raises(ValueError, match=r"vertices has shape \(4, 2\)"):
        mesh_to_splats(v[:, :2], f, max_splats=10, calibrate=False)
    with pytest.raises(ValueError, match=r"corner_uvs has shape"):
        mesh_to_splats(v, f, corner_uvs=np.zeros((len(f), 2)), max_splats=10, calibrate=False)
    with pytest.raises(ValueError, match="max_splats must be at least 1"):
        mesh_to_splats(v, f, max_splats=0, calibrate=False)


def test_textured_material_without_uvs_warns_and_uses_base_colour():
    v, f = grid_plane(1)
    mat = Material(base_color=(1.0, 0.0, 0.0), texture=np.zeros((4, 4, 3), np.uint8))
    with pytest.warns(UserWarning, match="no UVs"):
        cloud = mesh_to_splats(v, f, materials=[mat], max_splats=10, calibrate=False)
    np.testing.assert_allclose(display_colors(cloud), np.tile([1.0, 0, 0], (10, 1)), atol=2e-5)


def test_solids_know_outside_from_inside():
    v, f, _ = uv_sphere()
    normal_out = np.einsum("ij,ij->i", np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), v[f].mean(1))
    np.testing.assert_array_equal(Surface(v, f).outward_signs(), np.sign(normal_out))
    np.testing.assert_array_equal(Surface(v, f[:, ::-1]).outward_signs(), -np.sign(normal_out))
    # Open but enclosing (a head with eye holes, a bowl): still a solid; a flat sheet is not.
    np.testing.assert_array_equal(Surface(v, f[:-1]).outward_signs(), np.sign(normal_out[:-1]))
    bowl = v[f].mean(axis=1)[:, 1] < 0.1
    np.testing.assert_array_equal(Surface(v, f[bowl]).outward_signs(), np.sign(normal_out[bowl]))
    assert not Surface(*grid_plane(4)).outward_signs().any()


def test_a_ball_resting_on_a_floor_vertex_stays_a_solid():
    # The ball's pole welds to a floor vertex: one vertex shared, no edge. The ball is still a solid
    # and the floor still a sheet (before, the two were one open part and neither was a solid).
    v, f, _ = uv_sphere()
    ball = v[:, [0, 2, 1]] + np.array([2.0, 2.0, 1.0])  # poles on z; the south pole at (2, 2, 0)
    floor_v, floor_f = grid_plane(4, size=4.0)
    assert np.isclose(floor_v, [2.0, 2.0, 0.0]).all(axis=1).any()
    corners = ball[f]
    normal_out = np.einsum("ij,ij->i", np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                           corners.mean(1) - [2.0, 2.0, 1.0])  # fmt: skip
    signs = Surface(np.vstack([ball, floor_v]), np.vstack([f, floor_f + len(ball)])).outward_signs()
    np.testing.assert_array_equal(signs[: len(f)], np.sign(normal_out))
    assert not signs[len(f) :].any()


def test_a_solid_with_a_few_faces_wound_the_wrong_way_or_a_fin_stays_a_solid():
    v, f, _ = uv_sphere()
    centre_out = v[f].mean(axis=1)

    def outward(faces):  # the closed form: the sign turning each face's winding normal outward
        n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
        return np.sign(np.einsum("ij,ij->i", n, centre_out))

    a, b = f[5, 0], f[5, 1]
    shares_edge = [g for g in range(len(f)) if g != 5 and {a, b} <= set(f[g])]
    flipped = f.copy()
    for g in [5, *shares_edge, 40]:  # a patch of two, and one alone
        flipped[g] = flipped[g, ::-1]
    np.testing.assert_array_equal(Surface(v, flipped).outward_signs(), outward(flipped))
    # A fin on one edge (an edge of three faces) is one non-manifold edge among hundreds.
    fin_v = np.vstack([v, v[a] + 0.3 * (v[a] - v[f[5, 2]])])
    fin_f = np.vstack([f, [a, b, len(v)]])
    np.testing.assert_array_equal(Surface(fin_v, fin_f).outward_signs()[:-1], outward(f))
    # Two halves wound against each other: no majority to turn round, so no solid.
    halves = f.copy()
    top = centre_out[:, 1] > 0
    halves[top] = halves[top, ::-1]
    assert not Surface(v, halves).outward_signs().any()


# the mesh rasteriser -------------------------------------------------------------------------------


def ray_cast(camera, triangles, colors_fn):
    """Brute force, one pixel at a time in float64: nearest hit of the pixel-centre ray."""
    h, w = camera.height, camera.width
    color, depth = np.zeros((h, w, 3)), np.zeros((h, w))
    hit = np.zeros((h, w), bool)
    c2w = camera.rotation.T
    for i in range(h):
        for j in range(w):
            x, y = (j + 0.5 - camera.cx) / camera.fx, (i + 0.5 - camera.cy) / camera.fy
            if camera.is_orthographic:
                origin, direction = camera.center + c2w @ [x, y, 0.0], c2w @ [0, 0, 1.0]
            else:
                origin, direction = camera.center, c2w @ [x, y, 1.0]
            best = np.inf
            for k, (a, b, c) in enumerate(triangles):
                m = np.column_stack([b - a, c - a, -direction])
                if abs(np.linalg.det(m)) < 1e-14:
                    continue
                s, t, dist = np.linalg.solve(m, origin - a)
                z = (camera.world_to_camera @ np.append(origin + dist * direction, 1.0))[2]
                if s >= 0 and t >= 0 and s + t <= 1 and camera.near < z < best:
                    best, hit[i, j], depth[i, j] = z, True, z
                    color[i, j] = colors_fn(k, np.array([1 - s - t, s, t]))
    return hit, color, depth


@pytest.mark.parametrize("ortho", [False, True])
def test_rasteriser_matches_ray_casting(ortho):
    tex, coeff = affine_texture()
    v = np.array(
        [
            [-1, -1, 0],
            [1, -1, 0],
            [1, 1, 0],
            [-1, 1, 0],  # textured quad
            [-0.5, -0.3, 0.4],
            [0.9, 0.1, -0.3],
            [0.0, 0.8, 0.5],  # a triangle through it
            [-3, 0.5, 1.0],
            [3, 0.6, 1.0],
            [0.0, 0.7, 9.0],
        ],
        float,
    )  # crosses the near plane
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]])
    uv = 0.1 + 0.4 * (v[f][:, :, :2] + 1)
    mats = [Material(texture=tex, texture_srgb=False), Material(base_color=(0.9, 0.2, 0.1))]
    fm = np.array([0, 0, 1, 1])
    if ortho:
        cam = Camera.look_at_ortho((0.3, -0.4, 3.0), (0, 0, 0), ortho_scale=2.6, width=40, height=32)
    else:
        cam = Camera.look_at((0.3, -0.4, 3.0), (0, 0, 0), fov_deg=50, width=40, height=32, near=0.5)
    surface = Surface(v, f, uv, fm, mats)

    def colour(k, b):
        if fm[k] == 1:
            return srgb(np.array([0.9, 0.2, 0.1]))
        at = b @ uv[k]
        return srgb(coeff[0] + at[0] * coeff[1] + at[1] * coeff[2])

    hit, color, depth = ray_cast(cam, v[f], colour)
    got = render_mesh(surface, cam, supersample=1, pixel_filter="box", background=(0.0, 0.0, 0.0))
    assert 200 < hit.sum() < hit.size
    np.testing.assert_array_equal(got.face >= 0, hit)
    np.testing.assert_allclose(got.color[hit], color[hit], atol=1e-5)
    np.testing.assert_allclose(got.depth[hit], depth[hit], rtol=1e-6)  # stored as float32
    np.testing.assert_array_equal(got.color[~hit], 0.0)


def test_rasteriser_supersampling_averages_linear_light():
    v = np.array([[0, -5, 0], [5, -5, 0], [5, 5, 0], [0, 5, 0]], float)  # right half of the view
    f = np.array([[0, 1, 2], [0, 2, 3]])
    cam = Camera.look_at_ortho((0.1, 0, 3), (0.1, 0, 0), ortho_scale=2.0, width=10, height=4)
    got = render_mesh(
        v,
        cam,
        faces=f,
        materials=[Material(base_color=(1, 1, 1))],
        supersample=4,
        pixel_filter="box",
        background=(0, 0, 0),
    )
    # The edge x = 0 falls at pixel 4.5: that column is half covered, averaged in linear light.
    np.testing.assert_allclose(got.alpha[:, 4], 0.5)
    np.testing.assert_allclose(got.color[:, 4], srgb(0.5), atol=1e-6)
    np.testing.assert_allclose(got.alpha[:, 5:], 1.0)
    np.testing.assert_allclose(got.alpha[:, :4], 0.0)
    # Mixed as a splat renderer blends, the same samples average their display colours; the white
    # side is display 1, so the half-covered column is 0.5 there, where linear light gave 0.735.
    shown = render_mesh(
        v,
        cam,
        faces=f,
        materials=[Material(base_color=(0.2, 0.5, 1))],
        supersample=4,
        pixel_filter="box",
        background=(0, 0, 0),
        mix="display",
    )
    blue = np.broadcast_to(srgb(np.array([0.2, 0.5, 1.0])), (4, 3))
    np.testing.assert_allclose(shown.color[:, 4], 0.5 * blue, atol=1e-6)
    np.testing.assert_allclose(shown.color[:, 6], blue, atol=1e-6)
    with pytest.raises(ValueError, match="mix"):
        render_mesh(v, cam, faces=f, mix="sRGB")


def blackman_harris_cdf(t, width=1.5):
    """The share of Cycles' Blackman-Harris pixel filter (its window 2 x width pixels wide) left of
    t pixels from the pixel centre: the window's integral in closed form."""
    span = 2 * width
    u = np.clip(np.asarray(t, np.float64) / span + 0.5, 0.0, 1.0)
    a = (0.35875, 0.48829, 0.14128, 0.01168)
    integral = (
        a[0] * u
        - a[1] * np.sin(2 * np.pi * u) / (2 * np.pi)
        + a[2] * np.sin(4 * np.pi * u) / (4 * np.pi)
        - a[3] * np.sin(6 * np.pi * u) / (6 * np.pi)
    )
    return integral / a[0]


@pytest.mark.parametrize("edge", [0.0, 0.3, -0.45])
def test_rasteriser_pixel_filters_are_cycles_own(edge):
    """A half-plane x > edge seen straight on, one unit per pixel: each pixel's coverage is its
    filter's share right of the edge. Blackman-Harris (Cycles' default, reaching 1.5 px into the
    neighbours) against the closed form of its integral, Cycles' Gaussian (sigma = width / 4)
    against the normal distribution, and a box of one pixel whatever its width, as Cycles draws it."""
    ndtr = np.vectorize(lambda x: 0.5 * (1 + math.erf(x / math.sqrt(2))))  # the normal distribution
    v = np.array([[edge, -50, 0], [50, -50, 0], [50, 50, 0], [edge, 50, 0]], float)
    cam = Camera.look_at_ortho((0, 0, 3), (0, 0, 0), ortho_scale=12.0, width=12, height=4)
    s = 20
    # Samples 1/s apart place the edge to half a sample: at most half a sample's weight, the
    # window's peak over s, off the integral.
    bh_peak = lambda width: 1 / (0.35875 * 2 * width)  # noqa: E731
    gauss_peak = lambda width: 1 / (np.sqrt(2 * np.pi) * width / 4)  # noqa: E731
    centres = np.arange(12) + 0.5 - 6
    cases = [
        ("blackman-harris", 1.5, 1 - blackman_harris_cdf(edge - centres, 1.5), bh_peak(1.5)),
        ("blackman-harris", 3.0, 1 - blackman_harris_cdf(edge - centres, 3.0), bh_peak(3.0)),
        ("gaussian", 1.5, ndtr((centres - edge) / (1.5 / 4)), gauss_peak(1.5)),
        ("gaussian", 2.5, ndtr((centres - edge) / (2.5 / 4)), gauss_peak(2.5)),
        ("box", 1.5, np.clip(centres + 0.5 - edge, 0, 1), 1.0),
    ]
    for kind, width, want, peak in cases:
        got = render_mesh(
            v,
            cam,
            faces=[[0, 1, 2], [0, 2, 3]],
            materials=[Material(base_color=(1, 1, 1))],
            supersample=s,
            pixel_filter=kind,
            filter_width=width,
            background=(0, 0, 0),
        )
        np.testing.assert_allclose(
            got.alpha, np.broadcast_to(want, (4, 12)), atol=0.5 * peak / s + 1e-9, err_msg=f"{kind} {width}"
        )
        np.testing.assert_allclose(got.color[..., 0], srgb(got.alpha), atol=1e-6)  # linear light, filtered
    with pytest.raises(ValueError, match="pixel_filter"):
        render_mesh(v, cam, faces=[[0, 1, 2], [0, 2, 3]], pixel_filter="mitchell")
    with pytest.raises(ValueError, match="pixel_filter"):
        mesh_to_splats(v, np.array([[0, 1, 2], [0, 2, 3]]), max_splats=10, calibrate=False, pixel_filter="lanczos")
    with pytest.raises(ValueError, match="filter_width"):
        mesh_to_splats(v, np.array([[0, 1, 2], [0, 2, 3]]), max_splats=10, filter_width=0.0)


def assert_backends_agree(surface, cam):
    """The compiled rasteriser (which must load: backend="compiled" raises otherwise) gives the
    NumPy path's buffers bit for bit; returns them."""
    want = rasterize(surface, cam, backend="numpy")
    got = rasterize(surface, cam, backend="compiled")
    for name, g, w in zip(("face", "bary", "depth"), got, want):
        assert g.dtype == w.dtype and g.shape == w.shape, name
        np.testing.assert_array_equal(g, w, err_msg=name)
    return want


def tilted(v, seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return v @ q.T


@needs_numba
def test_compiled_rasteriser_loads_and_is_the_default():
    assert mesh_render.backend_status() == "compiled"
    v, f, uv = uv_sphere(24, 12)
    surface = Surface(v, f, uv)
    cam = Camera.look_at((0.5, 0.8, 3.0), (0, 0, 0), fov_deg=50, width=48, height=40)
    for default in (rasterize(surface, cam), rasterize(surface, cam, backend=None)):
        for g, w in zip(default, rasterize(surface, cam, backend="compiled")):
            np.testing.assert_array_equal(g, w)
    with pytest.raises(ValueError, match="backend"):
        rasterize(surface, cam, backend="gpu")


@needs_numba
@pytest.mark.parametrize("workers", [1, 2, 3])
@pytest.mark.parametrize("ortho", [False, True])
def test_compiled_rasteriser_matches_numpy_on_unstructured_meshes(ortho, workers, monkeypatch):
    """A sphere and a jittered, tilted grid through it, large enough to be split over threads
    (row y drawn by call y % workers)."""
    monkeypatch.setattr(mesh_render, "WORKERS", workers)
    sv, sf, _ = uv_sphere(48, 24)
    gv, gf = grid_plane(20, jitter=0.35, seed=3, size=2.4)
    v = np.concatenate([sv * [1.0, 0.8, 1.1], tilted(gv - [1.2, 1.2, 0.0], seed=4)])
    surface = Surface(v, np.concatenate([sf, gf + len(sv)]))
    if ortho:
        cam = Camera.look_at_ortho((0.7, 1.1, 3.0), (0, 0, 0), ortho_scale=2.6, width=320, height=256)
    else:
        cam = Camera.look_at((0.7, 1.1, 3.0), (0, 0, 0), fov_deg=45, width=320, height=256)
    assert cam.width * cam.height >= mesh_render.THREADED_PIXELS
    face, _, _ = assert_backends_agree(surface, cam)
    assert (face >= len(sf)).any() and (face >= 0).mean() > 0.3


@needs_numba
def test_compiled_rasteriser_matches_numpy_where_the_near_plane_cuts_faces():
    v, f, _ = uv_sphere(32, 16)
    surface = Surface(v, f)
    for near in (0.3, 0.6, 0.95):  # from just in front of the sphere to deep into it
        cam = Camera.look_at((0.2, 0.3, 1.4), (0, 0, 0), fov_deg=70, width=96, height=80, near=near)
        face, _, depth = assert_backends_agree(surface, cam)
        hit = face >= 0
        assert hit.any() and (depth[hit] > near).all()
    # Far plane through the sphere too.
    cam = Camera.look_at((0.2, 0.3, 2.5), (0, 0, 0), fov_deg=50, width=96, height=80, far=2.4)
    assert_backends_agree(surface, cam)


@needs_numba
@pytest.mark.parametrize("ortho", [False, True])
def test_compiled_rasteriser_matches_numpy_on_edge_on_faces_and_pixel_centre_edges(ortho):
    """A grid seen exactly edge-on (its plane holds the eye, or the view direction), and a quad
    whose diagonal and sides run through pixel centres."""
    gv, gf = grid_plane(6, jitter=0.2, seed=1)
    quad = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    v = np.concatenate([gv - [0.5, 0.5, 0.0], quad * [1, 1, 0] + [0, 0, 0.3]])
    v[: len(gv)] = v[: len(gv)][:, [0, 2, 1]]  # the grid in the plane y = 0
    f = np.concatenate([gf, [[0, 1, 2], [0, 2, 3]] + np.array(len(gv))])
    surface = Surface(v, f)
    if ortho:  # 16 px over 2 units, offset half a pixel: pixel centres at x, y = i / 8 - 0.875
        cam = Camera.look_at_ortho((1 / 16, 1 / 16, 3.0), (1 / 16, 1 / 16, 0.0), ortho_scale=2.0, width=16, height=16)
    else:
        cam = Camera.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov_deg=40, width=17, height=17)
    face, _, _ = assert_backends_agree(surface, cam)
    assert (face >= len(gf)).any()


@needs_numba
def test_compiled_rasteriser_breaks_depth_ties_to_the_lower_face():
    sv, sf, _ = uv_sphere(16, 8)
    gv, gf = grid_plane(4, jitter=0.3, seed=2)
    v = np.concatenate([sv, tilted(gv - 0.5, seed=5)])
    f = np.concatenate([sf, gf + len(sv)])
    twins = np.concatenate([f[::-1], f[::-1]])  # every face twice, the copies later
    surface = Surface(v, twins)
    for cam in (
        Camera.look_at((0.4, 0.9, 3.0), (0, 0, 0), fov_deg=50, width=64, height=48),
        Camera.look_at_ortho((0.4, 0.9, 3.0), (0, 0, 0), ortho_scale=2.5, width=64, height=48),
    ):
        face, _, _ = assert_backends_agree(surface, cam)
        hit = face >= 0
        assert hit.any() and (face[hit] < len(f)).all()


@needs_numba
def test_render_mesh_is_the_same_image_on_both_rasterisers():
    tex, _ = affine_texture()
    v, f, uv = uv_sphere(24, 12)
    surface = Surface(v, f, uv, materials=[Material(texture=tex, texture_srgb=False)])
    cam = Camera.look_at((0.5, 0.8, 3.0), (0, 0, 0), fov_deg=45, width=40, height=32)
    want = render_mesh(surface, cam, supersample=3, backend="numpy")
    got = render_mesh(surface, cam, supersample=3, backend="compiled")
    for name in ("color", "alpha", "depth", "face"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


# target PSNR -----------------------------------------------------------------------------------


def _wavy_texture():
    """A 64x64 sRGB texture of slow colour waves."""
    j, i = np.meshgrid(np.arange(64), np.arange(64))
    tex = np.stack(
        [
            0.5 + 0.4 * np.sin(2 * np.pi * j / 16),
            0.5 + 0.4 * np.cos(2 * np.pi * i / 16),
            0.5 + 0.3 * np.sin(2 * np.pi * (i + j) / 32),
        ],
        -1,
    )
    return (tex * 255).astype(np.uint8)


def test_target_psnr_is_reached_and_splats_go_where_the_detail_is():
    v, f, uv = uv_sphere(24, 12)
    mats = [Material(texture=_wavy_texture()), Material(base_color=(0.2, 0.5, 0.3))]
    north = v[f].mean(axis=1)[:, 1] > 0
    fm = np.where(north, 0, 1)  # textured top, one flat colour below
    info = {}
    target = 28.0
    cloud = mesh_to_splats(
        v,
        f,
        corner_uvs=uv,
        face_materials=fm,
        materials=mats,
        target_psnr=target,
        view_size=96,
        view_distances=(1.0,),
        view_count=8,
        info=info,
    )
    assert info["reached"] and info["psnr"] >= target and info["limit"] is None
    # Re-measure independently of the converter's bookkeeping: every one of the views reaches it.
    surface = Surface(v, f, uv, fm, mats)
    views = default_views(surface, 96, 8, distances=(1.0,))
    assert info["views"] == len(views) == 8
    for cam in views:
        assert psnr(render(cloud, cam).color, render_mesh(surface, cam, supersample=3).color) >= target
    tri = cloud.extras["source_triangle"]
    per_area = lambda sel: np.isin(tri, np.flatnonzero(sel)).sum() / surface.area[sel].sum()
    assert per_area(north) > 2.0 * per_area(~north)
    # The silhouettes were pulled in along the normals, towards the centre of the sphere.
    bary = cloud.extras["barycentric"].astype(np.float64)
    on_surface = np.einsum("nk,nkc->nc", bary, v[f[tri]])
    inward = np.linalg.norm(on_surface, axis=1) - np.linalg.norm(cloud.positions, axis=1)
    assert inward.min() > -1e-6 and inward.max() > 1e-3
    normal = np.cross(v[f[tri, 1]] - v[f[tri, 0]], v[f[tri, 2]] - v[f[tri, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    moved = on_surface + cloud.extras["normal_offset"][:, None].astype(np.float64) * normal
    np.testing.assert_allclose(cloud.positions, moved, atol=1e-6)


def test_the_round_reaching_the_target_is_kept_without_searching_its_shift_again(monkeypatch):
    """Every round whose cloud grew searches its silhouette shift again here (RECALIBRATE_GROWTH 1),
    except the round that reaches the target: rendered once and kept as it is. A search compares
    three shifts on the worst views only, then measures the best on all of them."""
    from splatwright.core import mesh_refine

    monkeypatch.setattr(mesh_refine, "RECALIBRATE_GROWTH", 1.0)
    measures, searched = [], []
    measure, psnr_of = mesh_refine._Views.measure, mesh_refine._Views.psnr_of
    monkeypatch.setattr(
        mesh_refine._Views,
        "measure",
        lambda views, cloud, *kept: measures.append(len(cloud)) or measure(views, cloud, *kept),
    )
    monkeypatch.setattr(
        mesh_refine._Views,
        "psnr_of",
        lambda views, cloud, which, *keep: searched.append(which) or psnr_of(views, cloud, which, *keep),
    )
    steps = []
    v, f, uv = uv_sphere(24, 12)
    info = {}
    mesh_to_splats(
        v,
        f,
        corner_uvs=uv,
        materials=[Material(texture=_wavy_texture())],
        target_psnr=28.0,
        view_size=96,
        view_distances=(1.0,),
        view_count=8,
        info=info,
        progress=lambda done, total, label: steps.append((len(measures), len(searched))),
    )
    per_round = np.diff(steps[1:-1], axis=0)  # (measures, searches) between rounds, from the second
    assert info["reached"] and info["rounds"] >= 3
    assert per_round[-1].tolist() == [1, 0]  # the round that reached the target
    assert (per_round[:-1, 1] == 3).all()  # the others: a search of three shifts,
    assert np.isin(per_round[:-1, 0], [1, 2]).all()  # their render, and the best shift's unless it was theirs
    assert all(len(which) == 4 for which in searched)  # a third of the 8 views, but at least 4


def test_shift_searches_on_the_worst_third_of_the_views_pick_the_shifts_all_views_pick(monkeypatch):
    """Silhouette shifts compared on the worst four of twelve views: the same shifts, the same
    splats and PSNR as searches on all twelve, with fewer views rendered."""
    from splatwright.core import mesh_refine

    v, f, uv = uv_sphere(24, 12)
    renders = mesh_refine._Views._renders

    def convert(share):
        monkeypatch.setattr(mesh_refine, "SEARCH_SHARE", share)
        rendered, info = [0], {}
        monkeypatch.setattr(
            mesh_refine._Views,
            "_renders",
            lambda views, cloud, which: (
                rendered.__setitem__(0, rendered[0] + len(which)) or renders(views, cloud, which)
            ),
        )
        cloud = mesh_to_splats(
            v,
            f,
            corner_uvs=uv,
            materials=[Material(texture=_wavy_texture())],
            target_psnr=30.0,
            view_size=96,
            info=info,
        )
        return cloud, info, rendered[0]

    cloud, info, rendered = convert(mesh_refine.SEARCH_SHARE)
    every_cloud, every_info, every_rendered = convert(1.0)
    assert info["views"] == 12 and info["inset_pixels"] > 0
    assert info["inset_pixels"] == every_info["inset_pixels"] and info["psnr"] == every_info["psnr"]
    np.testing.assert_array_equal(cloud.positions, every_cloud.positions)
    assert rendered < 0.8 * every_rendered


def test_background_samples_take_the_label_of_the_first_labelled_neighbour_step_by_step():
    """_dilate_labels against a loop over every sample, on random label images with holes, thin
    lines and borders, for 0 to 7 steps."""
    from splatwright.core.mesh_refine import _dilate_labels

    def reference(labels, steps):
        out = labels.copy()
        h, w = out.shape
        for _ in range(steps):
            before = out.copy()
            for r in range(h):
                for c in range(w):
                    if before[r, c] >= 0:
                        continue
                    for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):  # above, below, left, right
                        if 0 <= rr < h and 0 <= cc < w and before[rr, cc] >= 0:
                            out[r, c] = before[rr, cc]
                            break
        return out

    rng = np.random.default_rng(8)
    for _ in range(60):
        h, w = rng.integers(1, 24, 2)
        labels = np.where(rng.random((h, w)) < rng.uniform(0, 0.3), rng.integers(0, 6, (h, w)), -1).astype(np.int32)
        steps = int(rng.integers(0, 8))
        np.testing.assert_array_equal(_dilate_labels(labels, steps), reference(labels, steps))


def test_a_measure_takes_the_renders_a_search_kept_and_renders_only_the_others(monkeypatch):
    """The views a shift search rendered are not rendered again when its best is measured on all:
    the same Measured as a measure from scratch."""
    from splatwright.core import mesh_refine

    v, f, uv = uv_sphere(24, 12)
    surface = Surface(v, f, uv, None, [Material(texture=_wavy_texture())])
    views = mesh_refine._Views(surface, default_views(surface, 48), "antialiased", surface.outward_signs() != 0)
    cloud = build_splats(surface, np.full(len(f), 3000 / surface.area.sum()))
    kept, rendered = {}, []
    views.psnr_of(cloud, [1, 5, 6], kept)
    renders = mesh_refine._Views._renders
    monkeypatch.setattr(
        mesh_refine._Views, "_renders", lambda self, cloud, which: rendered.extend(which) or renders(self, cloud, which)
    )
    measured = views.measure(cloud, kept)
    assert rendered == [0, 2, 3, 4, 7, 8, 9, 10, 11]
    fresh = views.measure(cloud)
    assert measured.views == fresh.views and measured.edge_share == fresh.edge_share
    assert measured.dilation == fresh.dilation and 15 < measured.psnr < 40
    np.testing.assert_array_equal(measured.err, fresh.err)


def test_a_view_that_a_shift_search_left_out_joins_once_it_is_the_worst(monkeypatch):
    """Four views start worst and gain from larger shifts, eight lose (a classic cloud's far and
    near outlines): compared on the four alone, the largest shift would win; the others join once
    the best's measure shows them worse, and the search lands where a search on all views does."""
    from types import SimpleNamespace

    from splatwright.core import mesh_refine

    def psnr(view, x):
        return 20.0 + 5.0 * x if view < 4 else 40.0 - 10.0 * x

    class Views:
        cameras = [None] * 12
        search_views = mesh_refine._Views.search_views
        rendered = 0

        def psnr_of(self, x, which, keep):
            self.rendered += len(which)
            keep.update({i: x for i in which})
            return {i: psnr(i, x) for i in which}

        def measure(self, x, rendered=None):
            assert all(shift == x for shift in (rendered or {}).values())  # renders of this shift only
            self.rendered += 12 - len(rendered or {})
            views = [psnr(i, x) for i in range(12)]
            return SimpleNamespace(views=views, psnr=min(views))

    def search(share):
        monkeypatch.setattr(mesh_refine, "SEARCH_SHARE", share)
        views = Views()
        found = mesh_refine._Inset(views, lambda density, x: x).search(None, 0.0, 4.0, views.measure(0.0), 8)
        return found, views.rendered

    (x, _, m), rendered = search(1 / 3)
    (every_x, _, every_m), every_rendered = search(1.0)
    assert x == every_x and m.psnr == every_m.psnr
    assert abs(x - 4 / 3) < 0.1 and m.psnr > 26.0  # the true compromise: 20 + 5x = 40 - 10x
    assert rendered <= 2 * every_rendered  # here all eight joined: at most the search again


def test_splats_made_for_antialiased_rendering_reach_a_target_at_every_distance_classic_ones_cannot():
    v, f, _ = uv_sphere(24, 12)
    materials = [Material(base_color=(0.8, 0.3, 0.1))]
    options = dict(materials=materials, target_psnr=33.0, view_size=96, view_distances=(0.5, 1.0, 3.0), view_count=2)
    classic, antialiased = {}, {}
    assert not mesh_to_splats(v, f, render_mode="classic", info=classic, **options).antialiased
    cloud = mesh_to_splats(v, f, render_mode="antialiased", info=antialiased, **options)
    assert not classic["reached"] and "antialiased mode can" in classic["limit"]
    assert cloud.antialiased and antialiased["reached"]
    surface = Surface(v, f, materials=materials)
    for cam in default_views(surface, 96, 2, distances=(0.5, 1.0, 3.0)):  # rendered in its own mode by default
        assert psnr(render(cloud, cam).color, render_mesh(surface, cam, supersample=3).color) >= 33.0
    assert mesh_to_splats(v, f, max_splats=500, calibrate=False).antialiased  # antialiased by default


def test_budget_with_views_keeps_the_count_and_calibrates_silhouettes():
    v, f, uv = uv_sphere(24, 12)
    surface = Surface(v, f)
    views = default_views(surface, 64)[:3]
    info = {}
    cloud = mesh_to_splats(v, f, max_splats=3000, views=views, info=info)
    plain = mesh_to_splats(v, f, max_splats=3000, calibrate=False)
    assert len(cloud) == 3000 and info["views"] == 3 and "reached" not in info
    assert info["inset_pixels"] > 0 and (cloud.extras["normal_offset"] < 0).all()
    np.testing.assert_array_equal(cloud.extras["barycentric"], plain.extras["barycentric"])
    error = lambda c: np.mean([np.mean((render(c, cam).color - render_mesh(surface, cam).color) ** 2) for cam in views])
    assert error(cloud) < error(plain)


def held_out_views(surface, size, distances=(0.5, 1.0, 3.0), seed=11):
    """One camera per distance from random directions, framed like the converter's own views but
    not among them."""
    v = surface.vertices
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    framing = 1.1 * np.linalg.norm(v - centre, axis=1).max() / np.sin(np.radians(20.0))
    dirs = np.random.default_rng(seed).normal(size=(len(distances), 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return [
        Camera.look_at(centre + framing * d * u, centre, fov_deg=40.0, width=size, height=size, near=0.01 * framing)
        for d, u in zip(distances, dirs)
    ]


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_budget_never_renders_worse_with_more_splats(mode):
    v, f, uv = uv_sphere(24, 12)
    j, i = np.meshgrid(np.arange(64), np.arange(64))
    tex = np.stack(
        [
            0.5 + 0.4 * np.sin(2 * np.pi * j / 16),
            0.5 + 0.4 * np.cos(2 * np.pi * i / 16),
            0.5 + 0.3 * np.sin(2 * np.pi * (i + j) / 32),
        ],
        -1,
    )
    mats = [Material(texture=(tex * 255).astype(np.uint8))]
    surface = Surface(v, f, uv, None, mats)
    cams = held_out_views(surface, 64)
    refs = [render_mesh(surface, cam, supersample=3).color for cam in cams]
    worst, own, counts = [], [], []
    for budget in (2_000, 8_000, 32_000):
        info = {}
        cloud = mesh_to_splats(
            v,
            f,
            corner_uvs=uv,
            materials=mats,
            max_splats=budget,
            view_size=64,
            view_count=2,
            info=info,
            render_mode=mode,
        )
        assert info["budget"] == budget and len(cloud) == info["splats"] <= budget
        worst.append(min(psnr(render(cloud, cam).color, ref) for cam, ref in zip(cams, refs)))
        counts.append(len(cloud))
        own.append(info["psnr"])
    # Without the calibration (no silhouette shift, every splat of the budget), the silhouettes render fat.
    plain = [
        min(
            psnr(
                render(
                    mesh_to_splats(
                        v, f, corner_uvs=uv, materials=mats, max_splats=b, calibrate=False, render_mode=mode
                    ),
                    cam,
                ).color,
                ref,
            )
            for cam, ref in zip(cams, refs)
        )
        for b in (2_000, 32_000)
    ]
    assert all(b >= a - 0.2 for a, b in zip(worst, worst[1:])), worst
    assert worst[-1] > plain[1] + 3
    # Each budget is the best of itself and the ladder's rungs below it on the converter's views: these
    # budgets are rungs themselves, so a larger one tries what a smaller one kept and renders no worse.
    assert own == sorted(own), own
    assert all(n in [b] + budget_ladder(b) for n, b in zip(counts, (2_000, 8_000, 32_000)))
    if mode == "classic":  # edge-on splats fatten classic outlines: the largest budget keeps fewer
        assert counts[-1] < 32_000, counts
        assert f"{counts[-1]} of the 32000 splats budgeted: more rendered worse" in summary(info)
        kept = mesh_to_splats(
            v,
            f,
            corner_uvs=uv,
            materials=mats,
            max_splats=32_000,
            view_size=64,
            view_count=2,
            render_mode=mode,
            try_fewer=False,
            info=info,
        )
        assert len(kept) == 32_000 and info["inset_pixels"] > 0  # the whole budget, still calibrated


def test_a_missed_target_says_what_was_reached_where_and_why():
    v, f, _ = uv_sphere(16, 8)
    info = {}
    cloud = mesh_to_splats(v, f, target_psnr=60, max_splats=400, view_size=48, view_count=1, info=info)
    surface = Surface(v, f)
    views = default_views(surface, 48, 1)
    measured = [psnr(render(cloud, cam).color, render_mesh(surface, cam).color) for cam in views]
    assert not info["reached"] and len(cloud) <= 400
    np.testing.assert_allclose(info["psnr_views"], measured, atol=1e-6)
    assert info["worst_view"] == int(np.argmin(measured)) and info["psnr"] == pytest.approx(min(measured))
    assert info["worst_view_distance"] == (0.5, 1.0, 3.0)[info["worst_view"]]
    assert "max_splats=400" in info["limit"]


def test_refinement_stops_after_rounds_that_render_no_better_and_returns_the_best():
    """More splats fatten the outlines: once PATIENCE rounds in a row render worse than the best
    (each with its shift searched again), refinement stops and the best round's cloud comes back,
    its PSNR what the views measure. (Opaque splats: their outlines fatten the most.)"""
    from splatwright.core.mesh_refine import KNEE_GAIN_DB, MAX_ROUNDS, PATIENCE
    from splatwright.core.mesh_to_splats import OPAQUE

    v, f, _ = uv_sphere(16, 8)
    info, rounds = {}, []

    def progress(done, total, label):
        if 0 < done < total:
            rounds.append((int(label.split()[1]), float(label.split()[3])))

    cloud = mesh_to_splats(
        v, f, target_psnr=60, view_size=48, view_count=1, info=info, progress=progress, opacity=OPAQUE
    )
    best = max(range(len(rounds)), key=lambda k: rounds[k][1])
    assert len(rounds) == info["rounds"] < MAX_ROUNDS
    after = rounds[best + 1 :]
    if "per doubling" in info["limit"]:  # or it stopped at the knee: a round that bought too little
        (n, p), (n_best, p_best) = after[-1], rounds[best]
        assert len(after) == 1 and p - p_best < KNEE_GAIN_DB * math.log2(n / n_best)
    else:
        assert len(after) == PATIENCE and all(p <= rounds[best][1] for _, p in after)
    assert len(cloud) == rounds[best][0] < max(n for n, _ in rounds)
    surface = Surface(v, f)
    measured = min(
        psnr(render(cloud, cam).color, render_mesh(surface, cam).color) for cam in default_views(surface, 48, 1)
    )
    assert info["psnr"] == pytest.approx(measured) and abs(measured - rounds[best][1]) <= 0.05
    assert any(why in info["limit"] for why in ("more splats no longer lowered the error", "per doubling"))


def test_wall_thickness_of_faces_finer_than_its_points():
    """Faces much smaller than the points' spacing share points: every face of a finely cut 5 mm
    cup still gets its wall, not the rim's (40 mm of solid below it, past the reach), and a sphere
    none."""
    from splatwright.core.mesh_to_splats import wall_thickness

    cup = scenes.thin_walled_cup(radius=0.02, height=0.04, wall=0.005, n=512)
    surface = Surface(cup.vertices, cup.faces)
    n = 512
    thickness, _ = wall_thickness(surface, 0.02)
    assert surface.area.max() < (0.02 / 2) ** 2 / 10  # ten faces or more per point
    sides = np.r_[0 : 2 * n, 4 * n : 8 * n]  # outer and inner walls, floor, bottom
    np.testing.assert_allclose(thickness[sides], 0.005, rtol=0.1)
    assert np.isinf(thickness[2 * n : 4 * n]).all()
    v, f, _ = uv_sphere(96, 48)
    assert np.isinf(wall_thickness(Surface(v, f), 0.5)[0]).all()


def test_a_face_is_sized_by_the_finest_view_that_frames_it_seen_or_not():
    """Views from elsewhere at the same distance see the far side as close as these see the near
    side: a face's pixel is depth / focal length in the finest view whose frustum holds it, hidden
    or not, and faces outside every frustum get the coarsest pixel of the framed ones."""
    from splatwright.core.mesh_refine import _Views

    v, f, _ = uv_sphere(24, 12)
    v = np.concatenate([v, v + (40.0, 0, 0)])  # a second sphere, out of every view
    f = np.concatenate([f, f + len(v) // 2])
    surface = Surface(v, f)
    cams = [Camera.look_at((0, 0, z), (0, 0, 0), fov_deg=40, width=32, height=32) for z in (4.0, 8.0)]
    views = _Views(surface, cams, "classic", surface.outward_signs() != 0)
    centre = v[f].mean(axis=1)
    near = (4.0 - centre[:, 2]) / cams[0].fx  # the closer view frames the whole sphere
    first = np.arange(len(f)) < len(f) // 2
    hidden = first & (centre[:, 2] < -0.5)
    assert hidden.sum() > 50
    np.testing.assert_allclose(views.pixel[first], near[first], rtol=1e-12)
    np.testing.assert_allclose(views.pixel[~first], near[first].max(), rtol=1e-12)


def test_antialiased_default_views_size_faces_for_the_nearest_view_from_anywhere():
    """The default views stand for views from every direction at their distances: made for
    antialiased rendering, a face is sized for the nearest such view (closed form for a sphere
    centred on the views' target), seen or framed by these twelve or not."""
    from splatwright.core.mesh_refine import _pixel_all_around, _Views

    v, f, _ = uv_sphere(24, 12)
    surface = Surface(v, f)
    cams = default_views(surface, 64)
    nearest = min(np.linalg.norm(cam.center) for cam in cams)
    face_centre = v[f].mean(axis=1)
    want = (nearest - np.linalg.norm(face_centre, axis=1)) / cams[0].fx
    np.testing.assert_allclose(_pixel_all_around(surface, cams), want, rtol=1e-12)
    # Finer than the twelve views frame most faces.
    assert (want < _Views(surface, cams, "classic", np.zeros(len(f), bool)).pixel).mean() > 0.5


def thin_walled_cup():
    cup = scenes.thin_walled_cup(radius=0.02, height=0.04, wall=0.005, n=32)
    return cup.vertices, cup.faces, cup.face_materials, cup.materials


def test_thin_walls_do_not_show_the_other_side():
    v, f, fm, mats = thin_walled_cup()
    surface = Surface(v, f, None, fm, mats)
    assert (surface.outward_signs() == 1).all()
    # Close-ups of the outside from below and above, where the inside is right behind the wall.
    cams = [
        Camera.look_at((r * np.cos(a), y, r * np.sin(a)), (0, 0.02, 0), fov_deg=40, width=64, height=64, near=0.001)
        for a in (0.3, 2.0, 4.1)
        for r, y in ((0.045, -0.02), (0.05, 0.06))
    ]
    # Box-filtered: the leak is judged pixel by pixel, each pixel by its own samples alone.
    refs = [render_mesh(surface, cam, supersample=3, pixel_filter="box") for cam in cams]
    outer = [(ref.alpha == 1) & (fm[np.maximum(ref.face[1::3, 1::3], 0)] == 0) for ref in refs]
    assert all(o.sum() > 1000 for o in outer)

    def leak(cloud):
        """Fraction of the outside's pixels tinted by the inside's blue, and their PSNR."""
        colors = [render(cloud, cam).color for cam in cams]
        blue = np.concatenate([(c[..., 2] - ref.color[..., 2])[o] for c, ref, o in zip(colors, refs, outer)])
        error = np.concatenate([((c - ref.color) ** 2)[o] for c, ref, o in zip(colors, refs, outer)])
        return (blue > 0.05).mean(), -10 * np.log10(error.mean())

    cloud = mesh_to_splats(
        v, f, face_materials=fm, materials=mats, max_splats=20_000, calibrate=False, render_mode="classic"
    )
    # Splats as wide as 2500 spread evenly would be (sigma 0.35 of the wall): the inside shows.
    even = build_splats(surface, np.full(len(f), 2500 / surface.area.sum()))
    wall_sigma = np.exp(cloud.log_scales[:, :2].astype(np.float64)).max(axis=1)
    assert np.percentile(wall_sigma, 99) <= 0.005 / WALL_SIGMAS * 1.05
    tinted, clean_db = leak(cloud)
    tinted_even, even_db = leak(even)
    assert tinted < 0.005 and tinted_even > 0.02, (tinted, tinted_even)
    assert clean_db > even_db + 6, (clean_db, even_db)
    # Made for antialiased rendering (the default), the discs narrowed along the wall's creases fade
    # at these grazing 64-pixel views, and the inside shows along the bottom edge and the rim: the
    # wall's floor still keeps it to a few percent of the pixels, against 9% spread evenly.
    cloud = mesh_to_splats(v, f, face_materials=fm, materials=mats, max_splats=20_000, calibrate=False)
    tinted, clean_db = leak(cloud)
    tinted_even, even_db = leak(even.replace(antialiased=True))
    assert cloud.antialiased and tinted < 0.03 and tinted_even > 0.08, (tinted, tinted_even)
    assert clean_db > even_db + 6, (clean_db, even_db)


def test_steps_are_the_refinement_rounds_and_stop_when_closed():
    """mesh_to_splats_steps yields after every round (a caller may stop between rounds) and returns
    what mesh_to_splats returns; closed part-way it ends at once."""
    from splatwright.core.mesh_to_splats import mesh_to_splats_steps

    v, f, _ = uv_sphere(24, 12)
    options = dict(
        face_materials=np.zeros(len(f), int),
        materials=[Material(base_color=(0.7, 0.2, 0.1))],
        target_psnr=33.0,
        view_size=64,
    )
    seen = []
    whole = mesh_to_splats(v, f, progress=lambda *step: seen.append(step), **options)
    steps = mesh_to_splats_steps(v, f, **options)
    stepped = []
    while True:
        try:
            stepped.append(next(steps))
        except StopIteration as stop:
            cloud = stop.value
            break
    assert stepped == seen and len(seen) >= 3
    # one step after the silhouette calibration (0), then one per round
    assert [done for done, _, _ in seen[:-1]] == list(range(len(seen) - 1))
    np.testing.assert_array_equal(cloud.positions, whole.positions)
    steps = mesh_to_splats_steps(v, f, **options)
    next(steps)
    steps.close()
    with pytest.raises(StopIteration):
        next(steps)


def test_every_budget_tries_the_rungs_a_smaller_budget_tried():
    assert budget_ladder(100_000) == [64_000, 32_000, 16_000, 8_000, 4_000, 2_000]
    assert budget_ladder(30_000) == [16_000, 8_000, 4_000, 2_000]
    assert budget_ladder(2_400) == [] and budget_ladder(2_500) == [2_000]
    budgets = np.unique(np.geomspace(1_000, 1e6, 200).astype(int))
    for small, large in zip(budgets, budgets[1:]):
        assert set(budget_ladder(small)) <= set(budget_ladder(large))
        assert all(rung <= large / 1.25 for rung in budget_ladder(large))


def test_a_budget_steps_through_the_counts_it_tries():
    """A budget yields after each count it tries (the budget, then the ladder's 4,000 and 2,000),
    its progress never going back, and keeps the one its views rate best."""
    from splatwright.core.mesh_to_splats import mesh_to_splats_steps
    from splatwright.core.steps import drain

    v, f, _ = uv_sphere(24, 12)
    seen = []
    cloud = drain(
        mesh_to_splats_steps(v, f, max_splats=9000, view_size=48, view_count=2), lambda *step: seen.append(step)
    )
    fractions = [done / total for done, total, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    tried = [label for _, _, label in seen[:-1]]
    assert [t.split(": ")[1].split(" splats")[0] for t in tried] == ["9000", "4000", "2000"]
    rated = {int(t.split(": ")[1].split(" splats")[0]): float(t.split(", ")[1].split(" dB")[0]) for t in tried}
    assert len(cloud) in rated and rated[len(cloud)] == max(rated.values())
