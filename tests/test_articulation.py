"""Skinning splats to bones: closed forms, a per-splat float64 transcription of Blender's Armature
modifier (plain and Preserve Volume), rigid exactness, sign flips, weights, scaling bones."""

import numpy as np
import pytest
from helpers import cloud_covariances, random_cloud

from splatwright.core import SplatCloud
from splatwright.core import sh as shmod
from splatwright.core.articulation import Binding, BonePose, KinematicTree, SkinningError, skin, skin_centres

# independent references ---------------------------------------------------------------------------


def rot_z(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rodrigues(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def hom(r=np.eye(3), t=(0, 0, 0)):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def about(r, pivot):
    """The rigid transform turning by r about `pivot`."""
    pivot = np.asarray(pivot, float)
    return hom(r, pivot - r @ pivot)


def svd_polar(m):
    u, s, vt = np.linalg.svd(m)
    return u @ vt, vt.T @ np.diag(s) @ vt


def rel(a, b):
    """Largest error relative to the size of the reference."""
    return np.abs(np.asarray(a, float) - b).max() / max(np.abs(b).max(), 1e-300)


def cov_rel(a, b):
    """Per-splat covariance error relative to that splat's largest entry, worst case."""
    return float((np.abs(a - b).max(axis=(1, 2)) / np.abs(b).max(axis=(1, 2))).max())


# Blender's Armature modifier, one vertex at a time (float64 transcription of armature_deform.cc
# and the dual-quaternion routines of math_rotation.cc).


def q_mul(a, b):
    aw, av, bw, bv = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[aw * bw - av @ bv], aw * bv + bw * av + np.cross(av, bv)])


def mat_to_quat(m):
    """Unit quaternion (w >= 0) of a rotation: the top eigenvector of Bar-Itzhack's K matrix."""
    m = m / np.linalg.norm(m, axis=0)
    (a, b, c), (d, e, f), (g, h, i) = m
    k = (
        np.array(
            [
                [a - e - i, d + b, g + c, h - f],
                [d + b, e - a - i, h + f, c - g],
                [g + c, h + f, i - a - e, d - b],
                [h - f, c - g, d - b, a + e + i],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(k)
    x, y, z, w = vecs[:, -1]
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def blender_dquat(basemat, mat):
    base_rs = mat @ basemat
    size = np.linalg.norm(base_rs[:3, :3], axis=0)
    lin = mat[:3, :3]
    if np.abs(lin.T @ lin - np.eye(3)).max() > 1e-6 or np.linalg.det(mat) < 0 or ((size - 1) ** 2).sum() > 1e-8:
        y = base_rs[:3, 1] / np.linalg.norm(base_rs[:3, 1])
        z = np.cross(base_rs[:3, 0], y)
        z /= np.linalg.norm(z)
        base_r = hom(np.stack([np.cross(y, z), y, z], axis=1), base_rs[:3, 3])
        r = base_r @ np.linalg.inv(basemat)
        scale = basemat @ (np.linalg.inv(base_r) @ base_rs) @ np.linalg.inv(basemat)
        scale_weight = 1.0
    else:
        r, scale, scale_weight = mat, np.zeros((4, 4)), 0.0
    q = mat_to_quat(r[:3, :3])
    return {
        "quat": q,
        "trans": 0.5 * q_mul(np.concatenate([[0], r[:3, 3]]), q),
        "scale": scale,
        "scale_weight": scale_weight,
    }


def blender_dqs(p, bones, weights, dqs, parts=False):
    """Posed p and the linear map; with `parts`, the normalised blended quaternion and 3x3 scale
    matrix instead of the map."""
    s = {"quat": np.zeros(4), "trans": np.zeros(4), "scale": np.zeros((4, 4)), "scale_weight": 0.0}
    contrib = 0.0
    for b, w in zip(bones, weights):
        if w == 0:
            continue
        dq = {k: np.copy(v) for k, v in dqs[b].items()}
        if dq["scale_weight"]:  # add_weighted_dq_dq_pivot
            dst = (dq["scale"] @ np.append(p, 1))[:3] - p
            dq["trans"] = dq["trans"] + 0.5 * q_mul(dq["quat"], np.concatenate([[0], dst]))
            dq["scale"][:3, 3] -= dst
        flipped = s["quat"] @ dq["quat"] < 0  # add_weighted_dq_dq
        ws = -w if flipped else w
        s["quat"] = s["quat"] + ws * dq["quat"]
        s["trans"] = s["trans"] + ws * dq["trans"]
        if dq["scale_weight"]:
            s["scale"] = s["scale"] + w * dq["scale"]
            s["scale_weight"] += w
        contrib += w
    if contrib <= 1e-4:
        return (p, np.array([1.0, 0, 0, 0]), np.eye(3)) if parts else (p, np.eye(3))
    s["quat"], s["trans"] = s["quat"] / contrib, s["trans"] / contrib  # normalize_dq
    scale = np.eye(4)
    if s["scale_weight"]:
        scale = (s["scale"] + (contrib - s["scale_weight"]) * np.eye(4)) / contrib
    len2 = s["quat"] @ s["quat"]  # mul_v3m3_dq
    w, x, y, z = s["quat"]
    rot = np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w + y * y - x * x - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w + z * z - x * x - y * y],
        ]
    )
    t = 2 * q_mul(s["trans"], s["quat"] * [1, -1, -1, -1])[1:]
    out = (rot @ (scale @ np.append(p, 1))[:3] + t) / len2
    if parts:
        return out, s["quat"] / np.sqrt(len2), scale[:3, :3]
    return out, rot @ scale[:3, :3] / len2


