"""Collision at scene scale: a 2,000-splat arm on a table in a 1M-splat room, the Franka Panda of
pybullet's data made of splats, and the Blender demo rig.

Rows: the broad-phase build; soft overlap cost + gradient per configuration at several cutoffs,
each against brute force over the whole environment on a subsample of robot splats (the baseline
is that brute force, timed on the subsample and scaled to the whole robot); the joint-space
gradient; exact ellipsoid contacts; occupancy and signed distance queries; and per-link proxies
with the cost error they bring.

The Panda (its visual meshes as splats, io.urdf.read_robot) against python-fcl on the same meshes
and a box: collision verdicts (agreement, which way they err) and clearance (bias, worst case),
in random configurations; then standing on the room's table, free and reaching through it, every
query timed with and without 1,000 floaters scattered over a kilometre. The demo rig's contacts
(about 106k touching pairs) are timed against the code before (loaded from git, bench/_before.py).
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import Row, Timing, paired, print_rows, timeit  # noqa: E402

from splatwright.core import SplatCloud, geometry  # noqa: E402
from splatwright.core import collision as col
from splatwright.core.kinematics import KinematicTree, axis_angle_matrices, transforms  # noqa: E402

TOPIC = "collision"


# the scene ---------------------------------------------------------------------------------------


def _frames(normals, rng):
    """Random tangent frames (columns u, v, n) around unit normals."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    a = rng.uniform(0, 2 * np.pi, len(n))[:, None]
    u = np.cos(a) * t1 + np.sin(a) * np.cross(n, t1)
    return np.stack([u, np.cross(n, u), n], axis=2)


def surface_splats(points, normals, rng, sigma):
    """Flat splats on a surface: tangent sigmas log-uniform in `sigma`, 0.1-0.3 of that across."""
    n = len(points)
    t = np.exp(rng.uniform(np.log(sigma[0]), np.log(sigma[1]), (n, 2)))
    scales = np.column_stack([t, t.min(axis=1) * rng.uniform(0.1, 0.3, n)])
    q = geometry.matrices_to_quaternions(_frames(normals, rng))
    return SplatCloud.from_activated(points, q, scales, 1 / (1 + np.exp(-rng.normal(3, 2, n))))


def _box_faces(boxes, n, rng):
    """n points spread by area over the faces of axis-aligned boxes, with outward normals."""
    faces = [
        (np.asarray(lo, float), np.asarray(hi, float), ax, side)
        for lo, hi in boxes
        for ax in range(3)
        for side in (0, 1)
    ]
    area = np.array([np.prod(np.delete(hi - lo, ax)) for lo, hi, ax, _ in faces])
    pts, nrm = [], []
    for (lo, hi, ax, side), c in zip(faces, rng.multinomial(n, area / area.sum())):
        p = rng.uniform(lo, hi, (c, 3))
        p[:, ax] = hi[ax] if side else lo[ax]
        normal = np.zeros((c, 3))
        normal[:, ax] = 1.0 if side else -1.0
        pts.append(p)
        nrm.append(normal)
    return np.concatenate(pts), np.concatenate(nrm)


TABLE_TOP = 0.75


def room(n=1_000_000, seed=0):
    """A 6 x 5 x 3 m room (walls, floor, ceiling), a table with legs, a box on it and a crate on the
    floor: flat splats of 0.4-2.5 cm on every surface, plus 1% larger floaters (3-10 cm)."""
    rng = np.random.default_rng(seed)
    boxes = [
        ((0, 0, -0.01), (6, 5, 0)),
        ((0, 0, 3), (6, 5, 3.01)),
        ((-0.01, 0, 0), (0, 5, 3)),
        ((6, 0, 0), (6.01, 5, 3)),
        ((0, -0.01, 0), (6, 0, 3)),
        ((0, 5, 0), (6, 5.01, 3)),
        ((2.0, 2.0, TABLE_TOP - 0.03), (3.2, 2.8, TABLE_TOP)),
        *[((x, y, 0), (x + 0.05, y + 0.05, TABLE_TOP - 0.03)) for x in (2.05, 3.1) for y in (2.05, 2.7)],
        ((2.3, 2.2, TABLE_TOP), (2.6, 2.5, TABLE_TOP + 0.2)),
        ((4.0, 1.0, 0), (4.6, 1.5, 0.5)),
    ]
    n_surface = int(n * 0.99)
    surfaces = surface_splats(*_box_faces(boxes, n_surface, rng), rng, (0.004, 0.025))
    m = n - n_surface
    floaters = SplatCloud.from_activated(
        rng.uniform((0, 0, 0), (6, 5, 3), (m, 3)),
        rng.normal(size=(m, 4)),
        np.exp(rng.uniform(np.log(0.03), np.log(0.1), (m, 3))),
        rng.uniform(0.05, 0.5, m),
    )
    return SplatCloud.concatenate([surfaces, floaters])


