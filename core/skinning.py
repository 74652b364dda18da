"""Skinning: splats bound to bones follow them, centres, covariances and SH colours alike.

Each bone brings a 4x4 deform matrix D = pose @ inverse(rest) (both in the same object space, as
Blender's Armature modifier uses them). A splat carries up to k (bone, weight) pairs.

Linear blend (LBS): the splat's map is the weighted sum of its bones' D, exactly Blender's plain
Armature modifier (weights are normalised by their total). Its linear part M is not a rotation
where bones disagree (blending two turns shrinks space across the bend), so by default the
covariance turns by the polar rotation of M and stretches by the blend of the bones' own stretches
(the symmetric factors of their polar decompositions): a pure turn unless a bone scales.
`lbs_stretch="blend"` uses M Sigma M^T instead, shrink included.

Dual quaternion (DQS): Blender's "Preserve Volume". Each bone's D is split as Blender does into a
rigid part (a unit dual quaternion) and a scale/shear matrix about the bone's rest frame; dual
quaternions blend with the antipodal sign chosen against the running sum, the scale matrices
blend linearly about the splat centre, and the covariance goes through rotation @ blended scale.

The SH coefficients of every splat turn with the same rotation (sh.rotate, batched Wigner-D), and
splats bound to a single bone (rigid binding, as for robot links) move exactly by that bone:
mu' = T mu, Sigma' = R Sigma R^T.

Binding strength (the Armature modifier's vertex-group mask): a splat of strength m in [0, 1] moves
as Blender moves a masked vertex, mu' = (1 - m) mu + m mu_posed, in both modes. Its covariance and SH
turn by the blend of the bones' map with the identity: under LBS the identity joins as one more
influence of weight 1 - m (the bones sharing m), which is exactly the map that moves the centre;
under DQS the bones' unit rotation is blended with the identity quaternion, weights m and 1 - m
(on the same side, then normalised), and their scale matrix with I the same way. (Blender's DQS
centre is a linear blend of two positions, not a dual-quaternion blend with the identity, so under
DQS that turn is the consistent choice, not one map moving both.)
"""

from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from numpy.typing import NDArray

from . import geometry
from . import sh as shmod
from .arrays import ArrayLike, Floats, Matrices4, Positions, Weights
from .parallel import in_chunks
from .splats import NORMAL_EXTRAS, SplatCloud

# Blender leaves a vertex in place when the total of its weights is not above this.
MIN_TOTAL_WEIGHT = 1e-4
# A bone whose polar stretch is within RIGID_TOLERANCE of I does not scale. Blender's pose matrices are
# float32 products along the bone chain: turning bones alone leaves a stretch of about 1.5 float32 eps
# per chain level (measured: median 1.4 eps, at most 6.8 for 3-deep chains, 23 for 16-deep ones), which
# is rounding, not scale. 32 eps (3.8e-6) covers chains of about 20 bones, keeps a real scale of 1.001
# (a stretch of 1e-3) 260 times above it, and treating such a bone as rigid moves a covariance by at most
# 2 x 32 eps relative, below the 1e-5 to which Blender's own float32 skinning matches ours.
RIGID_TOLERANCE = 32 * float(np.finfo(np.float32).eps)
_POLAR_TOLERANCE = 1e-7  # the blended matrices' polar rotations to ~1e-12: far below float32 output
_CHUNK = 1 << 14  # splats per work item: float64 temporaries stay in cache


class SkinningError(ValueError):
    """A binding or pose that cannot be used; the message names the field and the problem."""