def blender_lbs(p, bones, weights, deform):
    acc, linear, contrib = np.zeros(3), np.zeros((3, 3)), 0.0
    for b, w in zip(bones, weights):
        if w == 0:
            continue
        acc += w * ((deform[b] @ np.append(p, 1))[:3] - p)
        linear += w * deform[b][:3, :3]
        contrib += w
    if contrib <= 1e-4:
        return p, np.eye(3)
    return p + acc / contrib, linear / contrib


def random_rigid(rng, n, spread=1.0):
    return np.stack(
        [hom(rodrigues(rng.normal(size=3), rng.uniform(-3, 3)), rng.normal(0, spread, 3)) for _ in range(n)]
    )


def cloud_at(points, rng, sh_degree=3):
    n = len(points)
    c = random_cloud(n, sh_degree=sh_degree, seed=int(rng.integers(1 << 30)))
    return c.replace(positions=np.asarray(points, np.float32))


# closed forms -------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_single_bone_rotation_moves_centres_covariances_and_colours(mode, rng):
    r, pivot = rodrigues([1, -2, 0.5], 1.2), np.array([0.3, -1.0, 2.0])
    cloud = random_cloud(300, seed=4)
    posed = skin(cloud, Binding.rigid(np.zeros(300, int)), [about(r, pivot)], mode=mode)
    p = cloud.positions.astype(np.float64)
    np.testing.assert_allclose(posed.positions, (p - pivot) @ r.T + pivot, atol=2e-6)
    assert cov_rel(cloud_covariances(posed), r @ cloud_covariances(cloud) @ r.T) < 2e-6
    np.testing.assert_array_equal(posed.log_scales, cloud.log_scales)
    d = rng.normal(size=(300, 3))
    np.testing.assert_allclose(shmod.evaluate(posed.sh, d), shmod.evaluate(cloud.sh, d @ r), atol=2e-5)
    np.testing.assert_array_equal(posed.opacity_logits, cloud.opacity_logits)


def two_bone_setup(a, theta, pivot, n=200, seed=0):
    rng = np.random.default_rng(seed)
    cloud = cloud_at(rng.normal(size=(n, 3)), rng)
    deform = np.stack([np.eye(4), about(rot_z(theta), pivot)])
    binding = Binding.from_weights(np.tile([0, 1], (n, 1)), np.tile([1 - a, a], (n, 1)))
    return cloud, deform, binding


@pytest.mark.parametrize("a, theta", [(0.3, 1.0), (0.5, 2.0), (0.9, -2.8)])
def test_two_bone_linear_blend_closed_form(a, theta):
    pivot = np.array([0.5, 0.2, -0.3])
    cloud, deform, binding = two_bone_setup(a, theta, pivot)
    p = cloud.positions.astype(np.float64)
    blend = (1 - a) * np.eye(3) + a * rot_z(theta)
    posed = skin(cloud, binding, deform, "lbs")
    np.testing.assert_allclose(posed.positions, (1 - a) * p + a * ((p - pivot) @ rot_z(theta).T + pivot), atol=3e-6)
    # (1-a) I + a Rz(theta) is a turn by phi about z times a uniform shrink of x and y.
    phi = np.arctan2(a * np.sin(theta), 1 - a + a * np.cos(theta))
    turn = rot_z(phi)
    assert cov_rel(cloud_covariances(posed), turn @ cloud_covariances(cloud) @ turn.T) < 3e-6
    d = np.random.default_rng(1).normal(size=(len(p), 3))
    np.testing.assert_allclose(shmod.evaluate(posed.sh, d), shmod.evaluate(cloud.sh, d @ turn), atol=3e-5)
    # The literal blended map, for comparison, shrinks splats in the bending plane.
    literal = skin(cloud, binding, deform, "lbs", lbs_stretch="blend")
    assert cov_rel(cloud_covariances(literal), blend @ cloud_covariances(cloud) @ blend.T) < 3e-6