# (name, joint type, axis, origin in the parent's frame, link radius, link length)
ARM = [
    ("base", "fixed", (0, 0, 1), (2.9, 2.55, TABLE_TOP), 0.06, 0.10),
    ("shoulder", "revolute", (0, 0, 1), (0, 0, 0.10), 0.05, 0.15),
    ("upper_arm", "revolute", (0, 1, 0), (0, 0, 0.15), 0.045, 0.35),
    ("forearm", "revolute", (0, 1, 0), (0, 0, 0.35), 0.04, 0.30),
    ("wrist", "revolute", (0, 1, 0), (0, 0, 0.30), 0.035, 0.08),
    ("hand", "revolute", (0, 0, 1), (0, 0, 0.08), 0.04, 0.06),
    ("finger_a", "prismatic", (1, 0, 0), (0.02, 0, 0.06), 0.012, 0.06),
    ("finger_b", "prismatic", (-1, 0, 0), (-0.02, 0, 0.06), 0.012, 0.06),
]


def arm(n=2000, seed=1):
    """A 7-joint arm standing on the table: its kinematic tree and n splats on its links' cylinders
    (world frame at rest, rigidly bound to links)."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(
        names=[a[0] for a in ARM],
        parents=[-1] + [0, 1, 2, 3, 4, 5, 5],
        origins=[transforms(translations=a[3]) for a in ARM],
        joint_types=[a[1] for a in ARM],
        axes=[a[2] for a in ARM],
        lower=[-np.inf, -3, -2, -2.5, -2, -3, 0, 0],
        upper=[np.inf, 3, 2, 2.5, 2, 3, 0.03, 0.03],
    )
    area = np.array([2 * np.pi * r * length for *_, r, length in ARM])
    counts = rng.multinomial(n, area / area.sum())
    pts, nrm, link = [], [], []
    rest = tree.rest_transforms()
    for k, ((*_, r, length), c) in enumerate(zip(ARM, counts)):
        a = rng.uniform(0, 2 * np.pi, c)
        radial = np.column_stack([np.cos(a), np.sin(a), np.zeros(c)])
        local = r * radial + np.outer(rng.uniform(0, length, c), [0, 0, 1])
        pts.append(local @ rest[k, :3, :3].T + rest[k, :3, 3])
        nrm.append(radial @ rest[k, :3, :3].T)
        link.append(np.full(c, k))
    cloud = surface_splats(np.concatenate(pts), np.concatenate(nrm), rng, (0.006, 0.02))
    return tree, col.Gaussians.from_cloud(cloud, links=np.concatenate(link))


def configurations(tree, count, seed=2):
    """Reaching poses: the arm leans over the table so the forearm and hand come near its top."""
    rng = np.random.default_rng(seed)
    q = np.zeros((count, tree.dof))
    q[:, 0] = rng.uniform(-2.5, 2.5, count)  # shoulder yaw
    q[:, 1] = rng.uniform(0.9, 1.4, count)  # shoulder pitch
    q[:, 2] = rng.uniform(0.6, 1.3, count)  # elbow
    q[:, 3] = rng.uniform(-0.5, 0.8, count)  # wrist pitch
    q[:, 4] = rng.uniform(-3, 3, count)  # wrist roll
    q[:, 5:] = rng.uniform(0, 0.03, (count, 2))  # fingers
    return q


# measurements ------------------------------------------------------------------------------------


def _subsample(robot, reference, rng, count):
    """Robot splats to check against brute force: half of them touching something, half at random."""
    touching = np.flatnonzero(reference.per_gaussian > 1e-9 * reference.per_gaussian.max())
    pick = rng.choice(touching, min(count // 2, len(touching)), replace=False)
    rest = np.setdiff1d(np.arange(len(robot)), pick)
    return np.sort(np.concatenate([pick, rng.choice(rest, count - len(pick), replace=False)]))


def _errors(result, exact, sub):
    cost = abs(result.per_gaussian[sub].sum() - exact.cost) / exact.cost
    grad = np.abs(result.grad_means[sub] - exact.grad_means).max() / np.abs(exact.grad_means).max()
    return cost, grad


def _per(t, n):
    """A timing of n configurations at once, per configuration."""
    return Timing(t.median / n, t.spread / n, t.runs)


# the Panda: against fcl, in the room, with floaters ------------------------------------------------


def panda(max_splats=55_000):
    """The Panda of pybullet's data as a splat robot, with its description (for fcl)."""
    import warnings

    from _oracles import panda_urdf

    from splatwright.io.urdf import read_description, read_robot

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its OBJ files name MTL files it does not ship
        return read_robot(panda_urdf(), max_splats=max_splats), read_description(panda_urdf())


