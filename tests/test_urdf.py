"""Kinematic trees, forward kinematics and the URDF reader, against hand-multiplied matrices."""

import numpy as np
import pytest

from splatwright.core.kinematics import KinematicsError, KinematicTree, quaternions_to_rotvec, rotvec_to_quaternions
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
    assert tree.axes[1].tolist() == [0, 0, 1]  # normalised
    assert tree.lower[4] == -np.inf and tree.upper[4] == np.inf  # continuous ignores limits


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
    q_quat = tree.pack({"wrist": -quat})  # the antipodal quaternion is the same turn
    q_vec = tree.pack({"wrist": axis * angle})
    np.testing.assert_allclose(q_quat, q_vec, atol=1e-14)
    np.testing.assert_allclose(
        tree.forward_kinematics(q_quat)[3], hand_fk(origins, 0, 0, axis * angle, 0)[3], atol=1e-14
    )
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
    assert np.linalg.norm(clamped[2:5]) == pytest.approx(0.8)  # ball angle <= upper
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
    rest = np.stack(
        [
            hom(rot_x(-np.pi / 2), (0, 0, 0)),
            hom(rot_x(-np.pi / 2) @ rot_z(0.3), (0, 0, 1)),
            hom(rot_y(0.5), (0.2, 0.1, 2)),
        ]
    )
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
    tree = KinematicTree(
        [f"l{i}" for i in range(n)],
        np.arange(n) - 1,
        np.broadcast_to(hom(t=(0, 0, 0.1)), (n, 4, 4)),
        ["revolute"] * n,
        axes=np.tile([0, 1, 0], (n, 1)),
    )
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
    for name, expect in [("shoulder", shoulder), ("upper", upper), ("slide", slide), ("tool", slide), ("wheel", wheel)]:
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


@pytest.mark.parametrize(
    "change, message",
    [
        (('type="continuous"', 'type="hinge"'), "joint 'spin' has type 'hinge'"),
        (
            ('<limit lower="0" upper="0.4" effort="1" velocity="1"/>', '<limit lower="0" upper="x"/>'),
            "joint 'extend' limit upper: 'x' is not 1 numbers",
        ),
        (('<child link="tool"/>', '<child link="toool"/>'), "child link 'toool' is not declared"),
        (('xyz="0.3 0 0"', 'xyz="0.3 0"'), "joint 'extend' origin xyz: '0.3 0' is not 3"),
        (('rpy="0.1 -0.2 0.3"', 'rpy="0.1 nan 0.3"'), "elbow' origin rpy"),
        (
            (
                '<mesh filename="package://x/shoulder.stl"/>',
                '<mesh filename="package://x/shoulder.stl"/><box size="1"/>',
            ),
            None,
        ),
        (('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>'), "joint 'elbow' has a zero axis"),
        (('<link name="tool"/>', '<link name="tool"/><link name="orphan"/>'), "exactly one root link"),
        (
            ("</robot>", '<joint name="spin" type="fixed"><parent link="tool"/><child link="world"/></joint></robot>'),
            "not unique",
        ),
        (
            (
                '<joint name="mount"',
                '<joint name="loop" type="fixed"><parent link="wheel"/><child link="world"/>'
                '</joint><joint name="mount"',
            ),
            "one root link",
        ),
        (("</robot>", ""), "not valid XML"),
    ],
)
def test_urdf_errors_name_the_problem(change, message):
    if message is None:  # visuals are not the kinematic reader's business
        parse_urdf(URDF.replace(*change), source="arm.urdf")
        return
    with pytest.raises(SplatFileError, match=message):
        parse_urdf(URDF.replace(*change), source="arm.urdf")


def test_a_missing_limit_is_no_limit_with_a_warning():
    with pytest.warns(UserWarning, match="joint 'extend' \\(prismatic\\) has no <limit>"):
        tree = parse_urdf(URDF.replace('<limit lower="0" upper="0.4" effort="1" velocity="1"/>', ""))
    assert tree.upper[tree.names.index("slide")] == np.inf


# mimic, floating and planar joints; leniency; hard inputs ------------------------------------------

