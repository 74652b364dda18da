"""The OBJ/MTL reader against small files written here, and the mesh2splats command."""

import numpy as np
import pytest
from PIL import Image

from splatwright.cli import main
from splatwright.core import mesh_refine
from splatwright.core.mesh_to_splats import mesh_to_splats
from splatwright.io import SplatFileError, read_splats
from splatwright.io.mesh import read_mesh

CUBE_OBJ = """\
# a unit cube: quads, one ngon split off, two materials, negative indices on the last face
mtllib cube.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
vt 0 0
vt 1 0
vt 1 1
vt 0 1
o cube
usemtl painted
f 1/1 4/4 3/3 2/2
f 5/1 6/2 7/3 8/4
f 1/1 2/2 6/3 5/4
usemtl textured
f 2/1 3/2 7/3 6/4
f 3/1 4/2 8/3 7/4
f -8/1 -4/2 -1/3 -5/4
"""

CUBE_MTL = """\
newmtl painted
Ns 250
Kd 0.8 0.1 0.05
Ks 0.5 0.5 0.5
newmtl textured
Kd 0.8 0.8 0.8
map_Kd -o 0.25 0.5 -s 2 2 1 tex file.png
"""


def srgb_decode(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


@pytest.fixture
def cube(tmp_path):
    (tmp_path / "cube.obj").write_text(CUBE_OBJ)
    (tmp_path / "cube.mtl").write_text(CUBE_MTL)
    tex = np.zeros((4, 8, 3), np.uint8)
    tex[:, :, 0] = np.arange(8)[None, :] * 30  # red grows to the right (u)
    tex[:, :, 1] = np.arange(4)[:, None] * 60  # green grows downwards (towards v = 0)
    Image.fromarray(tex).save(tmp_path / "tex file.png")
    return tmp_path / "cube.obj", tex


def test_obj_geometry_uvs_and_materials(cube):
    path, tex = cube
    mesh = read_mesh(path)
    assert mesh.vertices.shape == (8, 3) and mesh.faces.shape == (12, 3)
    # Fan triangulation keeps each polygon's winding: (a, b, c), (a, c, d).
    np.testing.assert_array_equal(mesh.faces[:2], [[0, 3, 2], [0, 2, 1]])
    np.testing.assert_array_equal(mesh.faces[10:], [[0, 4, 7], [0, 7, 3]])  # -8 -4 -1 -5
    np.testing.assert_array_equal(mesh.corner_uvs[1], [[0, 0], [1, 1], [1, 0]])
    np.testing.assert_array_equal(mesh.face_materials, [0] * 6 + [1] * 6)
    painted, textured = mesh.materials
    assert painted.name == "painted" and painted.texture is None
    np.testing.assert_allclose(painted.base_color, (0.8, 0.1, 0.05))
    np.testing.assert_array_equal(textured.texture, tex)
    assert textured.uv_offset == (0.25, 0.5) and textured.uv_scale == (2.0, 2.0)
    assert mesh.corner_colors is None


def test_obj_colours_reach_the_splats(cube):
    path, tex = cube
    mesh = read_mesh(path)
    cloud = mesh_to_splats(mesh.vertices, mesh.faces, **mesh.appearance(), max_splats=3000, calibrate=False)
    tri = cloud.extras["source_triangle"]
    rgb = 0.5 + 0.28209479177387814 * cloud.sh[:, 0].astype(np.float64)
    painted = mesh.face_materials[tri] == 0
    # Kd is scene-linear: the splats show its sRGB encoding.
    from splatwright.core.color import linear_to_srgb

    np.testing.assert_allclose(rgb[painted], np.tile(linear_to_srgb([0.8, 0.1, 0.05]), (painted.sum(), 1)), atol=2e-5)
    # Textured faces: bilinear between texel centres in linear light, repeat wrapping, at
    # uv * 2 + (0.25, 0.5) (the -s and -o options), row 0 of the image at v = 1.
    bary = cloud.extras["barycentric"].astype(np.float64)
    uv = np.einsum("nk,nkc->nc", bary, mesh.corner_uvs[tri])[~painted] * 2 + [0.25, 0.5]
    x, y = uv[:, 0] * 8 - 0.5, (1 - uv[:, 1]) * 4 - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    texel = lambda r, c: srgb_decode(tex[r % 4, c % 8] / 255.0)
    linear = (texel(y0, x0) * (1 - fx) + texel(y0, x0 + 1) * fx) * (1 - fy) + (
        texel(y0 + 1, x0) * (1 - fx) + texel(y0 + 1, x0 + 1) * fx
    ) * fy
    np.testing.assert_allclose(rgb[~painted], linear_to_srgb(linear), atol=2e-5)


def test_vertex_colours_are_srgb_in_the_file(tmp_path):
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0 1 0.5 0\nv 1 0 0 1 0.5 0\nv 0 1 0 1 0.5 0\nf 1 2 3\n")
    mesh = read_mesh(path)
    np.testing.assert_allclose(mesh.corner_colors, np.tile(srgb_decode([1, 0.5, 0]), (3, 1)))
    assert mesh.corner_uvs is None
    cloud = mesh_to_splats(mesh.vertices, mesh.faces, **mesh.appearance(), max_splats=5)
    # Default material (Kd 0.8 grey) times the vertex colour.
    from splatwright.core.color import linear_to_srgb

    np.testing.assert_allclose(
        0.5 + 0.28209479177387814 * cloud.sh[:, 0],
        np.tile(linear_to_srgb(0.8 * srgb_decode([1, 0.5, 0])), (5, 1)),
        atol=2e-5,
    )


@pytest.mark.parametrize(
    "text, problem",
    [
        ("v 0 0 0\nv 1 0 0\nf 1 2 3\n", "line 3: vertex index 3 out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", "line 4: vertex index 0"),
        ("v 0 0 0\nv 1 zero 0\n", "line 2: could not convert"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/2 3/1\n", "line 5: texture coordinate index 2 out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "line 4: a face needs at least 3 corners"),
        ("v 0 0 0\n", "no faces"),
        ("# nothing\n", "no vertices"),
    ],
)
def test_malformed_obj_is_reported_with_file_and_line(tmp_path, text, problem):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(SplatFileError, match=problem) as exc:
        read_mesh(path)
    assert str(path) in str(exc.value)


def test_missing_library_and_texture_fall_back_with_a_warning(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 0.1 0.2 0.3\nmap_Kd nowhere.png\n")
    obj = "mtllib m.mtl\nmtllib gone.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\n"
    (tmp_path / "m.obj").write_text(obj)
    with pytest.warns(UserWarning) as caught:
        mesh = read_mesh(tmp_path / "m.obj")
    messages = " ".join(str(w.message) for w in caught)
    assert "nowhere.png" in messages and "gone.mtl" in messages
    assert mesh.materials[0].texture is None
    np.testing.assert_allclose(mesh.materials[0].base_color, (0.1, 0.2, 0.3))


def test_wrong_extension_and_missing_file(tmp_path):
    with pytest.raises(SplatFileError, match="no such file"):
        read_mesh(tmp_path / "none.obj")
    (tmp_path / "x.stl").write_text("solid")
    with pytest.raises(SplatFileError, match="unknown mesh file extension"):
        read_mesh(tmp_path / "x.stl")


def counted_renders(monkeypatch):
    """The names of the renders (of the mesh, of splats) mesh conversion makes from now on."""
    made = []
    for name in ("render", "render_mesh"):
        original = getattr(mesh_refine, name)
        monkeypatch.setattr(mesh_refine, name, lambda *a, _f=original, _n=name, **k: made.append(_n) or _f(*a, **k))
    return made


def test_cli_mesh2splats_budget(cube, tmp_path, capsys, monkeypatch):
    path, _ = cube
    out = tmp_path / "cube.ply"
    renders = counted_renders(monkeypatch)
    assert main(["mesh2splats", str(path), str(out), "--max-splats", "2000", "--view-size", "32"]) == 0
    cloud = read_splats(out)
    assert len(cloud) == 2000 and not cloud.problems()
    assert "wrote 2000 splats from 12 faces, " in capsys.readouterr().out
    assert {"render", "render_mesh"} <= set(renders)  # silhouettes calibrated by default


@pytest.mark.parametrize(
    "options, expected",
    [([], ("blackman-harris", 1.5)), (["--pixel-filter", "gaussian", "--filter-width", "2.5"], ("gaussian", 2.5))],
)
def test_cli_mesh2splats_measures_against_the_pixel_filter_asked_for(cube, tmp_path, monkeypatch, options, expected):
    """The mesh is rendered with the filter of Cycles' Film settings the command names (its default:
    Cycles' own)."""
    filters = []
    original = mesh_refine.render_mesh
    monkeypatch.setattr(
        mesh_refine,
        "render_mesh",
        lambda *a, **k: filters.append((k["pixel_filter"], k["filter_width"])) or original(*a, **k),
    )
    path, _ = cube
    assert (
        main(
            [
                "mesh2splats",
                str(path),
                str(tmp_path / "cube.ply"),
                "--max-splats",
                "2000",
                "--view-size",
                "16",
                *options,
            ]
        )
        == 0
    )
    assert filters and set(filters) == {expected}


def test_cli_splats_made_for_antialiased_rendering_say_so_and_render_so(cube, tmp_path):
    path, _ = cube
    out = tmp_path / "cube.spz"
    assert (
        main(["mesh2splats", str(path), str(out), "--max-splats", "3000", "--view-size", "32", "--mode", "antialiased"])
        == 0
    )
    assert read_splats(out).antialiased
    images = {}
    for mode in ([], ["--mode", "antialiased"], ["--mode", "classic"]):
        png = tmp_path / f"{len(images)}.png"
        assert main(["render", str(out), "-o", str(png), "--width", "48", "--height", "48", *mode]) == 0
        images[tuple(mode[1:])] = np.asarray(Image.open(png), np.int16)
    assert np.array_equal(images[()], images[("antialiased",)])  # its own mode by default
    assert np.abs(images[()] - images[("classic",)]).max() > 8


def test_cli_mesh2splats_budget_without_calibration_renders_nothing(cube, tmp_path, capsys, monkeypatch):
    """--no-calibrate: no render at all, and every splat on its triangle of the file's mesh."""
    path, _ = cube
    out = tmp_path / "cube.ply"
    renders = counted_renders(monkeypatch)
    assert main(["mesh2splats", str(path), str(out), "--max-splats", "2000", "--no-calibrate"]) == 0
    assert renders == []
    said = capsys.readouterr().out
    assert "wrote 2000 splats from 12 faces to " in said and "dB" not in said
    cloud, mesh = read_splats(out), read_mesh(path)
    corners = mesh.vertices[mesh.faces[cloud.extras["source_triangle"]]]
    bary = np.column_stack([cloud.extras[f"barycentric_{i}"] for i in range(3)]).astype(np.float64)
    np.testing.assert_allclose(cloud.positions, np.einsum("nk,nkc->nc", bary, corners), atol=1e-6)
    np.testing.assert_array_equal(cloud.extras["normal_offset"], 0.0)
    assert main(["mesh2splats", str(path), str(out), "--target-psnr", "30", "--no-calibrate"]) == 1
    assert "--no-calibrate applies to a --max-splats budget" in capsys.readouterr().err


def test_cli_mesh2splats_target_and_errors(cube, tmp_path, capsys):
    path, _ = cube
    out = tmp_path / "cube.splat"
    assert main(["mesh2splats", str(path), str(out), "--target-psnr", "25", "--view-size", "48"]) == 0
    captured = capsys.readouterr()
    assert "dB PSNR in the worst view (view " in captured.out and " of 12, at " in captured.out
    assert len(read_splats(out)) > 0
    assert (
        main(
            [
                "mesh2splats",
                str(path),
                str(out),
                "--target-psnr",
                "70",
                "--view-size",
                "24",
                "--view-distances",
                "1",
                "--view-count",
                "2",
            ]
        )
        == 0
    )
    said = capsys.readouterr().out
    assert "target 70 dB not reached: " in said and " of 2, at 1x the framing distance); " in said
    assert "error lies" in said
    bad = tmp_path / "flat.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    assert main(["mesh2splats", str(bad), str(out), "--max-splats", "10"]) == 1
    assert "no face with positive area" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["mesh2splats", str(path), str(out), "--max-splats", "10", "--target-psnr", "30"])
