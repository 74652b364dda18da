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
                 its angle limited to `upper` when that is finite (URDF's "spherical")
    planar       translation (a, b) in the plane normal to `axis` (along `plane_axes`), then rotation
                 by theta about `axis`: 3 values a, b, theta
    floating     translation (x, y, z) then rotation by a rotation vector: 6 values (`pack` also takes
                 x, y, z and a w,x,y,z quaternion, or a 4x4 rigid transform)

A joint may mimic another one-value joint (URDF's <mimic>): its value is multiplier * q_source +
offset, it has no value of its own in the configuration, and chains of mimics resolve to the
joint they all follow.

This is URDF's model (links, joints with origin/axis/limit) and Blender's too (bones whose rest
transforms are relative to their parent, posed by a rotation in the bone's own frame). Links are
kept in topological order (parents before children), so forward kinematics is one compiled pass
over the links per configuration (core.jit), or without numba one vectorised matrix product per
tree level, for one configuration or a batch of them.
"""

from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from . import geometry, jit
from .arrays import ArrayLike, Floats, Matrix4

Configuration = Annotated[Floats, "(dof,) one configuration, or (B, dof) a batch"]
LinkTransforms = Annotated[Floats, "(L, 4, 4) per link, or (B, L, 4, 4) for a batch"]

JOINT_DOF = {"fixed": 0, "revolute": 1, "continuous": 1, "prismatic": 1, "ball": 3, "planar": 3, "floating": 6}
_ROTATING = ("revolute", "continuous")
_ONE_VALUE = ("revolute", "continuous", "prismatic")
_CODES = {"fixed": 0, "revolute": 1, "continuous": 1, "prismatic": 2, "ball": 3, "planar": 4, "floating": 5}


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
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)  # the short way round
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
    shape = r.shape[:-2] if r is not None else t.shape[:-1]
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
    mimic: optional, per link None or (name of the joint it follows, multiplier, offset).
    """

    # Given as any sequences or array-likes; __post_init__ stores tuples and float64 arrays.
    names: Any
    parents: Any
    origins: Any
    joint_types: Any
    axes: Any = None
    lower: Any = None
    upper: Any = None
    joint_names: Any = None
    mimic: Any = None
    _levels: list = field(init=False, repr=False)

    def __post_init__(self):
        n = len(self.names)
        self.names = tuple(str(s) for s in self.names)
        self.joint_names = self.names if self.joint_names is None else tuple(str(s) for s in self.joint_names)
        self.joint_types = tuple("ball" if t == "spherical" else t for t in self.joint_types)
        self.mimic = (None,) * n if self.mimic is None else tuple(self.mimic)
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
        for name, arr, shape in (
            ("parents", self.parents, (n,)),
            ("origins", self.origins, (n, 4, 4)),
            ("axes", self.axes, (n, 3)),
            ("lower", self.lower, (n,)),
            ("upper", self.upper, (n,)),
        ):
            if arr.shape != shape:
                problems.append(f"{name} has shape {arr.shape}, expected {shape}")
        if len(self.joint_types) != n or len(self.joint_names) != n or len(self.mimic) != n:
            problems.append(f"expected {n} joint types, names and mimic entries")
        if problems:
            raise KinematicsError("malformed kinematic tree: " + "; ".join(problems))
        where = lambda i: f"link '{self.names[i]}' (joint '{self.joint_names[i]}')"
        unknown = [i for i, kind in enumerate(self.joint_types) if kind not in JOINT_DOF]
        if unknown:
            raise KinematicsError(
                f"{where(unknown[0])}: unknown joint type '{self.joint_types[unknown[0]]}' "
                f"(known: {', '.join(JOINT_DOF)})"
            )
        # whole-array checks, then the first offender by name (trees of 20,000 links stay fast)
        axis_ok = np.isfinite(self.axes).all(axis=1) & (np.linalg.norm(self.axes, axis=1) > 1e-12)
        uses_axis = np.isin(np.array(self.joint_types), ("revolute", "continuous", "prismatic", "planar"))
        checks = [
            (
                ~((self.parents >= -1) & (self.parents < np.arange(n))),
                lambda i: f"parent index {self.parents[i]} is not an earlier link (links must be in topological order)",
            ),
            (~np.isfinite(self.origins).all(axis=(1, 2)), lambda i: "origin is not finite"),
            (
                (self.origins[:, 3] != [0.0, 0.0, 0.0, 1.0]).any(axis=1),
                lambda i: f"origin's last row {self.origins[i, 3].tolist()} is not 0 0 0 1 (not affine)",
            ),
            (uses_axis & ~axis_ok, lambda i: f"axis {self.axes[i].tolist()} is zero or not finite"),
            (
                np.isnan(self.lower) | np.isnan(self.upper) | (self.lower > self.upper),
                lambda i: f"limits [{self.lower[i]}, {self.upper[i]}] are not an interval",
            ),
        ]
        for bad, message in checks:
            if bad.any():
                i = int(np.argmax(bad))
                raise KinematicsError(f"{where(i)}: {message(i)}")
        self.axes[~axis_ok] = [1.0, 0.0, 0.0]  # axes of fixed, ball and floating joints are unused

    def _resolve_mimics(self):
        """Per link: the joint whose value it takes (itself unless it mimics), and the multiplier and
        offset that map that value to its own."""
        n = len(self.names)
        index = {name: i for i, name in enumerate(self.joint_names)}
        source, scale, shift = np.arange(n), np.ones(n), np.zeros(n)
        for i, spec in enumerate(self.mimic):
            if spec is None:
                continue
            name, multiplier, offset = spec
            where = f"joint '{self.joint_names[i]}'"
            if name not in index:
                raise KinematicsError(f"{where} mimics '{name}', which is not a joint of this tree")
            if self.joint_types[i] not in _ONE_VALUE or self.joint_types[index[name]] not in _ONE_VALUE:
                raise KinematicsError(
                    f"{where} ({self.joint_types[i]}) mimics '{name}' "
                    f"({self.joint_types[index[name]]}): only one-value joints can mimic"
                )
            if not (np.isfinite(multiplier) and np.isfinite(offset)):
                raise KinematicsError(f"{where}: mimic multiplier {multiplier} and offset {offset} must be finite")
            source[i], scale[i], shift[i] = index[name], multiplier, offset
        mimics = np.flatnonzero(source != np.arange(n))
        for i in mimics:  # follow chains: q_i = m_i (m_s q + o_s) + o_i
            for _ in range(n):
                s = source[i]
                if source[s] == s:
                    break
                source[i], scale[i], shift[i] = source[s], scale[i] * scale[s], scale[i] * shift[s] + shift[i]
            else:
                raise KinematicsError(f"joint '{self.joint_names[i]}' is in a cycle of mimic joints")
            if source[i] == i:
                raise KinematicsError(f"joint '{self.joint_names[i]}' is in a cycle of mimic joints")
        return source, scale, shift

    def _index_joints(self):
        n = len(self.names)
        source, self._scale, self._shift = self._resolve_mimics()
        self._follows = source != np.arange(n)
        own = np.array([JOINT_DOF[t] for t in self.joint_types]) * ~self._follows
        offsets = np.concatenate([[0], np.cumsum(own)])[:-1] if n else np.zeros(0, np.int64)
        self.dof_offsets = offsets[source]
        self.dof = int(own.sum())
        kinds = np.array(self.joint_types)
        self._codes = np.array([_CODES[t] for t in self.joint_types], np.int64)
        self._rotating = np.flatnonzero(np.isin(kinds, _ROTATING))
        self._prismatic = np.flatnonzero(kinds == "prismatic")
        self._ball = np.flatnonzero(kinds == "ball")
        self._planar = np.flatnonzero(kinds == "planar")
        self._floating = np.flatnonzero(kinds == "floating")
        self._limited = np.flatnonzero(np.isin(kinds, _ONE_VALUE) & ~self._follows)
        self._ball_cols = self.dof_offsets[self._ball][:, None] + np.arange(3)
        self.plane_axes = _plane_axes(self.axes)
        k = _skew(self.axes[self._rotating])
        o = self.origins[self._rotating, :3, :3]
        self._origin_rodrigues = (o @ k, o @ k @ k)
        depth = np.zeros(n, np.int64)
        for i, p in enumerate(self.parents.tolist()):  # once per tree, not per configuration
            depth[i] = 0 if p < 0 else depth[p] + 1
        order = np.argsort(depth, kind="stable")
        self._levels = np.split(order, np.flatnonzero(np.diff(depth[order])) + 1) if n else []
        # the compiled pass takes two tables (few arguments: each costs time at every call)
        self._kernel_ints = np.ascontiguousarray(
            np.column_stack([self.parents, self._codes, self.dof_offsets]), dtype=np.int64
        )
        self._kernel_floats = np.ascontiguousarray(
            np.column_stack(
                [
                    self.origins[:, :3, :].reshape(n, 12),
                    self._scale,
                    self._shift,
                    self.axes,
                    self.plane_axes.reshape(n, 6),
                ]
            )
        )

    # construction ---------------------------------------------------------------------------

    @classmethod
    def from_joints(cls, joints: list[dict], root: str | None = None) -> "KinematicTree":
        """Build from an unordered list of joint dicts, one per non-root link:
        {"name", "parent", "child", "type", "origin" (4,4), "axis" (3,), "lower", "upper",
        "mimic" (None or (joint name, multiplier, offset))}.

        Links are put in topological (breadth-first) order; `root` names the root link when the
        joints do not make it obvious. Raises KinematicsError for cycles, second parents and
        several roots.
        """
        children: dict[str, dict] = {}
        for j in joints:
            if j["child"] in children:
                raise KinematicsError(
                    f"link '{j['child']}' has two parent joints ('{children[j['child']]['name']}' and '{j['name']}')"
                )
            children[j["child"]] = j
        parents = {j["parent"] for j in joints}
        roots = sorted(parents - set(children)) if root is None else [root]
        if len(roots) != 1:
            raise KinematicsError(f"expected one root link, found {roots or 'none (the joints form a cycle)'}")
        order, by_parent = [roots[0]], dict[str, list[str]]()
        for j in joints:
            by_parent.setdefault(j["parent"], []).append(j["child"])
        for link in order:  # breadth-first; the list grows as we go
            order.extend(by_parent.get(link, []))
        unreached = set(children) - set(order)
        if unreached:
            raise KinematicsError(
                f"links {sorted(unreached)} are not connected to root '{roots[0]}' (their joints form a cycle)"
            )
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
            mimic=[None if s is None else s.get("mimic") for s in spec],
        )

    @classmethod
    def from_rest_matrices(
        cls, names: list[str], parents: ArrayLike, rest: ArrayLike, joint_type: str = "ball"
    ) -> "KinematicTree":
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
    def dof_names(self) -> list[str]:
        """One name per configuration value: the joint name, with .x/.y/.z for ball joints,
        .a/.b/.theta for planar ones and .x/.y/.z/.rx/.ry/.rz for floating ones; mimic joints
        have none."""
        suffixes = {
            "ball": ("x", "y", "z"),
            "planar": ("a", "b", "theta"),
            "floating": ("x", "y", "z", "rx", "ry", "rz"),
        }
        out = []
        for name, kind, follows in zip(self.joint_names, self.joint_types, self._follows):
            if not follows:
                out += [f"{name}.{c}" for c in suffixes[kind]] if kind in suffixes else [name] * JOINT_DOF[kind]
        return out

    def zero(self, batch: int | None = None) -> Configuration:
        return np.zeros(self.dof if batch is None else (batch, self.dof))

    def pack(self, values: dict[str, Any]) -> Configuration:
        """A configuration vector from {joint name: value}; unnamed joints stay at 0. A ball joint
        takes a rotation vector (3 values) or a w,x,y,z quaternion (4 values); a floating joint
        x, y, z and a rotation vector (6), x, y, z and a quaternion (7) or a 4x4 rigid transform;
        a planar joint a, b, theta. Mimic joints follow the joint they mimic and take no value."""
        q = self.zero()
        index = {name: i for i, name in enumerate(self.joint_names)}
        for name, value in values.items():
            if name not in index:
                raise KinematicsError(f"no joint named '{name}'")
            i = index[name]
            if self._follows[i]:
                raise KinematicsError(f"joint '{name}' mimics '{self.mimic[i][0]}': set that joint instead")
            kind, value = self.joint_types[i], np.asarray(value, np.float64)
            if not np.isfinite(value).all():
                raise KinematicsError(f"joint '{name}': value {value.tolist()} is not finite")
            value = _joint_values(name, kind, value)
            q[self.dof_offsets[i] : self.dof_offsets[i] + len(value)] = value
        return q

    def _check_configuration(self, q):
        q = np.asarray(q, dtype=np.float64)
        if q.shape[-1:] != (self.dof,) or q.ndim > 2:
            raise KinematicsError(f"configuration has shape {q.shape}, expected ({self.dof},) or (B, {self.dof})")
        if not np.isfinite(q).all():
            raise KinematicsError("configuration has non-finite values")
        return q

    def clamp(self, q: Configuration) -> Configuration:
        """The configuration with every joint inside its limits (ball joints: angle <= upper)."""
        q = self._check_configuration(q).copy()
        one = self._limited
        cols = self.dof_offsets[one]
        q[..., cols] = np.clip(q[..., cols], self.lower[one], self.upper[one])
        if len(self._ball):
            v = q[..., self._ball_cols]
            angle = np.linalg.norm(v, axis=-1)
            shrink = np.minimum(1.0, self.upper[self._ball] / np.where(angle > 0, angle, 1.0))
            q[..., self._ball_cols] = v * shrink[..., None]
        return q

    def within_limits(self, q: Configuration, tol: float = 1e-12) -> Any:
        """True for each configuration (scalar for one) whose joints all respect their limits."""
        q = self._check_configuration(q)
        return np.all(np.abs(self.clamp(q) - q) <= tol, axis=-1)

    def joint_values(self, q):
        """(..., L) the value of each one-value joint (mimic joints included: multiplier * q_source +
        offset); 0 for other joints."""
        q = self._check_configuration(q)
        one = np.concatenate([self._rotating, self._prismatic])
        out = np.zeros(q.shape[:-1] + (len(self),))
        out[..., one] = q[..., self.dof_offsets[one]] * self._scale[one] + self._shift[one]
        return out

    # forward kinematics ---------------------------------------------------------------------

    def _local_transforms(self, q):
        """Parent-relative transforms origins[i] @ motion_i(q) for a batch (B, dof), laid out
        (L, B, 4, 4) so that each tree level gathers whole contiguous blocks."""
        local = np.empty((len(self), len(q), 4, 4))
        local[:] = self.origins[:, None]
        rot, pri = self._rotating, self._prismatic
        value = lambda links: (q[:, self.dof_offsets[links]] * self._scale[links] + self._shift[links]).T
        if len(rot):
            # Rodrigues with the origin folded in: O R(t) = O + sin(t) O K + (1 - cos(t)) O K^2.
            angle = value(rot)[..., None, None]
            o_k, o_k2 = self._origin_rodrigues
            local[rot, :, :3, :3] += np.sin(angle) * o_k[:, None] + (1.0 - np.cos(angle)) * o_k2[:, None]
        if len(pri):
            shift = self.origins[pri, :3, :3] @ self.axes[pri, :, None]  # axis in the parent frame
            local[pri, :, :3, 3] += value(pri)[..., None] * shift[:, None, :, 0]
        for links, turn, move in self._free_motions(q):
            o = self.origins[links, None, :3, :3]
            local[links, :, :3, 3] += (o @ move[..., None])[..., 0]
            local[links, :, :3, :3] = o @ turn
        return local

    def _free_motions(self, q):
        """(links, (n,B,3,3) rotations, (n,B,3) translations) for ball, planar and floating joints."""
        cols = lambda links, k: np.swapaxes(q[:, self.dof_offsets[links][:, None] + np.arange(k)], 0, 1)
        out = []
        if len(self._ball):
            out.append((self._ball, _rotvec_matrices(cols(self._ball, 3)), np.zeros((len(self._ball), len(q), 3))))
        if len(self._planar):
            v = cols(self._planar, 3)
            axes, plane = self.axes[self._planar, None], self.plane_axes[self._planar, None]
            move = v[..., :1] * plane[..., 0, :] + v[..., 1:2] * plane[..., 1, :]
            out.append((self._planar, axis_angle_matrices(axes, v[..., 2]), move))
        if len(self._floating):
            v = cols(self._floating, 6)
            out.append((self._floating, _rotvec_matrices(v[..., 3:]), v[..., :3]))
        return out

    def forward_kinematics(
        self, q: ArrayLike | None = None, base: Matrix4 | None = None, clamp: bool = False
    ) -> LinkTransforms:
        """World transforms of every link: (L,4,4) for one configuration (dof,), (B,L,4,4) for a
        batch (B,dof). `base` (4,4) places the roots; `clamp` first applies the joint limits."""
        kernel = _fk_kernel()
        if kernel is not None and q is not None and not clamp and self.names:
            q = np.asarray(q, dtype=np.float64)
            if q.ndim == 1 and base is None and q.shape[0] == self.dof:  # the planner's hot path
                world = np.empty((1, len(self.names), 4, 4))
                if kernel(q.reshape(1, -1), self._kernel_ints, self._kernel_floats, _IDENTITY, world):
                    return world[0]
            return self._compiled_fk(q, base)
        q = self.zero() if q is None else self._check_configuration(q)
        if clamp:
            q = self.clamp(q)
        if kernel is not None and len(self):
            return self._compiled_fk(q, base)
        base = _IDENTITY if base is None else _check_base(base)
        single = q.ndim == 1
        local = self._local_transforms(np.atleast_2d(q))
        world = np.empty_like(local)
        for level in self._levels:
            parent = self.parents[level]
            if parent[0] < 0:  # depth 0: the roots
                world[level] = base @ local[level]
            else:
                world[level] = world[parent] @ local[level]
        return world[:, 0] if single else np.ascontiguousarray(np.swapaxes(world, 0, 1))

    def _compiled_fk(self, q, base):
        """The compiled pass, checks included (it reports non-finite values itself): a few
        microseconds for one configuration."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape[-1:] != (self.dof,) or q.ndim > 2:
            self._check_configuration(q)  # raises, naming the shape
        base = _IDENTITY if base is None else _check_base(base)
        q2 = q if q.ndim == 2 else q.reshape(1, self.dof)
        world = np.empty((len(q2), len(self), 4, 4))
        tables, kernel = (self._kernel_ints, self._kernel_floats, base), _fk_kernel()
        if len(q2) >= _PARALLEL_BATCH:
            from .parallel import map_threads

            halves = [(h[0], h[-1] + 1) for h in np.array_split(np.arange(len(q2)), 2)]
            finite = all(map_threads(lambda h: kernel(q2[h[0] : h[1]], *tables, world[h[0] : h[1]]), halves))
        else:
            finite = kernel(q2, *tables, world)
        if not finite:
            raise KinematicsError("configuration has non-finite values")
        return world if q.ndim == 2 else world[0]

    def rest_transforms(self, base: Matrix4 | None = None) -> LinkTransforms:
        """World transforms of every link at the zero configuration, (L,4,4)."""
        return self.forward_kinematics(None, base=base)

    def deform_matrices(
        self, q: ArrayLike | None = None, base: Matrix4 | None = None, clamp: bool = False
    ) -> LinkTransforms:
        """Per-link skinning matrices world(q) @ inverse(world(0)): what a splat bound to a link
        at rest goes through (Blender's pose @ inverse(rest))."""
        rest_inv = np.linalg.inv(self.rest_transforms(base))
        return self.forward_kinematics(q, base=base, clamp=clamp) @ rest_inv


_IDENTITY = np.eye(4)
_PARALLEL_BATCH = 8192  # configurations from which both cores share forward kinematics


def _check_base(base):
    base = np.asarray(base, np.float64)
    if base.shape != (4, 4):
        raise KinematicsError(f"base has shape {base.shape}, expected (4, 4)")
    if not np.isfinite(base).all():
        raise KinematicsError("base matrix has non-finite values")
    if (base[3] != [0.0, 0.0, 0.0, 1.0]).any():
        raise KinematicsError(f"base matrix's last row {base[3].tolist()} is not 0 0 0 1 (not affine)")
    return np.ascontiguousarray(base)


def _plane_axes(axes):
    """(L,2,3) two unit vectors spanning the plane normal to each axis: x projected into the plane
    (y when the axis is along x) and axis x that; for the z axis they are x and y."""
    axes = np.asarray(axes, np.float64)
    helper = np.where(np.abs(axes[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    u = helper - (helper * axes).sum(axis=1, keepdims=True) * axes
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.stack([u, np.cross(axes, u)], axis=1)


def _rotvec_matrices(v):
    return geometry.quaternions_to_matrices(rotvec_to_quaternions(v))


def _joint_values(name, kind, value):
    """A joint's configuration values from what `pack` was given."""
    if kind == "ball" and value.size == 4:
        value = quaternions_to_rotvec(value.reshape(4))
    elif kind == "floating" and value.shape == (4, 4):
        r, t = value[:3, :3], value[:3, 3]
        rigid = np.abs(r.T @ r - np.eye(3)).max() <= 1e-6 and np.linalg.det(r) > 0
        if not rigid or (value[3] != [0, 0, 0, 1]).any():
            raise KinematicsError(f"joint '{name}' (floating): the 4x4 matrix is not a rigid transform")
        value = np.concatenate([t, quaternions_to_rotvec(geometry.matrices_to_quaternions(r))])
    elif kind == "floating" and value.size == 7:
        value = np.concatenate([value.reshape(7)[:3], quaternions_to_rotvec(value.reshape(7)[3:])])
    value = value.reshape(-1)
    if len(value) != JOINT_DOF[kind]:
        raise KinematicsError(f"joint '{name}' ({kind}) takes {JOINT_DOF[kind]} values, got {len(value)}")
    return value


# the compiled pass: one configuration at a time, every link in topological order ------------------


def _rotvec_into(vx, vy, vz, r):
    """r (3,3) = the rotation by rotation vector v (Rodrigues; a series below 1e-4 rad)."""
    t2 = vx * vx + vy * vy + vz * vz
    if t2 < 1e-8:
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        t = np.sqrt(t2)
        a, b = np.sin(t) / t, (1.0 - np.cos(t)) / t2
    r[0, 0] = 1.0 - b * (vy * vy + vz * vz)
    r[1, 1] = 1.0 - b * (vx * vx + vz * vz)
    r[2, 2] = 1.0 - b * (vx * vx + vy * vy)
    r[0, 1], r[1, 0] = b * vx * vy - a * vz, b * vx * vy + a * vz
    r[0, 2], r[2, 0] = b * vx * vz + a * vy, b * vx * vz - a * vy
    r[1, 2], r[2, 1] = b * vy * vz - a * vx, b * vy * vz + a * vx


def _fk_pass(q, ints, floats, base, out):
    """out (B,L,4,4) = world transforms for configurations q (B,dof); False (nothing written) when q
    holds a non-finite value. ints (L,3): parent, joint code, first column; floats (L,23): the
    origin's top 3x4, mimic multiplier and offset, axis, two plane axes (see KinematicTree)."""
    for b in range(q.shape[0]):
        for c in range(q.shape[1]):
            if not np.isfinite(q[b, c]):
                return False
    r = np.empty((3, 3))
    t = np.empty(3)
    local = np.empty((3, 4))
    for b in range(q.shape[0]):
        for i in range(ints.shape[0]):
            p, code, c = ints[i, 0], ints[i, 1], ints[i, 2]
            o = floats[i]
            ax, ay, az = o[14], o[15], o[16]
            for a in range(3):
                t[a] = 0.0
                for k in range(3):
                    r[a, k] = 1.0 if a == k else 0.0
            if code == 1:  # revolute, continuous
                x = q[b, c] * o[12] + o[13]
                _rotvec_into(ax * x, ay * x, az * x, r)
            elif code == 2:  # prismatic
                x = q[b, c] * o[12] + o[13]
                t[0], t[1], t[2] = ax * x, ay * x, az * x
            elif code == 3:  # ball
                _rotvec_into(q[b, c], q[b, c + 1], q[b, c + 2], r)
            elif code == 4:  # planar
                x = q[b, c + 2]
                _rotvec_into(ax * x, ay * x, az * x, r)
                for a in range(3):
                    t[a] = q[b, c] * o[17 + a] + q[b, c + 1] * o[20 + a]
            elif code == 5:  # floating
                _rotvec_into(q[b, c + 3], q[b, c + 4], q[b, c + 5], r)
                for a in range(3):
                    t[a] = q[b, c + a]
            for a in range(3):  # local = origin @ [r | t]
                for k in range(3):
                    local[a, k] = o[4 * a] * r[0, k] + o[4 * a + 1] * r[1, k] + o[4 * a + 2] * r[2, k]
                local[a, 3] = o[4 * a] * t[0] + o[4 * a + 1] * t[1] + o[4 * a + 2] * t[2] + o[4 * a + 3]
            out[b, i, 3, 0], out[b, i, 3, 1], out[b, i, 3, 2], out[b, i, 3, 3] = 0.0, 0.0, 0.0, 1.0
            for a in range(3):  # world = world[parent] (or base) @ local
                for k in range(4):
                    if p >= 0:
                        s = out[b, p, a, 3] if k == 3 else 0.0
                        for m in range(3):
                            s += out[b, p, a, m] * local[m, k]
                    else:
                        s = base[a, 3] if k == 3 else 0.0
                        for m in range(3):
                            s += base[a, m] * local[m, k]
                    out[b, i, a, k] = s
    return True


def _fk_kernel():
    """The compiled FK pass (core.jit), or None: the NumPy path then does the work."""
    return jit.compiled(__name__, ("_rotvec_into", "_fk_pass"))