@pytest.mark.parametrize("a, theta", [(0.3, 1.0), (0.5, 2.0), (0.9, -2.8)])
def test_two_bone_dual_quaternion_closed_form(a, theta):
    pivot = np.array([0.5, 0.2, -0.3])
    cloud, deform, binding = two_bone_setup(a, theta, pivot)
    p = cloud.positions.astype(np.float64)
    # Both bones turn about the same axis through the pivot: the blend is a turn by phi about it.
    phi = 2 * np.arctan2(a * np.sin(theta / 2), 1 - a + a * np.cos(theta / 2))
    turn = rot_z(phi)
    posed = skin(cloud, binding, deform, "dqs")
    np.testing.assert_allclose(posed.positions, (p - pivot) @ turn.T + pivot, atol=3e-6)
    assert cov_rel(cloud_covariances(posed), turn @ cloud_covariances(cloud) @ turn.T) < 3e-6
    d = np.random.default_rng(2).normal(size=(len(p), 3))
    np.testing.assert_allclose(shmod.evaluate(posed.sh, d), shmod.evaluate(cloud.sh, d @ turn), atol=3e-5)


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_degree_4_colours_turn_with_the_blended_rotation(mode):
    """SH degree 4 under skinning: the two-bone closed forms above (a turn by phi about z), and
    every splat on a bone of its own (random rigid turns): each posed colour is the rest colour
    seen from the direction turned back, at every direction."""
    a, theta, pivot = 0.3, 1.0, np.array([0.5, 0.2, -0.3])
    cloud, deform, binding = two_bone_setup(a, theta, pivot)
    cloud = cloud.replace(sh=random_cloud(len(cloud), sh_degree=4, seed=8).sh)
    if mode == "lbs":
        phi = np.arctan2(a * np.sin(theta), 1 - a + a * np.cos(theta))
    else:
        phi = 2 * np.arctan2(a * np.sin(theta / 2), 1 - a + a * np.cos(theta / 2))
    posed = skin(cloud, binding, deform, mode)
    assert posed.sh_degree == 4
    d = np.random.default_rng(3).normal(size=(len(cloud), 3))
    np.testing.assert_allclose(shmod.evaluate(posed.sh, d), shmod.evaluate(cloud.sh, d @ rot_z(phi)), atol=3e-5)
    rng = np.random.default_rng(4)
    bones = random_rigid(rng, len(cloud))
    posed = skin(cloud, Binding.rigid(np.arange(len(cloud))), bones, mode)
    turned_back = np.einsum("nji,nj->ni", bones[:, :3, :3], d)  # R^T d per splat
    np.testing.assert_allclose(shmod.evaluate(posed.sh, d), shmod.evaluate(cloud.sh, turned_back), atol=3e-5)


@pytest.mark.parametrize("weights", [(0.5, 0.5), (0.7, 0.3), (0.3, 0.7)])
def test_dual_quaternion_antipodal_sign_flip(weights):
    # +170 and -170 degrees about z: their quaternions (w >= 0) point into opposite half-spaces,
    # and the short way between the two turns passes through 180 degrees, not 0.
    n = 50
    rng = np.random.default_rng(5)
    cloud = cloud_at(rng.normal(size=(n, 3)), rng, sh_degree=1)
    angles = np.radians([170.0, -170.0])
    deform = np.stack([hom(rot_z(t)) for t in angles])
    binding = Binding.from_weights(np.tile([0, 1], (n, 1)), np.tile(weights, (n, 1)))
    # Blender adds the second quaternion on the side of the first: -170 becomes +190.
    first = int(np.argmax(weights))
    halves = np.where(np.arange(2) == first, angles / 2, angles / 2 + np.pi * np.sign(angles[first]))
    phi = 2 * np.angle(np.sum(np.asarray(weights) * np.exp(1j * halves)))
    posed = skin(cloud, binding, deform, "dqs")
    np.testing.assert_allclose(posed.positions, cloud.positions @ rot_z(phi).T, atol=3e-6)
    if weights == (0.5, 0.5):
        np.testing.assert_allclose(posed.positions[:, :2], -cloud.positions[:, :2], atol=3e-6)


