"""Robots made of splats: URDF visuals (primitives, STL, OBJ and DAE meshes, package:// paths,
materials) converted to splats bound to their links, posed by forward kinematics, and the
urdf2splats verb. References: the primitives' closed forms, STL files written by hand, and
hand-multiplied link transforms."""

import numpy as np
import pytest

from splatwright.cli import main
from splatwright.core import color
from splatwright.core.robot import primitive
from splatwright.io import read_splats
from splatwright.io.common import SplatFileError
from splatwright.io.meshes import read_mesh_file
from splatwright.io.urdf import read_description, read_robot

C0 = 0.28209479177387814


def write_stl(path, vertices, faces):
    """A binary STL written by hand (80-byte header, count, then normal + 3 corners + 2 bytes)."""
    tri = np.asarray(vertices, np.float32)[np.asarray(faces)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    record = np.zeros(len(tri), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    record["n"], record["v"] = normal, tri
    with open(path, "wb") as f:
        f.write(b"splatwright test".ljust(80, b" "))
        f.write(np.uint32(len(tri)).tobytes())
        f.write(record.tobytes())


TETRA = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float), [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])

URDF = """<?xml version="1.0"?>
<robot name="testbot">
  <material name="red"><color rgba="0.9 0.1 0.1 1"/></material>
  <link name="base">
    <visual><origin xyz="0 0 0.05"/><geometry><box size="0.4 0.3 0.1"/></geometry><material name="red"/></visual>
  </link>
  <link name="upper">
    <visual><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.05" length="0.4"/></geometry>
      <material name="teal"><color rgba="0.1 0.6 0.6 1"/></material></visual>
  </link>
  <link name="ball"><visual><geometry><sphere radius="0.06"/></geometry><material name="teal"/></visual></link>
  <link name="claw">
    <visual><origin xyz="0.02 0 0" rpy="0 0 0.3"/>
      <geometry><mesh filename="package://toolkit/meshes/tetra.stl" scale="0.1 0.2 0.05"/></geometry>
      <material name="red"/></visual>
  </link>
  <link name="plate"><visual><geometry><mesh filename="plate.obj"/></geometry><material name="red"/></visual></link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="ball"/><origin xyz="0 0 0.4"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2"/></joint>
  <joint name="grip" type="prismatic"><parent link="ball"/><child link="claw"/><origin xyz="0 0 0.06"/>
    <axis xyz="0 0 1"/><limit lower="0" upper="0.1"/></joint>
  <joint name="grip_twin" type="prismatic"><parent link="ball"/><child link="plate"/><origin xyz="0 0.1 0"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.1"/><mimic joint="grip" multiplier="-1"/></joint>
</robot>
"""

PLATE_OBJ = """mtllib plate.mtl
v -0.05 -0.05 0
v 0.05 -0.05 0
v 0.05 0.05 0
v -0.05 0.05 0
usemtl green
f 1 2 3 4
"""


@pytest.fixture
def robot_dir(tmp_path):
    (tmp_path / "robot").mkdir()
    (tmp_path / "robot" / "testbot.urdf").write_text(URDF)
    (tmp_path / "robot" / "plate.obj").write_text(PLATE_OBJ)
    (tmp_path / "robot" / "plate.mtl").write_text("newmtl green\nKd 0.1 0.7 0.2\n")
    meshes = tmp_path / "share" / "toolkit" / "meshes"
    meshes.mkdir(parents=True)
    write_stl(meshes / "tetra.stl", *TETRA)
    return tmp_path


def test_primitives_are_closed_and_match_their_volumes():
    for kind, size, volume, tolerance in (
        ("box", (0.4, 0.3, 0.1), 0.012, 1e-15),
        ("cylinder", (0.05, 0.4), np.pi * 0.05**2 * 0.4, 3e-3),
        ("sphere", (0.06,), 4 / 3 * np.pi * 0.06**3, 1e-2),
    ):
        v, f = primitive(kind, size)
        t = v[f]
        signed = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6  # outward winding: > 0
        assert signed == pytest.approx(volume, rel=tolerance)
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()  # watertight


