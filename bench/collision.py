"""Collision at scene scale: a 2,000-splat arm on a table in a 1M-splat room.

Rows: the broad-phase build; soft overlap cost + gradient per configuration at several cutoffs,
each against brute force over the whole environment on a subsample of robot splats (the baseline
is that brute force, timed on the subsample and scaled to the whole robot); the joint-space
gradient; exact ellipsoid contacts; occupancy and signed distance queries; and per-link proxies
with the cost error they bring.
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import Row, Timing, print_rows, timeit  # noqa: E402

from splatwright.core import SplatCloud, collision as col, geometry  # noqa: E402
from splatwright.core.kinematics import KinematicTree, transforms  # noqa: E402

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
    faces = [(np.asarray(lo, float), np.asarray(hi, float), ax, side)
             for lo, hi in boxes for ax in range(3) for side in (0, 1)]
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
    boxes = [((0, 0, -0.01), (6, 5, 0)), ((0, 0, 3), (6, 5, 3.01)), ((-0.01, 0, 0), (0, 5, 3)),
             ((6, 0, 0), (6.01, 5, 3)), ((0, -0.01, 0), (6, 0, 3)), ((0, 5, 0), (6, 5.01, 3)),
             ((2.0, 2.0, TABLE_TOP - 0.03), (3.2, 2.8, TABLE_TOP)),
             *[((x, y, 0), (x + 0.05, y + 0.05, TABLE_TOP - 0.03)) for x in (2.05, 3.1) for y in (2.05, 2.7)],
             ((2.3, 2.2, TABLE_TOP), (2.6, 2.5, TABLE_TOP + 0.2)), ((4.0, 1.0, 0), (4.6, 1.5, 0.5))]
    n_surface = int(n * 0.99)
    surfaces = surface_splats(*_box_faces(boxes, n_surface, rng), rng, (0.004, 0.025))
    m = n - n_surface
    floaters = SplatCloud.from_activated(rng.uniform((0, 0, 0), (6, 5, 3), (m, 3)), rng.normal(size=(m, 4)),
                                         np.exp(rng.uniform(np.log(0.03), np.log(0.1), (m, 3))),
                                         rng.uniform(0.05, 0.5, m))
    return SplatCloud.concatenate([surfaces, floaters])


# (name, joint type, axis, origin in the parent's frame, link radius, link length)
ARM = [("base", "fixed", (0, 0, 1), (2.9, 2.55, TABLE_TOP), 0.06, 0.10),
       ("shoulder", "revolute", (0, 0, 1), (0, 0, 0.10), 0.05, 0.15),
       ("upper_arm", "revolute", (0, 1, 0), (0, 0, 0.15), 0.045, 0.35),
       ("forearm", "revolute", (0, 1, 0), (0, 0, 0.35), 0.04, 0.30),
       ("wrist", "revolute", (0, 1, 0), (0, 0, 0.30), 0.035, 0.08),
       ("hand", "revolute", (0, 0, 1), (0, 0, 0.08), 0.04, 0.06),
       ("finger_a", "prismatic", (1, 0, 0), (0.02, 0, 0.06), 0.012, 0.06),
       ("finger_b", "prismatic", (-1, 0, 0), (-0.02, 0, 0.06), 0.012, 0.06)]


def arm(n=2000, seed=1):
    """A 7-joint arm standing on the table: its kinematic tree and n splats on its links' cylinders
    (world frame at rest, rigidly bound to links)."""
    rng = np.random.default_rng(seed)
    tree = KinematicTree(names=[a[0] for a in ARM], parents=[-1] + [0, 1, 2, 3, 4, 5, 5],
                         origins=[transforms(translations=a[3]) for a in ARM],
                         joint_types=[a[1] for a in ARM], axes=[a[2] for a in ARM],
                         lower=[-np.inf, -3, -2, -2.5, -2, -3, 0, 0], upper=[np.inf, 3, 2, 2.5, 2, 3, 0.03, 0.03])
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
    q[:, 0] = rng.uniform(-2.5, 2.5, count)          # shoulder yaw
    q[:, 1] = rng.uniform(0.9, 1.4, count)           # shoulder pitch
    q[:, 2] = rng.uniform(0.6, 1.3, count)           # elbow
    q[:, 3] = rng.uniform(-0.5, 0.8, count)          # wrist pitch
    q[:, 4] = rng.uniform(-3, 3, count)              # wrist roll
    q[:, 5:] = rng.uniform(0, 0.03, (count, 2))      # fingers
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
    rows.append(Row(TOPIC, f"build index, {n_env:,} splats", t_build,
                    extra={"levels": len(index.levels), "cells": cells}))

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
        rows.append(Row(TOPIC, f"cost+gradient, cutoff {cutoff:g}{label}",
                        Timing(float(np.median(times)), float(np.ptp(times) / 2), len(times)), baseline,
                        error={"cost rel err": float(errors[:, 0].max()), "grad rel err": float(errors[:, 1].max()),
                               "rel bound": float(max(bounds))},
                        extra={"pairs": int(np.median(pairs)), "robot": len(robot_rest)}))

    t = timeit(lambda: [col.overlap_at(tree, q, robot_rest, index) for q in qs], repeat=3)
    rows.append(Row(TOPIC, "cost+dC/dq (FK, pose, chain rule), cutoff 6", _per(t, len(qs)),
                    extra={"dof": tree.dof}))

    contacts = None

    def hard():
        nonlocal contacts
        contacts = [col.ellipsoid_contacts(robot, index, k=3.0) for robot in robots]
    t = timeit(hard, repeat=3)
    rows.append(Row(TOPIC, "hard contacts, 3-sigma ellipsoids", _per(t, len(robots)),
                    extra={"pairs": int(np.median([len(c) for c in contacts]))}))

    probes = rng.uniform([1.8, 1.8, 0.5], [3.4, 3.0, 1.2], (10_000, 3))
    t = timeit(lambda: col.occupancy(index, probes), repeat=3)
    occ = col.occupancy(index, probes)
    rows.append(Row(TOPIC, "occupancy, 10k points, cutoff 6", t,
                    error={"max bound": float(occ.bound.max())}))
    t = timeit(lambda: col.signed_distance(index, probes[:2000], k=3.0, max_distance=0.5), repeat=3)
    rows.append(Row(TOPIC, "signed distance, 2k points, 3 sigma, max 0.5 m", t))

    full_time = np.median([timeit(lambda: col.overlap(r, index, bound=False), repeat=5).median for r in robots])
    for per_link in (4, 16, 64):
        proxies = col.fit_proxies(robot_rest, per_link=per_link, reference_sigma=index.typical_sigma)
        posed = [col.pose_robot(proxies, d) for d in deform]
        t = [timeit(lambda: col.overlap(p, index, bound=False), repeat=3).median for p in posed]
        err = [col.proxy_error(r, p, index) for r, p in zip(robots, posed)]
        rows.append(Row(TOPIC, f"proxies, {per_link} per link ({len(proxies)} Gaussians)",
                        Timing(float(np.median(t)), float(np.ptp(t) / 2), len(t)),
                        Timing(float(full_time), 0.0, len(robots)),
                        error={"cost rel err": float(max(err))}))
    return rows


if __name__ == "__main__":
    quick = "--quick" in sys.argv
    print_rows(run(quick=quick))