MIMIC_URDF = """
  <?xml version="1.0"?>
<robot name="gripper">
  <link name="base"/><link name="arm"/><link name="left"/><link name="right"/><link name="cam"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="arm"/><origin xyz="0 0 0.3" rpy="0 0.2 0"/><axis xyz="0 1 0"/>
    <limit lower="1.2" upper="-1.2"/>
  </joint>
  <joint name="left_slide" type="prismatic">
    <parent link="arm"/><child link="left"/><origin xyz="0.1 0.02 0"/><axis xyz="0 1 0"/>
    <limit lower="0" upper="0.04"/>
  </joint>
  <joint name="right_slide" type="prismatic">
    <parent link="arm"/><child link="right"/><origin xyz="0.1 -0.02 0"/><axis xyz="0 -1 0"/>
    <limit lower="0" upper="0.04"/><mimic joint="left_slide" multiplier="0.5" offset="0.01"/>
  </joint>
  <joint name="cam_tilt" type="revolute">
    <parent link="right"/><child link="cam"/><axis xyz="1 0 0"/><limit lower="-1" upper="1"/>
    <mimic joint="right_slide" multiplier="10"/>
  </joint>
</robot>
"""


def test_mimic_joints_follow_their_joint_in_dof_pack_and_fk():
    with pytest.warns(UserWarning, match="limit lower 1.2 is above upper -1.2; swapped"):
        tree = parse_urdf(MIMIC_URDF)  # blank line before <?xml, swapped limits
    i = {name: k for k, name in enumerate(tree.names)}
    assert tree.dof == 2 and tree.dof_names == ["shoulder", "left_slide"]
    assert (tree.lower[i["arm"]], tree.upper[i["arm"]]) == (-1.2, 1.2)
    q = tree.pack({"shoulder": 0.4, "left_slide": 0.03})
    with pytest.raises(KinematicsError, match="'right_slide' mimics 'left_slide': set that joint instead"):
        tree.pack({"right_slide": 0.01})
    world = tree.forward_kinematics(q)
    arm = hom(rot_y(0.2), (0, 0, 0.3)) @ hom(rot_y(0.4))
    right_value = 0.5 * 0.03 + 0.01
    right = arm @ hom(t=(0.1, -0.02, 0)) @ hom(t=(0, -right_value, 0))
    cam = right @ hom(rot_x(10 * right_value))  # a mimic of a mimic: 10 * (0.5 q + 0.01)
    np.testing.assert_allclose(world[i["right"]], right, atol=1e-15)
    np.testing.assert_allclose(world[i["cam"]], cam, atol=1e-15)
    np.testing.assert_allclose(
        tree.joint_values(q)[[i["left"], i["right"], i["cam"]]], [0.03, right_value, 10 * right_value], atol=1e-15
    )


@pytest.mark.filterwarnings("ignore:.*swapped")
def test_mimic_errors_are_named():
    with pytest.raises(SplatFileError, match="mimics 'nowhere', which is not a joint"):
        parse_urdf(MIMIC_URDF.replace('mimic joint="left_slide"', 'mimic joint="nowhere"'))
    loop = MIMIC_URDF.replace(
        '<limit lower="0" upper="0.04"/>\n  </joint>',
        '<limit lower="0" upper="0.04"/><mimic joint="right_slide"/>\n  </joint>',
        1,
    )
    with pytest.raises(SplatFileError, match="cycle of mimic joints"):
        parse_urdf(loop)
    with pytest.raises(SplatFileError, match="mimic multiplier"):
        parse_urdf(MIMIC_URDF.replace('multiplier="0.5"', 'multiplier="nan"'))


FREE_URDF = """<robot name="free">
  <link name="world"/><link name="body"/><link name="cart"/><link name="head"/>
  <joint name="float" type="floating"><parent link="world"/><child link="body"/>
    <origin xyz="1 0 0" rpy="0 0 0.5"/></joint>
  <joint name="table" type="planar"><parent link="body"/><child link="cart"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 0 1"/></joint>
  <joint name="neck" type="spherical"><parent link="cart"/><child link="head"/><origin xyz="0 0 0.1"/></joint>
</robot>"""