def box_splats(size, centre, count=20_000):
    from splatwright.core.mesh_to_splats import mesh_to_splats
    from splatwright.core.robot import primitive

    v, f = primitive("box", size)
    return mesh_to_splats(v + centre, f, max_splats=count)


def random_configurations(tree, count, seed):
    rng = np.random.default_rng(seed)
    lower = np.where(np.isfinite(tree.lower), tree.lower, -np.pi)[tree._limited]
    upper = np.where(np.isfinite(tree.upper), tree.upper, np.pi)[tree._limited]
    return rng.uniform(lower, upper, (count, tree.dof))


def _box_gap(points, size, centre):
    """Distance from points to an axis-aligned box (0 inside)."""
    return np.linalg.norm(np.maximum(np.abs(points - centre) - np.asarray(size) / 2, 0.0), axis=1)


def fcl_rows(robot, description, quick):
    """Verdicts and clearance of the splat Panda against fcl on its own meshes, near a box."""
    from _oracles import run_oracle

    size, centre = np.array([0.3, 0.8, 0.5]), np.array([0.55, 0.0, 0.25])
    env = col.EnvironmentIndex(box_splats(size, centre))
    qs = random_configurations(robot.tree, 24 if quick else 120, seed=7)
    worlds = robot.tree.forward_kinematics(qs)
    index = {name: i for i, name in enumerate(robot.tree.names)}
    visuals = description.visuals
    fcl = run_oracle(
        "fcl_distances",
        files=np.array([str(v.path) for v in visuals]),
        links=np.array([index[v.link] for v in visuals]),
        origins=np.array([v.origin for v in visuals]),
        scales=np.array([v.scale for v in visuals]),
        worlds=worlds,
        box_size=size,
        box_pose=np.eye(4) + np.pad(centre[:, None], ((0, 1), (3, 0))),
        repeat=3,
    )
    rest = robot.gaussians()
    rest_inv = np.linalg.inv(robot.tree.rest_transforms())
    hit, clearance, t_free, t_contact = [], [], [], []
    near = 0.1  # clearance compared where the true distance is below this
    for world in worlds:
        posed = col.pose_robot(rest, world @ rest_inv)
        t0 = time.perf_counter()
        contacts = col.ellipsoid_contacts(posed, env, k=3.0)
        (t_contact if len(contacts) else t_free).append(time.perf_counter() - t0)
        hit.append(len(contacts) > 0)
        close = _box_gap(posed.means, size, centre) < near + 0.05
        sdf = col.signed_distance(env, posed.means[close], k=3.0, max_distance=near) if close.any() else [near]
        clearance.append(float(np.min(sdf)))
    hit, clearance = np.array(hit), np.array(clearance)
    truth_hit, truth = fcl["hit"], fcl["distance"]
    compare = ~truth_hit & ~hit & (truth < near)
    diff = clearance[compare] - truth[compare]
    median = lambda t: Timing(float(np.median(t)), float(np.ptp(t) / 2), len(t)) if t else Timing(0.0, 0.0, 0)
    fcl_time = Timing(float(np.median(fcl["collide_time"])), float(np.ptp(fcl["collide_time"]) / 2), len(worlds))
    verdicts = {
        "agree": float(np.mean(hit == truth_hit)),
        "false free": int((~hit & truth_hit).sum()),
        "false hit": int((hit & ~truth_hit).sum()),
    }
    fcl_us = f"{fcl_time.median * 1e6:.0f} us per configuration (exact meshes against a box primitive)"
    rows = [
        Row(
            TOPIC,
            f"Panda ({len(rest):,} splats) vs box: verdicts against fcl, contacts when free",
            median(t_free),
            error={
                "clearance bias m": float(diff.mean()) if len(diff) else float("nan"),
                "clearance worst m": float(np.abs(diff).max()) if len(diff) else float("nan"),
                "clearance above truth m": float(diff.max()) if len(diff) else float("nan"),
            },
            extra={
                **verdicts,
                "configs": len(worlds),
                "in contact (fcl)": int(truth_hit.sum()),
                "clearance compared": int(compare.sum()),
                "fcl collide": fcl_us,
            },
        ),
        Row(
            TOPIC,
            "Panda vs box: contacts in configurations that touch",
            median(t_contact),
            extra={**verdicts, "fcl collide": fcl_us},
        ),
    ]
    return rows