def test_weights_not_summing_to_one_are_normalised_and_tiny_totals_stay_put():
    rng = np.random.default_rng(6)
    n = 40
    cloud = cloud_at(rng.normal(size=(n, 3)), rng)
    deform = np.stack([hom(rot_z(0.4), (1, 0, 0)), about(rodrigues([0, 1, 1], 1.1), (0, 1, 0)), hom(t=(5, 5, 5))])
    halves = Binding.from_weights(np.tile([0, 1, 2], (n, 1)), np.tile([0.2, 0.3, 0.0], (n, 1)))
    whole = Binding.from_weights(np.tile([0, 1], (n, 1)), np.tile([0.4, 0.6], (n, 1)))
    assert halves.influences == 2  # the zero weight is gone
    for mode in ("lbs", "dqs"):
        a, b = skin(cloud, halves, deform, mode), skin(cloud, whole, deform, mode)
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.rotations, b.rotations)
    # Blender leaves a vertex whose weights total at most 1e-4 where it is.
    tiny = Binding.from_weights(np.tile([0, 1], (n, 1)), np.tile([5e-5, 4e-5], (n, 1)))
    assert tiny.report()["unbound"] == n
    for mode in ("lbs", "dqs"):
        posed = skin(cloud, tiny, deform, mode)
        np.testing.assert_array_equal(posed.positions, cloud.positions)
        assert cov_rel(cloud_covariances(posed), cloud_covariances(cloud)) < 1e-6


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_scaling_bone_carries_scale_into_covariances(mode):
    rng = np.random.default_rng(7)
    n = 100
    cloud = cloud_at(rng.normal(size=(n, 3)), rng, sh_degree=2)
    rest = hom(rodrigues([1, 0, 1], 0.7), (0.2, 0.5, -1))
    # Posed: moved, turned, and scaled non-uniformly along the bone's own axes.
    pose = hom(rodrigues([0, 1, 0], -0.4), (1, 2, 3)) @ rest @ hom(np.diag([1.5, 0.5, 2.0]))
    deform = pose @ np.linalg.inv(rest)
    posed = skin(cloud, Binding.rigid(np.zeros(n, int)), BonePose(deform[None], rest[None]), mode)
    p = cloud.positions.astype(np.float64)
    np.testing.assert_allclose(posed.positions, p @ deform[:3, :3].T + deform[:3, 3], atol=1e-5)
    a = deform[:3, :3]
    assert cov_rel(cloud_covariances(posed), a @ cloud_covariances(cloud) @ a.T) < 1e-5
    turn = svd_polar(a)[0]
    d = rng.normal(size=(n, 3))
    np.testing.assert_allclose(shmod.evaluate(posed.sh, d), shmod.evaluate(cloud.sh, d @ turn), atol=3e-5)


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_needles_keep_their_thin_axis_under_a_scaling_bone(mode):
    # Axis-aligned splats with scales 1e-7 .. 1e4 in one splat, a bone scaling along the same axes.
    scales = np.array([[1e-7, 1.0, 1e4], [1e4, 1e-7, 1e-3]])
    cloud = SplatCloud.from_activated(np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), scales, [0.5, 0.5])
    stretch = np.array([2.0, 3.0, 0.5])
    posed = skin(cloud, Binding.rigid([0, 0]), hom(np.diag(stretch))[None], mode)
    np.testing.assert_allclose(np.sort(posed.scales, axis=1), np.sort(scales * stretch, axis=1), rtol=1e-6)


# brute force against Blender's algorithm ----------------------------------------------------------


def random_armature(rng, n_bones=5):
    rest = random_rigid(rng, n_bones)
    pose = random_rigid(rng, n_bones)
    # Two bones scale (one with shear-free non-uniform scale, one uniform), as pose bones can.
    pose[1] = pose[1] @ hom(np.diag([1.3, 0.7, 1.1]))
    pose[3] = pose[3] @ hom(np.eye(3) * 0.6)
    return rest, pose


def random_skinning_case(seed, n=300):
    """A random armature posed, Blender's dual quaternions of its bones, and n splats bound to three
    bones each with random weights (some zero, the first ten on one bone); the rng goes on from there."""
    rng = np.random.default_rng(seed)
    rest, pose = random_armature(rng)
    deform = pose @ np.linalg.inv(rest)
    dqs = [blender_dquat(rest[b], deform[b]) for b in range(len(rest))]
    cloud = cloud_at(rng.normal(size=(n, 3)), rng)
    idx = np.stack([rng.choice(len(rest), 3, replace=False) for _ in range(n)])
    w = rng.uniform(0, 1, (n, 3)) * (rng.uniform(size=(n, 3)) > 0.2)  # some zeros
    w[:10] = [1.0, 0.0, 0.0]  # single bone
    return rng, rest, pose, deform, dqs, cloud, idx, w


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_matches_blender_armature_modifier_per_splat(mode):
    rng, rest, pose, deform, dqs, cloud, idx, w = random_skinning_case(8)
    n = len(cloud)
    w[10:15] = [3e-5, 2e-5, 0.0]  # unbound
    w[15:25] *= 7.0  # totals above one
    binding = Binding.from_weights(idx, w, tolerance=0.0)
    posed = skin(cloud, binding, BonePose.from_blender(rest, pose), mode)
    centres = skin_centres(cloud.positions, binding, BonePose(deform, rest), mode)
    expect, maps = [], []
    for i in range(n):
        p = cloud.positions[i].astype(np.float64)
        if mode == "lbs":
            c, m = blender_lbs(p, idx[i], w[i], deform)
            used = w[i] > 0
            turn = svd_polar(m)[0] if used.any() and w[i].sum() > 1e-4 else np.eye(3)
            stretch = sum(wk * svd_polar(deform[b][:3, :3])[1] for b, wk in zip(idx[i], w[i]))
            m = turn @ (stretch / w[i].sum() if w[i].sum() > 1e-4 else np.eye(3))
        else:
            c, m = blender_dqs(p, idx[i], w[i], dqs)
        expect.append(c)
        maps.append(m)
    expect, maps = np.array(expect), np.array(maps)
    # Blender's 1e-5 bar; weights are stored as float32 (as Blender stores them), positions too.
    assert rel(centres, expect) < 1e-6
    assert rel(posed.positions, expect) < 1e-6
    assert cov_rel(cloud_covariances(posed), maps @ cloud_covariances(cloud) @ maps.transpose(0, 2, 1)) < 1e-5