# binding ------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Binding:
    """Sparse per-splat bone weights: indices (N,k) int32 and weights (N,k) float32. Build it
    with `from_weights`, `from_dense` or `rigid`, which validate, normalise and prune.

    Rows sum to 1 and keep the order the influences were given in (see `from_weights`); a row of
    zeros is unbound and its splat stays where it is. `pruned` (N,) is the fraction of each
    splat's original weight that the tolerance or the influence limit dropped.
    """

    indices: Annotated[NDArray[np.integer], "(N, k) bone indices"]
    weights: Annotated[Floats, "(N, k)"]
    pruned: Annotated[Floats, "(N,)"] | None = None

    def __post_init__(self) -> None:
        self.indices = np.asarray(self.indices, dtype=np.int32)
        self.weights = np.asarray(self.weights, dtype=np.float32)
        if self.pruned is None:
            self.pruned = np.zeros(len(self.weights), np.float32)
        if self.indices.ndim != 2 or self.indices.shape != self.weights.shape:
            raise SkinningError(
                f"binding indices {self.indices.shape} and weights {self.weights.shape} must both have shape (N, k)"
            )

    def __len__(self):
        return len(self.weights)

    @property
    def influences(self) -> int:
        return self.weights.shape[1]

    @classmethod
    def from_weights(
        cls, indices: ArrayLike, weights: ArrayLike, max_influences: int | None = None, tolerance: float = 1e-6
    ) -> "Binding":
        """Normalise and prune per-splat (bone index, weight) lists of any width m.

        Weights below `tolerance` times their splat's total are dropped, then all but the
        `max_influences` largest; the rest is renormalised (Blender divides by the total too) and
        keeps its given order. That order matters to dual-quaternion blending of three or more
        bones whose rotations differ widely (each quaternion joins the running sum on its side),
        so give a vertex's groups in Blender's order to match Blender there.
        A splat whose weights total no more than MIN_TOTAL_WEIGHT is unbound, as in Blender.
        """
        indices = np.asarray(indices)
        weights = np.asarray(weights, dtype=np.float64)
        if indices.ndim == 1:
            indices, weights = indices[:, None], weights[:, None]
        _check_weights(indices, weights)
        return cls._build(indices, weights, weights.sum(axis=1), max_influences, tolerance)

    @classmethod
    def from_dense(cls, weights: Weights, max_influences: int | None = None, tolerance: float = 1e-6) -> "Binding":
        """From a dense (N, B) weight matrix (e.g. Blender vertex groups, one column per bone)."""
        weights = np.asarray(weights, dtype=np.float64)
        if weights.ndim != 2:
            raise SkinningError(f"dense weights must have shape (N, B), got {weights.shape}")
        bones = np.broadcast_to(np.arange(weights.shape[1]), weights.shape)
        _check_weights(bones, weights)
        k = weights.shape[1] if max_influences is None else max(1, min(max_influences, weights.shape[1]))
        top = np.sort(np.argpartition(-weights, k - 1, axis=1)[:, :k], axis=1) if k < weights.shape[1] else bones
        # The totals come from every bone, so what the influence limit drops counts as pruned.
        return cls._build(top, np.take_along_axis(weights, top, axis=1), weights.sum(axis=1), max_influences, tolerance)

    @classmethod
    def _build(cls, indices, weights, total, max_influences, tolerance):
        if max_influences is not None and max_influences < 1:
            raise SkinningError(f"max_influences must be at least 1, got {max_influences}")
        bound = total > MIN_TOTAL_WEIGHT
        # Rank by weight to choose what stays, but keep the given order of what stays: dual
        # quaternions are blended in that order, as Blender blends a vertex's groups.
        by_weight = np.argsort(-weights, axis=1, kind="stable")
        keep_ranked = bound[:, None] & (np.take_along_axis(weights, by_weight, axis=1) > tolerance * total[:, None])
        if max_influences is not None:
            keep_ranked[:, max_influences:] = False
        keep = np.zeros_like(keep_ranked)
        np.put_along_axis(keep, by_weight, keep_ranked, axis=1)
        order = np.argsort(~keep, axis=1, kind="stable")  # kept ones first, in given order
        width = max(int(keep.sum(axis=1).max(initial=0)), 1)
        order = order[:, :width]
        keep = np.take_along_axis(keep, order, axis=1)
        kept = np.where(keep, np.take_along_axis(weights, order, axis=1), 0.0)
        kept_total = kept.sum(axis=1)
        normalised = kept / np.where(kept_total > 0, kept_total, 1.0)[:, None]
        pruned = np.where(bound, 1.0 - kept_total / np.where(bound, total, 1.0), 0.0)
        return cls(np.where(keep, np.take_along_axis(indices, order, axis=1), 0), normalised, pruned)

    @classmethod
    def rigid(cls, bone_of_splat: ArrayLike) -> "Binding":
        """One bone per splat with weight 1 (robot links): the exact rigid special case."""
        bone = np.asarray(bone_of_splat).reshape(-1, 1)
        if (bone < 0).any():
            raise SkinningError("rigid binding has negative bone indices")
        return cls(bone, np.ones(bone.shape))

    def report(self):
        """What binding and pruning did, as plain numbers."""
        bound = self.weights.sum(axis=1) > 0
        used = (self.weights > 0).sum(axis=1)
        return {
            "splats": len(self),
            "unbound": int((~bound).sum()),
            "max_influences": int(used.max(initial=0)),
            "mean_influences": float(used[bound].mean()) if bound.any() else 0.0,
            "pruned_splats": int((self.pruned > 0).sum()),
            "max_pruned_weight": float(self.pruned.max(initial=0.0)),
            "mean_pruned_weight": float(self.pruned.mean()) if len(self) else 0.0,
        }

    def _check_against(self, n_splats, n_bones):
        if len(self) != n_splats:
            raise SkinningError(f"binding has {len(self)} rows for {n_splats} splats")
        used = self.weights > 0
        if used.any() and (self.indices[used].max() >= n_bones or self.indices[used].min() < 0):
            raise SkinningError(
                f"binding refers to bone {int(self.indices[used].max())} but the pose has {n_bones} bones"
            )


