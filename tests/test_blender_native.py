"""Blender 5.3's own splat point clouds, made by its PLY and SPZ importers, through Splatwright.

The worker (tests/workers/native.py) opens files with `wm.ply_import` / `wm.spz_import` and passes
the clouds to Splatwright's export, Apply Splat Transform, Join and render engine. Judged here:
exports against the source files read by plyfile (an independent PLY reader) and by splatwright.io,
transformed exports against float64 maps of the source, and each other format against our own writer
given the source itself. Blender's PLY importer normalises quaternions as float32 q * (1 / |q|): the
exported rotations are Blender's bit for bit, and the source's to that rounding.
"""

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import covariances, euler_matrix, format_errors, quat_matrices, random_cloud, read
from workers.native import MOVES

pytestmark = [pytest.mark.blender, pytest.mark.slow]


def _write_inputs(work):
    from splatwright.io import write_splats

    for degree in (3, 4):
        write_splats(work / f"src{degree}.ply", random_cloud(400, degree, degree))
    write_splats(work / "other.ply", random_cloud(100, 3, 7, spread=2.0))
    write_splats(work / "src.spz", random_cloud(300, 3, 8))
    scene = random_cloud(300, 3, 9, spread=0.6)
    scene.log_scales[:] = np.random.default_rng(10).uniform(-3.2, -2.0, scene.log_scales.shape)
    write_splats(work / "scene.ply", scene)
    np.savez(work / "generated.npz", **_generated_arrays())
    blobs = random_cloud(80, 0, 12)
    blobs.log_scales[:] = np.random.default_rng(13).uniform(-2.5, -1.5, blobs.log_scales.shape)
    write_splats(work / "collide.ply", blobs)


def _generated_arrays():
    """A degree-1 cloud as Blender's native attributes (float32), for the geometry-nodes worker step."""
    rng = np.random.default_rng(11)
    n = 200
    q = rng.normal(size=(n, 4))
    arrays = {
        "position": rng.normal(0, 0.6, (n, 3)),
        "scale": np.exp(rng.uniform(-3.2, -2.0, (n, 3))),
        "rotation": q / np.linalg.norm(q, axis=1, keepdims=True),
        "radiance:base": np.c_[rng.normal(0, 0.5, (n, 3)), rng.uniform(0.2, 0.95, n)],
    }
    arrays.update({f"radiance:sh_{j}": rng.normal(0, 0.2, (n, 3)) for j in range(3)})
    return {k: v.astype(np.float32) for k, v in arrays.items()}


blender = blender_fixture("workers.native", _write_inputs, since="5.3")


def ply_columns(path):
    """Every vertex property of a PLY, float64, read by plyfile."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    return {p.name: np.asarray(vertex[p.name], np.float64) for p in vertex.properties}


def blender_normalised(q):
    """Quaternions as Blender's PLY importer stores them: float32 q * (1 / sqrt(sum q^2))."""
    q = np.asarray(q, np.float32)
    return q * (np.float32(1) / np.sqrt((q * q).sum(axis=1, keepdims=True)))


def sigmoid(x):
    return 1 / (1 + np.exp(-np.asarray(x, np.float64)))


def test_blenders_import_is_a_native_splat_cloud(blender):
    res = blender.step("blender_ply")
    for degree in (3, 4):
        assert res[str(degree)]["type"] == "POINTCLOUD" and res[str(degree)]["data_type"] == "GAUSSIAN_SPLAT"
        assert res[str(degree)]["attributes"]["radiance:base"] == "FLOAT4"
        assert f"radiance:sh_{(degree + 1) ** 2 - 2}" in res[str(degree)]["attributes"]
        assert np.array_equal(res[str(degree)]["matrix_world"], np.eye(4))  # left where it landed