def quat_matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_binding_strength_blends_with_the_rest_as_blenders_modifier_mask(mode):
    """Strength m: centre (1 - m) rest + m posed (armature_deform.cc's armature_weight); covariance and
    SH turned by the bones' map blended with the identity (LBS: an identity influence of weight
    1 - m; DQS: the unit rotation nlerped from the identity, the scale matrix lerped from I)."""
    rng, rest, pose, deform, dqs, cloud, idx, w = random_skinning_case(18)
    n = len(cloud)
    strength = rng.uniform(0, 1, n)
    strength[::7], strength[::11] = 0.0, 1.0
    binding = Binding.from_weights(idx, w, tolerance=0.0)
    bones = BonePose.from_blender(rest, pose)
    posed = skin(cloud, binding, bones, mode, strength=strength)
    centres = skin_centres(cloud.positions, binding, bones, mode, strength=strength)
    expect, maps, turns = [], [], []
    for i in range(n):
        p, m = cloud.positions[i].astype(np.float64), strength[i]
        if mode == "lbs":
            c, lin = blender_lbs(p, idx[i], w[i], deform)
            total = w[i].sum()
            stretch = (
                sum(wk * svd_polar(deform[b][:3, :3])[1] for b, wk in zip(idx[i], w[i])) / total
                if total > 1e-4
                else np.eye(3)
            )  # unbound: stays
            turn = svd_polar(m * lin + (1 - m) * np.eye(3))[0]
            mapped = turn @ (m * stretch + (1 - m) * np.eye(3))
        else:
            c, q, scale = blender_dqs(p, idx[i], w[i], dqs, parts=True)
            q = m * q + (1 - m) * np.array([np.sign(q[0]) or 1.0, 0, 0, 0])
            turn = quat_matrix(q)
            mapped = turn @ (m * scale + (1 - m) * np.eye(3))
        expect.append(p + m * (c - p))
        maps.append(mapped)
        turns.append(turn)
    expect, maps, turns = np.array(expect), np.array(maps), np.array(turns)
    assert rel(centres, expect) < 1e-6
    assert rel(posed.positions, expect) < 1e-6
    still = strength == 0.0
    np.testing.assert_array_equal(posed.positions[still], cloud.positions[still])
    assert np.abs(posed.positions[~still] - cloud.positions[~still]).max() > 0.5
    assert cov_rel(cloud_covariances(posed), maps @ cloud_covariances(cloud) @ maps.transpose(0, 2, 1)) < 1e-5
    np.testing.assert_allclose(posed.sh, shmod.rotate(cloud.sh.astype(np.float64), turns), atol=2e-5)
    full = skin(cloud, binding, bones, mode)  # strength 1 everywhere: the plain binding
    np.testing.assert_array_equal(skin(cloud, binding, bones, mode, strength=np.ones(n)).positions, full.positions)


def test_bad_binding_strengths_are_refused():
    cloud = random_cloud(5, seed=3)
    binding = Binding.rigid(np.zeros(5, int))
    for bad, words in (
        (np.ones(4), "4 binding strengths for 5 splats"),
        ([0, 0.5, 1, 1.5, 1], "0..1"),
        ([0, np.nan, 1, 1, 1], "0..1"),
    ):
        with pytest.raises(SkinningError, match=words):
            skin(cloud, binding, [np.eye(4)], strength=bad)


# exactness, hard cases ----------------------------------------------------------------------------


def test_rigid_binding_is_exact():
    rng = np.random.default_rng(9)
    bones = random_rigid(rng, 7, spread=10.0)
    n = 2000
    cloud = random_cloud(n, seed=10, spread=5.0)
    link = rng.integers(0, 7, n)
    for mode in ("lbs", "dqs"):
        posed = skin(cloud, Binding.rigid(link), bones, mode)
        p = cloud.positions.astype(np.float64)
        expect = np.einsum("nij,nj->ni", bones[link, :3, :3], p) + bones[link, :3, 3]
        # Exact up to rounding the float64 result to float32 (and float64 order of operations).
        ulp = np.spacing(np.abs(expect).astype(np.float32)).astype(np.float64)
        assert (np.abs(posed.positions - expect) <= ulp).all()
        r = bones[link, :3, :3]
        assert cov_rel(cloud_covariances(posed), r @ cloud_covariances(cloud) @ r.transpose(0, 2, 1)) < 1e-6
        np.testing.assert_array_equal(posed.log_scales, cloud.log_scales)


