"""Articulation: skinning speed against error, forward kinematics speed, and the bent-cylinder check.

Skinning: 1M splats, SH degree 3, 4 influences on 20 bones, one pose, linear blend (LBS) and dual
quaternion (DQS); then the full pose again with two of the bones scaled (37% of the splats feel
them and need re-diagonalised covariances). Each of centres only, centres + covariances, and everything
including SH is timed against a straightforward float64 baseline timed in the same run (alternating
runs, so both meet the same machine load): dense gathers and einsum, SVD polar decomposition and
eigh re-diagonalisation over the whole cloud at once, on one thread. The baseline's float64 result
is the exact reference for the error columns (ours stores float32): centres relative to the cloud's
extent, covariances relative to each splat's largest entry, colours as the largest difference over
one random view direction per splat.

Forward kinematics: a random 50-link tree (revolute, continuous, prismatic, ball, fixed joints),
batches of 1000 configurations, against a per-configuration, per-joint loop of 4x4 products.

Bent cylinder: an analytic cylinder with a checker pattern and a view-dependent rim, bent 70 degrees
at a smooth-weighted joint. Splats made from its rest mesh are skinned and rendered against splats
made directly from the bent mesh (the same skinning applied to its vertices); PSNR for full
skinning, without SH rotation, with the literal blended-matrix covariance, and centres only. Two
independent samplings of the same surface give the floor that sampling alone allows.
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from common import Row, Timing, machine, paired, print_rows, timeit  # noqa: E402
from helpers import random_cloud  # noqa: E402

from splatwright.core import geometry  # noqa: E402
from splatwright.core import sh as shmod
from splatwright.core.articulation import (
    Binding,
    BonePose,
    KinematicTree,
    axis_angle_matrices,  # noqa: E402
    skin,
    skin_centres,
    transforms,
)

TOPIC = "articulation"


# timing -------------------------------------------------------------------------------------------


def cpu_seconds(fn):
    """CPU time of one call, all threads: on a machine shared with other jobs it shows what the
    call would take on idle cores (about this divided by the cores it keeps busy)."""
    start = time.process_time()
    fn()
    return time.process_time() - start


def armature(n_bones=20, seed=1, scaled=False):
    """Rest and pose matrices in Blender's terms; with `scaled`, bones 3 and 7 also scale (one of
    them non-uniformly), which sends every splat they touch through re-diagonalisation."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(2, n_bones, 3))
    axes /= np.linalg.norm(axes, axis=2, keepdims=True)
    rest = transforms(axis_angle_matrices(axes[0], rng.uniform(-np.pi, np.pi, n_bones)), rng.normal(size=(n_bones, 3)))
    turn = transforms(axis_angle_matrices(axes[1], rng.uniform(-1.5, 1.5, n_bones)), rng.normal(0, 0.3, (n_bones, 3)))
    pose = rest @ turn
    if scaled:
        pose[3] = pose[3] @ np.diag([1.3, 0.8, 1.1, 1.0])
        pose[7] = pose[7] @ np.diag([0.7, 0.7, 0.7, 1.0])
    return rest, pose


def workload(n, seed=0, scaled=False):
    cloud = random_cloud(n, sh_degree=3, seed=seed, spread=2.0)
    rng = np.random.default_rng(seed + 1)
    rest, pose = armature(scaled=scaled)
    indices = np.stack([rng.choice(len(rest), 4, replace=False) for _ in range(min(n, 4096))])
    indices = indices[rng.integers(0, len(indices), n)]
    binding = Binding.from_weights(indices, rng.uniform(0.05, 1.0, (n, 4)))
    return cloud, binding, BonePose.from_blender(rest, pose)


# straightforward float64 baselines ----------------------------------------------------------------


def baseline_lbs(cloud, binding, pose):
    """Centres, per-splat linear maps (for covariances) and rotations (for SH), whole cloud at once."""
    w = binding.weights.astype(np.float64)
    w /= w.sum(axis=1, keepdims=True)
    _, stretch = geometry.polar_decomposition(pose.deform[:, :3, :3])
    blended, stretch_sum = np.zeros((len(w), 4, 4)), np.zeros((len(w), 3, 3))
    for j in range(binding.influences):
        blended += w[:, j, None, None] * pose.deform[binding.indices[:, j]]
        stretch_sum += w[:, j, None, None] * stretch[binding.indices[:, j]]
    p = cloud.positions.astype(np.float64)
    centres = np.einsum("nij,nj->ni", blended[:, :3, :3], p) + blended[:, :3, 3]
    u, _, vt = np.linalg.svd(blended[:, :3, :3])
    turn = u @ vt
    return centres, turn @ stretch_sum, turn