def _check_weights(indices, weights):
    if indices.shape != weights.shape or indices.ndim != 2:
        raise SkinningError(f"bone indices {indices.shape} and weights {weights.shape} must both be (N, m)")
    if not np.issubdtype(indices.dtype, np.integer):
        raise SkinningError(f"bone indices must be integers, got {indices.dtype}")
    bad = ~np.isfinite(weights)
    if bad.any():
        raise SkinningError(f"weights are not finite for {int(bad.any(axis=1).sum())} splats")
    if (weights < 0).any():
        raise SkinningError(f"weights are negative for {int((weights < 0).any(axis=1).sum())} splats")
    if (indices[weights > 0] < 0).any():
        raise SkinningError("bone indices with a nonzero weight are negative")


# pose ---------------------------------------------------------------------------------------------


def deform_matrices(rest: Matrices4, pose: Matrices4) -> Matrices4:
    """Blender's skinning matrices pose @ inverse(rest) for (B,4,4) rest and pose bone matrices
    (e.g. `bone.matrix_local` and `pose_bone.matrix`, both in armature space)."""
    rest, pose = np.asarray(rest, np.float64), np.asarray(pose, np.float64)
    return pose @ np.linalg.inv(rest)


@dataclass(eq=False)
class BonePose:
    """Per-bone transforms of one pose, with what both skinning modes need precomputed.

    deform: (B,4,4) pose @ inverse(rest). rest: (B,4,4) rest matrices; only dual-quaternion
    skinning of scaled bones uses them (Blender splits scale from rotation in the bone's rest
    frame); None means identity.
    """

    deform: Matrices4
    rest: Matrices4 | None = None
    derived: dict = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.deform = _check_matrices("deform", self.deform)
        n = len(self.deform)
        self.rest = np.broadcast_to(np.eye(4), (n, 4, 4)) if self.rest is None else _check_matrices("rest", self.rest)
        if self.rest.shape != self.deform.shape:
            raise SkinningError(f"rest matrices {self.rest.shape} do not match deform matrices {self.deform.shape}")
        flat = np.abs(geometry.determinants(self.rest[:, :3, :3])) < 1e-12
        if flat.any():
            raise SkinningError(f"rest matrices of bones {np.flatnonzero(flat)[:10].tolist()} are singular")
        self.derived = {**_lbs_bones(self.deform), **_dqs_bones(self.deform, self.rest)}

    @classmethod
    def from_blender(cls, rest: Matrices4, pose: Matrices4) -> "BonePose":
        """From armature-space rest (`bone.matrix_local`) and pose (`pose_bone.matrix`) matrices."""
        return cls(deform_matrices(rest, pose), rest)

    def __len__(self):
        return len(self.deform)


