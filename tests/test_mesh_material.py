"""Mesh to splats with `material=True`: albedo against a float64 brute force of the texture
averaged over each splat's footprint (or exactly the base colour), normals against the faces' own,
roughness and metallic from each face's material."""

import numpy as np
import pytest
from helpers import cloud_covariances, linear_to_srgb, srgb_to_linear

from splatwright.core import material as mat
from splatwright.core import mesh_corpus
from splatwright.core.mesh import Material
from splatwright.core.mesh_to_splats import mesh_to_splats

OVERLAP = 0.8


def textured_plane(n=6, size=1.0, texels=64):
    """A square in z = 0 with uv = xy / size + 0.5 and a smooth sRGB 8-bit texture."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(xs, xs)
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    ty, tx = np.mgrid[:texels, :texels] / texels
    tex = np.stack(
        [0.5 + 0.4 * np.sin(2 * np.pi * 3 * tx), 0.5 + 0.4 * np.cos(2 * np.pi * 2 * ty), 0.3 + 0.6 * tx * ty], -1
    )
    return v, f, (v[:, :2] / size + 0.5)[f], np.round(tex * 255).astype(np.uint8)


def bilinear(linear, uv):
    """Float64 bilinear texture lookup, repeat wrapping, texel centres, v up (row 0 at v = 1)."""
    h, w = linear.shape[:2]
    x, y = uv[..., 0] * w - 0.5, (1 - uv[..., 1]) * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    at = lambda yy, xx: linear[yy % h, xx % w]  # noqa: E731
    top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
    bottom = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
    return top * (1 - fy) + bottom * fy


def brute_albedo(linear, uv, cov_uv, order=24):
    """The texture averaged over Gaussians N(uv, cov_uv) by a Gauss-Hermite product rule (order^2
    points per splat), float64."""
    z, wz = np.polynomial.hermite_e.hermegauss(order)
    zx, zy = np.meshgrid(z, z)
    weights = np.outer(wz, wz).ravel() / np.outer(wz, wz).sum()
    chol = np.linalg.cholesky(cov_uv)  # (N,2,2)
    points = uv[:, None, :] + np.einsum("nij,mj->nmi", chol, np.column_stack([zx.ravel(), zy.ravel()]))
    return np.einsum("nmc,m->nc", bilinear(linear, points), weights)


def test_albedo_is_the_texture_averaged_over_each_footprint_in_linear_light():
    v, f, uv, tex = textured_plane()
    cloud = mesh_to_splats(
        v, f, corner_uvs=uv, materials=[Material(texture=tex)], max_splats=600, calibrate=False, material=True
    )
    linear = srgb_to_linear(tex / 255.0)
    # The footprint: the splat's own in-plane Gaussian shrunk by 2 overlap (the colour's), in uv
    # units (uv = xy / size on this plane).
    cov_uv = cloud_covariances(cloud)[:, :2, :2] / (2 * OVERLAP) ** 2
    reference = brute_albedo(linear, cloud.positions[:, :2].astype(np.float64) + 0.5, cov_uv)
    albedo = mat.albedo(cloud)
    error = np.abs(albedo - reference)
    # measured: rms 0.0044, max 0.045 (core.mesh_texture.footprint_average's mip approximation, on
    # splats narrowed below a texel; its own test allows rms 0.035, max 0.15)
    assert np.sqrt(np.mean(error**2)) < 0.008 and error.max() < 0.06
    # The colour (no fit without views) read the same footprint in display sRGB.
    np.testing.assert_allclose(linear_to_srgb(albedo), cloud.colors(), atol=2e-6)
    assert np.abs(albedo - cloud.colors()).mean() > 0.1  # linear light, not display
    np.testing.assert_allclose(mat.normals(cloud), np.tile([0.0, 0.0, 1.0], (len(cloud), 1)), atol=1e-7)


def test_flat_colours_normals_roughness_and_metallic_come_from_the_faces():
    mesh = mesh_corpus.vertex_coloured_sphere(24, 12)
    faces = mesh.faces
    materials = [
        Material(base_color=(0.9, 0.4, 0.1), roughness=0.2),
        Material(base_color=(0.1, 0.2, 0.7), metallic=1.0),
    ]
    face_materials = (np.arange(len(faces)) % 2).astype(np.int64)
    cloud = mesh_to_splats(
        mesh.vertices, faces, face_materials=face_materials, materials=materials, max_splats=3000, material=True
    )
    tri = cloud.extras["source_triangle"].astype(int)
    which = face_materials[tri]
    np.testing.assert_allclose(mat.albedo(cloud), np.array([m.base_color for m in materials])[which], atol=1e-7)
    np.testing.assert_allclose(mat.roughness(cloud), np.array([0.2, 0.5])[which], atol=1e-7)
    np.testing.assert_allclose(mat.metallic(cloud), np.array([0.0, 1.0])[which])
    corners = mesh.vertices[faces[tri]]
    winding = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    np.testing.assert_allclose(mat.normals(cloud), winding / np.linalg.norm(winding, axis=1)[:, None], atol=1e-6)
    assert np.allclose(np.linalg.norm(mat.normals(cloud), axis=1), 1.0, atol=1e-6)


def test_corner_colours_multiply_the_albedo_and_no_material_by_default():
    mesh = mesh_corpus.vertex_coloured_sphere(24, 12)
    plain = mesh_to_splats(mesh.vertices, mesh.faces, **mesh.appearance(), max_splats=2000, calibrate=False)
    assert not mat.has_material(plain)
    lit = mesh_to_splats(
        mesh.vertices, mesh.faces, **mesh.appearance(), max_splats=2000, calibrate=False, material=True
    )
    tri, bary = lit.extras["source_triangle"].astype(int), lit.extras["barycentric"].astype(np.float64)
    upper = mesh.vertices[mesh.faces[tri]].mean(axis=1)[:, 1] > 0.05  # flat-coloured bands: one colour per face
    expected = mesh.corner_colors[tri, 0]
    np.testing.assert_allclose(mat.albedo(lit)[upper], expected[upper], atol=1e-6)
    # The smooth lower half: the corner colours' barycentric blend (uniform within a footprint
    # to first order: a linear function's Gaussian mean is its value at the centre).
    blend = np.einsum("nk,nkc->nc", bary, mesh.corner_colors[tri])
    np.testing.assert_allclose(mat.albedo(lit)[~upper], blend[~upper], atol=1e-6)


def test_the_square_footprint_route_also_reads_linear_light():
    v, f, uv, tex = textured_plane()
    cloud = mesh_to_splats(
        v,
        f,
        corner_uvs=uv,
        materials=[Material(texture=tex)],
        max_splats=600,
        calibrate=False,
        material=True,
        texture_aware=False,
    )
    linear = srgb_to_linear(tex / 255.0)
    sigma = np.exp(cloud.log_scales.astype(np.float64)[:, :2]).max(axis=1) / OVERLAP
    # A box of the splats' spacing has the variance of a Gaussian of sigma spacing / sqrt(12).
    cov_uv = (sigma**2 / 12)[:, None, None] * np.eye(2)
    reference = brute_albedo(linear, cloud.positions[:, :2].astype(np.float64) + 0.5, cov_uv)
    # measured: rms 0.012 (a mip level's blur is a box only roughly)
    assert np.sqrt(np.mean((mat.albedo(cloud) - reference) ** 2)) < 0.02
    # The colour read the same footprint, its display value the albedo's, but at the square's
    # corners, whose splats are narrowed both ways (their spacing is then read as smaller).
    off = np.abs(linear_to_srgb(mat.albedo(cloud)) - cloud.colors()).max(axis=1)
    assert np.mean(off < 2e-6) > 0.97 and off.max() < 0.05


def test_mtl_pr_and_pm_give_roughness_and_metallic(tmp_path):
    from splatwright.io.common import SplatFileError
    from splatwright.io.mesh import read_mtl

    path = tmp_path / "m.mtl"
    path.write_text("newmtl shiny\nKd 0.5 0.5 0.5\nPr 0.125\nPm 1\nnewmtl plain\nKd 1 0 0\nnewmtl odd\nPr 1.5\n")
    materials = read_mtl(path)
    assert (materials["shiny"].roughness, materials["shiny"].metallic) == (0.125, 1.0)
    assert (materials["plain"].roughness, materials["plain"].metallic) == (0.5, 0.0)  # Blender's defaults
    assert materials["odd"].roughness == 1.0
    path.write_text("newmtl bad\nPr nan\n")
    with pytest.raises(SplatFileError, match="line 2"):
        read_mtl(path)


def test_the_command_line_writes_the_material_to_ply(tmp_path):
    from splatwright.cli import main
    from splatwright.io import read_splats

    (tmp_path / "quad.mtl").write_text("newmtl m\nKd 0.2 0.4 0.6\nPr 0.3\nPm 0.75\n")
    (tmp_path / "quad.obj").write_text(
        "mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nusemtl m\nf 1 2 3\nf 1 3 4\n"
    )
    out = tmp_path / "quad.ply"
    args = [str(tmp_path / "quad.obj"), str(out), "--max-splats", "200", "--no-calibrate"]
    assert main(["mesh2splats", *args, "--material"]) == 0
    cloud = read_splats(out)
    np.testing.assert_allclose(mat.albedo(cloud), np.tile([0.2, 0.4, 0.6], (len(cloud), 1)), atol=1e-7)
    np.testing.assert_allclose(mat.normals(cloud), np.tile([0.0, 0.0, 1.0], (len(cloud), 1)), atol=1e-7)
    np.testing.assert_allclose(mat.roughness(cloud), 0.3, atol=1e-7)
    np.testing.assert_allclose(mat.metallic(cloud), 0.75, atol=1e-7)
    assert main(["mesh2splats", *args]) == 0
    assert not mat.has_material(read_splats(out))


def test_corner_normals_are_interpolated_for_smooth_shading():
    mesh = mesh_corpus.vertex_coloured_sphere(24, 12)
    vertex_normals = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)  # a smooth sphere's
    cloud = mesh_to_splats(
        mesh.vertices, mesh.faces, max_splats=2000, calibrate=False, material=True, corner_normals=vertex_normals
    )
    tri, bary = cloud.extras["source_triangle"].astype(int), cloud.extras["barycentric"].astype(np.float64)
    expected = np.einsum("nk,nkc->nc", bary, vertex_normals[mesh.faces[tri]])
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(mat.normals(cloud), expected, atol=1e-6)
    # Closer to the sphere's own normal at the splat than the faces' normals are.
    radial = cloud.positions / np.linalg.norm(cloud.positions, axis=1, keepdims=True)
    faceted = mesh_to_splats(mesh.vertices, mesh.faces, max_splats=2000, calibrate=False, material=True)
    smooth_error = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", mat.normals(cloud), radial), -1, 1)))
    flat_error = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", mat.normals(faceted), radial), -1, 1)))
    assert np.median(smooth_error) < np.median(flat_error) / 3
    with pytest.raises(ValueError, match="corner_normals has shape"):
        mesh_to_splats(mesh.vertices, mesh.faces, max_splats=50, material=True, corner_normals=np.zeros((5, 3)))


def test_normals_point_out_of_solids_whichever_way_they_are_wound():
    """A closed sphere's splat normals point out of it, even with its faces wound inwards; an open
    sheet's follow its winding."""
    mesh = mesh_corpus.vertex_coloured_sphere(24, 12)
    for faces in (mesh.faces, mesh.faces[:, ::-1]):
        cloud = mesh_to_splats(mesh.vertices, faces, max_splats=2000, calibrate=False, material=True)
        radial = cloud.positions / np.linalg.norm(cloud.positions, axis=1, keepdims=True)
        assert (np.einsum("ij,ij->i", mat.normals(cloud), radial) > 0.9).all()
    v, f, _, _ = textured_plane()
    cloud = mesh_to_splats(v, f, max_splats=500, calibrate=False, material=True)
    np.testing.assert_allclose(mat.normals(cloud), np.tile([0.0, 0.0, 1.0], (len(cloud), 1)), atol=1e-6)
