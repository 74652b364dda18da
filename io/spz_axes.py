"""The axes an SPZ file's values are in, and the turns between them and the model's RDF axes.

SPZ's documentation says RUB (x right, y up, z back); many files in the wild hold PLY's RDF values
instead, since Niantic's PLY converter long wrote "unspecified" axes. The coordinate-system extension
record (type 0xADBE0003, a u32 payload) names the axes a file's values are stored in: one of 16
systems, codes 1..16 in AXES order, 0 meaning unspecified (taken as absent). Each name's letters say
where the file's x, y and z axes point: Right/Left, Up/Down, Front/Back (codes 9..16 put front/back
on y and up/down on z, as Blender's RFU).

A turn is a signed permutation M (file axes -> RDF), proper or a mirror. Positions take M; each
covariance C becomes M C M^T, built back as the rotation M R M^T (for a mirror, the proper (-M) R (-M)^T: the
quaternion's vector part takes det(M) M) with the scales permuted as M permutes the axes; the SH
colour function f'(d) = f(M^T d), mirrors included (core.sh.rotate).

Niantic's library negates the m = +4 coefficient of degree 4 (our coefficient 24) whenever it
reverses the up/down axis, though that function is even in every axis; so a file whose vertical axis
says Up (RUB, RFU, ...) holds that coefficient negated, and reading and writing follow it, so that
files mean the same to that library and to us, both ways. Its conversion of LFD, RFD, LBU and RBU
(flipping the axes before its quarter turn about x) lands a further half turn about x from what their
letters say; we follow the letters.
"""

import numpy as np

from ..core import sh as shmod
from ..core.splats import NORMAL_EXTRAS, SplatCloud

COORDINATE_SYSTEM_EXT = 0xADBE0003
AXES = (
    "LDB", "RDB", "LUB", "RUB", "LDF", "RDF", "LUF", "RUF",
    "LFD", "RFD", "LFU", "RFU", "LBD", "RBD", "LBU", "RBU",
)  # fmt: skip
DEFAULT_AXES = "RUB"  # the documented axes, what a file without the record holds
# each letter as (model axis, sign) in RDF: x right, y down, z front
DIRECTIONS = {"R": (0, 1), "L": (0, -1), "D": (1, 1), "U": (1, -1), "F": (2, 1), "B": (2, -1)}
SH_M4 = 24  # the coefficient Niantic's tables negate with the vertical axis


def axes_name(axes: str) -> str:
    """The canonical (upper-case) name of an axis system, or ValueError listing the valid ones."""
    name = str(axes).upper()
    if name not in AXES:
        raise ValueError(f"unknown SPZ axes {axes!r}; one of {', '.join(AXES)} (e.g. 'rub', 'rdf')")
    return name


def axes_code(axes: str) -> int:
    """The coordinate-system record's value for an axis system (1..16)."""
    return AXES.index(axes_name(axes)) + 1


def axes_of_code(code: int) -> str | None:
    """The axis system a record's value names; None for 0 (unspecified) or a value past 16."""
    return AXES[code - 1] if 1 <= code <= len(AXES) else None


def axis_matrix(axes: str) -> np.ndarray:
    """M (3, 3), float64: a file's values in `axes` are M @ v in RDF (column i: where file axis i
    points)."""
    m = np.zeros((3, 3))
    for column, letter in enumerate(axes_name(axes)):
        row, sign = DIRECTIONS[letter]
        m[row, column] = sign
    return m


def up_negates_m4(axes: str) -> bool:
    """Whether a file in `axes` holds coefficient 24 negated (its vertical axis says Up)."""
    return "U" in axes_name(axes)


def to_model(cloud: SplatCloud, axes: str) -> SplatCloud:
    """The cloud whose values are stored in `axes`, in the model's RDF axes."""
    return _turn(_niantic_m4(cloud, axes), axis_matrix(axes))


def from_model(cloud: SplatCloud, axes: str) -> SplatCloud:
    """The values an SPZ file in `axes` stores for a cloud in RDF axes."""
    return _niantic_m4(_turn(cloud, axis_matrix(axes).T), axes)


def _niantic_m4(cloud, axes):
    if cloud.sh.shape[1] <= SH_M4 or not up_negates_m4(axes):
        return cloud
    sh = cloud.sh.copy()
    sh[:, SH_M4] *= -1
    return cloud.replace(sh=sh)


def _turn(cloud, m):
    """The cloud under the signed permutation m: exact for positions, normals, scales and quaternions
    (only moves and signs); SH by parity for a diagonal m, else by core.sh.rotate."""
    if np.array_equal(m, np.eye(3)):
        return cloud
    source = np.argmax(np.abs(m), axis=1)  # new axis i is sign[i] times old axis source[i]
    sign = m[np.arange(3), source].astype(np.float32)
    handed = np.float32(np.linalg.det(m))
    rotations = cloud.rotations.copy()
    rotations[:, 1:] = cloud.rotations[:, 1 + source] * (handed * sign)
    extras = dict(cloud.extras)
    if all(k in extras for k in NORMAL_EXTRAS):  # normals move like positions (m is orthogonal)
        extras.update({NORMAL_EXTRAS[i]: extras[NORMAL_EXTRAS[source[i]]] * sign[i] for i in range(3)})
    return cloud.replace(
        positions=cloud.positions[:, source] * sign,
        rotations=rotations,
        log_scales=cloud.log_scales[:, source],
        sh=_turn_sh(cloud.sh, m),
        extras=extras,
    )


def _turn_sh(sh, m):
    if sh.shape[1] == 1:
        return sh
    if np.array_equal(m, np.diag(np.diag(m))):  # axes reversed only: each function's parity, exact
        return sh * sh_signs(np.diag(m))[: sh.shape[1], None].astype(sh.dtype)
    return shmod.rotate(sh, m)


def sh_signs(signs) -> np.ndarray:
    """Sign of each SH basis function (degrees 0..4) under (x, y, z) -> signs * (x, y, z)."""
    d = np.array([[0.267, 0.535, 0.802]])  # no basis function vanishes here
    degree = shmod.MAX_DEGREE
    return np.sign(shmod.basis(d * signs, degree)[0] / shmod.basis(d, degree)[0]).astype(np.float32)