def floaters(count=1000, seed=8):
    """Splats scattered over a kilometre around the room."""
    rng = np.random.default_rng(seed)
    sizes = np.exp(rng.uniform(np.log(0.004), np.log(0.1), (count, 3)))
    return SplatCloud.from_activated(
        rng.uniform(-500, 500, (count, 3)) + [3, 2.5, 1.5],
        rng.normal(size=(count, 4)),
        sizes,
        rng.uniform(0.05, 0.9, count),
    )


PANDA_ON_TABLE = transforms(translations=(2.9, 2.55, TABLE_TOP + 0.05))  # on a 5 cm plate: free means free


def room_rows(robot, env, quick):
    """The Panda on the table: every query free (standing up) and in deep contact (reaching through
    the table), in the room and in the room with floaters; contacts also with the code before."""
    from _before import module_before

    before = module_before("core/collision.py")
    rest = robot.gaussians()
    rest_inv = np.linalg.inv(robot.tree.rest_transforms())
    deform = lambda q: robot.tree.forward_kinematics(q, base=PANDA_ON_TABLE) @ rest_inv
    free = robot.tree.pack({"panda_joint4": -0.3})  # clear of the table (the room's own floaters touch it)
    deep = robot.tree.pack({"panda_joint2": 1.6, "panda_joint4": -0.4, "panda_joint6": 1.5})
    poses = {"free": col.pose_robot(rest, deform(free)), "deep contact": col.pose_robot(rest, deform(deep))}
    indexes = {
        "room": col.EnvironmentIndex(env),
        "room + 1,000 floaters over 1 km": col.EnvironmentIndex(SplatCloud.concatenate([env, floaters()])),
    }
    rng = np.random.default_rng(9)
    probes = rng.uniform([2.3, 2.0, 0.5], [3.5, 3.1, 1.6], (10_000, 3))
    queries = {
        "cost+gradient": lambda r, ix: col.overlap(r, ix),
        "contacts, 3 sigma": lambda r, ix: col.ellipsoid_contacts(r, ix, k=3.0),
        "signed distance of 2k robot splats, max 0.1 m": lambda r, ix: col.signed_distance(
            ix, r.means[:: len(r) // 2000][:2000], max_distance=0.1
        ),
        "occupancy, 10k points": lambda r, ix: col.occupancy(ix, probes),
    }
    rows = []
    repeat = 3 if quick else 5
    ((room, floating),) = [tuple(indexes.values())]
    for state, posed in poses.items():
        for name, query in queries.items():
            # the room and the room with floaters timed alternately, so both meet the same load
            t_room, t_float = paired(lambda: query(posed, room), lambda: query(posed, floating), repeat)
            extra = {"robot": state}
            if name.startswith("contacts"):
                extra["pairs"] = len(query(posed, room))
                if state == "deep contact":
                    t_free, t_deep = paired(lambda: query(poses["free"], room), lambda: query(posed, room), repeat)
                    extra["deep / free"] = f"{t_deep.median / t_free.median:.2f}x (target <= 3x)"
                old_robot = before.Gaussians(posed.means, posed.covs, posed.weights, posed.links)
                old_index = before.EnvironmentIndex(env)
                baseline = timeit(lambda: before.ellipsoid_contacts(old_robot, old_index, k=3.0), repeat=1)
                rows.append(
                    Row(
                        TOPIC,
                        f"Panda {state}, room: {name}",
                        t_room,
                        baseline,
                        extra={**extra, "baseline": "the code before"},
                    )
                )
            else:
                rows.append(Row(TOPIC, f"Panda {state}, room: {name}", t_room, extra=extra))
            rows.append(
                Row(
                    TOPIC,
                    f"Panda {state}, room + 1,000 floaters over 1 km: {name}",
                    t_float,
                    t_room,
                    extra={
                        "robot": state,
                        "baseline": "the room alone, timed alternately",
                        "floaters / room": f"{t_float.median / t_room.median:.2f}x (target <= 1.5x)",
                    },
                )
            )
    return rows


def sdf_rows(robot, quick):
    """Signed distance from 11k points around the Panda to its own (flat) splats, and to round splats
    at the same centres: time against the splats within reach, and against the code before."""
    from _before import module_before

    before = module_before("core/collision.py")
    flat = robot.cloud
    round_ = flat.replace(log_scales=np.repeat(flat.log_scales.mean(axis=1, keepdims=True), 3, axis=1))
    rng = np.random.default_rng(10)
    lo, hi = flat.positions.min(axis=0), flat.positions.max(axis=0)
    points = rng.uniform(lo - 0.2, hi + 0.2, (3000 if quick else 11_000, 3))
    rows = []
    for label, cloud in (("flat", flat), ("round", round_)):
        index, old_index = col.EnvironmentIndex(cloud), before.EnvironmentIndex(cloud)
        for reach in (0.05, 0.1, 0.5):
            t = timeit(lambda: col.signed_distance(index, points, max_distance=reach), repeat=2 if quick else 3)
            near = _pairs_within(index, points, reach)
            baseline = None
            if reach < 0.5 or not quick:
                baseline = timeit(
                    lambda: before.signed_distance(old_index, points, max_distance=reach), repeat=1, warmup=0
                )
            rows.append(
                Row(
                    TOPIC,
                    f"signed distance, {len(points):,} points to the Panda's {label} splats, max {reach:g} m",
                    t,
                    baseline,
                    extra={
                        "splats within max (pairs)": near,
                        "baseline": "the code before",
                        "ns per pair": f"{t.median / max(near, 1) * 1e9:.0f}",
                    },
                )
            )
    return rows


def _pairs_within(index, points, reach):
    """How many (point, splat) pairs have their centres within `reach`."""

    def count(i, j):
        d = (points[i, 0] - index.mx[j]) ** 2 + (points[i, 1] - index.my[j]) ** 2 + (points[i, 2] - index.mz[j]) ** 2
        return int((d <= reach * reach).sum())

    return sum(index.query(points, lambda lv: np.full(len(points), reach), count))


def demo_rig_clouds(arm_splats=20_000, env_splats=20_000):
    """The Blender demo rig's arm and environment splats, built as the add-on builds them (its prisms,
    floor and box through core.mesh_to_splats; its geometry helpers import bpy but do not use it),
    with the arm bent as at frame 12 (Upper and Fore tipped towards the box, Hand twisted)."""
    from splatwright.core.mesh_to_splats import mesh_to_splats
    from splatwright.core.skinning import Binding, skin
    from splatwright.splat_addon.convert import demo_rig as rig

    arm = mesh_to_splats(
        *_triangles([rig.prism(r, s, rig.JOINTS[i], rig.JOINTS[i + 1]) for i, (r, s, _, _) in enumerate(rig.LINKS)]),
        max_splats=arm_splats,
    )
    half = rig.FLOOR_SIZE / 2
    centre, edge = rig.ENVIRONMENT_BOX
    corners = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], float) * edge / 2 + centre
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    floor = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], float)
    env = mesh_to_splats(*_triangles([(floor, [[0, 1, 2, 3]], None), (corners, quads, None)]), max_splats=env_splats)
    world = np.broadcast_to(np.eye(4), (len(rig.BONES), 4, 4)).copy()
    for b, name in enumerate(rig.BONES):  # bones run up z; pose Euler X tips, Z twists
        rx, _, rz = rig.POSE.get(name, (0.0, 0.0, 0.0))
        head = transforms(translations=(0, 0, rig.JOINTS[b]))
        turn = transforms(axis_angle_matrices([1.0, 0, 0], rx) @ axis_angle_matrices([0, 0, 1.0], rz))
        world[b] = (world[b - 1] if b else np.eye(4)) @ head @ turn @ np.linalg.inv(head)
    weights = rig.bone_weights(arm.positions[:, 2].astype(np.float64))
    return skin(arm, Binding.from_dense(weights, max_influences=4), world), env


