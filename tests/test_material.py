"""The material splats carry for relighting (core.material) and how cloud operations treat it."""

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.core import SplatCloud, geometry
from splatwright.core import material as mat


def _material_cloud(n=64, seed=0):
    rng = np.random.default_rng(seed)
    cloud = random_cloud(n, sh_degree=1, seed=seed)
    return mat.with_material(
        cloud,
        albedo=rng.uniform(0, 1, (n, 3)),
        normals=rng.normal(size=(n, 3)),
        roughness=rng.uniform(0, 1, n),
        metallic=rng.uniform(0, 1, n),
    )


def test_accessors_and_defaults():
    cloud = random_cloud(5, sh_degree=0)
    assert not mat.has_material(cloud)
    assert mat.albedo(cloud) is None and mat.normals(cloud) is None
    np.testing.assert_array_equal(mat.roughness(cloud), np.full(5, 0.5))
    np.testing.assert_array_equal(mat.metallic(cloud), np.zeros(5))
    given = np.array([[3.0, 0, 0], [0, -2, 0], [1, 1, 0], [0, 0, 5], [1, 2, 2]])
    lit = mat.with_material(cloud, albedo=np.full((5, 3), 0.25), normals=given, roughness=0.2)
    assert mat.has_material(lit) and not mat.has_material(cloud)
    np.testing.assert_allclose(mat.normals(lit), given / np.linalg.norm(given, axis=1)[:, None], atol=1e-7)
    np.testing.assert_allclose(mat.albedo(lit), 0.25)
    np.testing.assert_allclose(mat.roughness(lit), 0.2, atol=1e-7)
    assert all(lit.extras[k].dtype == np.float32 and lit.extras[k].shape == (5,) for k in mat.NORMALS)
    assert lit.extras[mat.ALBEDO].shape == (5, 3)


@pytest.mark.parametrize(
    "parts, message",
    [
        ({"albedo": np.zeros((4, 3))}, "shape"),
        ({"albedo": np.full((5, 3), 1.5)}, "expected"),
        ({"normals": np.zeros((5, 3))}, "zero-length"),
        ({"normals": np.full((5, 3), np.nan)}, "not finite"),
        ({"roughness": np.full(5, np.inf)}, "non-finite"),
        ({"metallic": -0.1}, "expected"),
    ],
)
def test_bad_material_is_refused(parts, message):
    with pytest.raises(ValueError, match=message):
        mat.with_material(random_cloud(5, sh_degree=0), **parts)


def test_selection_join_and_copy_keep_the_material():
    cloud = _material_cloud()
    picked = cloud[np.arange(0, 64, 3)]
    np.testing.assert_array_equal(mat.normals(picked), mat.normals(cloud)[::3])
    joined = SplatCloud.concatenate([cloud, picked])
    np.testing.assert_array_equal(mat.albedo(joined), np.concatenate([mat.albedo(cloud), mat.albedo(picked)]))
    np.testing.assert_array_equal(mat.metallic(cloud.copy()), mat.metallic(cloud))


@pytest.mark.parametrize(
    "linear",
    [
        np.diag([3.0, 0.5, 1.0]),  # non-uniform stretch
        np.diag([-1.0, 1.0, 1.0]),  # mirror
        np.array([[1.0, 0.7, 0.0], [0.0, 1.0, 0.0], [0.2, 0.0, 2.0]]),  # shear
        2.0 * geometry.quaternions_to_matrices(np.array([0.9, 0.1, -0.3, 0.2])),  # similarity
    ],
)
def test_transformed_normals_follow_the_inverse_transpose(linear):
    cloud = _material_cloud()
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = linear, [1.0, -2.0, 0.5]
    moved = cloud.transformed(matrix)
    # Closed form: n' = A^-T n / |A^-T n|, in float64.
    expected = np.linalg.inv(linear).T @ mat.normals(cloud).T
    expected = (expected / np.linalg.norm(expected, axis=0)).T
    np.testing.assert_allclose(mat.normals(moved), expected, atol=2e-7)
    # Perpendicular to any tangent the map carries: t' = A t with t perpendicular to n.
    tangent = np.cross(mat.normals(cloud), [0.3, 0.5, 0.81])
    np.testing.assert_allclose(np.einsum("ij,ij->i", tangent @ linear.T, mat.normals(moved)), 0, atol=1e-6)
    np.testing.assert_array_equal(moved.extras[mat.ALBEDO], cloud.extras[mat.ALBEDO])