def test_hard_cases_stay_finite_symmetric_and_positive():
    rng = np.random.default_rng(11)
    n = 400
    cloud = random_cloud(n, seed=12)
    log_scales = cloud.log_scales.copy()
    log_scales[:100] = np.log(rng.choice([1e-7, 1e-3, 1.0, 1e4], size=(100, 3)))  # needles, pancakes
    rotations = cloud.rotations.copy()
    rotations[100:110] = 0.0  # zero quaternions
    rotations[110:120] *= 1e-20  # tiny ones
    cloud = cloud.replace(log_scales=log_scales, rotations=rotations)
    deform = np.stack(
        [
            np.eye(4),
            hom(rot_z(np.pi)),  # half turn: LBS blend of 50/50 collapses
            hom(np.array([[1, 0.8, 0], [0, 1, 0], [0, 0, 1.0]])),  # shear
            hom(np.diag([-1.0, 1, 1])),  # mirror
            hom(np.diag([1e-6, 1, 1])),  # almost flat
            hom(np.diag([1.0, 0, 1])),  # collapsed along the bone's Y
        ]
    )
    idx = rng.integers(0, 6, (n, 3))
    idx[:50] = [0, 1, 0]
    w = rng.uniform(size=(n, 3))
    w[:50] = [0.5, 0.5, 0.0]
    binding = Binding.from_weights(idx, w, tolerance=0.0)
    for mode in ("lbs", "dqs"):
        for stretch in ("bones", "blend"):
            posed = skin(cloud, binding, deform, mode, lbs_stretch=stretch)
            for name in ("positions", "rotations", "log_scales", "sh"):
                assert np.isfinite(getattr(posed, name)).all(), (mode, stretch, name)
            cov = cloud_covariances(posed)
            assert np.allclose(cov, cov.transpose(0, 2, 1))
            assert (np.linalg.eigvalsh(cov) >= -1e-6 * np.abs(cov).max(axis=(1, 2))[:, None]).all()


def test_far_from_origin():
    # Bones and splats a million units out: centres stay within float32 storage of the exact ones.
    rng = np.random.default_rng(13)
    offset = np.array([1e6, -2e6, 5e5])
    n = 200
    cloud = cloud_at(offset + rng.normal(size=(n, 3)), rng, sh_degree=0)
    deform = np.stack([about(rot_z(0.3), offset), about(rodrigues([1, 1, 0], -0.5), offset + [0, 1, 0])])
    binding = Binding.from_weights(np.tile([0, 1], (n, 1)), rng.uniform(size=(n, 2)))
    p = cloud.positions.astype(np.float64)
    exact = {
        "lbs": np.array([blender_lbs(p[i], binding.indices[i], binding.weights[i], deform)[0] for i in range(n)]),
        "dqs": np.array(
            [
                blender_dqs(
                    p[i], binding.indices[i], binding.weights[i], [blender_dquat(np.eye(4), d) for d in deform]
                )[0]
                for i in range(n)
            ]
        ),
    }
    for mode in ("lbs", "dqs"):
        assert np.abs(skin_centres(cloud.positions, binding, deform, mode) - exact[mode]).max() < 1e-6
        posed = skin(cloud, binding, deform, mode)
        assert np.abs(posed.positions - exact[mode]).max() <= np.spacing(np.float32(2e6))


def test_centres_only_and_no_sh_paths_agree_with_the_full_one():
    rng = np.random.default_rng(14)
    cloud = random_cloud(500, seed=15)
    rest, pose = random_armature(rng)
    bp = BonePose.from_blender(rest, pose)
    binding = Binding.from_dense(rng.uniform(size=(500, 5)) ** 4, max_influences=4)
    for mode in ("lbs", "dqs"):
        full = skin(cloud, binding, bp, mode)
        centres = skin_centres(cloud.positions, binding, bp, mode)
        np.testing.assert_array_equal(full.positions, centres.astype(np.float32))
        moved = skin(cloud, binding, bp, mode, covariances=False, sh=False)
        np.testing.assert_array_equal(moved.positions, full.positions)
        assert moved.rotations is cloud.rotations and moved.sh is cloud.sh
        no_sh = skin(cloud, binding, bp, mode, sh=False)
        np.testing.assert_array_equal(no_sh.rotations, full.rotations)


# binding ------------------------------------------------------------------------------------------