def _blender_dq(rest, deform):
    """Blender's mat4_to_dquat for every bone: (quaternion, translation quaternion, 4x4 scale, scaled?)."""
    out = []
    for basemat, mat in zip(rest, deform):
        base_rs = mat @ basemat
        lin = mat[:3, :3]
        size = np.linalg.norm(base_rs[:3, :3], axis=0)
        if np.abs(lin.T @ lin - np.eye(3)).max() > 1e-6 or np.linalg.det(lin) < 0 or ((size - 1) ** 2).sum() > 1e-8:
            y = base_rs[:3, 1] / np.linalg.norm(base_rs[:3, 1])
            z = np.cross(base_rs[:3, 0], y)
            z /= np.linalg.norm(z)
            base_r = transforms(np.stack([np.cross(y, z), y, z], axis=1), base_rs[:3, 3])
            r = base_r @ np.linalg.inv(basemat)
            scale, scaled = basemat @ np.linalg.inv(base_r) @ base_rs @ np.linalg.inv(basemat), True
        else:
            r, scale, scaled = mat, np.eye(4), False
        q = geometry.matrices_to_quaternions(r[:3, :3])
        t = np.concatenate([[0.0], r[:3, 3]])
        out.append((q, 0.5 * _qmul(t, q), scale, scaled))
    return [np.array(v) for v in zip(*out)]


