"""The splat model: one cloud of N Gaussians stored as 3DGS training produces them."""

from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from . import geometry
from . import sh as shmod
from .arrays import (
    ArrayLike,
    Colors,
    Covariances,
    Floats,
    Logits,
    LogScales,
    Mask,
    Positions,
    Quaternions,
    SHCoefficients,
)

FIELDS = ("positions", "rotations", "log_scales", "opacity_logits", "sh")
# The extras holding a unit surface normal per splat (the PLY convention; core.material names them
# for relighting): transforms turn them, where every other extra is kept as it is.
NORMAL_EXTRAS = ("nx", "ny", "nz")

# transformed(): a linear part whose anisotropy (geometry.anisotropy) is at most this is treated as a
# similarity; the covariance error that allows (about twice this, relative) is float32 round-off.
SIMILARITY_TOLERANCE = 1e-6

# Values that overflow once used count as non-finite: a position coordinate beyond MAX_MAGNITUDE
# squares (and sums three squares, as distances and depths do) past float32's largest number, and a
# log-scale beyond MAX_LOG_SCALE has a linear scale exp(log_scale) past it (what OpenUSD, .splat and
# glTF store; exp(1e30) is inf outright). Quaternions are normalised in float64 (any float32 norm is
# fine), logits go through a sigmoid and SH enter colours linearly: those fields are refused only for
# NaN and Inf.
MAX_MAGNITUDE = float(np.sqrt(np.finfo(np.float32).max / 3.0))  # about 1.06e19
MAX_LOG_SCALE = 88.72  # exp: 3.39e38, float32's largest is 3.40e38
BOUNDED_FIELDS = ("positions",)


def bad_rows(name: str, values: ArrayLike) -> Mask:
    """(N,) True where a splat's values of field `name` (or of a float extra) are NaN, infinite, or
    overflow float32 once activated (see MAX_MAGNITUDE and MAX_LOG_SCALE). Integer extras are never bad."""
    values = np.asarray(values)
    flat = values.reshape(len(values), int(np.prod(values.shape[1:])))  # also for N = 0
    if values.dtype.kind not in "fc":
        return np.zeros(len(values), bool)
    with np.errstate(invalid="ignore"):
        if name == "log_scales":
            ok = (flat <= MAX_LOG_SCALE) & (flat > -np.inf)  # NaN fails both; -inf is a zero scale
        elif name in BOUNDED_FIELDS:
            ok = np.abs(flat) <= MAX_MAGNITUDE
        else:
            ok = np.isfinite(flat)
    return ~ok.all(axis=1) if flat.shape[1] else np.zeros(len(values), bool)


def memory_bytes(count: int, sh_degree: int) -> int:
    """Bytes the float32 fields of a cloud of `count` splats of `sh_degree` hold (extras aside): what
    one copy of the splats takes in memory, in the model or as Blender's attributes of either form."""
    return 4 * count * (3 + 4 + 3 + 1 + 3 * (sh_degree + 1) ** 2)


class SplatValidationError(ValueError):
    """A cloud whose arrays are malformed or hold values no renderer can use."""


def sigmoid(x: ArrayLike) -> Floats:
    x = np.asarray(x, dtype=np.float64)
    # exp(-|x|) never overflows, so +-1e4 logits give exactly 0 or 1 instead of a warning.
    with np.errstate(under="ignore"):
        e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def logit(p: ArrayLike, eps: float = 1e-7) -> Floats:
    p = np.clip(np.asarray(p, dtype=np.float64), eps, 1.0 - eps)
    return np.log(p) - np.log1p(-p)


def _float32(values) -> np.ndarray:
    """values as a float32 array, the same object when it is one already: np.asarray makes a new
    view of an array whose float32 dtype is an equal but other object (one unpickled, as from
    another process), and a replaced cloud's arrays would then no longer be its own
    (core.render.Shapes tells a cloud by them)."""
    if type(values) is np.ndarray and values.dtype == np.float32:
        return values
    return np.asarray(values, dtype=np.float32)