def test_a_mirror_flips_only_the_mirrored_component():
    cloud = mat.with_material(random_cloud(1, sh_degree=0), normals=[[0.6, 0.8, 0.0]])
    moved = cloud.transformed(np.diag([-1.0, 1.0, 1.0]))
    np.testing.assert_allclose(mat.normals(moved), [[-0.6, 0.8, 0.0]], atol=1e-7)


def _bones(rng, count=4, scale_bone=None):
    """(B,4,4) deform matrices: random turns and shifts, one bone also stretched if asked."""
    deform = np.tile(np.eye(4), (count, 1, 1))
    deform[:, :3, :3] = geometry.quaternions_to_matrices(rng.normal(size=(count, 4)))
    deform[:, :3, 3] = rng.normal(size=(count, 3))
    if scale_bone is not None:
        deform[scale_bone, :3, :3] = deform[scale_bone, :3, :3] @ np.diag([1.6, 0.7, 1.2])
    return deform


def _polar(m):
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _binding(rng, n, bones):
    from splatwright.core.skinning import Binding

    idx = np.stack([rng.choice(bones, 2, replace=False) for _ in range(n)])
    weights = rng.uniform(0.1, 1.0, (n, 2))
    return Binding.from_weights(idx, weights), idx, weights / weights.sum(axis=1, keepdims=True)


@pytest.mark.parametrize("scale_bone", [None, 2])
def test_lbs_turns_normals_like_a_float64_brute_force(scale_bone):
    from splatwright.core.skinning import skin

    rng = np.random.default_rng(5)
    cloud = _material_cloud(200)
    deform = _bones(rng, scale_bone=scale_bone)
    binding, idx, w = _binding(rng, len(cloud), 4)
    posed = skin(cloud, binding, deform, mode="lbs")
    w = binding.weights.astype(np.float64)  # as normalised and stored (float32)
    blended = np.einsum("nk,nkij->nij", w, deform[idx][:, :, :3, :3])
    turn = _polar(blended)
    if scale_bone is None:
        expected = np.einsum("nij,nj->ni", turn, mat.normals(cloud))
    else:
        # The covariance map: the splat's turn times the blend of the bones' own stretches.
        stretch = np.array([_polar(d).T @ d for d in deform[:, :3, :3]])
        maps = turn @ np.einsum("nk,nkij->nij", w, stretch[idx])
        expected = np.einsum("nji,nj->ni", np.linalg.inv(maps), mat.normals(cloud))
        expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(mat.normals(posed), expected, atol=2e-6)
    np.testing.assert_array_equal(mat.albedo(posed), mat.albedo(cloud))
    # The normal keeps its place in the splat's own frame: the frame turned as the normal did.
    before = np.einsum("nji,nj->ni", geometry.quaternions_to_matrices(cloud.rotations), mat.normals(cloud))
    after = np.einsum("nji,nj->ni", geometry.quaternions_to_matrices(posed.rotations), mat.normals(posed))
    if scale_bone is None:
        np.testing.assert_allclose(after, before, atol=2e-6)


def test_dqs_turns_normals_by_the_blended_rotation():
    from splatwright.core.skinning import skin

    rng = np.random.default_rng(6)
    cloud = _material_cloud(200)
    deform = _bones(rng)
    binding, idx, _ = _binding(rng, len(cloud), 4)
    posed = skin(cloud, binding, deform, mode="dqs")
    w = binding.weights.astype(np.float64)
    q = geometry.matrices_to_quaternions(deform[:, :3, :3])[idx]  # (N,2,4) the bones' turns
    # Blender's blend: the second quaternion joins on the first one's side.
    side = np.where(np.einsum("ni,ni->n", q[:, 0], q[:, 1]) < 0, -1.0, 1.0)
    blend = w[:, :1] * q[:, 0] + (side * w[:, 1])[:, None] * q[:, 1]
    turn = geometry.quaternions_to_matrices(blend / np.linalg.norm(blend, axis=1, keepdims=True))
    np.testing.assert_allclose(mat.normals(posed), np.einsum("nij,nj->ni", turn, mat.normals(cloud)), atol=2e-6)


def test_centres_only_skinning_keeps_the_normals():
    from splatwright.core.skinning import skin

    rng = np.random.default_rng(7)
    cloud = _material_cloud(50)
    binding, _, _ = _binding(rng, len(cloud), 4)
    posed = skin(cloud, binding, _bones(rng), covariances=False)
    np.testing.assert_array_equal(mat.normals(posed), mat.normals(cloud))