def test_binding_prunes_reports_and_normalises():
    dense = np.array(
        [
            [0.5, 0.3, 0.15, 0.05, 0.0],
            [0.0, 2.0, 0.0, 0.0, 0.0],
            [1e-9, 0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 0.0, 0.0],
        ]
    )
    b = Binding.from_dense(dense, max_influences=3, tolerance=1e-6)
    assert b.influences == 3
    np.testing.assert_array_equal(b.indices[0], [0, 1, 2])
    np.testing.assert_allclose(b.weights[0], np.array([0.5, 0.3, 0.15]) / 0.95, rtol=1e-7)
    np.testing.assert_allclose(b.weights[1], [1, 0, 0])
    np.testing.assert_allclose(b.weights[2], [1, 0, 0])
    np.testing.assert_allclose(b.weights[3], [0, 0, 0])
    np.testing.assert_allclose(b.pruned, [0.05, 0.0, 1e-9 / (1 + 1e-9), 0.0], rtol=1e-6, atol=1e-12)
    report = b.report()
    assert report["unbound"] == 1 and report["max_influences"] == 3 and report["pruned_splats"] == 2
    assert report["max_pruned_weight"] == pytest.approx(0.05, rel=1e-6)
    same = Binding.from_weights(np.tile(np.arange(5), (4, 1)), dense, max_influences=3)
    np.testing.assert_array_equal(same.indices, b.indices)
    np.testing.assert_allclose(same.pruned, b.pruned, atol=1e-12)


def test_bad_bindings_and_poses_are_rejected_clearly():
    cloud = random_cloud(4, sh_degree=0)
    eye = np.eye(4)[None]
    with pytest.raises(SkinningError, match="not finite for 1 splats"):
        Binding.from_weights([[0], [0]], [[np.nan], [1.0]])
    with pytest.raises(SkinningError, match="negative for 1 splats"):
        Binding.from_weights([[0], [0]], [[-1.0], [1.0]])
    with pytest.raises(SkinningError, match="max_influences must be at least 1"):
        Binding.from_dense(np.ones((2, 3)), max_influences=0)
    with pytest.raises(SkinningError, match="must both be"):
        Binding.from_weights([[0, 1]], [[1.0]])
    with pytest.raises(SkinningError, match="3 rows for 4 splats"):
        skin(cloud, Binding.rigid([0, 0, 0]), eye)
    with pytest.raises(SkinningError, match="refers to bone 2 but the pose has 1 bones"):
        skin(cloud, Binding.rigid([0, 2, 0, 0]), eye)
    with pytest.raises(SkinningError, match=r"shape \(B, 4, 4\)"):
        skin(cloud, Binding.rigid([0] * 4), np.eye(3)[None])
    with pytest.raises(SkinningError, match=r"bones \[0\] are not finite"):
        skin(cloud, Binding.rigid([0] * 4), eye * np.nan)
    with pytest.raises(SkinningError, match="unknown skinning mode 'slerp'"):
        skin(cloud, Binding.rigid([0] * 4), eye, mode="slerp")
    bad = cloud.replace(positions=np.where(np.arange(4)[:, None] == 2, np.nan, cloud.positions))
    with pytest.raises(SkinningError, match="1 splats have non-finite positions"):
        skin(bad, Binding.rigid([0] * 4), eye)


# kinematics into skinning -------------------------------------------------------------------------


def test_links_carry_their_splats_through_forward_kinematics():
    tree = KinematicTree(
        ["base", "upper", "lower"],
        [-1, 0, 1],
        [np.eye(4), hom(t=(0, 0, 1)), hom(rot_z(0.5), (0, 0, 1))],
        ["fixed", "revolute", "prismatic"],
        axes=[(1, 0, 0), (0, 1, 0), (0, 0, 1)],
    )
    cloud = random_cloud(90, sh_degree=1, seed=17)
    link = np.repeat([0, 1, 2], 30)
    q = np.array([0.6, 0.25])
    posed = skin(cloud, Binding.rigid(link), tree.deform_matrices(q))
    # Each splat keeps its coordinates in its link's frame.
    rest, world = tree.rest_transforms(), tree.forward_kinematics(q)
    local = np.einsum("nij,nj->ni", np.linalg.inv(rest)[link], np.c_[cloud.positions, np.ones(90)])
    np.testing.assert_allclose(posed.positions, np.einsum("nij,nj->ni", world[link], local)[:, :3], atol=2e-6)


