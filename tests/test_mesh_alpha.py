"""Alpha-cut materials (core.mesh.Material's alpha_mode) in the reference mesh rasteriser: a quad
with a cut-out pattern over a coloured quad behind it, against a float64 ray cast that walks every
hit along each pixel's ray, and both rasteriser backends against each other; a BLEND quad against
the closed form of its mix with what lies behind; the rasteriser's clip depth."""

import numpy as np
import pytest
from helpers import needs_numba

from splatwright.core import color
from splatwright.core.camera import Camera
from splatwright.core.mesh import Material, Mesh, Surface
from splatwright.core.mesh_render import rasterize, rasterize_layers, render_mesh

FRONT = (0.9, 0.2, 0.1)  # linear: the cut quad's colour where it stays
BEHIND = (0.1, 0.3, 0.8)  # the quad behind


def cut_texture(size=16):
    """RGBA float: FRONT everywhere, alpha 0 in a checkerboard of 4-texel squares and in a disc."""
    i, j = np.mgrid[0:size, 0:size]
    alpha = (((i // 4) + (j // 4)) % 2 == 0).astype(np.float32)
    alpha[(i - 10.5) ** 2 + (j - 5.5) ** 2 < 9] = 0.0
    rgb = np.broadcast_to(np.asarray(FRONT, np.float32), (size, size, 3))
    return np.concatenate([rgb, alpha[..., None]], axis=2), alpha


def scene(front_material):
    """Two unit quads facing +z: the textured one at z = 0 (material 0), the plain one at z = -0.5
    (material 1), wider, and a camera looking at them slightly from the side."""
    quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    v = np.concatenate([np.column_stack([quad, np.zeros(4)]), np.column_stack([1.5 * quad, np.full(4, -0.5)])])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    uv = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]] * 2, float)
    materials = [front_material, Material(base_color=BEHIND)]
    mesh = Mesh(v, f, uv, np.array([0, 0, 1, 1]), materials)
    cam = Camera.look_at((0.6, -0.4, 3.0), (0, 0, -0.2), fov_deg=50, width=48, height=40)
    return mesh, cam


def bilinear(alpha, uv):
    """The alpha texture read bilinearly at texel centres, repeating, in float64 (the test's own)."""
    h, w = alpha.shape
    x, y = uv[0] * w - 0.5, (1 - uv[1]) * h - 0.5
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0
    a = lambda r, c: float(alpha[r % h, c % w])  # noqa: E731
    return (1 - fy) * ((1 - fx) * a(y0, x0) + fx * a(y0, x0 + 1)) + fy * (
        (1 - fx) * a(y0 + 1, x0) + fx * a(y0 + 1, x0 + 1)
    )


def ray_cast_through(cam, mesh, stops):
    """Per pixel centre, float64: every hit along the ray, nearest first, the first one `stops`
    (face, barycentrics) accepts. Returns face (H,W), -1 where none."""
    face = np.full((cam.height, cam.width), -1)
    c2w = cam.rotation.T
    tris = mesh.vertices[mesh.faces].astype(np.float64)
    for i in range(cam.height):
        for j in range(cam.width):
            d = c2w @ [(j + 0.5 - cam.cx) / cam.fx, (i + 0.5 - cam.cy) / cam.fy, 1.0]
            hits = []
            for k, (a, b, c) in enumerate(tris):
                s, t, dist = np.linalg.solve(np.column_stack([b - a, c - a, -d]), cam.center - a)
                if s >= 0 and t >= 0 and s + t <= 1 and dist > 0:
                    hits.append((dist, k, np.array([1 - s - t, s, t])))
            for _, k, bary in sorted(hits, key=lambda h: h[0]):
                if stops(k, bary):
                    face[i, j] = k
                    break
    return face