def _triangles(parts):
    vertices, faces = [], []
    for v, f, _ in parts:
        offset = sum(len(x) for x in vertices)
        vertices.append(np.asarray(v, float))
        faces += [[p[0] + offset, p[k] + offset, p[k + 1] + offset] for p in f for k in range(1, len(p) - 1)]
    return np.concatenate(vertices), np.array(faces)


def demo_rig_rows(quick):
    """ellipsoid_contacts on the demo rig's splats at frame 12, CPU seconds per frame (all threads):
    today's compiled path and its NumPy path (what Blender's Python runs) against the code before."""
    from _before import module_before

    from splatwright.core.collision import contacts

    before = module_before("core/collision.py")
    arm, env = demo_rig_clouds()
    index, old_index = col.EnvironmentIndex(env), before.EnvironmentIndex(env)
    cpu = lambda fn: min(_cpu_seconds(fn) for _ in range(2 if quick else 3))
    old = cpu(lambda: before.ellipsoid_contacts(arm, old_index, k=3.0))
    rows = []
    for label, kernel in (("compiled", contacts._contact_kernel), ("NumPy", lambda: None)):
        saved, contacts._contact_kernel = contacts._contact_kernel, kernel
        try:
            ours = cpu(lambda: col.ellipsoid_contacts(arm, index, k=3.0))
            pairs = len(col.ellipsoid_contacts(arm, index, k=3.0))
        finally:
            contacts._contact_kernel = saved
        rows.append(
            Row(
                TOPIC,
                f"demo rig contacts per frame, {label} (CPU s)",
                Timing(ours, 0.0, 1),
                Timing(old, 0.0, 1),
                extra={"pairs": pairs, "target": "4x faster than before", "baseline": "the code before"},
            )
        )
    return rows