def _qmul(a, b):
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate(
        [aw * bw - np.sum(av * bv, axis=-1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], axis=-1
    )


def baseline_dqs(cloud, binding, pose):
    """Blender's Preserve Volume, vectorised over splats in the plainest way."""
    quat, dual, scale, scaled = _blender_dq(pose.rest, pose.deform)
    w = binding.weights.astype(np.float64)
    w /= w.sum(axis=1, keepdims=True)
    p = cloud.positions.astype(np.float64)
    n = len(p)
    real_sum, dual_sum = np.zeros((n, 4)), np.zeros((n, 4))
    scale_sum, scale_weight = np.zeros((n, 3, 3)), np.zeros(n)
    for j in range(binding.influences):
        b, wj = binding.indices[:, j], w[:, j]
        q, d, s = quat[b], dual[b].copy(), scale[b]
        hs = scaled[b]
        shift = np.einsum("nij,nj->ni", s[:, :3, :3], p) + s[:, :3, 3] - p
        d[hs] += 0.5 * _qmul(q[hs], np.concatenate([np.zeros((hs.sum(), 1)), shift[hs]], axis=1))
        scale_sum[hs] += wj[hs, None, None] * s[hs, :3, :3]
        scale_weight[hs] += wj[hs]
        signed = np.where(np.sum(real_sum * q, axis=1) < 0, -wj, wj)[:, None]
        real_sum += signed * q
        dual_sum += signed * d
    norm2 = np.sum(real_sum**2, axis=1)
    turn = geometry.quaternions_to_matrices(real_sum)
    translation = 2 * _qmul(dual_sum, real_sum * [1, -1, -1, -1])[:, 1:] / norm2[:, None]
    centres = np.einsum("nij,nj->ni", turn, p) + translation
    stretch = scale_sum + (1 - scale_weight)[:, None, None] * np.eye(3)
    return centres, turn @ stretch, turn


def baseline_cloud(cloud, fn, binding, pose, parts):
    """The baseline's result in the form skin() gives, float64, for `parts` in centres/gaussians/all."""
    centres, maps, turn = fn(cloud, binding, pose)
    if parts == "centres":
        return centres, None, None
    factor = maps @ (geometry.quaternions_to_matrices(cloud.rotations) * cloud.scales[:, None, :])
    cov = factor @ np.swapaxes(factor, 1, 2)
    vals, vecs = np.linalg.eigh(cov)  # re-diagonalise every splat
    rotations = geometry.matrices_to_quaternions(vecs * np.where(np.linalg.det(vecs) < 0, -1.0, 1.0)[:, None, None])
    log_scales = np.log(np.sqrt(np.maximum(vals, 1e-300)))
    sh = shmod.rotate(cloud.sh, turn) if parts == "all" else None
    return centres, (rotations, log_scales, cov), (sh, turn)


def errors(cloud, ours, exact, parts, rng):
    """Error columns of our result against the float64 baseline."""
    extent = np.abs(exact[0]).max()
    err = {
        "centre_rel_err": float(
            np.abs(np.asarray(ours.positions if parts != "centres" else ours, np.float64) - exact[0]).max() / extent
        )
    }
    if parts == "centres":
        return err
    mine = geometry.covariances(ours.rotations, ours.scales)
    ref = exact[1][2]
    err["cov_rel_err"] = float((np.abs(mine - ref).max(axis=(1, 2)) / np.abs(ref).max(axis=(1, 2))).max())
    if parts == "all":
        d = rng.normal(size=(len(cloud), 3))
        rest_dirs = np.einsum("nji,nj->ni", exact[2][1], d)  # R^T d
        err["color_abs_err"] = float(np.abs(shmod.evaluate(ours.sh, d) - shmod.evaluate(cloud.sh, rest_dirs)).max())
    return err


def skinning_rows(n, repeat, scaled=False):
    cloud, binding, pose = workload(n, scaled=scaled)
    rng = np.random.default_rng(5)
    rows = []
    for mode, fn in (("lbs", baseline_lbs), ("dqs", baseline_dqs)):
        for parts in ("all",) if scaled else ("centres", "gaussians", "all"):
            if parts == "centres":
                ours = lambda: skin_centres(cloud.positions, binding, pose, mode)  # noqa: E731
            else:
                ours = lambda: skin(cloud, binding, pose, mode, sh=parts == "all")  # noqa: E731
            base_t, ours_t = paired(lambda: baseline_cloud(cloud, fn, binding, pose, parts), ours, repeat)
            exact = baseline_cloud(cloud, fn, binding, pose, parts)
            label = {
                "centres": "centres only",
                "gaussians": "centres + covariances",
                "all": "centres + covariances + SH",
            }[parts]
            bones = "20 bones, 2 scaled" if scaled else "20 bones turning"
            rows.append(
                Row(
                    TOPIC,
                    f"{mode.upper()} {label}, {n:,} splats, degree 3, 4 influences, {bones}",
                    ours_t,
                    base_t,
                    error=errors(cloud, ours(), exact, parts, rng),
                    extra={"cpu_s": f"{cpu_seconds(ours):.3g}", "baseline": "float64 einsum/SVD/eigh, one pass"},
                )
            )
    return rows


def blender_float32_rows(n, repeat):
    """One LBS frame posed by Blender-like matrices (rest and pose stored as float32, as Blender's
    bone.matrix_local and pose_bone.matrix are; turning bones only) against DQS of the same frame in
    the same run, and the same frame with the tolerance before (1e-9, below float32's rounding: every
    turned bone took the per-splat stretch path). Errors against the float64 baseline."""
    from splatwright.core import skinning

    cloud, binding, exact_pose = workload(n)
    pose = BonePose.from_blender(
        exact_pose.rest.astype(np.float32), (exact_pose.deform @ exact_pose.rest).astype(np.float32)
    )
    _, stretch = geometry.polar_decomposition(pose.deform[:, :3, :3])
    noise = np.abs(stretch - np.eye(3)).max() / np.finfo(np.float32).eps
    lbs = lambda: skin(cloud, binding, pose, "lbs")  # noqa: E731
    dqs = lambda: skin(cloud, binding, pose, "dqs")  # noqa: E731
    dqs_t, lbs_t = paired(dqs, lbs, repeat, clock=time.process_time)
    rng = np.random.default_rng(5)
    err = errors(cloud, lbs(), baseline_cloud(cloud, baseline_lbs, binding, pose, "all"), "all", rng)
    label = f"{n:,} splats, degree 3, 4 influences, 20 bones turning, Blender float32 matrices"
    rows = [
        Row(
            TOPIC,
            f"LBS centres + covariances + SH, {label} (vs DQS, CPU s)",
            lbs_t,
            dqs_t,
            error=err,
            extra={
                "baseline": "DQS of the same frame, same run (CPU s)",
                "target": "within 1.5x of DQS (speed-up >= 0.67)",
                "stretch_eps": f"{noise:.2g} (rigid below {skinning.RIGID_TOLERANCE / np.finfo(np.float32).eps:g})",
            },
        )
    ]
    saved, skinning.RIGID_TOLERANCE = skinning.RIGID_TOLERANCE, 1e-9
    try:
        strict = BonePose.from_blender(pose.rest, pose.deform @ pose.rest)
        before_t = timeit(
            lambda: skin(cloud, binding, strict, "lbs"), repeat=max(1, repeat // 2), clock=time.process_time
        )
    finally:
        skinning.RIGID_TOLERANCE = saved
    rows.append(
        Row(
            TOPIC,
            f"LBS centres + covariances + SH, {label}, rigid tolerance 1e-9 (before; vs DQS, CPU s)",
            before_t,
            dqs_t,
            extra={"baseline": "DQS of the same frame, same run (CPU s)"},
        )
    )
    return rows


# forward kinematics -------------------------------------------------------------------------------


def random_tree(n=50, seed=2):
    rng = np.random.default_rng(seed)
    kinds = ["fixed"] + list(rng.choice(["revolute", "continuous", "prismatic", "ball", "revolute"], n - 1))
    axes = rng.normal(size=(n, 3))
    origins = transforms(
        axis_angle_matrices(axes / np.linalg.norm(axes, axis=1, keepdims=True), rng.uniform(-1, 1, n)),
        rng.normal(0, 0.3, (n, 3)),
    )
    parents = [-1] + [int(rng.integers(max(0, i - 3), i)) for i in range(1, n)]
    return KinematicTree([f"link{i}" for i in range(n)], parents, origins, kinds, axes=rng.normal(size=(n, 3)))


def loop_fk(tree, q):
    """One configuration at a time, one joint at a time: what a first implementation does."""
    out = np.empty((len(q), len(tree), 4, 4))
    for b, config in enumerate(q):
        for i, (kind, parent) in enumerate(zip(tree.joint_types, tree.parents)):
            o = tree.dof_offsets[i]
            motion = np.eye(4)
            if kind in ("revolute", "continuous"):
                motion[:3, :3] = axis_angle_matrices(tree.axes[i], config[o])
            elif kind == "ball":
                angle = np.linalg.norm(config[o : o + 3])
                if angle > 0:
                    motion[:3, :3] = axis_angle_matrices(config[o : o + 3] / angle, angle)
            elif kind == "prismatic":
                motion[:3, 3] = tree.axes[i] * config[o]
            local = tree.origins[i] @ motion
            out[b, i] = local if parent < 0 else out[b, parent] @ local
    return out


def fk_rows(repeat):
    tree = random_tree()
    q = np.random.default_rng(3).uniform(-1, 1, (1000, tree.dof))
    few = q[:50]
    base_t, ours_t = paired(lambda: loop_fk(tree, few), lambda: tree.forward_kinematics(q), repeat)
    base_per = Timing(base_t.median * len(q) / len(few), base_t.spread * len(q) / len(few), base_t.runs)
    err = float(np.abs(tree.forward_kinematics(few) - loop_fk(tree, few)).max())
    return [
        Row(
            TOPIC,
            f"forward kinematics, {len(tree)}-link tree ({tree.dof} dof), batch of {len(q)}",
            ours_t,
            base_per,
            error={"max_abs_err": err},
            extra={
                "us_per_config": f"{ours_t.median / len(q) * 1e6:.1f}",
                "cpu_us_per_config": f"{cpu_seconds(lambda: tree.forward_kinematics(q)) / len(q) * 1e6:.1f}",
                "baseline": f"per-config per-joint loop, timed on {len(few)} configs, scaled",
            },
        )
    ]


def panda_fk_rows(repeat):
    """The Franka Panda of pybullet's data against Pinocchio (framesForwardKinematics) in its own
    environment: one configuration at a time, and a batch of 1000 against a Python loop of
    Pinocchio calls; the compiled pass and the NumPy one (what Blender's Python runs)."""
    import warnings

    from _oracles import panda_urdf, run_oracle

    from splatwright.core import kinematics
    from splatwright.io.urdf import read_urdf

    path = panda_urdf()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tree = read_urdf(path)
    rng = np.random.default_rng(4)
    lower = np.where(np.isfinite(tree.lower), tree.lower, -np.pi)[tree._limited]
    upper = np.where(np.isfinite(tree.upper), tree.upper, np.pi)[tree._limited]
    q = rng.uniform(lower, upper, (1000, tree.dof))
    one = np.flatnonzero(np.isin(tree.joint_types, ("revolute", "continuous", "prismatic")))
    pin = run_oracle(
        "pinocchio_fk",
        urdf=str(path),
        links=np.array(tree.names),
        joint_names=np.array([tree.joint_names[i] for i in one]),
        joint_values=tree.joint_values(q)[:, one],
        repeat=repeat + 2,
    )
    err = float(np.abs(tree.forward_kinematics(q) - pin["transforms"]).max())
    rows = []
    for label, fk_kernel in (("compiled", kinematics._fk_kernel), ("NumPy", lambda: None)):
        saved, kinematics._fk_kernel = kinematics._fk_kernel, fk_kernel
        try:
            single = timeit(lambda: [tree.forward_kinematics(q[0]) for _ in range(1000)], repeat=repeat + 2)
            batch = timeit(lambda: tree.forward_kinematics(q), repeat=repeat + 2)
        finally:
            kinematics._fk_kernel = saved
        common = {"dof": f"{tree.dof} (Pinocchio: {int(pin['nq'])}, the mimic finger counted)", "links": len(tree)}
        rows.append(
            Row(
                TOPIC,
                f"Panda FK, one configuration, {label} (vs Pinocchio)",
                _per(single, 1000),
                Timing(float(pin["single"]), 0.0, repeat + 2),
                error={"max_abs_err": err},
                extra={**common, "target": "within 5x of Pinocchio (speed-up >= 0.2)"},
            )
        )
        rows.append(
            Row(
                TOPIC,
                f"Panda FK, batch of {len(q)}, {label} (vs a Pinocchio loop)",
                batch,
                Timing(float(pin["batch"]), 0.0, repeat + 2),
                error={"max_abs_err": err},
                extra={**common, "target": "faster than the loop (speed-up > 1)"},
            )
        )
    return rows


def chain_urdf(n):
    links = "".join(f'<link name="l{k}"/>' for k in range(n))
    joints = "".join(
        f'<joint name="j{k}" type="revolute"><parent link="l{k}"/><child link="l{k + 1}"/>'
        f'<origin xyz="0 0 0.01"/><axis xyz="0 1 0"/><limit lower="-1" upper="1"/></joint>'
        for k in range(n - 1)
    )
    return f"<robot name='chain'>{links}{joints}</robot>"


def urdf_rows(quick):
    """Reading long chains: today's reader against the one before (quadratic in links)."""
    from _before import module_before

    from splatwright.io.urdf import parse_urdf

    module_before("core/kinematics.py")
    before = module_before("io/urdf.py", {"..core.kinematics import": "..core._kinematics_before import"})
    rows = []
    for n in (1000, 4000) if quick else (4000, 20_000):
        text = chain_urdf(n)
        ours = timeit(lambda: parse_urdf(text), repeat=3)
        baseline = timeit(lambda: before.parse_urdf(text), repeat=1, warmup=0) if n <= 4000 else None
        rows.append(
            Row(
                TOPIC,
                f"read a URDF chain of {n:,} links",
                ours,
                baseline,
                extra={"baseline": "the reader before (quadratic)" if baseline else "before: > 120 s, not run"},
            )
        )
    return rows


def _per(t, n):
    return Timing(t.median / n, t.spread / n, t.runs)


# the bent cylinder --------------------------------------------------------------------------------

JOINT_Y, BLEND_HALF_WIDTH, BEND_DEGREES = 1.0, 0.25, 70.0


def cylinder(around=96, along=128, radius=0.3, length=2.0):
    """Vertices, faces and checker vertex colours (scene-linear) of an open cylinder along +y."""
    phi = np.linspace(0, 2 * np.pi, around, endpoint=False)
    y = np.linspace(0, length, along)
    ph, yy = np.meshgrid(phi, y)
    vertices = np.stack([radius * np.cos(ph), yy, radius * np.sin(ph)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(along - 1), np.arange(around), indexing="ij")
    a, b = i * around + j, i * around + (j + 1) % around
    faces = np.concatenate(
        [np.stack([a, b, b + around], -1).reshape(-1, 3), np.stack([a, b + around, a + around], -1).reshape(-1, 3)]
    )
    checker = ((np.floor(ph / (2 * np.pi) * 12) + np.floor(yy / length * 16)) % 2).reshape(-1)
    colors = np.where(checker[:, None] > 0, [0.9, 0.5, 0.1], [0.1, 0.3, 0.8])
    return vertices, faces, colors


def joint_binding(y):
    """Two bones, lower and upper, blended smoothly across the joint."""
    t = np.clip((np.asarray(y, np.float64) - (JOINT_Y - BLEND_HALF_WIDTH)) / (2 * BLEND_HALF_WIDTH), 0, 1)
    upper = t * t * (3 - 2 * t)
    return Binding.from_weights(np.tile([0, 1], (len(upper), 1)), np.stack([1 - upper, upper], -1))


def bend_pose(degrees=BEND_DEGREES):
    turn = axis_angle_matrices(np.array([1.0, 0.0, 0.0]), np.radians(degrees))
    pivot = np.array([0.0, JOINT_Y, 0.0])
    return BonePose(np.stack([np.eye(4), transforms(turn, pivot - turn @ pivot)]))


def bent_cylinder_images(mode, max_splats, size, around=96, along=128):
    """{case: (image, seconds of skinning)} and the reference image of splats from the bent mesh."""
    from splatwright.core.camera import Camera
    from splatwright.core.mesh import Material
    from splatwright.core.mesh_to_splats import mesh_to_splats
    from splatwright.core.render import render

    vertices, faces, colors = cylinder(around, along)
    pose = bend_pose()
    bent = skin_centres(vertices, joint_binding(vertices[:, 1]), pose, mode)
    style = dict(
        corner_colors=colors,
        face_materials=np.zeros(len(faces), int),
        materials=[Material(base_color=(1, 1, 1), rim_color=(0.05, 0.05, 0.05))],
        max_splats=max_splats,
        calibrate=False,
    )  # splats on the surface: skinning is measured, not silhouette calibration
    rest_cloud = mesh_to_splats(vertices, faces, **style)
    direct = mesh_to_splats(bent, faces, **style)
    resampled = mesh_to_splats(bent, faces, seed=1, **style)
    binding = joint_binding(rest_cloud.positions[:, 1])
    camera = Camera.look_at(eye=(2.2, 1.1, 0.6), target=(0.0, 1.05, 0.15), fov_deg=40, width=size, height=size)
    shoot = lambda cloud: render(cloud, camera, background=(1.0, 1.0, 1.0)).color  # noqa: E731
    cases = {
        "full skinning": dict(),
        "no SH rotation": dict(sh=False),
        "blended-matrix covariance": dict(lbs_stretch="blend"),
        "centres only": dict(covariances=False, sh=False),
    }
    images = {}
    for name, options in cases.items():
        t = timeit(lambda: skin(rest_cloud, binding, pose, mode, **options), repeat=3)
        images[name] = (shoot(skin(rest_cloud, binding, pose, mode, **options)), t)
    images["sampling floor (second sampling)"] = (shoot(resampled), None)
    return images, shoot(direct), len(rest_cloud)


def cylinder_rows(quick):
    from splatwright.core.metrics import psnr

    rows = []
    for mode in ("lbs", "dqs"):
        images, reference, n = bent_cylinder_images(mode, 10_000 if quick else 40_000, 128 if quick else 256)
        for name, (image, t) in images.items():
            if name == "blended-matrix covariance" and mode == "dqs":
                continue  # the same map as full skinning for DQS
            rows.append(
                Row(
                    TOPIC,
                    f"bent cylinder {mode.upper()}, {n:,} splats: {name}",
                    t or Timing(0.0, 0.0, 0),
                    error={"psnr_db": psnr(image, reference)},
                    extra={"reference": "splats made from the bent mesh"},
                )
            )
    return rows


def run(quick=False):
    n = 100_000 if quick else 1_000_000
    repeat = 3 if quick else 5
    return (
        fk_rows(repeat)
        + panda_fk_rows(repeat)
        + urdf_rows(quick)
        + skinning_rows(n, repeat)
        + skinning_rows(n, repeat, scaled=True)
        + blender_float32_rows(n, repeat)
        + cylinder_rows(quick)
    )


# rows that `./run bench articulation --only NAME` runs alone (merged into the report's section)
PARTS = {"blender-float32": lambda quick: blender_float32_rows(100_000 if quick else 1_000_000, 3 if quick else 5)}


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
