"""Kinematic trees: links with parents, rest transforms and joints, and forward kinematics.

Every link has one parent (or none: a root) and is reached through one joint. A link's world
transform is

    world[i] = world[parent[i]] @ origins[i] @ motion_i(q)

where `origins[i]` is the joint frame in the parent link's frame (the rest transform) and
`motion_i` is the joint's own motion about/along its axis, given in the joint frame:

    fixed        no motion, no degree of freedom
    revolute     rotation by q radians about `axis`, limited to [lower, upper]
    continuous   rotation by q radians about `axis`, unlimited
    prismatic    translation by q along `axis`, limited to [lower, upper]
    ball         rotation by a rotation vector (3 values; `pack` also takes a w,x,y,z quaternion),
                 its angle limited to `upper` when that is finite

This is URDF's model (links, joints with origin/axis/limit) and Blender's too (bones whose rest
transforms are relative to their parent, posed by a rotation in the bone's own frame). Links are
kept in topological order (parents before children), so forward kinematics is one vectorised
matrix product per tree level, for one configuration or a batch of them.
"""

from dataclasses import dataclass, field

import numpy as np

from . import geometry

JOINT_DOF = {"fixed": 0, "revolute": 1, "continuous": 1, "prismatic": 1, "ball": 3}
_ROTATING = ("revolute", "continuous")


class KinematicsError(ValueError):
    """A tree, configuration or matrix that cannot be used; the message names the part."""


# small rotation helpers ---------------------------------------------------------------------------

def rotvec_to_quaternions(rotvec):
    """(..., 3) rotation vectors (axis * angle) -> (..., 4) unit quaternions w,x,y,z."""
    v = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    # sin(angle/2)/angle written with np.sinc stays exact as the angle goes to zero.
    half_sinc = 0.5 * np.sinc(angle / (2.0 * np.pi))
    return np.concatenate([np.cos(0.5 * angle), half_sinc * v], axis=-1)


def quaternions_to_rotvec(q):
    """(..., 4) w,x,y,z (any norm) -> (..., 3) rotation vectors with angles in [0, pi]."""
    q = geometry.normalize_quaternions(q)
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)          # the short way round
    vec_norm = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vec_norm, q[..., :1])
    # angle / sin(angle/2), again through sinc so that tiny rotations stay exact.
    scale = 1.0 / (0.5 * np.sinc(angle / (2.0 * np.pi)))
    return q[..., 1:] * scale


def axis_angle_matrices(axes, angles):
    """Rotation matrices for unit `axes` (..., 3) and `angles` (...), broadcast together."""
    axes, angles = np.asarray(axes, np.float64), np.asarray(angles, np.float64)
    return geometry.quaternions_to_matrices(rotvec_to_quaternions(axes * angles[..., None]))


def _skew(v):
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices K with K @ x = v x x."""
    v = np.asarray(v, dtype=np.float64)
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return k


def rpy_matrices(rpy):
    """URDF roll-pitch-yaw (..., 3) -> rotation matrices Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    rpy = np.asarray(rpy, dtype=np.float64)
    eye = np.eye(3)
    rx, ry, rz = (axis_angle_matrices(eye[k], rpy[..., k]) for k in range(3))
    return rz @ ry @ rx


