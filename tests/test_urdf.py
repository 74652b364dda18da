"""Kinematic trees, forward kinematics and the URDF reader, against hand-multiplied matrices."""

import numpy as np
import pytest

from splatwright.core.kinematics import (KinematicsError, KinematicTree, quaternions_to_rotvec,
                                         rotvec_to_quaternions)
from splatwright.io.common import SplatFileError
from splatwright.io.urdf import parse_urdf, read_urdf


# hand-written reference matrices ----------------------------------------------------------------

def rot_x(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def hom(r=np.eye(3), t=(0, 0, 0)):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def rodrigues(axis, angle):
    """Textbook axis-angle matrix, independent of the code under test."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


# a small tree with every joint type ---------------------------------------------------------------

def small_tree():
    #   base -(revolute z)-> arm -(prismatic x)-> slider -(ball)-> wrist
    #                     \-(continuous y)-> wheel,  arm -(fixed)-> sensor
    o_arm = hom(rot_x(0.3), (0, 0, 1))
    o_slider = hom(rot_z(0.5), (1, 0, 0))
    o_wrist = hom(np.eye(3), (0, 0.2, 0))
    o_wheel = hom(rot_y(-0.4), (0.5, 0.5, 0))
    o_sensor = hom(rot_z(1.0), (0, 0, 0.3))
    tree = KinematicTree(
        names=["base", "arm", "slider", "wrist", "wheel", "sensor"],
        parents=[-1, 0, 1, 2, 0, 1],
        origins=[np.eye(4), o_arm, o_slider, o_wrist, o_wheel, o_sensor],
        joint_types=["fixed", "revolute", "prismatic", "ball", "continuous", "fixed"],
        axes=[(1, 0, 0), (0, 0, 2), (1, 0, 0), (0, 0, 0), (0, 1, 0), (0, 0, 0)],
        lower=[-np.inf, -1.0, 0.0, -np.inf, -5.0, -np.inf],
        upper=[np.inf, 1.0, 0.5, 0.8, 5.0, np.inf],
    )
    return tree, (o_arm, o_slider, o_wrist, o_wheel, o_sensor)


def hand_fk(origins, theta, d, rotvec, phi):
    o_arm, o_slider, o_wrist, o_wheel, o_sensor = origins
    arm = o_arm @ hom(rot_z(theta))
    slider = arm @ o_slider @ hom(t=(d, 0, 0))
    angle = np.linalg.norm(rotvec)
    ball = rodrigues(rotvec, angle) if angle > 0 else np.eye(3)
    wrist = slider @ o_wrist @ hom(ball)
    wheel = o_wheel @ hom(rot_y(phi))
    sensor = arm @ o_sensor
    return np.stack([np.eye(4), arm, slider, wrist, wheel, sensor])


def test_layout_of_configuration():
    tree, _ = small_tree()
    assert tree.dof == 6
    assert tree.dof_names == ["arm", "slider", "wrist.x", "wrist.y", "wrist.z", "wheel"]
    assert tree.axes[1].tolist() == [0, 0, 1]            # normalised
    assert tree.lower[4] == -np.inf and tree.upper[4] == np.inf   # continuous ignores limits


def test_forward_kinematics_matches_hand_products():
    tree, origins = small_tree()
    q = np.array([0.7, 0.3, 0.1, -0.4, 0.25, 2.0])
    world = tree.forward_kinematics(q)
    expect = hand_fk(origins, 0.7, 0.3, np.array([0.1, -0.4, 0.25]), 2.0)
    np.testing.assert_allclose(world, expect, atol=1e-14)


def test_batch_equals_one_by_one_and_base():
    tree, origins = small_tree()
    rng = np.random.default_rng(3)
    q = rng.normal(size=(7, tree.dof))
    base = hom(rot_x(0.2) @ rot_z(-1.1), (3, -2, 1))
    batch = tree.forward_kinematics(q, base=base)
    assert batch.shape == (7, 6, 4, 4)
    for b in range(7):
        expect = base @ hand_fk(origins, q[b, 0], q[b, 1], q[b, 2:5], q[b, 5])
        np.testing.assert_allclose(batch[b], expect, atol=1e-13)


def test_ball_joint_takes_quaternion_or_rotation_vector():
    tree, origins = small_tree()
    axis, angle = np.array([1.0, 2.0, -2.0]) / 3.0, 2.5
    quat = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
    q_quat = tree.pack({"wrist": -quat})                 # the antipodal quaternion is the same turn
    q_vec = tree.pack({"wrist": axis * angle})
    np.testing.assert_allclose(q_quat, q_vec, atol=1e-14)
    np.testing.assert_allclose(tree.forward_kinematics(q_quat)[3],
                               hand_fk(origins, 0, 0, axis * angle, 0)[3], atol=1e-14)
    with pytest.raises(KinematicsError, match="takes 1 values, got 3"):
        tree.pack({"arm": [1, 2, 3]})
    with pytest.raises(KinematicsError, match="no joint named 'elbow'"):
        tree.pack({"elbow": 1.0})


def test_rotation_vectors_tiny_and_half_turn():
    for v in ([1e-12, 0, 0], [0, 0, 0], [0, np.pi, 0], [1e-300, 1e-300, 0]):
        q = rotvec_to_quaternions(v)
        assert np.isfinite(q).all() and abs(np.linalg.norm(q) - 1) < 1e-15
        np.testing.assert_allclose(quaternions_to_rotvec(q), v, atol=1e-15)
    # tiny angles are exact, not rounded to zero
    assert quaternions_to_rotvec(rotvec_to_quaternions([1e-20, 0, 0]))[0] == pytest.approx(1e-20, rel=1e-12)


def test_limits_clamp_and_report():
    tree, _ = small_tree()
    q = np.array([2.0, -1.0, 3.0, 0.0, 0.0, 100.0])
    clamped = tree.clamp(q)
    assert clamped[0] == 1.0 and clamped[1] == 0.0 and clamped[5] == 100.0
    assert np.linalg.norm(clamped[2:5]) == pytest.approx(0.8)          # ball angle <= upper
    np.testing.assert_allclose(clamped[2:5] / 0.8, [1, 0, 0])
    assert not tree.within_limits(q) and tree.within_limits(clamped)
    np.testing.assert_array_equal(tree.within_limits(np.stack([q, clamped])), [False, True])
    np.testing.assert_allclose(tree.forward_kinematics(q, clamp=True), tree.forward_kinematics(clamped))


def test_deform_matrices_are_pose_times_inverse_rest():
    tree, _ = small_tree()
    q = np.array([0.4, 0.2, 0.3, 0.0, -0.2, 1.0])
    deform = tree.deform_matrices(q)
    expect = tree.forward_kinematics(q) @ np.linalg.inv(tree.forward_kinematics())
    np.testing.assert_allclose(deform, expect, atol=1e-14)
    np.testing.assert_allclose(tree.deform_matrices(tree.zero()), np.broadcast_to(np.eye(4), (6, 4, 4)), atol=1e-15)


def test_blender_style_skeleton_from_rest_matrices():
    # Armature-space rest matrices; a posed bone is parent_pose @ (parent_rest^-1 rest) @ basis.
    rest = np.stack([hom(rot_x(-np.pi / 2), (0, 0, 0)), hom(rot_x(-np.pi / 2) @ rot_z(0.3), (0, 0, 1)),
                     hom(rot_y(0.5), (0.2, 0.1, 2))])
    tree = KinematicTree.from_rest_matrices(["root", "spine", "head"], [-1, 0, 1], rest)
    np.testing.assert_allclose(tree.rest_transforms(), rest, atol=1e-15)
    basis = [rot_z(0.2), rot_x(0.7), rodrigues([1, 1, 0], 0.4)]
    q = np.concatenate([[0, 0, 0.2], [0.7, 0, 0], np.array([1, 1, 0]) / np.sqrt(2) * 0.4])
    pose0 = rest[0] @ hom(basis[0])
    pose1 = pose0 @ np.linalg.inv(rest[0]) @ rest[1] @ hom(basis[1])
    pose2 = pose1 @ np.linalg.inv(rest[1]) @ rest[2] @ hom(basis[2])
    np.testing.assert_allclose(tree.forward_kinematics(q), np.stack([pose0, pose1, pose2]), atol=1e-14)


def test_deep_chain_batch():
    n = 40
    tree = KinematicTree([f"l{i}" for i in range(n)], np.arange(n) - 1,
                         np.broadcast_to(hom(t=(0, 0, 0.1)), (n, 4, 4)), ["revolute"] * n,
                         axes=np.tile([0, 1, 0], (n, 1)))
    q = np.full((3, n), 0.05)
    tip = tree.forward_kinematics(q)[:, -1]
    # A planar chain of equal links bending evenly: the tip angle is the sum of the joint angles.
    np.testing.assert_allclose(tip[:, :3, :3], np.broadcast_to(rot_y(0.05 * n), (3, 3, 3)), atol=1e-13)
    # Link k's offset is turned by the k joints before it.
    expect = sum(0.1 * rot_y(0.05 * k)[:, 2] for k in range(n))
    np.testing.assert_allclose(tip[:, :3, 3], np.broadcast_to(expect, (3, 3)), atol=1e-13)


def test_tree_errors_are_specific():
    eye = np.broadcast_to(np.eye(4), (2, 4, 4))
    with pytest.raises(KinematicsError, match="topological order"):
        KinematicTree(["a", "b"], [1, -1], eye, ["fixed", "fixed"])
    with pytest.raises(KinematicsError, match="unknown joint type 'hinge'"):
        KinematicTree(["a", "b"], [-1, 0], eye, ["fixed", "hinge"])
    with pytest.raises(KinematicsError, match="axis .* is zero"):
        KinematicTree(["a", "b"], [-1, 0], eye, ["fixed", "revolute"], axes=np.zeros((2, 3)))
    with pytest.raises(KinematicsError, match="not an interval"):
        KinematicTree(["a", "b"], [-1, 0], eye, ["fixed", "prismatic"], lower=[0, 1], upper=[0, -1])
    with pytest.raises(KinematicsError, match="origin is not finite"):
        KinematicTree(["a", "b"], [-1, 0], np.stack([np.eye(4), np.full((4, 4), np.nan)]), ["fixed"] * 2)
    tree, _ = small_tree()
    with pytest.raises(KinematicsError, match=r"expected \(6,\)"):
        tree.forward_kinematics(np.zeros(5))
    with pytest.raises(KinematicsError, match="non-finite"):
        tree.forward_kinematics(np.full(6, np.nan))


def test_from_joints_orders_and_rejects_bad_graphs():
    joint = lambda name, parent, child: {"name": name, "parent": parent, "child": child, "type": "fixed"}
    tree = KinematicTree.from_joints([joint("j2", "b", "c"), joint("j1", "a", "b")])
    assert tree.names == ("a", "b", "c") and tree.parents.tolist() == [-1, 0, 1]
    assert tree.joint_names == ("a", "j1", "j2")
    with pytest.raises(KinematicsError, match="two parent joints"):
        KinematicTree.from_joints([joint("j1", "a", "c"), joint("j2", "b", "c")])
    with pytest.raises(KinematicsError, match="one root"):
        KinematicTree.from_joints([joint("j1", "a", "b"), joint("j2", "c", "d")])
    with pytest.raises(KinematicsError, match="cycle"):
        KinematicTree.from_joints([joint("j1", "a", "b"), joint("j2", "c", "d"), joint("j3", "d", "c")], root="a")


# URDF --------------------------------------------------------------------------------------------

URDF = """<?xml version="1.0"?>
<robot name="test_arm">
  <link name="world"/>
  <link name="shoulder"><visual><geometry><mesh filename="package://x/shoulder.stl"/></geometry></visual></link>
  <link name="upper"/>
  <link name="slide"/>
  <link name="tool"/>
  <link name="wheel"/>
  <joint name="elbow" type="revolute">
    <parent link="shoulder"/><child link="upper"/>
    <origin xyz="0 0 0.5" rpy="0.1 -0.2 0.3"/>
    <axis xyz="0 1 0"/>
    <limit lower="-1.5" upper="2.0" effort="10" velocity="1"/>
  </joint>
  <joint name="mount" type="fixed">
    <parent link="world"/><child link="shoulder"/>
    <origin xyz="1 2 3"/>
  </joint>
  <joint name="extend" type="prismatic">
    <parent link="upper"/><child link="slide"/>
    <origin xyz="0.3 0 0" rpy="0 0 1.5707963267948966"/>
    <axis xyz="1 0 1"/>
    <limit lower="0" upper="0.4" effort="1" velocity="1"/>
  </joint>
  <joint name="tool_fix" type="fixed">
    <parent link="slide"/><child link="tool"/>
  </joint>
  <joint name="spin" type="continuous">
    <parent link="shoulder"/><child link="wheel"/>
    <origin rpy="1.5707963267948966 0 0"/>
    <axis xyz="0 0 -1"/>
  </joint>
</robot>
"""


def test_urdf_tree_and_forward_kinematics():
    tree = parse_urdf(URDF)
    assert tree.names[0] == "world" and set(tree.names) == {"world", "shoulder", "upper", "slide", "tool", "wheel"}
    i = {name: k for k, name in enumerate(tree.names)}
    assert tree.joint_types[i["upper"]] == "revolute" and tree.joint_names[i["upper"]] == "elbow"
    assert (tree.lower[i["upper"]], tree.upper[i["upper"]]) == (-1.5, 2.0)
    assert (tree.lower[i["slide"]], tree.upper[i["slide"]]) == (0.0, 0.4)
    assert tree.upper[i["wheel"]] == np.inf
    q = tree.pack({"elbow": 0.8, "extend": 0.25, "spin": -2.2})
    world = tree.forward_kinematics(q)
    # By hand: URDF rpy is roll about X, then pitch about Y, then yaw about Z (all fixed axes).
    shoulder = hom(t=(1, 2, 3))
    upper = shoulder @ hom(rot_z(0.3) @ rot_y(-0.2) @ rot_x(0.1), (0, 0, 0.5)) @ hom(rot_y(0.8))
    slide = upper @ hom(rot_z(np.pi / 2), (0.3, 0, 0)) @ hom(t=0.25 * np.array([1, 0, 1]) / np.sqrt(2))
    wheel = shoulder @ hom(rot_x(np.pi / 2)) @ hom(rot_z(2.2))
    for name, expect in [("shoulder", shoulder), ("upper", upper), ("slide", slide), ("tool", slide),
                         ("wheel", wheel)]:
        np.testing.assert_allclose(world[i[name]], expect, atol=1e-14, err_msg=name)
    # A point at the tool tip, by the same matrices
    np.testing.assert_allclose(world[i["tool"]] @ [0, 0, 0, 1], slide[:, 3], atol=1e-14)


def test_read_urdf_file(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text(URDF)
    tree = read_urdf(path)
    assert len(tree) == 6 and tree.dof == 3
    with pytest.raises(SplatFileError, match="no such file"):
        read_urdf(tmp_path / "missing.urdf")


@pytest.mark.parametrize("change, message", [
    (('type="continuous"', 'type="floating"'), "joint 'spin' has type 'floating'"),
    (('<limit lower="0" upper="0.4" effort="1" velocity="1"/>', ""), "joint 'extend' \\(prismatic\\) has no <limit>"),
    (('<child link="tool"/>', '<child link="toool"/>'), "child link 'toool' is not declared"),
    (('xyz="0.3 0 0"', 'xyz="0.3 0"'), "joint 'extend' origin xyz: '0.3 0' is not 3"),
    (('rpy="0.1 -0.2 0.3"', 'rpy="0.1 nan 0.3"'), "elbow' origin rpy"),
    (('lower="-1.5" upper="2.0"', 'lower="2.5" upper="2.0"'), "limit lower 2.5 is above upper 2.0"),
    (('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>'), "joint 'elbow' has a zero axis"),
    (('<link name="tool"/>', '<link name="tool"/><link name="orphan"/>'), "exactly one root link"),
    (('</robot>', '<joint name="spin" type="fixed"><parent link="tool"/><child link="world"/></joint></robot>'),
     "not unique"),
    (('<joint name="mount"', '<joint name="loop" type="fixed"><parent link="wheel"/><child link="world"/>'
      '</joint><joint name="mount"'), "one root link"),
    (('</robot>', ''), "not valid XML"),
])
def test_urdf_errors_name_the_problem(change, message):
    with pytest.raises(SplatFileError, match=message):
        parse_urdf(URDF.replace(*change), source="arm.urdf")