def test_floating_planar_and_spherical_joints_match_hand_products():
    tree = parse_urdf(FREE_URDF)
    assert tree.dof == 12 and tree.joint_types[1:] == ("floating", "planar", "ball")
    assert tree.dof_names[:9] == [
        "float.x",
        "float.y",
        "float.z",
        "float.rx",
        "float.ry",
        "float.rz",
        "table.a",
        "table.b",
        "table.theta",
    ]
    t, axis, angle = np.array([0.3, -0.2, 0.5]), np.array([1.0, 2.0, 2.0]) / 3, 0.9
    neck = np.array([0.2, -0.1, 0.3])
    q = tree.pack({"float": np.concatenate([t, axis * angle]), "table": [0.4, -0.7, 1.1], "neck": neck})
    body = hom(rot_z(0.5), (1, 0, 0)) @ hom(rodrigues(axis, angle), t)
    cart = body @ hom(t=(0, 0, 0.2)) @ hom(rot_z(1.1), (0.4, -0.7, 0))
    head = cart @ hom(t=(0, 0, 0.1)) @ hom(rodrigues(neck, np.linalg.norm(neck)))
    np.testing.assert_allclose(tree.forward_kinematics(q)[1:], np.stack([body, cart, head]), atol=1e-15)
    # the floating joint also takes x, y, z and a quaternion, or a rigid 4x4 matrix
    quat = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
    np.testing.assert_allclose(tree.pack({"float": np.concatenate([t, quat])})[:6], q[:6], atol=1e-15)
    np.testing.assert_allclose(tree.pack({"float": hom(rodrigues(axis, angle), t)})[:6], q[:6], atol=1e-15)
    with pytest.raises(KinematicsError, match="not a rigid transform"):
        tree.pack({"float": np.diag([2.0, 1, 1, 1])})
    with pytest.raises(KinematicsError, match="takes 3 values"):
        tree.pack({"table": [1.0, 2.0]})


def test_non_finite_values_and_bases_are_refused():
    tree, _ = small_tree()
    with pytest.raises(KinematicsError, match="joint 'arm': value nan is not finite"):
        tree.pack({"arm": np.nan})
    with pytest.raises(KinematicsError, match="base matrix has non-finite values"):
        tree.forward_kinematics(tree.zero(), base=np.full((4, 4), np.nan))
    with pytest.raises(KinematicsError, match="base has shape"):
        tree.forward_kinematics(tree.zero(), base=np.eye(3))
    with pytest.raises(KinematicsError, match="not affine"):
        tree.forward_kinematics(tree.zero(), base=np.ones((4, 4)))


def test_compiled_and_numpy_forward_kinematics_agree(monkeypatch):
    from splatwright.core import kinematics

    tree = parse_urdf(
        FREE_URDF.replace('<link name="head"/>', '<link name="head"/><link name="tip"/>').replace(
            "</robot>",
            '<joint name="tip" type="revolute"><parent link="head"/><child link="tip"/><axis xyz="0 1 1"/>'
            '<origin xyz="0.1 0 0"/><limit lower="-1" upper="1"/></joint></robot>',
        )
    )
    q = np.random.default_rng(4).normal(size=(3000, tree.dof))  # above the two-thread batch size
    base = hom(rot_x(0.3), (1, 2, 3))
    compiled = tree.forward_kinematics(q, base=base)
    single = tree.forward_kinematics(q[7], base=base)
    monkeypatch.setattr(kinematics, "_fk_kernel", lambda: None)
    numpy_path = tree.forward_kinematics(q, base=base)
    np.testing.assert_allclose(compiled, numpy_path, atol=1e-14)
    np.testing.assert_allclose(single, numpy_path[7], atol=1e-14)