def test_description_resolves_packages_materials_and_scales(robot_dir):
    urdf = robot_dir / "robot" / "testbot.urdf"
    with pytest.raises(SplatFileError, match="mesh 'package://toolkit/meshes/tetra.stl' not found"):
        read_description(urdf)
    d = read_description(urdf, package_paths=[robot_dir / "share"])
    assert d.name == "testbot" and [v.link for v in d.visuals] == ["base", "upper", "ball", "claw", "plate"]
    base, upper, ball, claw, plate = d.visuals
    assert base.geometry == "box" and base.size == (0.4, 0.3, 0.1) and base.rgba == (0.9, 0.1, 0.1, 1.0)
    assert ball.rgba == (0.1, 0.6, 0.6, 1.0)  # declared inside another link
    assert claw.path == robot_dir / "share" / "toolkit" / "meshes" / "tetra.stl"
    np.testing.assert_array_equal(claw.scale, [0.1, 0.2, 0.05])
    assert plate.path == robot_dir / "robot" / "plate.obj"
    np.testing.assert_allclose(upper.origin[:3, 3], [0, 0, 0.2])


def test_stl_read_through_trimesh_matches_the_written_triangles(robot_dir):
    mesh = read_mesh_file(robot_dir / "share" / "toolkit" / "meshes" / "tetra.stl")
    tri = mesh.vertices[mesh.faces]
    expect = TETRA[0][np.array(TETRA[1])]
    assert sorted(map(tuple, tri.reshape(-1, 9).round(6))) == sorted(map(tuple, expect.reshape(-1, 9).round(6)))
    with pytest.raises(SplatFileError, match="no such file"):
        read_mesh_file(robot_dir / "missing.stl")
    (robot_dir / "broken.stl").write_bytes(b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0")
    with pytest.raises(SplatFileError, match="broken.stl"):
        read_mesh_file(robot_dir / "broken.stl")


DAE = """<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit name="meter" meter="1"/><up_axis>Z_UP</up_axis></asset>
  <library_effects><effect id="blue-fx"><profile_COMMON><technique sid="common"><lambert>
    <diffuse><color>0.2 0.6 0.8 1</color></diffuse></lambert></technique></profile_COMMON></effect></library_effects>
  <library_materials><material id="blue" name="blue"><instance_effect url="#blue-fx"/></material></library_materials>
  <library_geometries><geometry id="quad"><mesh>
    <source id="quad-pos"><float_array id="quad-pos-array" count="12">0 0 0 1 0 0 1 1 0 0 1 0</float_array>
      <technique_common><accessor source="#quad-pos-array" count="4" stride="3">
        <param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
      </accessor></technique_common></source>
    <vertices id="quad-vtx"><input semantic="POSITION" source="#quad-pos"/></vertices>
    <triangles material="mat" count="2"><input semantic="VERTEX" source="#quad-vtx" offset="0"/>
      <p>0 1 2 0 2 3</p></triangles>
  </mesh></geometry></library_geometries>
  <library_visual_scenes><visual_scene id="scene"><node id="n">
    <matrix>2 0 0 0.5  0 3 0 0  0 0 1 0.25  0 0 0 1</matrix>
    <instance_geometry url="#quad"><bind_material><technique_common>
      <instance_material symbol="mat" target="#blue"/></technique_common></bind_material></instance_geometry>
  </node></visual_scene></library_visual_scenes>
  <scene><instance_visual_scene url="#scene"/></scene>
</COLLADA>
"""


def test_dae_read_through_trimesh_keeps_node_transforms_and_colour(tmp_path):
    path = tmp_path / "quad.dae"
    path.write_text(DAE)
    mesh = read_mesh_file(path)
    tri = mesh.vertices[mesh.faces]
    # the unit quad scaled by (2, 3) and moved by (0.5, 0, 0.25): area 6, all at z = 0.25
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert area == pytest.approx(6.0, rel=1e-6)
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [0.5, 0, 0.25], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [2.5, 3, 0.25], atol=1e-6)
    np.testing.assert_allclose(mesh.materials[mesh.face_materials[0]].base_color, (0.2, 0.6, 0.8), atol=1 / 255)


def box_distance(p, size):
    """Distance from points on or in an axis-aligned centred box to its surface."""
    half = np.asarray(size) / 2
    return np.min(half - np.abs(p), axis=1)