def test_cut_outs_show_what_lies_behind_as_a_ray_cast_does():
    tex, alpha = cut_texture()
    mesh, cam = scene(Material(texture=tex, texture_srgb=False, alpha_mode="MASK", alpha_cutoff=0.5))

    def stops(k, bary):
        if k >= 2:
            return True
        uv = bary @ mesh.corner_uvs[k]
        return bilinear(alpha, uv) >= 0.5

    want = ray_cast_through(cam, mesh, stops)
    face, _, _ = rasterize(Surface(mesh.vertices, mesh.faces, **mesh.appearance()), cam)
    assert np.isin(want, [0, 1]).sum() > 200
    # The same hit everywhere but where an alpha sits within round-off of the cutoff or a ray
    # grazes the diagonal both quads share (none here: measured 0 pixels of 1920 differ).
    assert (face != want).sum() <= 2
    # and its colour: the cut quad's where it stops the ray, else the quad behind's
    image = render_mesh(mesh, cam, supersample=1, pixel_filter="box").color
    expected = np.where((want < 2)[..., None], FRONT, BEHIND)
    expected = np.where((want < 0)[..., None], 0.0, color.linear_to_srgb(np.asarray(expected)))
    same = face == want
    np.testing.assert_allclose(image[same], expected[same], atol=1e-5)
    # Ignoring alpha, the cut quad hides the one behind wherever it lies in front of it.
    opaque, _ = scene(Material(texture=tex[..., :3], texture_srgb=False))
    face_opaque, _, _ = rasterize(Surface(opaque.vertices, opaque.faces, **opaque.appearance()), cam)
    assert not np.isin(face_opaque[(want >= 0) & (want < 2)], [2, 3]).any()
    assert (np.isin(face_opaque, [0, 1]) & np.isin(want, [2, 3])).sum() > 200


def test_a_blend_quad_mixes_with_what_lies_behind():
    """BLEND: a constant alpha of 0.4 (the base colour's) over the quad behind, in linear light;
    the depth and face buffers are the first surface at least half opaque: the one behind."""
    mesh, cam = scene(Material(base_color=FRONT + (0.4,), alpha_mode="BLEND"))
    result = render_mesh(mesh, cam, supersample=1, pixel_filter="box")
    face, _, depth = rasterize(Surface(mesh.vertices, mesh.faces, **mesh.appearance()), cam)
    layers = rasterize_layers(Surface(mesh.vertices, mesh.faces, **mesh.appearance()), cam)
    over = layers[0][0] >= 0
    over &= np.isin(layers[0][0], [0, 1]) & (layers[1][0] >= 2)
    assert over.sum() > 300
    mixed = color.linear_to_srgb(0.4 * np.asarray(FRONT) + 0.6 * np.asarray(BEHIND))
    np.testing.assert_allclose(result.color[over], np.broadcast_to(mixed, (over.sum(), 3)), atol=1e-5)
    assert np.isin(face[over], [2, 3]).all() and (depth[over] > 2.9).all()
    alone = np.isin(layers[0][0], [0, 1]) & (layers[1][0] < 0)  # nothing behind: the black background
    np.testing.assert_allclose(result.alpha[alone], 0.4, atol=1e-6)


@needs_numba
def test_peeling_gives_the_same_layers_in_both_backends():
    tex, _ = cut_texture(32)
    rng = np.random.default_rng(5)
    n = 12  # twelve cut quads stacked with jitter: rays pass through several before they stop
    quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    v = np.concatenate([np.column_stack([quad + rng.normal(0, 0.1, 2), np.full(4, -0.1 * k)]) for k in range(n)])
    f = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(n)])
    uv = np.tile(np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float), (n, 1, 1))
    uv += rng.uniform(0, 1, (len(f), 1, 2)).round(1)  # each quad cut differently
    surface = Surface(v, f, uv, None, [Material(texture=tex, alpha_mode="MASK")])
    cam = Camera.look_at((0.3, -0.2, 3.0), (0, 0, -0.5), fov_deg=45, width=64, height=48)
    want = rasterize_layers(surface, cam, backend="numpy")
    got = rasterize_layers(surface, cam, backend="compiled")
    assert len(want) == len(got) >= 3
    for g, w in zip(got, want):
        for name, a, b in zip(("face", "bary", "depth", "alpha"), g, w):
            np.testing.assert_array_equal(a, b, err_msg=name)