# the bent cylinder: skinned splats against splats made from the bent surface ----------------------


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_bent_cylinder_renders_like_splats_of_the_bent_surface(mode):
    import importlib.util
    import sys
    from pathlib import Path

    from splatwright.core.metrics import psnr

    bench_dir = Path(__file__).resolve().parent.parent / "bench"
    sys.path.insert(0, str(bench_dir))
    spec = importlib.util.spec_from_file_location("bench_articulation", bench_dir / "articulation.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    images, reference, _ = bench.bent_cylinder_images(mode, max_splats=6000, size=128, around=48, along=64)
    score = {name: psnr(image, reference) for name, (image, _) in images.items()}
    floor = score["sampling floor (second sampling)"]
    # Loose bounds (the bench reports the numbers): full skinning comes close to what resampling the
    # bent surface gives, and clearly beats moving centres only or leaving the SH unrotated.
    assert score["full skinning"] > floor - 4.0, score
    assert score["full skinning"] > score["centres only"] + 8.0, score
    assert score["full skinning"] > score["no SH rotation"] + 2.0, score


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_zero_scales_skin_as_points(mode):
    # log-scale -inf (a zero scale) renders and collides as a point; skinning keeps it one
    cloud = random_cloud(40, 1, seed=41)
    cloud.log_scales[:4, 2] = -np.inf
    cloud.log_scales[4:6] = -np.inf
    deform = np.stack([np.eye(4), np.eye(4)])
    deform[1, :3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    deform[1, :3, 3] = [0.5, 0, 0]
    posed = skin(cloud, Binding.rigid(np.arange(40) % 2), deform, mode=mode)
    np.testing.assert_array_equal(np.isneginf(posed.log_scales), np.isneginf(cloud.log_scales))
    odd = np.arange(40) % 2 == 1
    expect = cloud.positions[odd] @ deform[1, :3, :3].T + [0.5, 0, 0]
    np.testing.assert_allclose(posed.positions[odd], expect, atol=1e-6)
    with pytest.raises(SkinningError, match="non-finite log_scales"):
        skin(
            cloud.replace(log_scales=np.where(np.isneginf(cloud.log_scales), np.inf, cloud.log_scales)),
            Binding.rigid(np.arange(40) % 2),
            deform,
        )


# rigid bones at float32 precision ------------------------------------------------------------------


def _float32_chain(rng, depth):
    """A Blender-like pose: a chain of turned bones whose armature-space matrices are products
    rounded to float32 at every level, as Blender computes pose_bone.matrix; rest likewise."""
    rest, pose = np.eye(4, dtype=np.float32), np.eye(4, dtype=np.float32)
    for _ in range(depth):
        axis = rng.normal(size=3)
        offset = hom(rodrigues(axis, rng.uniform(-3, 3)), rng.normal(0, 0.5, 3)).astype(np.float32)
        turn = hom(rodrigues(rng.normal(size=3), rng.uniform(-3, 3))).astype(np.float32)
        rest = (rest @ offset).astype(np.float32)
        pose = (pose @ offset @ turn).astype(np.float32)
    return rest.astype(np.float64), pose.astype(np.float64)


def test_float32_rounded_turns_are_rigid_and_a_thousandth_of_scale_is_not():
    from splatwright.core.skinning import RIGID_TOLERANCE

    rng = np.random.default_rng(3)
    chains = [_float32_chain(rng, depth) for depth in (1, 4, 8, 12) for _ in range(25)]
    rest, pose = (np.stack(m) for m in zip(*chains))
    stretch = np.abs(svd_polar_batch(pose @ np.linalg.inv(rest)) - np.eye(3)).max(axis=(1, 2))
    assert stretch.max() > 1e-9  # the rounding the old tolerance took for scale
    assert not BonePose.from_blender(rest, pose).derived["scales"].any()
    for scale in (np.diag([1.001, 1.001, 1.001, 1.0]), np.diag([1.0, 1.001, 1.0, 1.0]), np.diag([0.999, 1, 1, 1.0])):
        scaled = pose.copy()
        scaled[::7] = scaled[::7] @ scale
        flags = BonePose.from_blender(rest, scaled).derived["scales"]
        assert np.array_equal(flags, np.arange(len(pose)) % 7 == 0)
    assert stretch.max() < RIGID_TOLERANCE < 1e-3 / 100  # rounding below it, a scale of 1.001 far above


def svd_polar_batch(m):
    u, s, vt = np.linalg.svd(m[:, :3, :3])
    return np.einsum("bji,bj,bjk->bik", vt, s, vt)


def test_skinning_with_float32_turns_stays_within_float32_of_float64():
    """LBS with every bone's exact stretch (float64, SVD) against ours, which drops the rounding."""
    rng = np.random.default_rng(4)
    rest, pose = (np.stack(m) for m in zip(*[_float32_chain(rng, d) for d in (2, 5, 9, 12) * 3]))
    deform = pose @ np.linalg.inv(rest)
    cloud = random_cloud(2000, sh_degree=1, seed=5)
    binding = Binding.from_weights(
        np.stack([rng.choice(len(pose), 3, replace=False) for _ in range(len(cloud))]),
        rng.uniform(0.1, 1.0, (len(cloud), 3)),
    )
    ours = skin(cloud, binding, BonePose.from_blender(rest, pose), "lbs")
    w = binding.weights.astype(np.float64)
    w /= w.sum(axis=1, keepdims=True)
    blended = np.einsum("nk,nkij->nij", w, deform[binding.indices][:, :, :3, :3])
    s_blend = np.einsum("nk,nkij->nij", w, svd_polar_batch(deform)[binding.indices])
    m = np.stack([svd_polar(b)[0] for b in blended]) @ s_blend
    ref = m @ cloud_covariances(cloud) @ np.swapaxes(m, 1, 2)
    mine = cloud_covariances(ours)
    rel = (np.abs(mine - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))).max()
    dropped = np.abs(svd_polar_batch(deform) - np.eye(3)).max()
    assert rel <= 2 * dropped + 4 * np.finfo(np.float32).eps
    assert rel < 2e-6