def test_splat_robot_sits_on_its_visuals_with_their_colours(robot_dir):
    robot = read_robot(robot_dir / "robot" / "testbot.urdf", [robot_dir / "share"], max_splats=6000)
    names = robot.tree.names
    link = {n: np.flatnonzero(robot.links == names.index(n)) for n in names}
    assert all(len(v) > 20 for v in link.values()) and len(robot.cloud) == 6000
    np.testing.assert_array_equal(robot.cloud.extras["link"], robot.links)
    p = robot.cloud.positions.astype(np.float64)
    rgb = 0.5 + C0 * robot.cloud.sh[:, 0]
    # base: on the box, 5 cm up; red as written (display sRGB)
    assert np.abs(box_distance(p[link["base"]] - [0, 0, 0.05], (0.4, 0.3, 0.1))).max() < 1e-6
    np.testing.assert_allclose(rgb[link["base"]], np.broadcast_to([0.9, 0.1, 0.1], (len(link["base"]), 3)), atol=2e-3)
    # upper: on the cylinder between z = 0.1 and 0.5 (the shoulder is 0.1 up, the visual 0.2 more)
    q = p[link["upper"]]
    radial = np.hypot(q[:, 0], q[:, 1])
    side = (q[:, 2] > 0.1 + 1e-6) & (q[:, 2] < 0.5 - 1e-6)
    assert (radial[side] > 0.05 * np.cos(np.pi / 48) - 1e-6).all() and (radial <= 0.05 + 1e-6).all()
    assert q[:, 2].min() > 0.1 - 1e-6 and q[:, 2].max() < 0.5 + 1e-6
    # ball: on the sphere at the elbow
    r = np.linalg.norm(p[link["ball"]] - [0, 0, 0.5], axis=1)
    assert (r > 0.06 * np.cos(np.pi / 24) - 1e-6).all() and (r < 0.06 + 1e-6).all()
    np.testing.assert_allclose(rgb[link["ball"]].mean(axis=0), [0.1, 0.6, 0.6], atol=2e-3)
    # claw: on the scaled, turned tetrahedron 6 cm above the elbow
    turn = np.array([[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])
    local = (p[link["claw"]] - [0.02, 0, 0.56]) @ turn / [0.1, 0.2, 0.05]  # back to the unit tetrahedron
    on_face = np.min(np.abs(np.column_stack([local, 1 - local.sum(axis=1)])), axis=1)
    assert on_face.max() < 1e-5 and (local > -1e-5).all()
    # plate: its own OBJ material wins over the URDF's red (Kd is linear, splats hold display sRGB)
    np.testing.assert_allclose(rgb[link["plate"]].mean(axis=0), color.linear_to_srgb([0.1, 0.7, 0.2]), atol=2e-3)


def hom(r=np.eye(3), t=(0, 0, 0)):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def test_posed_robot_moves_each_link_by_its_transform(robot_dir):
    robot = read_robot(robot_dir / "robot" / "testbot.urdf", [robot_dir / "share"], max_splats=3000)
    q = robot.tree.pack({"shoulder": 0.7, "elbow": -0.4, "grip": 0.05})
    posed = robot.pose(q)
    c, s = np.cos(0.7), np.sin(0.7)
    ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    c, s = np.cos(-0.4), np.sin(-0.4)
    rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    upper = hom(t=(0, 0, 0.1)) @ hom(ry)
    ball = upper @ hom(t=(0, 0, 0.4)) @ hom(rx)
    claw = ball @ hom(t=(0, 0, 0.06 + 0.05))
    plate = ball @ hom(t=(0, 0.1 - 0.05, 0))  # the mimic joint moves by -grip
    rest = {
        "upper": hom(t=(0, 0, 0.1)),
        "ball": hom(t=(0, 0, 0.5)),
        "claw": hom(t=(0, 0, 0.56)),
        "plate": hom(t=(0, 0.1, 0.5)),
    }
    for name, world in (("upper", upper), ("ball", ball), ("claw", claw), ("plate", plate)):
        pick = robot.links == robot.tree.names.index(name)
        m = world @ np.linalg.inv(rest[name])
        expect = robot.cloud.positions[pick] @ m[:3, :3].T + m[:3, 3]
        np.testing.assert_allclose(posed.positions[pick], expect, atol=2e-7, err_msg=name)
    g = robot.gaussians()
    assert len(g) == len(robot.cloud) and (g.links == robot.links).all()


def test_urdf2splats_verb_writes_the_posed_robot(robot_dir, capsys):
    out = robot_dir / "bot.ply"
    urdf = str(robot_dir / "robot" / "testbot.urdf")
    code = main(
        [
            "urdf2splats",
            urdf,
            str(out),
            "--package-path",
            str(robot_dir / "share"),
            "--max-splats",
            "3000",
            "--joint",
            "shoulder=0.7",
            "--joint",
            "grip=0.05",
        ]
    )
    printed = capsys.readouterr().out
    assert code == 0 and "wrote 3000 splats on 5 of 5 links of 'testbot' (3 degrees of freedom)" in printed
    written = read_splats(out)
    robot = read_robot(urdf, [robot_dir / "share"], max_splats=3000)
    expect = robot.pose(robot.tree.pack({"shoulder": 0.7, "grip": 0.05}))
    np.testing.assert_allclose(written.positions, expect.positions, atol=1e-7)
    np.testing.assert_array_equal(written.extras["link"], robot.links)
    # a mesh it cannot find, an unknown joint, a mimic joint and a malformed --joint are refused by name
    assert main(["urdf2splats", urdf, str(out)]) == 1
    assert "tetra.stl' not found" in capsys.readouterr().err
    args = ["urdf2splats", urdf, str(out), "--package-path", str(robot_dir / "share"), "--max-splats", "100"]
    assert main(args + ["--joint", "knee=1"]) == 1
    assert "no joint named 'knee'" in capsys.readouterr().err
    assert main(args + ["--joint", "grip_twin=0.01"]) == 1
    assert "mimics 'grip'" in capsys.readouterr().err
    assert main(args + ["--joint", "shoulder"]) == 1
    assert "--joint expects NAME=VALUE" in capsys.readouterr().err


def test_everything_works_where_numba_cannot_be_imported(robot_dir):
    """Blender's Python has no numba: forward kinematics, contacts and distances take their NumPy
    paths there and give the same numbers as the compiled ones here."""
    import json
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(f"""
        import json, sys
        class NoNumba:
            def find_spec(self, name, path=None, target=None):
                if name == "numba" or name.startswith("numba."):
                    raise ImportError("numba is blocked in this test")
        sys.meta_path.insert(0, NoNumba())
        import numpy as np
        from splatwright.core import collision as col, jit, kinematics
        from splatwright.core.collision import contacts
        from splatwright.io.urdf import read_robot
        assert kinematics._fk_kernel() is None and contacts._contact_kernel() is None
        assert "numba is blocked" in jit.status("splatwright.core.kinematics:_fk_pass")
        urdf, share = {str(robot_dir / "robot" / "testbot.urdf")!r}, {str(robot_dir / "share")!r}
        robot = read_robot(urdf, [share], max_splats=2000)
        q = robot.tree.pack({{"shoulder": 2.0, "elbow": -1.9}})          # folded onto the base
        posed = col.pose_robot(robot.gaussians(), robot.deform(q))
        hits = col.ellipsoid_contacts(posed, robot.cloud, k=3.0)
        sdf = col.signed_distance(robot.cloud, np.array([[0.3, 0.2, 0.4], [0, 0, 0.8]]), max_distance=1.0)
        print(json.dumps({{"fk": robot.tree.forward_kinematics(q).tolist(), "pairs": len(hits),
                          "sigma": float(hits.sigma.sum()), "sdf": sdf.tolist()}}))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    there = json.loads(done.stdout.strip().splitlines()[-1])
    from splatwright.core import collision as col

    robot = read_robot(robot_dir / "robot" / "testbot.urdf", [robot_dir / "share"], max_splats=2000)
    q = robot.tree.pack({"shoulder": 2.0, "elbow": -1.9})
    posed = col.pose_robot(robot.gaussians(), robot.deform(q))
    hits = col.ellipsoid_contacts(posed, robot.cloud, k=3.0)
    assert there["pairs"] == len(hits) > 100
    np.testing.assert_allclose(there["fk"], robot.tree.forward_kinematics(q), atol=1e-14)
    np.testing.assert_allclose(there["sigma"], hits.sigma.sum(), rtol=1e-9)
    np.testing.assert_allclose(
        there["sdf"],
        col.signed_distance(robot.cloud, np.array([[0.3, 0.2, 0.4], [0, 0, 0.8]]), max_distance=1.0),
        rtol=1e-12,
    )