def test_an_obj_map_d_cuts_the_surface_as_a_mask(tmp_path):
    """MTL map_d: the mask image's grey level (or its alpha) becomes the texture's alpha, MASK."""
    from PIL import Image

    from splatwright.io.mesh import read_mesh

    colour = np.zeros((8, 8, 3), np.uint8)
    colour[..., 1] = 200
    mask = np.zeros((4, 4), np.uint8)
    mask[:, :2] = 255  # the left half stays
    Image.fromarray(colour).save(tmp_path / "leaf.png")
    Image.fromarray(mask).save(tmp_path / "mask.png")
    rgba = np.dstack([colour[:4, :4], 255 - mask])
    Image.fromarray(rgba, "RGBA").save(tmp_path / "cut.png")
    (tmp_path / "m.mtl").write_text(
        "newmtl leaf\nmap_d mask.png\nmap_Kd leaf.png\nnewmtl plain\nKd 0.5 0.25 0.125\nmap_d -imfchan m cut.png\n"
    )
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "usemtl leaf\nf 1/1 2/2 3/3\nusemtl plain\nf 1/1 3/3 4/4\n"
    )
    mesh = read_mesh(tmp_path / "m.obj")
    leaf, plain = sorted(mesh.materials, key=lambda m: m.name)
    assert leaf.alpha_mode == plain.alpha_mode == "MASK"
    assert leaf.texture.shape == (8, 8, 4)  # the mask resampled to the colour texture
    np.testing.assert_array_equal(leaf.texture[..., 3], np.repeat(np.repeat(mask, 2, 0), 2, 1) / 255)
    np.testing.assert_allclose(leaf.linear_texture(), color.srgb_to_linear(colour / 255), atol=1e-6)
    np.testing.assert_array_equal(plain.texture[..., 3], 1 - mask / 255)  # the image's own alpha
    np.testing.assert_allclose(plain.linear_texture()[0, 0], (0.5, 0.25, 0.125), atol=1e-6)  # Kd, linear
    surface = Surface(mesh.vertices, mesh.faces, **mesh.appearance())
    tri = np.array([0, 0, 1, 1])
    bary = np.array([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.8, 0.1, 0.1], [0.1, 0.1, 0.8]])  # u 0.2, 0.9, 0.1, 0.1
    np.testing.assert_array_equal(surface.hit_alpha(tri, bary), [1, 0, 0, 0])


def test_splats_of_a_blend_material_carry_its_alpha_in_their_opacity():
    from splatwright.core.mesh_sampling import OPAQUE, build_splats

    mesh, _ = scene(Material(base_color=FRONT + (0.4,), alpha_mode="BLEND"))
    surface = Surface(mesh.vertices, mesh.faces, **mesh.appearance())
    cloud = build_splats(surface, np.full(4, 400.0))
    front = cloud.extras["source_triangle"] < 2
    assert front.sum() > 1000 and (~front).sum() > 1000  # every splat kept
    np.testing.assert_allclose(cloud.opacities[front], 0.4 * OPAQUE, rtol=1e-5)
    np.testing.assert_allclose(cloud.opacities[~front], OPAQUE, rtol=1e-5)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("compiled", marks=needs_numba)])
def test_a_clip_depth_leaves_out_what_lies_nearer(backend):
    """rasterize(beyond=d), a clip plane across an orthographic view: a quad tilted through depth
    d shows only its far half, and where it is clipped the flat quad behind it shows; every depth
    is the closed form of its plane."""
    tilted = [[-1, -1, 0.5], [1, -1, -0.5], [1, 1, -0.5], [-1, 1, 0.5]]  # z = -x / 2
    flat = [[-2, -2, -1], [2, -2, -1], [2, 2, -1], [-2, 2, -1]]
    surface = Surface(np.array(tilted + flat, float), np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]))
    cam = Camera.look_at_ortho((0, 0, 5), (0, 0, 0), ortho_scale=1.6, width=40, height=40)  # within the tilted quad
    u, v = np.meshgrid(np.arange(40) + 0.5, np.arange(40) + 0.5)
    local = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.zeros_like(u)], axis=-1)
    x = (local @ cam.rotation + cam.center)[..., 0]  # each pixel's world x
    face, _, depth = rasterize(surface, cam, backend=backend, beyond=5.0)
    near = x < 0  # the tilted quad's half nearer the camera than depth 5 (z > 0)
    assert near.sum() > 500 and (~near).sum() > 500
    np.testing.assert_array_equal(face[near] >= 2, True)  # the flat quad behind
    np.testing.assert_allclose(depth[near], 6.0, atol=1e-9)
    np.testing.assert_array_equal(face[~near] < 2, True)
    np.testing.assert_allclose(depth[~near], 5.0 + x[~near] / 2, atol=1e-9)