@dataclass(eq=False)
class SplatCloud:
    """N Gaussians. Arrays are float32; see the field table in the design notes.

    positions (N,3), rotations (N,4) w,x,y,z as stored, log_scales (N,3), opacity_logits (N,),
    sh (N,K,3) with K=(d+1)^2 and sh[:,0] the DC term. `extras` holds any other per-splat arrays
    (first axis N) that a file carried or a tool attached, e.g. PLY normals or the source triangle
    of a converted mesh; selection and concatenation keep them aligned. `antialiased` says the splats
    were made to be rendered with opacity compensation (Mip-Splatting's 2D filter, core.render's
    "antialiased" mode, SPZ's flag), which is then the mode they render in by default.
    """

    positions: Positions
    rotations: Quaternions
    log_scales: LogScales
    opacity_logits: Logits
    sh: SHCoefficients
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    antialiased: bool = False

    def __post_init__(self) -> None:
        for name in FIELDS:
            setattr(self, name, _float32(getattr(self, name)))
        self.extras = {k: np.asarray(v) for k, v in self.extras.items()}
        self.antialiased = bool(self.antialiased)
        self._check_shapes()

    # construction ---------------------------------------------------------------------------

    @classmethod
    def empty(cls, sh_degree: int = 0) -> "SplatCloud":
        k = shmod.num_coeffs(sh_degree)
        return cls(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, k, 3)))

    @classmethod
    def from_activated(
        cls,
        positions: Positions,
        rotations: Quaternions,
        scales: Floats,
        opacities: Floats,
        colors: Colors | None = None,
        sh: SHCoefficients | None = None,
        extras: dict[str, np.ndarray] | None = None,
    ) -> "SplatCloud":
        """Build from linear scales, opacities in [0,1] and either display-sRGB colours or raw SH."""
        positions = np.asarray(positions, dtype=np.float64)
        if sh is None:
            colors = np.zeros((len(positions), 3)) + 0.5 if colors is None else np.asarray(colors, np.float64)
            sh = shmod.rgb_to_dc(colors)[:, None, :]
        with np.errstate(divide="ignore"):
            log_scales = np.log(np.asarray(scales, dtype=np.float64))
        return cls(positions, rotations, log_scales, logit(opacities), sh, extras or {})

    @classmethod
    def concatenate(cls, clouds: Iterable["SplatCloud"]) -> "SplatCloud":
        """One cloud from many; lower SH degrees are zero-padded (same colours), extras kept where
        every cloud has them. Clouds made for different render modes cannot share one (ValueError):
        either mode would render some of them wrongly."""
        clouds = list(clouds)
        if not clouds:
            return cls.empty()
        modes = {c.antialiased for c in clouds}
        if len(modes) > 1:
            raise ValueError(
                "cannot join splats made for antialiased rendering with splats made for classic "
                "rendering; convert one of them again in the other mode"
            )
        degree = max(c.sh_degree for c in clouds)
        clouds = [c.with_sh_degree(degree) for c in clouds]
        common = set.intersection(*(set(c.extras) for c in clouds))
        return cls(
            **{name: np.concatenate([getattr(c, name) for c in clouds]) for name in FIELDS},
            extras={k: np.concatenate([c.extras[k] for c in clouds]) for k in sorted(common)},
            antialiased=modes.pop(),
        )

    # basic protocol ------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.positions)

    def __getitem__(self, index: Any) -> "SplatCloud":
        """Select splats by boolean mask, integer indices or slice."""
        if isinstance(index, (int, np.integer)):
            index = [index]
        return self.replace(
            **{name: getattr(self, name)[index] for name in FIELDS},
            extras={k: v[index] for k, v in self.extras.items()},
        )

    select = __getitem__

    def copy(self) -> "SplatCloud":
        return self.replace(
            **{name: getattr(self, name).copy() for name in FIELDS},
            extras={k: v.copy() for k, v in self.extras.items()},
        )

    def replace(self, **changes: Any) -> "SplatCloud":
        """A new cloud with some fields replaced (arrays are shared, not copied); what is not replaced,
        such as the render mode the splats were made for, carries over."""
        return replace(self, **changes)

    def __repr__(self) -> str:
        mode = ", antialiased" if self.antialiased else ""
        return f"SplatCloud(n={len(self)}, sh_degree={self.sh_degree}, extras={sorted(self.extras)}{mode})"

    # activated views ---------------------------------------------------------------------------

    @property
    def sh_degree(self) -> int:
        return shmod.degree_of(self.sh.shape[1])

    @property
    def scales(self) -> Floats:
        with np.errstate(over="ignore"):  # a log-scale beyond 709 is an infinite sigma: finite_mask says so
            return np.exp(self.log_scales.astype(np.float64))

    @property
    def opacities(self) -> Floats:
        return sigmoid(self.opacity_logits)

    @property
    def unit_rotations(self) -> Quaternions:
        """Normalised quaternions w,x,y,z, float64."""
        return geometry.normalize_quaternions(self.rotations)

    def rotation_matrices(self) -> Covariances:
        return geometry.quaternions_to_matrices(self.rotations)

    def covariances(self) -> Covariances:
        """World-space covariances R S S^T R^T, float64 (N,3,3)."""
        return geometry.covariances(self.rotations, self.scales)

    def colors(self, camera_center: ArrayLike | None = None, directions: Positions | None = None) -> Colors:
        """Display-sRGB colours (N,3) seen from a camera centre or along given view directions."""
        if directions is None:
            if camera_center is None:
                directions = np.tile([0.0, 0.0, 1.0], (len(self), 1))
            else:
                directions = self.positions.astype(np.float64) - np.asarray(camera_center, np.float64)
        return shmod.colors(self.sh, directions)

    def with_sh_degree(self, degree: int) -> "SplatCloud":
        """Truncate (or zero-pad) the SH to `degree`; truncation drops view-dependent detail only."""
        if degree == self.sh_degree:
            return self
        return self.replace(sh=shmod.truncate(self.sh, degree))

    # transforms ----------------------------------------------------------------------------------

    def transformed(self, matrix: ArrayLike) -> "SplatCloud":
        """The cloud under the affine map x -> A x + t, given as a 4x4 matrix (or a 3x3 A, t = 0).

        Positions become A p + t (in float64), covariances A Sigma A^T, re-diagonalised into rotations
        and log-scales, and the SH turn with R of the polar decomposition A = R S. Rigid and similarity
        maps, mirrors included, are exact; a non-uniform stretch S changes view-dependent colour in a
        way no SH rotation expresses, and geometry.anisotropy(A) says by how much. Output quaternions
        are unit (a zero one is read as the identity, as everywhere); non-finite values stay
        non-finite, so validation still reports them. Normals (NORMAL_EXTRAS) turn by the inverse
        transpose of A, renormalised; other extras are kept as they are. A singular, projective or
        non-finite matrix raises ValueError.
        """
        a, t = geometry.split_affine(matrix)
        rotation = geometry.polar_rotation(a)
        if geometry.anisotropy(a) <= SIMILARITY_TOLERANCE:
            rotations, log_scales = self._similarity_frames(a, rotation)
        else:
            rotations, log_scales = self._affine_frames(a)
        return self.replace(
            positions=self.positions.astype(np.float64) @ a.T + t,
            rotations=rotations,
            log_scales=log_scales,
            sh=shmod.rotate(self.sh, rotation),
            extras=self._transformed_normals(a),
        )

    def _transformed_normals(self, a) -> dict[str, np.ndarray]:
        """The extras with the normals (if the cloud has all three) turned by A^-T."""
        if not all(k in self.extras for k in NORMAL_EXTRAS):
            return self.extras
        stacked = np.stack([self.extras[k].reshape(len(self)) for k in NORMAL_EXTRAS], axis=1)
        turned = geometry.transform_normals(a, stacked).astype(np.float32)
        return {**self.extras, **{k: turned[:, i].copy() for i, k in enumerate(NORMAL_EXTRAS)}}

    def _similarity_frames(self, a, rotation):
        """A = scale * Q: quaternions compose with Q's proper part (-Q if Q mirrors, which leaves
        covariances alone) and log-scales shift by log(scale)."""
        turn = geometry.matrices_to_quaternions(rotation * np.sign(np.linalg.det(a)))
        rotations = self.rotations.astype(np.float64)
        ok = np.isfinite(rotations).all(axis=1)  # non-finite rows stay as they are
        rotations[ok] = geometry.multiply_quaternions(turn, self.unit_rotations[ok])
        return rotations, self.log_scales.astype(np.float64) + np.log(abs(np.linalg.det(a))) / 3.0

    def _affine_frames(self, a):
        """General A: re-diagonalise A Sigma A^T per splat (splats with non-finite values kept as they are)."""
        rotations, log_scales = self.rotations.astype(np.float64), self.log_scales.astype(np.float64)
        scales = self.scales
        ok = np.isfinite(rotations).all(axis=1) & np.isfinite(scales).all(axis=1)
        quaternions, sigma = geometry.transform_covariances(a, rotations[ok], scales[ok])
        rotations[ok] = quaternions
        with np.errstate(divide="ignore"):  # a zero scale stays a zero scale (log -inf)
            log_scales[ok] = np.log(sigma)
        return rotations, log_scales

    # validation --------------------------------------------------------------------------------

    def _check_shapes(self):
        n = len(self.positions)
        expect = {"positions": (n, 3), "rotations": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        wrong = [
            f"{k} has shape {getattr(self, k).shape}, expected {v}"
            for k, v in expect.items()
            if getattr(self, k).shape != v
        ]
        if (
            self.sh.ndim != 3
            or self.sh.shape[0] != n
            or self.sh.shape[2] != 3
            or self.sh.shape[1] not in shmod.VALID_COUNTS
        ):
            wrong.append(f"sh has shape {self.sh.shape}, expected ({n}, K, 3) with K in {shmod.VALID_COUNTS}")
        wrong += [
            f"extra '{k}' has {len(v)} rows, expected {n}" for k, v in self.extras.items() if v.ndim == 0 or len(v) != n
        ]
        if wrong:
            raise SplatValidationError("malformed splat cloud: " + "; ".join(wrong))

    def checked_arrays(self) -> dict[str, np.ndarray]:
        """{name: array} of every field and float extra the non-finite rule covers; extras are
        named "extra 'name'"."""
        arrays = {name: getattr(self, name) for name in FIELDS}
        arrays.update({f"extra '{k}'": v for k, v in self.extras.items() if v.dtype.kind in "fc"})
        return arrays

    def bad_counts(self) -> dict[str, int]:
        """{field: splats with NaN/Inf or overflowing values in it}, only the fields that have some."""
        counts = {}
        for name, values in self.checked_arrays().items():
            bad = int(bad_rows(name, values).sum())
            if bad:
                counts[name] = bad
        return counts

    def problems(self) -> list[str]:
        """Human-readable list of value problems (empty when the cloud is usable)."""
        found = [f"{count} splats with non-finite {name}" for name, count in self.bad_counts().items()]
        qn = np.linalg.norm(self.rotations.astype(np.float64), axis=1)
        zero = np.isfinite(qn) & (qn < 1e-12)
        if zero.any():
            found.append(f"{int(zero.sum())} splats with a zero rotation quaternion")
        return found

    def validate(self) -> "SplatCloud":
        """Raise SplatValidationError naming every problem and its count; return self if clean."""
        found = self.problems()
        if found:
            raise SplatValidationError("invalid splat cloud: " + "; ".join(found))
        return self

    def finite_mask(self) -> Mask:
        """True for splats whose every stored value (float extras included) is finite and stays
        finite when activated (see bad_rows)."""
        ok = np.ones(len(self), bool)
        for name, values in self.checked_arrays().items():
            ok &= ~bad_rows(name, values)
        return ok