@pytest.mark.parametrize("degree", [3, 4])
def test_a_ply_blender_imported_exports_as_the_source_file(blender, degree):
    res = blender.step("blender_ply")[str(degree)]
    assert res["exports"][".ply"]["error"] is None
    source, written = ply_columns(blender.work / f"src{degree}.ply"), ply_columns(blender.out / f"blender{degree}.ply")
    rest = 3 * (degree + 1) ** 2 - 3
    exact = ["x", "y", "z", *(f"f_dc_{i}" for i in range(3)), *(f"f_rest_{i}" for i in range(rest))]
    assert set(exact) <= set(written)
    for name in exact:
        np.testing.assert_array_equal(written[name], source[name], err_msg=name)
    rotations = np.stack([written[f"rot_{i}"] for i in range(4)], axis=1)
    np.testing.assert_array_equal(rotations, blender.npz(f"blender_rotation{degree}")["rotation"])
    np.testing.assert_array_equal(rotations, blender_normalised(np.stack([source[f"rot_{i}"] for i in range(4)], 1)))
    for i in range(3):  # log(float32(exp(s))): float32 round-off of the scale and of its log
        np.testing.assert_allclose(written[f"scale_{i}"], source[f"scale_{i}"], rtol=0, atol=5e-7)
    np.testing.assert_allclose(sigmoid(written["opacity"]), sigmoid(source["opacity"]), rtol=0, atol=1.2e-7)


@pytest.mark.parametrize("ext", [".spz", ".usd", ".usda", ".splat", ".glb"])
def test_every_format_writes_a_blender_imported_cloud_as_it_writes_the_source(blender, tmp_path, ext):
    """Each format's own quantisation and degree limits, applied alike to Blender's cloud and the source."""
    import warnings

    from splatwright.io import write_splats

    res = blender.step("blender_ply")
    for degree in (3, 4):
        assert res[str(degree)]["exports"][ext]["error"] is None, res[str(degree)]["exports"][ext]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # what the format cannot hold, said by both writers
            write_splats(tmp_path / f"src{degree}{ext}", read(blender.work / f"src{degree}.ply"))
            ours, theirs = read(tmp_path / f"src{degree}{ext}"), read(blender.out / f"blender{degree}{ext}")
        assert theirs.sh_degree == ours.sh_degree
        errors = format_errors(theirs, ours)
        assert errors["positions"] == 0 and errors["covariance"] < 1e-5, (ext, degree, errors)
        assert errors["opacity"] < 1e-6 and errors["colour"] < 1e-6, (ext, degree, errors)


@pytest.mark.parametrize("move", list(MOVES))
def test_a_moved_blender_import_exports_in_world_space(blender, move):
    """World coordinates as the file's (the object landed in the file's axes): centres and covariances
    under the object's matrix, colours turned with its rotation, opacity kept; Apply Splat Transform
    then leaves an identity and the same file."""
    from splatwright.core import sh as shmod

    res = blender.step("blender_ply_moved")[move]
    assert res["export"]["error"] is None and res["apply"]["error"] is None
    turn = euler_matrix(MOVES[move]["rotation_euler"])
    linear = turn @ np.diag(MOVES[move]["scale"])
    np.testing.assert_allclose(np.array(res["matrix_world"])[:3, :3], linear, atol=1e-6)
    source, written = read(blender.work / "src3.ply"), read(blender.out / f"{move}.ply")
    np.testing.assert_allclose(
        written.positions,
        source.positions.astype(np.float64) @ linear.T + MOVES[move]["location"],
        rtol=1e-6,
        atol=1e-6,
    )
    expected = linear @ covariances(source.rotations, source.log_scales) @ linear.T
    relative = np.abs(covariances(written.rotations, written.log_scales) - expected).max(axis=(1, 2)) / np.abs(
        expected
    ).max(axis=(1, 2))
    assert relative.max() < 2e-5
    np.testing.assert_allclose(written.opacities, source.opacities, rtol=0, atol=1.2e-7)
    directions = np.random.default_rng(1).normal(size=(len(source), 3))
    np.testing.assert_allclose(
        shmod.colors(written.sh, directions @ turn.T), shmod.colors(source.sh, directions), atol=2e-5
    )
    assert np.allclose(res["applied_matrix"], np.eye(4)) and res["applied_export"]["error"] is None
    applied = read(blender.out / f"{move}_applied.ply")
    errors = format_errors(applied, written)
    assert errors["positions"] < 1e-5 and errors["covariance"] < 1e-5 and errors["colour"] < 1e-5, errors