def rigid_inverse(m):
    """Inverse of (..., 4, 4) rigid transforms (rotation + translation), exact to round-off."""
    m = np.asarray(m, dtype=np.float64)
    out = np.zeros_like(m)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, m[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def transforms(rotations=None, translations=None):
    """(..., 4, 4) homogeneous transforms from (..., 3, 3) rotations and/or (..., 3) translations."""
    r = None if rotations is None else np.asarray(rotations, np.float64)
    t = None if translations is None else np.asarray(translations, np.float64)
    shape = (r.shape[:-2] if r is not None else t.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = np.eye(3) if r is None else r
    if t is not None:
        out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


# the tree -----------------------------------------------------------------------------------------

@dataclass(eq=False)
class KinematicTree:
    """Links in topological order, each reached from its parent through one joint.

    names: link names; parents: (L,) parent index or -1 for a root (parents[i] < i);
    origins: (L,4,4) rest transform of each joint frame in its parent link's frame (for a root:
    in the world); joint_types: one of JOINT_DOF per link (a root's joint moves it in the world);
    axes: (L,3) joint axes in the joint frame (normalised here); lower/upper: (L,) limits in
    radians or metres (-inf/inf when unlimited; for a ball joint `upper` bounds the angle).
    joint_names: optional names of the joints (default: the link names).
    """

    names: tuple
    parents: np.ndarray
    origins: np.ndarray
    joint_types: tuple
    axes: np.ndarray = None
    lower: np.ndarray = None
    upper: np.ndarray = None
    joint_names: tuple = None
    _levels: list = field(init=False, repr=False)

    def __post_init__(self):
        n = len(self.names)
        self.names = tuple(str(s) for s in self.names)
        self.joint_names = self.names if self.joint_names is None else tuple(str(s) for s in self.joint_names)
        self.joint_types = tuple(self.joint_types)
        self.parents = np.asarray(self.parents, dtype=np.int64).reshape(-1)
        self.origins = np.asarray(self.origins, dtype=np.float64)
        self.axes = np.tile([1.0, 0.0, 0.0], (n, 1)) if self.axes is None else np.array(self.axes, np.float64)
        self.lower = np.full(n, -np.inf) if self.lower is None else np.asarray(self.lower, np.float64).copy()
        self.upper = np.full(n, np.inf) if self.upper is None else np.asarray(self.upper, np.float64).copy()
        self._validate(n)
        self.axes = self.axes / np.linalg.norm(self.axes, axis=1, keepdims=True)
        continuous = np.array([t == "continuous" for t in self.joint_types], bool)
        self.lower[continuous], self.upper[continuous] = -np.inf, np.inf
        self._index_joints()

    def _validate(self, n):
        problems = []
        if len(set(self.names)) != n:
            problems.append("link names are not unique")
        for name, arr, shape in (("parents", self.parents, (n,)), ("origins", self.origins, (n, 4, 4)),
                                 ("axes", self.axes, (n, 3)), ("lower", self.lower, (n,)),
                                 ("upper", self.upper, (n,))):
            if arr.shape != shape:
                problems.append(f"{name} has shape {arr.shape}, expected {shape}")
        if len(self.joint_types) != n or len(self.joint_names) != n:
            problems.append(f"expected {n} joint types and names")
        if problems:
            raise KinematicsError("malformed kinematic tree: " + "; ".join(problems))
        for i, (name, kind) in enumerate(zip(self.names, self.joint_types)):
            where = f"link '{name}' (joint '{self.joint_names[i]}')"
            if kind not in JOINT_DOF:
                raise KinematicsError(f"{where}: unknown joint type '{kind}' (known: {', '.join(JOINT_DOF)})")
            if not -1 <= self.parents[i] < i:
                raise KinematicsError(f"{where}: parent index {self.parents[i]} is not an earlier link "
                                      "(links must be in topological order)")
            if not np.isfinite(self.origins[i]).all():
                raise KinematicsError(f"{where}: origin is not finite")
            if kind in ("revolute", "continuous", "prismatic") and \
                    not (np.isfinite(self.axes[i]).all() and np.linalg.norm(self.axes[i]) > 1e-12):
                raise KinematicsError(f"{where}: axis {self.axes[i].tolist()} is zero or not finite")
            if np.isnan(self.lower[i]) or np.isnan(self.upper[i]) or self.lower[i] > self.upper[i]:
                raise KinematicsError(f"{where}: limits [{self.lower[i]}, {self.upper[i]}] are not an interval")
        bad_axes = ~(np.isfinite(self.axes).all(axis=1) & (np.linalg.norm(self.axes, axis=1) > 1e-12))
        self.axes[bad_axes] = [1.0, 0.0, 0.0]       # axes of fixed and ball joints are unused

    def _index_joints(self):
        dof = np.array([JOINT_DOF[t] for t in self.joint_types])
        self.dof_offsets = np.concatenate([[0], np.cumsum(dof)])[:-1]
        self.dof = int(dof.sum())
        kinds = np.array(self.joint_types)
        self._rotating = np.flatnonzero(np.isin(kinds, _ROTATING))
        self._prismatic = np.flatnonzero(kinds == "prismatic")
        self._ball = np.flatnonzero(kinds == "ball")
        self._ball_cols = self.dof_offsets[self._ball][:, None] + np.arange(3)
        k = _skew(self.axes[self._rotating])
        o = self.origins[self._rotating, :3, :3]
        self._origin_rodrigues = (o @ k, o @ k @ k)
        depth = np.zeros(len(self.names), np.int64)
        for i, p in enumerate(self.parents):           # once per tree, not per configuration
            depth[i] = 0 if p < 0 else depth[p] + 1
        self._levels = [np.flatnonzero(depth == d) for d in range(depth.max() + 1 if len(depth) else 0)]

    # construction ---------------------------------------------------------------------------

    @classmethod
    def from_joints(cls, joints, root=None):
        """Build from an unordered list of joint dicts, one per non-root link:
        {"name", "parent", "child", "type", "origin" (4,4), "axis" (3,), "lower", "upper"}.

        Links are put in topological (breadth-first) order; `root` names the root link when the
        joints do not make it obvious. Raises KinematicsError for cycles, second parents and
        several roots.
        """
        children = {}
        for j in joints:
            if j["child"] in children:
                raise KinematicsError(f"link '{j['child']}' has two parent joints "
                                      f"('{children[j['child']]['name']}' and '{j['name']}')")
            children[j["child"]] = j
        parents = {j["parent"] for j in joints}
        roots = sorted(parents - set(children)) if root is None else [root]
        if len(roots) != 1:
            raise KinematicsError(f"expected one root link, found {roots or 'none (the joints form a cycle)'}")
        order, by_parent = [roots[0]], {}
        for j in joints:
            by_parent.setdefault(j["parent"], []).append(j["child"])
        for link in order:                               # breadth-first; the list grows as we go
            order.extend(by_parent.get(link, []))
        unreached = set(children) - set(order)
        if unreached:
            raise KinematicsError(f"links {sorted(unreached)} are not connected to root '{roots[0]}' "
                                  "(their joints form a cycle)")
        index = {name: i for i, name in enumerate(order)}
        spec = [children.get(name) for name in order]
        eye = np.eye(4)
        return cls(
            names=order,
            parents=[-1 if s is None else index[s["parent"]] for s in spec],
            origins=[eye if s is None else s.get("origin", eye) for s in spec],
            joint_types=["fixed" if s is None else s["type"] for s in spec],
            axes=[(1.0, 0.0, 0.0) if s is None else s.get("axis", (1.0, 0.0, 0.0)) for s in spec],
            lower=[-np.inf if s is None else s.get("lower", -np.inf) for s in spec],
            upper=[np.inf if s is None else s.get("upper", np.inf) for s in spec],
            joint_names=[name if s is None else s["name"] for name, s in zip(order, spec)],
        )

    @classmethod
    def from_rest_matrices(cls, names, parents, rest, joint_type="ball"):
        """A skeleton in Blender's terms: bones with parents (topologically ordered) and rest
        matrices in armature space (Blender's `bone.matrix_local`). Every bone gets a joint of
        `joint_type` at its head, so a ball joint's rotation vector is the pose rotation in the
        bone's own frame, as in `pose_bone.rotation_quaternion`."""
        rest = np.asarray(rest, dtype=np.float64)
        parents = np.asarray(parents, dtype=np.int64)
        parent_rest = np.where((parents >= 0)[:, None, None], rest[np.maximum(parents, 0)], np.eye(4))
        origins = rigid_inverse(parent_rest) @ rest
        return cls(names, parents, origins, [joint_type] * len(names))

    # configurations -------------------------------------------------------------------------

    def __len__(self):
        return len(self.names)

    @property
    def dof_names(self):
        """One name per configuration value: the joint name, with .x/.y/.z for ball joints."""
        out = []
        for name, kind in zip(self.joint_names, self.joint_types):
            out += [f"{name}.{c}" for c in "xyz"] if kind == "ball" else [name] * JOINT_DOF[kind]
        return out

    def zero(self, batch=None):
        return np.zeros(self.dof if batch is None else (batch, self.dof))

    def pack(self, values):
        """A configuration vector from {joint name: value}; unnamed joints stay at 0. A ball joint
        takes a rotation vector (3 values) or a w,x,y,z quaternion (4 values)."""
        q = self.zero()
        index = {name: i for i, name in enumerate(self.joint_names)}
        for name, value in values.items():
            if name not in index:
                raise KinematicsError(f"no joint named '{name}'")
            i = index[name]
            kind, value = self.joint_types[i], np.asarray(value, np.float64).reshape(-1)
            if kind == "ball" and len(value) == 4:
                value = quaternions_to_rotvec(value)
            if len(value) != JOINT_DOF[kind]:
                raise KinematicsError(f"joint '{name}' ({kind}) takes {JOINT_DOF[kind]} values, got {len(value)}")
            q[self.dof_offsets[i]:self.dof_offsets[i] + len(value)] = value
        return q

    def _check_configuration(self, q):
        q = np.asarray(q, dtype=np.float64)
        if q.shape[-1:] != (self.dof,) or q.ndim > 2:
            raise KinematicsError(f"configuration has shape {q.shape}, expected ({self.dof},) or (B, {self.dof})")
        if not np.isfinite(q).all():
            raise KinematicsError("configuration has non-finite values")
        return q

    def clamp(self, q):
        """The configuration with every joint inside its limits (ball joints: angle <= upper)."""
        q = self._check_configuration(q).copy()
        one = np.concatenate([self._rotating, self._prismatic])
        cols = self.dof_offsets[one]
        q[..., cols] = np.clip(q[..., cols], self.lower[one], self.upper[one])
        if len(self._ball):
            v = q[..., self._ball_cols]
            angle = np.linalg.norm(v, axis=-1)
            shrink = np.minimum(1.0, self.upper[self._ball] / np.where(angle > 0, angle, 1.0))
            q[..., self._ball_cols] = v * shrink[..., None]
        return q

    def within_limits(self, q, tol=1e-12):
        """True for each configuration (scalar for one) whose joints all respect their limits."""
        q = self._check_configuration(q)
        return np.all(np.abs(self.clamp(q) - q) <= tol, axis=-1)

    # forward kinematics ---------------------------------------------------------------------

    def _local_transforms(self, q):
        """Parent-relative transforms origins[i] @ motion_i(q) for a batch (B, dof), laid out
        (L, B, 4, 4) so that each tree level gathers whole contiguous blocks."""
        local = np.empty((len(self), len(q), 4, 4))
        local[:] = self.origins[:, None]
        rot, pri, ball = self._rotating, self._prismatic, self._ball
        if len(rot):
            # Rodrigues with the origin folded in: O R(t) = O + sin(t) O K + (1 - cos(t)) O K^2.
            angle = q[:, self.dof_offsets[rot]].T[..., None, None]
            o_k, o_k2 = self._origin_rodrigues
            local[rot, :, :3, :3] += np.sin(angle) * o_k[:, None] + (1.0 - np.cos(angle)) * o_k2[:, None]
        if len(ball):
            r = geometry.quaternions_to_matrices(rotvec_to_quaternions(np.swapaxes(q[:, self._ball_cols], 0, 1)))
            local[ball, :, :3, :3] = self.origins[ball, None, :3, :3] @ r
        if len(pri):
            shift = self.origins[pri, :3, :3] @ self.axes[pri, :, None]          # axis in the parent frame
            local[pri, :, :3, 3] += q[:, self.dof_offsets[pri]].T[..., None] * shift[:, None, :, 0]
        return local

    def forward_kinematics(self, q=None, base=None, clamp=False):
        """World transforms of every link: (L,4,4) for one configuration (dof,), (B,L,4,4) for a
        batch (B,dof). `base` (4,4) places the roots; `clamp` first applies the joint limits."""
        q = self.zero() if q is None else self._check_configuration(q)
        if clamp:
            q = self.clamp(q)
        single = q.ndim == 1
        local = self._local_transforms(np.atleast_2d(q))
        world = np.empty_like(local)
        for level in self._levels:
            parent = self.parents[level]
            if parent[0] < 0:                                        # depth 0: the roots
                world[level] = local[level] if base is None else np.asarray(base, np.float64) @ local[level]
            else:
                world[level] = world[parent] @ local[level]
        return world[:, 0] if single else np.ascontiguousarray(np.swapaxes(world, 0, 1))

    def rest_transforms(self, base=None):
        """World transforms of every link at the zero configuration, (L,4,4)."""
        return self.forward_kinematics(None, base=base)

    def deform_matrices(self, q=None, base=None, clamp=False):
        """Per-link skinning matrices world(q) @ inverse(world(0)): what a splat bound to a link
        at rest goes through (Blender's pose @ inverse(rest))."""
        rest_inv = np.linalg.inv(self.rest_transforms(base))
        return self.forward_kinematics(q, base=base, clamp=clamp) @ rest_inv
