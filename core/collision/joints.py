"""Robots on kinematic trees: Gaussians posed by per-link transforms, and the soft overlap's
gradient with respect to the joint values."""

import math

import numpy as np

from .gaussians import DEFAULT_CUTOFF, CollisionInputError
from .overlap import overlap


def pose_robot(robot_rest, deform):
    """Robot Gaussians rigidly bound to links (robot_rest.links), given in the world frame at the
    rest configuration, moved by per-link deform matrices world(q) @ world(0)^-1 (L,4,4)."""
    if robot_rest.links is None:
        raise CollisionInputError("robot_rest.links: a link index per Gaussian is needed to pose a robot")
    m = np.asarray(deform, np.float64)
    if len(robot_rest) and robot_rest.links.max() >= len(m):
        raise CollisionInputError(f"links: index {int(robot_rest.links.max())} but only {len(m)} link transforms")
    m = m[robot_rest.links]
    return robot_rest.transformed(m[:, :3, :3], m[:, :3, 3])


def overlap_at(tree, q, robot_rest, env, cutoff=DEFAULT_CUTOFF, base=None, threads=None, **kwargs):
    """Soft overlap of a robot on a kinematic tree at configuration q, with dC/dq.

    robot_rest: Gaussians in the world frame at q = 0 with `links` (rigid binding). Forward
    kinematics is the tree's own; the chain rule goes through each joint's world motion: a joint
    turning by dt about unit axis w through point p moves a Gaussian of its subtree by
    dmu = w x (mu - p) dt and dSigma = (W Sigma - Sigma W) dt (W = [w]x), so
    dC/dt = w . sum_subtree (mu x g + tau - p x g), g = dC/dmu, tau = -2 vex(Sigma G - G Sigma),
    G = dC/dSigma. A prismatic joint gives a . sum g; a ball joint's three values turn about the
    columns of the SO(3) left Jacobian of its rotation vector; planar and floating joints slide
    (a . sum g per direction) and turn about the point they slid to; a mimic joint adds multiplier x
    its own derivative to the column of the joint it follows.
    """
    q = tree._check_configuration(q)
    world = tree.forward_kinematics(q, base=base)
    robot = pose_robot(robot_rest, world @ np.linalg.inv(tree.rest_transforms(base)))
    result = overlap(robot, env, cutoff, gradient=True, cov_gradient=True, threads=threads, **kwargs)
    result.grad_q = _joint_gradient(tree, q, world, base, robot, result.grad_means, result.grad_covs)
    return result


def _joint_gradient(tree, q, world, base, robot, g, gcov):
    n_links = len(tree)
    sg = np.einsum("nij,njk->nik", robot.covs, gcov)
    a = sg - np.swapaxes(sg, 1, 2)  # Sigma G - G Sigma
    tau = -2.0 * np.stack([a[:, 2, 1], a[:, 0, 2], a[:, 1, 0]], axis=1)
    moment = np.cross(robot.means, g) + tau
    force = np.stack([np.bincount(robot.links, g[:, k], n_links) for k in range(3)], axis=1)
    moment = np.stack([np.bincount(robot.links, moment[:, k], n_links) for k in range(3)], axis=1)
    for i in range(n_links - 1, 0, -1):  # subtree sums (parents come first)
        if tree.parents[i] >= 0:
            force[tree.parents[i]] += force[i]
            moment[tree.parents[i]] += moment[i]
    # joint frames in the world: F_i = world[parent] @ origins[i] (roots: base @ origins[i])
    parent_world = np.where(
        (tree.parents >= 0)[:, None, None],
        world[np.maximum(tree.parents, 0)],
        np.eye(4) if base is None else np.asarray(base, np.float64),
    )
    frames = parent_world @ tree.origins
    grad = np.zeros(tree.dof)
    for i, kind in enumerate(tree.joint_types):
        col, scale = tree.dof_offsets[i], tree._scale[i]  # a mimic joint adds to its source's column
        rot, point = frames[i, :3, :3], frames[i, :3, 3]
        axis = rot @ tree.axes[i]
        if kind in ("revolute", "continuous"):
            grad[col] += scale * axis @ (moment[i] - np.cross(point, force[i]))
        elif kind == "prismatic":
            grad[col] += scale * axis @ force[i]
        elif kind == "ball":
            grad[col : col + 3] += (rot @ _left_jacobian(q[col : col + 3])).T @ (moment[i] - np.cross(point, force[i]))
        elif kind == "planar":  # slide along the plane, then turn about the axis
            a, b, _ = q[col : col + 3]
            u, v = rot @ tree.plane_axes[i, 0], rot @ tree.plane_axes[i, 1]
            pivot = point + a * u + b * v
            grad[col : col + 3] += [u @ force[i], v @ force[i], axis @ (moment[i] - np.cross(pivot, force[i]))]
        elif kind == "floating":  # translate, then turn about the moved point
            pivot = point + rot @ q[col : col + 3]
            grad[col : col + 3] += rot.T @ force[i]
            torque = moment[i] - np.cross(pivot, force[i])
            grad[col + 3 : col + 6] += (rot @ _left_jacobian(q[col + 3 : col + 6])).T @ torque
    return grad


def _left_jacobian(v):
    """SO(3) left Jacobian of a rotation vector: exp(v + dv) = exp((J dv)^) exp(v)."""
    theta = float(np.linalg.norm(v))
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    if theta < 1e-6:  # series to second order
        return np.eye(3) + 0.5 * k + k @ k / 6.0
    return np.eye(3) + (1.0 - math.cos(theta)) / theta**2 * k + (theta - math.sin(theta)) / theta**3 * k @ k