def test_urdf_reading_is_linear_in_links():
    # a 20,000-link chain (reading was quadratic: minutes); its tip is the sum of the offsets
    n = 20_000
    links = "".join(f'<link name="l{k}"/>' for k in range(n))
    joints = "".join(
        f'<joint name="j{k}" type="revolute"><parent link="l{k}"/><child link="l{k + 1}"/>'
        f'<origin xyz="0 0 0.001"/><axis xyz="0 1 0"/><limit lower="-1" upper="1"/></joint>'
        for k in range(n - 1)
    )
    tree = parse_urdf(f"<robot name='chain'>{links}{joints}</robot>")
    assert len(tree) == n and tree.dof == n - 1 and len(tree._levels) == n
    tip = tree.forward_kinematics(np.full(n - 1, 1e-4))[-1]
    expect = sum(0.001 * rot_y(1e-4 * k)[:, 2] for k in range(n - 1))
    np.testing.assert_allclose(tip[:3, 3], expect, rtol=1e-9)


def test_forward_kinematics_matches_yourdfpy(tmp_path):
    yourdfpy = pytest.importorskip("yourdfpy")
    rng = np.random.default_rng(5)
    # a random tree of revolute, continuous, prismatic, fixed and mimic joints, written as URDF
    n, parts, kinds, kinds_of = 30, [], ["revolute", "continuous", "prismatic", "fixed"], {}
    for k in range(1, n):
        kind = kinds[rng.integers(4)]
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)  # (yourdfpy takes a prismatic axis as written)
        mimic = (
            f'<mimic joint="j{k - 1}" multiplier="{rng.uniform(-2, 2):.6f}" offset="{rng.uniform(-0.3, 0.3):.6f}"/>'
            if k > 1
            and kind != "fixed"
            and kinds_of.get(k - 1) in ("revolute", "prismatic", "continuous")
            and rng.uniform() < 0.3
            else ""
        )  # (yourdfpy follows one mimic, not chains of them)
        kinds_of[k] = "mimic" if mimic else kind
        parts.append(
            f'<joint name="j{k}" type="{kind}"><parent link="l{rng.integers(k)}"/><child link="l{k}"/>'
            f'<origin xyz="{" ".join(f"{v:.6f}" for v in rng.normal(0, 0.3, 3))}" '
            f'rpy="{" ".join(f"{v:.6f}" for v in rng.uniform(-3, 3, 3))}"/>'
            f'<axis xyz="{" ".join(f"{v:.17g}" for v in axis)}"/><limit lower="-3" upper="3"/>{mimic}</joint>'
        )
    links = "".join(f"<link name='l{k}'/>" for k in range(n))
    text = f'<robot name="r">{links}{"".join(parts)}</robot>'
    path = tmp_path / "random.urdf"
    path.write_text(text)
    ours = read_urdf(path)
    theirs = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    assert ours.dof == len(theirs.actuated_joint_names)
    for _ in range(5):
        q = rng.uniform(-2, 2, ours.dof)
        theirs.update_cfg(dict(zip(theirs.actuated_joint_names, q)))
        world = ours.forward_kinematics(ours.pack(dict(zip(theirs.actuated_joint_names, q))))
        for k, name in enumerate(ours.names):
            np.testing.assert_allclose(world[k], theirs.get_transform(name, "l0"), atol=1e-12, err_msg=name)


def test_a_package_the_urdf_lies_in_is_named_as_the_package_path_to_pass(tmp_path):
    """ROS's layout (robot/urdf/robot.urdf naming package://robot/meshes/...): the package's folder is
    outside the URDF's folder, so it is read only from a package path, which the error names."""
    from splatwright.io.urdf import read_description

    (tmp_path / "robot" / "urdf").mkdir(parents=True)
    (tmp_path / "robot" / "meshes").mkdir()
    (tmp_path / "robot" / "meshes" / "a.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    urdf = tmp_path / "robot" / "urdf" / "robot.urdf"
    urdf.write_text(
        '<robot name="r"><link name="base"><visual><geometry>'
        '<mesh filename="package://robot/meshes/a.obj"/></geometry></visual></link></robot>'
    )
    with pytest.raises(SplatFileError, match=f"a package path of '{tmp_path}' would allow it"):
        read_description(urdf)
    description = read_description(urdf, package_paths=[tmp_path])
    assert [v.path for v in description.visuals] == [tmp_path / "robot" / "meshes" / "a.obj"]