def _cpu_seconds(fn):
    start = time.process_time()
    fn()
    return time.process_time() - start


def run(quick=False):
    rows = []
    n_env, n_conf, n_sub = (100_000, 2, 24) if quick else (1_000_000, 4, 64)
    env = room(n_env)
    tree, robot_rest = arm()
    qs = configurations(tree, n_conf)
    rng = np.random.default_rng(3)

    index = None

    def build():
        nonlocal index
        index = col.EnvironmentIndex(env)

    t_build = timeit(build, repeat=3)
    cells = sum(int(np.prod(lv.dims)) for lv in index.levels)
    rows.append(
        Row(TOPIC, f"build index, {n_env:,} splats", t_build, extra={"levels": len(index.levels), "cells": cells})
    )

    deform = tree.forward_kinematics(qs) @ np.linalg.inv(tree.rest_transforms())
    robots = [col.pose_robot(robot_rest, d) for d in deform]
    env_gauss = col.Gaussians.from_cloud(env)

    # brute force over the whole environment, on a subsample of robot splats per configuration
    checks, brute_times = [], []
    for robot in robots:
        ref = col.overlap(robot, index, cutoff=10.0, bound=False)
        sub = _subsample(robot, ref, rng, n_sub)
        t0 = time.perf_counter()
        exact = col.overlap_all_pairs(robot.subset(sub), env_gauss)
        brute_times.append((time.perf_counter() - t0) * len(robot) / len(sub))
        checks.append((sub, exact))
    baseline = Timing(float(np.median(brute_times)), float(np.ptp(brute_times) / 2), len(brute_times))

    for cutoff in (4.0, 5.0, col.DEFAULT_CUTOFF, 7.0, 8.0):
        errors, times, bounds, pairs = [], [], [], []
        for robot, (sub, exact) in zip(robots, checks):
            t = timeit(lambda: col.overlap(robot, index, cutoff), repeat=5)
            times.append(t.median)
            r = col.overlap(robot, index, cutoff)
            errors.append(_errors(r, exact, sub))
            bounds.append(r.relative_bound)
            pairs.append(r.pairs)
        errors = np.array(errors)
        label = " (default)" if cutoff == col.DEFAULT_CUTOFF else ""
        rows.append(
            Row(
                TOPIC,
                f"cost+gradient, cutoff {cutoff:g}{label}",
                Timing(float(np.median(times)), float(np.ptp(times) / 2), len(times)),
                baseline,
                error={
                    "cost rel err": float(errors[:, 0].max()),
                    "grad rel err": float(errors[:, 1].max()),
                    "rel bound": float(max(bounds)),
                },
                extra={"pairs": int(np.median(pairs)), "robot": len(robot_rest)},
            )
        )

    t = timeit(lambda: [col.overlap_at(tree, q, robot_rest, index) for q in qs], repeat=3)
    rows.append(Row(TOPIC, "cost+dC/dq (FK, pose, chain rule), cutoff 6", _per(t, len(qs)), extra={"dof": tree.dof}))

    contacts = None

    def hard():
        nonlocal contacts
        contacts = [col.ellipsoid_contacts(robot, index, k=3.0) for robot in robots]

    t = timeit(hard, repeat=3)
    rows.append(
        Row(
            TOPIC,
            "hard contacts, 3-sigma ellipsoids",
            _per(t, len(robots)),
            extra={"pairs": int(np.median([len(c) for c in contacts]))},
        )
    )

    probes = rng.uniform([1.8, 1.8, 0.5], [3.4, 3.0, 1.2], (10_000, 3))
    t = timeit(lambda: col.occupancy(index, probes), repeat=3)
    occ = col.occupancy(index, probes)
    rows.append(Row(TOPIC, "occupancy, 10k points, cutoff 6", t, error={"max bound": float(occ.bound.max())}))
    t = timeit(lambda: col.signed_distance(index, probes[:2000], k=3.0, max_distance=0.5), repeat=3)
    rows.append(Row(TOPIC, "signed distance, 2k points, 3 sigma, max 0.5 m", t))

    full_time = np.median([timeit(lambda: col.overlap(r, index, bound=False), repeat=5).median for r in robots])
    for per_link in (4, 16, 64):
        proxies = col.fit_proxies(robot_rest, per_link=per_link, reference_sigma=index.typical_sigma)
        posed = [col.pose_robot(proxies, d) for d in deform]
        t = [timeit(lambda: col.overlap(p, index, bound=False), repeat=3).median for p in posed]
        err = [col.proxy_error(r, p, index) for r, p in zip(robots, posed)]
        rows.append(
            Row(
                TOPIC,
                f"proxies, {per_link} per link ({len(proxies)} Gaussians)",
                Timing(float(np.median(t)), float(np.ptp(t) / 2), len(t)),
                Timing(float(full_time), 0.0, len(robots)),
                error={"cost rel err": float(max(err))},
            )
        )
    robot, description = panda()
    rows += fcl_rows(robot, description, quick)
    rows += room_rows(robot, env, quick)
    rows += sdf_rows(robot, quick)
    rows += demo_rig_rows(quick)
    return rows


if __name__ == "__main__":
    quick = "--quick" in sys.argv
    print_rows(run(quick=quick))