def _check_matrices(name, m):
    m = np.asarray(m, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] != (4, 4):
        raise SkinningError(f"{name} matrices must have shape (B, 4, 4), got {m.shape}")
    bad = ~np.isfinite(m).all(axis=(1, 2))
    if bad.any():
        raise SkinningError(f"{name} matrices of bones {np.flatnonzero(bad)[:10].tolist()} are not finite")
    return m


# Per-splat work is done on component-first arrays (components, n): every gather and product
# then runs over contiguous rows, several times faster than on (n, 3, 4) stacks.
_LINEAR = [0, 1, 2, 4, 5, 6, 8, 9, 10]  # the 3x3 part of a flattened 3x4 affine
_IDENTITY12 = np.eye(3, 4).reshape(12, 1)


def _lbs_bones(deform):
    """Per bone: the affine rows, the polar rotation and stretch of the linear part, and the
    rotation's quaternion (of the proper rotation, for mirrored bones)."""
    rotation, stretch = geometry.polar_decomposition(deform[:, :3, :3])
    rigid = np.abs(stretch - np.eye(3)).max(axis=(1, 2)) <= RIGID_TOLERANCE
    stretch[rigid] = np.eye(3)
    sign = np.where(geometry.determinants(rotation) < 0, -1.0, 1.0)[:, None, None]
    return {
        "affine": _rows(deform[:, :3, :4]),
        "rotation": rotation,
        "stretch": _rows(stretch),
        "scales": ~rigid,
        "quat": _rows(geometry.matrices_to_quaternions(sign * rotation)),
    }


def _dqs_bones(deform, rest):
    """Per bone, Blender's split of a deform matrix into a dual quaternion and a scale matrix."""
    lin = deform[:, :3, :3]
    base = deform @ rest  # the posed bone frame, scale included
    sizes = np.linalg.norm(base[:, :3, :3], axis=1)  # column lengths
    off = np.abs(np.swapaxes(lin, 1, 2) @ lin - np.eye(3)).max(axis=(1, 2))
    scaled = (off > 1e-6) | (geometry.determinants(lin) < 0) | (((sizes - 1.0) ** 2).sum(axis=1) > 1e-8)
    rigid = deform.copy()
    scale = np.broadcast_to(np.eye(4), deform.shape).copy()
    if scaled.any():
        base_r = _orthonormal_keep_y(base[scaled])  # Blender keeps the bone's Y axis
        rest_inv = np.linalg.inv(rest[scaled])
        rigid[scaled] = base_r @ rest_inv
        scale[scaled] = rest[scaled] @ np.linalg.inv(base_r) @ base[scaled] @ rest_inv
    quat = _rows(geometry.matrices_to_quaternions(_normalize_columns(rigid[:, :3, :3])))
    dual = 0.5 * _qmul(_pure(_rows(rigid[:, :3, 3])), quat)
    return {"dq_real": quat, "dq_dual": dual, "dq_scale": _rows(scale[:, :3, :4]), "dq_scaled": scaled}


def _rows(a):
    """(B, ...) per-bone values -> (components, B), contiguous."""
    return np.ascontiguousarray(a.reshape(len(a), -1).T)