def test_an_spz_stands_where_blenders_importer_and_ours_place_it(blender):
    res = blender.step("blender_spz")
    assert res["import"]["error"] is None
    world = blender.npz("spz_world")
    np.testing.assert_allclose(world["blender"], world["ours"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("ext", [".spz", ".ply"])
def test_an_spz_blender_imported_exports_as_ours_reads_it(blender, ext):
    res = blender.step("blender_spz")
    assert res["blender"]["data_type"] == "GAUSSIAN_SPLAT"
    assert res["export_" + ext[1:]]["error"] is None
    source, written = read(blender.work / "src.spz"), read(blender.out / f"spz_blender{ext}")
    errors = format_errors(written, source)
    # Blender turned the rotations upright, Splatwright turns them back: float32 round-off, which an SPZ
    # written again can carry across one step of its 9-bit smallest-three components (~1.4e-3 rad).
    assert errors["positions"] < 1e-6 and errors["covariance"] < (3e-3 if ext == ".spz" else 1e-5), errors
    assert errors["opacity"] < 1e-6 and errors["colour"] < 2e-6, errors


def test_splatwrights_import_makes_blenders_own_splat_cloud(blender):
    res = blender.step("ours_native")
    assert res["error"] is None
    assert (res["type"], res["data_type"]) == ("POINTCLOUD", "GAUSSIAN_SPLAT")
    assert res["attributes"]["radiance:base"] == "FLOAT4"


def test_blender_imports_join_in_their_file_axes(blender):
    res = blender.step("join")
    assert res["join"]["error"] is None and res["export"]["error"] is None
    first, second = ply_columns(blender.work / "src3.ply"), ply_columns(blender.work / "other.ply")
    joined = ply_columns(blender.out / "joined.ply")
    for name in ("x", "y", "z", "f_dc_0", "f_rest_44"):
        np.testing.assert_array_equal(joined[name], np.concatenate([first[name], second[name]]), err_msg=name)


def test_f12_renders_a_blender_imported_cloud_as_the_same_splats_of_ours(blender):
    from splatwright.io.exr import read_exr

    res = blender.step("render")
    assert res["blender"]["error"] is None and res["ours_render"]["error"] is None
    images = []
    for name in ("blender", "ours"):
        channels = read_exr(blender.out / f"render_{name}.exr")
        images.append(np.stack([channels[c] for c in "RGB"], axis=-1))
    assert np.abs(images[0] - images[0].mean()).max() > 0.05  # splats are drawn
    # the two clouds' own differences (colour up to 2e-6, covariance 1e-5: the import test above)
    # move a pixel by a few 1e-6 as the frame's origin rounds the centres (measured 2.9e-6 at worst)
    np.testing.assert_allclose(images[0], images[1], rtol=0, atol=5e-6)


def _images(blender, *names):
    from splatwright.io.exr import read_exr

    return [np.stack([read_exr(blender.out / f"render_{name}.exr")[c] for c in "RGB"], axis=-1) for name in names]


def test_splats_made_by_geometry_nodes_export_and_render(blender):
    """Written in the default axes (Blender x, y, z -> file x, -z, y), as any upright splat object."""
    from splatwright.core import sh as shmod

    res = blender.step("geometry_nodes")
    assert all(res[k]["error"] is None for k in ("export", "render", "import", "imported_render")), res
    arrays, written = _generated_arrays(), read(blender.out / "generated.ply")
    to_file = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(written.positions, arrays["position"].astype(np.float64) @ to_file.T, atol=1e-7)
    rs = quat_matrices(arrays["rotation"]) * arrays["scale"].astype(np.float64)[:, None, :]
    expected = to_file @ (rs @ rs.transpose(0, 2, 1)) @ to_file.T
    got = covariances(written.rotations, written.log_scales)
    assert (np.abs(got - expected).max(axis=(1, 2)) / np.abs(expected).max(axis=(1, 2))).max() < 1e-5
    np.testing.assert_allclose(written.opacities, arrays["radiance:base"][:, 3], rtol=0, atol=1.2e-7)
    sh = np.stack([arrays["radiance:base"][:, :3]] + [arrays[f"radiance:sh_{j}"] for j in range(3)], axis=1)
    directions = np.random.default_rng(2).normal(size=(len(sh), 3))
    np.testing.assert_allclose(
        shmod.colors(written.sh, directions @ to_file.T), shmod.colors(sh, directions), atol=1e-6
    )
    generated, imported = _images(blender, "generated", "generated_imported")
    assert np.abs(generated - generated.mean()).max() > 0.05
    np.testing.assert_allclose(generated, imported, rtol=0, atol=2e-6)


def test_converted_pruned_and_commanded_exports_keep_the_files_axes(blender):
    res = blender.step("tools")
    for key in ("to_mesh", "mesh_export", "to_native", "native_export", "prune", "pruned_export"):
        assert res[key]["error"] is None, (key, res[key])
    assert res["mesh_type"] == "MESH" and res["command"] == 0
    source = ply_columns(blender.work / "src3.ply")
    for name in ("converted", "reconverted", "command_0001"):
        written = ply_columns(blender.out / f"{name}.ply")
        for column in ("x", "y", "z", "f_dc_0", "f_rest_44"):
            np.testing.assert_array_equal(written[column], source[column], err_msg=f"{name} {column}")
    kept = sigmoid(source["opacity"]) >= 0.5
    pruned = ply_columns(blender.out / "pruned.ply")
    assert 0 < kept.sum() < len(kept)
    np.testing.assert_array_equal(pruned["x"], source["x"][kept])


def test_a_blender_import_bound_to_an_armature_poses_by_its_weights(blender):
    """At rest the file itself; posed, every centre the weighted blend of its bones' deform matrices
    (float64 linear blend of the bind's own weights)."""
    res = blender.step("bind")
    assert all(res[k]["error"] is None for k in ("bind", "rest_export", "posed_export")), res
    source = read(blender.work / "src3.ply")
    np.testing.assert_array_equal(read(blender.out / "bound_rest.ply").positions, source.positions)
    saved = blender.npz("bind")
    weights, deform = saved["weights"].astype(np.float64), saved["deform"]
    assert np.allclose(weights.sum(axis=1), 1, atol=1e-6) and (weights[:, 1] > 0.5).any()
    rest = np.c_[source.positions.astype(np.float64), np.ones(len(source))]
    expected = np.einsum("nb,bij,nj->ni", weights, deform, rest)[:, :3]
    np.testing.assert_allclose(read(blender.out / "bound_posed.ply").positions, expected, atol=2e-5)


def _contact_pairs(a, b, k, min_opacity, steps=2001):
    """For each pair of k-sigma ellipsoids, by brute force over s, min over s in (0, 1) of
    1 - d^T (A / (1 - s) + B / s)^-1 d (shape matrices A, B = k^2 Sigma, d = m_b - m_a): they meet iff it
    is >= 0 (Gilitschenski and Hanebeck's criterion); its size tells pairs too close to call."""
    a, b = a[a.opacities >= min_opacity], b[b.opacities >= min_opacity]
    shape_a = k * k * covariances(a.rotations, a.log_scales)
    shape_b = k * k * covariances(b.rotations, b.log_scales)
    d = b.positions.astype(np.float64)[None] - a.positions.astype(np.float64)[:, None]
    best = np.full(d.shape[:2], np.inf)
    for s in np.linspace(0, 1, steps)[1:-1]:
        combined = shape_a[:, None] / (1 - s) + shape_b[None] / s
        best = np.minimum(best, 1 - np.einsum("abi,abi->ab", d, np.linalg.solve(combined, d[..., None])[..., 0]))
    return best


def test_collisions_between_blender_imports_match_the_brute_force(blender):
    res = blender.step("collisions")
    assert res["op"]["error"] is None
    k, min_opacity = res["defaults"]["sigma"], res["defaults"]["min_opacity"]
    best = _contact_pairs(read(blender.work / "other.ply"), read(blender.work / "collide.ply"), k, min_opacity)
    near = res["near"]["frames"][0]["pairs"]
    assert (best >= 1e-3).sum() <= near <= (best >= -1e-3).sum() and near > 0
    assert res["far"]["frames"][0]["pairs"] == 0