def _normalize_columns(m):
    norm = np.linalg.norm(m, axis=-2, keepdims=True)
    return m / np.where(norm > 0, norm, 1.0)


def _orthonormal_keep_y(m):
    """Rigid transforms with the rotation rebuilt around each matrix's Y column (as Blender's
    orthogonalize_m4(m, 1)) and the translation kept."""
    x, y = m[:, :3, 0], _normalize_columns(m[:, :3, 1:2])[:, :, 0]
    y[np.linalg.norm(y, axis=1) == 0] = [0.0, 1.0, 0.0]  # a bone scaled to nothing along Y
    z = np.cross(x, y)
    degenerate = np.linalg.norm(z, axis=1) < 1e-12
    if degenerate.any():  # X along Y: any perpendicular will do
        helper = np.where(np.abs(y[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
        z[degenerate] = np.cross(helper, y)[degenerate]
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    out = np.zeros_like(m)
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2] = np.cross(y, z), y, z
    out[:, :3, 3], out[:, 3, 3] = m[:, :3, 3], 1.0
    return out


# component-first helpers --------------------------------------------------------------------------


def _pure(v):
    """(3, n) vectors as (4, n) quaternions (0, v)."""
    return np.concatenate([np.zeros((1,) + v.shape[1:]), v])


def _qmul(a, b):
    """Hamilton products of (4, n) w,x,y,z quaternions."""
    return geometry.multiply_quaternions(a.T, b.T).T


def _qrotate(q, p):
    """(3, n) points turned by (4, n) unit quaternions: p + w t + v x t with t = 2 v x p."""
    v = q[1:]
    t = 2.0 * np.cross(v, p, axis=0)
    return p + q[0] * t + np.cross(v, t, axis=0)


def _apply(m, p):
    """(12, n) flattened 3x4 affine maps applied to (3, n) points."""
    return np.stack([m[4 * i] * p[0] + m[4 * i + 1] * p[1] + m[4 * i + 2] * p[2] + m[4 * i + 3] for i in range(3)])


def _blend(table, idx, w):
    """sum_j w[j] * table[:, idx[j]]: (c, B) per-bone rows, (k, n) indices and weights -> (c, n)."""
    out = np.take(table, idx[0], axis=1)
    out *= w[0]
    for j in range(1, len(idx)):
        term = np.take(table, idx[j], axis=1)
        term *= w[j]
        out += term
    return out


def _matrices(rows9):
    """(9, n) row-major 3x3 entries -> (n, 3, 3)."""
    return np.ascontiguousarray(rows9.T).reshape(-1, 3, 3)


def _exact_weights(w):
    """(k, n) float64 weights summing to 1 to round-off (float32 storage is 6e-8 off, which would
    move splats a million units out by 0.06), and whether each splat is bound at all."""
    w = w.astype(np.float64)
    total = w.sum(axis=0)
    bound = total > 0
    return w / np.where(bound, total, 1.0), bound


# per-chunk skinning: p (3, n) float64, idx and w (k, n) -------------------------------------------


def _lbs_chunk(p, idx, w, m, bones, want_linear):
    """Centres, and (if wanted) the rotation and the covariance map of each splat under LBS; `m` (n,)
    binding strengths or None (all 1)."""
    w, bound = _exact_weights(w)
    blended = _blend(bones["affine"], idx, w)
    blended[:, ~bound] = _IDENTITY12  # unbound splats stay where they are
    if m is not None:  # the identity as an influence of weight 1 - m
        blended = m * blended + (1.0 - m) * _IDENTITY12
    centres = _apply(blended, p)
    if not want_linear:
        return centres, None
    linear_part = _matrices(blended[_LINEAR])
    multi = w[0] != 1.0  # kept influences come first
    if m is not None:
        multi |= m != 1.0
    if multi.all():
        rotation = geometry.polar_rotation(linear_part, _POLAR_TOLERANCE)
        sign = np.where(geometry.determinants(rotation) < 0, -1.0, 1.0)[:, None, None]
        quat = geometry.matrices_to_quaternions(sign * rotation).T
    else:
        rotation = bones["rotation"][idx[0]]
        quat = np.take(bones["quat"], idx[0], axis=1)
        if multi.any():
            rotation[multi] = geometry.polar_rotation(linear_part[multi], _POLAR_TOLERANCE)
            sign = np.where(geometry.determinants(rotation[multi]) < 0, -1.0, 1.0)[:, None, None]
            quat[:, multi] = geometry.matrices_to_quaternions(sign * rotation[multi]).T
    linear = {"rotation": rotation, "quat": quat, "blended": linear_part}
    if bones["scales"].any():
        scaled = (bones["scales"][idx] & (w > 0)).any(axis=0)
        stretch = _blend(bones["stretch"], idx[:, scaled], w[:, scaled])
        if m is not None:
            stretch = m[scaled] * stretch + (1.0 - m[scaled]) * np.eye(3).reshape(9, 1)
        linear["stretched"], linear["stretch"] = scaled, _matrices(stretch)
    return centres, linear


def _dqs_chunk(p, idx, w, m, bones, want_linear):
    """Centres, and (if wanted) the rotation and the covariance map of each splat under DQS; `m` (n,)
    binding strengths or None (all 1)."""
    w, _ = _exact_weights(w)
    n = p.shape[1]
    real, dual = np.zeros((4, n)), np.zeros((4, n))
    any_scaled = bones["dq_scaled"].any()
    if any_scaled:
        scale_sum, scale_weight = np.zeros((9, n)), np.zeros(n)
    for b, wj in zip(idx, w):
        q, d = np.take(bones["dq_real"], b, axis=1), np.take(bones["dq_dual"], b, axis=1)
        hit = np.flatnonzero(bones["dq_scaled"][b] & (wj > 0)) if any_scaled else ()
        if len(hit):
            s = np.take(bones["dq_scale"], b[hit], axis=1)
            # Blender blends scale about the splat centre: the shift the scale gives the centre
            # moves into the dual part, so the blended scale matrix keeps the centre fixed.
            d[:, hit] += 0.5 * _qmul(q[:, hit], _pure(_apply(s, p[:, hit]) - p[:, hit]))
            if want_linear:
                scale_sum[:, hit] += wj[hit] * s[_LINEAR]
                scale_weight[hit] += wj[hit]
        # Antipodal quaternions are the same rotation: add each on the side of the running sum.
        signed = np.where(np.einsum("in,in->n", real, q) < 0, -wj, wj)
        real += signed * q
        dual += signed * d
    norm2 = np.einsum("in,in->n", real, real)
    unbound = norm2 == 0.0  # all weights zero: stays in place
    real[0, unbound], norm2[unbound] = 1.0, 1.0
    unit = real / np.sqrt(norm2)
    conj = real * np.array([[1.0], [-1.0], [-1.0], [-1.0]])
    centres = _qrotate(unit, p) + 2.0 * _qmul(dual, conj)[1:] / norm2
    if m is not None:  # Blender: co + m (posed - co)
        centres = p + m * (centres - p)
    if not want_linear:
        return centres, None
    if m is not None:  # nlerp from the identity, on unit's side
        unit = m * unit
        unit[0] += np.where(unit[0] < 0, m - 1.0, 1.0 - m)
        unit /= np.linalg.norm(unit, axis=0)
        if any_scaled:
            scale_sum *= m
            scale_weight *= m
    linear = {"rotation": geometry.quaternions_to_matrices(unit.T), "quat": unit}
    if any_scaled:
        stretched = scale_weight > 0
        stretch = scale_sum[:, stretched] + (1.0 - scale_weight[stretched]) * np.eye(3).reshape(9, 1)
        linear["stretched"], linear["stretch"] = stretched, _matrices(stretch)
    return centres, linear


def _covariance_chunk(rotations, log_scales, linear, lbs_stretch):
    """New (4, n) w,x,y,z rotations and (3, n) log scales: a pure turn where no stretch applies,
    else Sigma' = M Sigma M^T re-diagonalised."""
    quat = geometry.normalize_quaternions(rotations)
    new_rot = _qmul(linear["quat"], quat.T)
    new_log = log_scales.T.astype(np.float64)
    if lbs_stretch == "blend":
        general = np.ones(len(quat), bool)
        maps = linear["blended"]
    elif "stretched" in linear:
        general = linear["stretched"]
        maps = linear["rotation"][general] @ linear["stretch"]
    else:
        return new_rot, new_log
    if general.any():
        q, sigma = geometry.transform_covariances(maps, quat[general], np.exp(new_log[:, general]).T)
        new_rot[:, general] = q.T
        new_log[:, general] = np.log(np.maximum(sigma, np.finfo(np.float32).tiny)).T
    return new_rot, new_log


_MODES = {"lbs": _lbs_chunk, "dqs": _dqs_chunk}


def _chunk_inputs(positions, binding, strength, a, b):
    """Splats a..b component-first: positions (3, n) float64, indices and weights (k, n), strengths
    (n,) float64 or None."""
    return (
        np.ascontiguousarray(positions[a:b].T, dtype=np.float64),
        np.ascontiguousarray(binding.indices[a:b].T),
        np.ascontiguousarray(binding.weights[a:b].T),
        None if strength is None else strength[a:b],
    )


def _check_strength(strength, n):
    """(n,) float64 binding strengths in [0, 1], or None when all are 1 (or none are given)."""
    if strength is None:
        return None
    strength = np.asarray(strength, np.float64).reshape(-1)
    if len(strength) != n:
        raise SkinningError(f"{len(strength)} binding strengths for {n} splats")
    bad = ~np.isfinite(strength) | (strength < 0) | (strength > 1)
    if bad.any():
        raise SkinningError(f"binding strengths must lie in 0..1; {int(bad.sum())} splats do not")
    return None if (strength == 1.0).all() else strength


def _check_call(arrays, binding, pose, mode, lbs_stretch="bones"):
    """Validate a skinning call; `arrays` maps field names to per-splat arrays that must be finite."""
    for name, values in arrays.items():
        ok = np.isfinite(values) | (np.isneginf(values) if name == "log_scales" else False)  # -inf: a zero scale
        bad = ~ok.reshape(len(values), -1).all(axis=1)
        if bad.any():
            raise SkinningError(f"{int(bad.sum())} splats have non-finite {name}")
    if mode not in _MODES:
        raise SkinningError(f"unknown skinning mode '{mode}' (known: {', '.join(_MODES)})")
    if lbs_stretch not in ("bones", "blend"):
        raise SkinningError(f"lbs_stretch must be 'bones' or 'blend', got '{lbs_stretch}'")
    if not isinstance(pose, BonePose):
        pose = BonePose(pose)
    binding._check_against(len(next(iter(arrays.values()))), len(pose))
    return pose


# public API ---------------------------------------------------------------------------------------


def skin_centres(
    positions: Positions,
    binding: Binding,
    pose: "BonePose | Matrices4",
    mode: str = "lbs",
    strength: Floats | None = None,
) -> Positions:
    """Posed centres (N,3) float64 only: the fastest path, and exactly what Blender's Armature
    modifier does to vertices (`mode="dqs"` is its Preserve Volume; `strength` (N,) in 0..1 its
    vertex-group mask). `pose` is a BonePose or (B,4,4) deform matrices."""
    positions = np.asarray(positions)
    bone_pose = _check_call({"positions": positions}, binding, pose, mode)
    strength = _check_strength(strength, len(positions))
    out = np.empty((len(positions), 3))
    chunk_fn, bones = _MODES[mode], bone_pose.derived

    def work(a, b):
        out[a:b] = chunk_fn(*_chunk_inputs(positions, binding, strength, a, b), bones, False)[0].T

    in_chunks(len(positions), work, _CHUNK)
    return out


def skin(
    cloud: SplatCloud,
    binding: Binding,
    pose: "BonePose | Matrices4",
    mode: str = "lbs",
    covariances: bool = True,
    sh: bool = True,
    lbs_stretch: str = "bones",
    strength: Floats | None = None,
) -> SplatCloud:
    """The posed cloud: centres moved, covariances turned (and stretched where bones scale), SH
    rotated. `covariances=False` moves centres only (as mesh-based add-ons do), `sh=False` keeps
    the SH as they are; `strength` (N,) in 0..1 fades each splat's binding (see the module's
    docstring). Normals (NORMAL_EXTRAS) turn with the covariances: by each splat's rotation, or by
    the inverse transpose of its covariance map where that stretches (_normal_chunk). Opacities and
    other extras are carried over unchanged."""
    finite = {"positions": cloud.positions}
    if covariances:
        finite.update(rotations=cloud.rotations, log_scales=cloud.log_scales)
    bone_pose = _check_call(finite, binding, pose, mode, lbs_stretch)
    n = len(cloud)
    strength = _check_strength(strength, n)
    positions = np.empty((n, 3), np.float32)
    rotations, log_scales = (
        (np.empty((n, 4), np.float32), np.empty((n, 3), np.float32))
        if covariances
        else (cloud.rotations, cloud.log_scales)
    )
    turn = np.empty((n, 3, 3)) if sh and cloud.sh_degree > 0 else None
    normals = _normals(cloud) if covariances else None
    chunk_fn, bones = _MODES[mode], bone_pose.derived
    stretch_mode = lbs_stretch if mode == "lbs" else "bones"

    def work(a, b):
        centres, linear = chunk_fn(
            *_chunk_inputs(cloud.positions, binding, strength, a, b), bones, covariances or turn is not None
        )
        positions[a:b] = centres.T
        if covariances:
            rot, log = _covariance_chunk(cloud.rotations[a:b], cloud.log_scales[a:b], linear, stretch_mode)
            rotations[a:b], log_scales[a:b] = rot.T, log.T
        if normals is not None:
            normals[a:b] = _normal_chunk(normals[a:b], linear, stretch_mode)
        if turn is not None:
            turn[a:b] = linear["rotation"]

    in_chunks(n, work, _CHUNK)
    new_sh = shmod.rotate(cloud.sh, turn) if turn is not None else cloud.sh
    extras = dict(cloud.extras)
    if normals is not None:
        extras.update({k: normals[:, i].astype(np.float32) for i, k in enumerate(NORMAL_EXTRAS)})
    return cloud.replace(positions=positions, rotations=rotations, log_scales=log_scales, sh=new_sh, extras=extras)


def _normals(cloud):
    """(N,3) float64 copy of the cloud's normals, or None when it has none."""
    if not all(k in cloud.extras for k in NORMAL_EXTRAS):
        return None
    return np.stack([cloud.extras[k].reshape(len(cloud)).astype(np.float64) for k in NORMAL_EXTRAS], axis=1)


def _normal_chunk(normals, linear, lbs_stretch):
    """(n,3) normals through the map the covariances take (_covariance_chunk): the rotation R (a
    rotation is its own inverse transpose), or the inverse transpose of M = R S where a stretch S
    applies (M, the blended matrix, with lbs_stretch="blend"), renormalised."""
    out = np.einsum("nij,nj->ni", linear["rotation"], normals)
    if lbs_stretch == "blend":
        return geometry.transform_normals(linear["blended"], normals)
    if "stretched" in linear and linear["stretched"].any():
        general = linear["stretched"]
        maps = linear["rotation"][general] @ linear["stretch"]
        out[general] = geometry.transform_normals(maps, normals[general])
    return out
