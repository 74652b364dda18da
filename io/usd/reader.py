"""Reading splats from an OpenUSD stage (`read`, `read_stage`, `read_frames`, `time_codes`).

Every splat prim of the stage (instance proxies included) in any dialect dialects.py reads; other
prims are skipped with a SplatFileWarning listing them. Each prim's local-to-world transform is
applied, then the stage's upAxis and metersPerUnit, then the flip from USD's Y-up (RUB) to the
model's 3DGS axes (RDF), so clouds come out in the model's axes and metres (see stage_matrix and
read_stage for the options). A ParticleField3DGaussianSplat without schema.UPRIGHT_OP is taken as
capture coordinates by default (unmarked="capture"). A transform that is not a rotation times a
uniform scale is exact for positions and covariances but not for SH colours; its anisotropy is
reported. A cloud read unchanged through an identity or flip keeps the file's linear values
(schema._READ_LINEAR), so writing it back reproduces them.
"""

import math
import os
import stat
import warnings
from dataclasses import dataclass, field

import numpy as np

from ...core import SplatCloud, geometry
from ..common import SplatFileError, SplatFileWarning, apply_nonfinite_policy
from ..spz import flip_yz
from . import stages
from .dialects import _dialect
from .schema import _READ_LINEAR, ANISOTROPY_TOLERANCE, TYPE_NAME, UNMARKED, UPRIGHT_OP, _file


@dataclass
class SplatPrim:
    """One splat prim of a stage: its path, the cloud (world space, target axes and units) and what
    reading it had to report."""

    path: str
    cloud: SplatCloud
    source: str  # "ParticleField3DGaussianSplat" or "Points (Adobe 3DGS primvars)"
    to_world: np.ndarray  # 4x4 (column vectors) applied to the prim's local values
    anisotropy: float = 0.0  # how far to_world is from rotation * uniform scale
    notes: list = field(default_factory=list)


# opening ------------------------------------------------------------------------------------------

MAGIC = {".usdc": (b"PXR-USDC",), ".usdz": (b"PK\x03\x04",), ".usda": (b"#usda",), ".usd": (b"PXR-USDC", b"#usda")}


def _open(path, allow_outside=False):
    """The stage (through the active stage implementation) of a regular file whose header matches
    its extension; the layers it composes (sublayers, references, payloads, value clips) must lie
    in its package or folder unless allow_outside (see pxr_stages._LayerWalk)."""
    path = os.fspath(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would hang the read, a device never end
            raise SplatFileError(path, "not a regular file (a FIFO, device or folder?)")
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise SplatFileError(path, f"cannot open: {exc.strerror or exc}") from None
    expected = MAGIC.get(os.path.splitext(path)[1].lower(), ())
    if expected and not any(head.startswith(m) for m in expected):
        names = " or ".join(repr(m.decode("latin-1")) for m in expected)
        raise SplatFileError(path, f"not a {os.path.splitext(path)[1]} file (it does not start with {names})")
    return stages.active.open(path, allow_outside)


# stage units and axes ----------------------------------------------------------------------------

Z_UP_TO_Y_UP = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)  # (x, y, z) -> (x, z, -y)
RUB_TO_RDF = np.diag([1.0, -1.0, -1.0])  # y and z reversed
AXES = ("RDF", "RUB", None)
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def stage_matrix(stage, axes="RDF", meters_per_unit=1.0, notes=None):
    """4x4 taking stage coordinates to the target axes and units.

    axes: "RDF" (the model's convention, as 3DGS PLY: y down, z forward), "RUB" (Y-up as USD
    itself), or None (keep the stage's axes, Z-up included). meters_per_unit None keeps its units.
    """
    if axes not in AXES:
        raise ValueError(f"axes must be one of {AXES}, got {axes!r}")
    notes = [] if notes is None else notes
    m = np.eye(4)
    if axes is not None:
        if _stage_metadata(stage, "upAxis", "Y") == "Z":
            m[:3, :3] = Z_UP_TO_Y_UP
        if axes == "RDF":
            m[:3, :3] = RUB_TO_RDF @ m[:3, :3]
    if meters_per_unit is not None:
        units = _stage_metadata(stage, "metersPerUnit", None)
        if units is None:
            notes.append("metersPerUnit is not authored; USD's fallback of 0.01 (centimetres) applies")
        m[:3, :3] *= (0.01 if units is None else units) / float(meters_per_unit)
    return m


def _stage_metadata(stage, key, fallback):
    """Layer metadata `key` (upAxis as "Y"/"Z", metersPerUnit as a positive float), or fallback if
    unauthored; any other value is a SplatFileError naming it (read raw: pxr's own accessors take an
    upAxis of "X" for Y)."""
    value = stages.active.metadata(stage, key)
    if value is None:
        return fallback
    path = stage.GetRootLayer().identifier
    if key == "upAxis":
        if str(value) not in ("Y", "Z"):
            raise SplatFileError(path, f"upAxis {str(value)!r}: an OpenUSD stage is Y-up or Z-up")
        return str(value)
    try:
        units = float(value)
    except (TypeError, ValueError):
        units = math.nan
    if not (math.isfinite(units) and units > 0):
        raise SplatFileError(path, f"metersPerUnit {value!r}: it must be a positive, finite number of metres")
    return units


# prims -------------------------------------------------------------------------------------------


def _op_order(prim):
    """The prim's xformOpOrder as a list of op names ([] if unauthored), or a SplatFileError when it
    holds anything else (a damaged crate file can point it at any value)."""
    attr = prim.GetAttribute("xformOpOrder")
    order = attr.Get() if attr else None
    if order is None:
        return []
    names = list(order) if not isinstance(order, str) and hasattr(order, "__iter__") else None
    if names is None or not all(isinstance(n, str) for n in names):
        raise SplatFileError(
            _file(prim),
            f"{prim.GetPath()}: xformOpOrder holds a {type(order).__name__}, not a list of transform op names",
        )
    return names


def _is_upright(prim):
    """Whether the prim stands a capture upright with our transform op."""
    return UPRIGHT_OP in _op_order(prim)


def _nonfinite_ops(prim, time):
    """Names of the prim's own transform ops whose values hold NaN or Inf."""
    names = [n.removeprefix("!invert!") for n in _op_order(prim)]
    bad = []
    for name in names:
        attr = prim.GetAttribute(name)
        value = attr.Get(time) if attr else None
        if hasattr(value, "GetImaginary"):  # a Gf quaternion
            value = [value.GetReal(), *value.GetImaginary()]
        try:
            numbers = np.asarray(value, np.float64)
        except (TypeError, ValueError):
            continue
        if not np.isfinite(numbers).all():
            bad.append(name)
    return bad


def _read_prim(prim, time, matrices, notes, world):
    """SplatPrim for a splat prim, or None for any other prim. matrices: (stage, capture) 4x4s taking
    world space to the target axes and units: stage-axes geometry, and the captures of prims that
    carry no upright transform (unmarked="capture")."""
    stage_m, capture_m = matrices
    dialect = _dialect(prim)
    if dialect is None:
        return None
    source, reader = dialect
    if source == TYPE_NAME and not _is_upright(prim):
        stage_m = capture_m
    prim_notes = []
    cloud, opacities, scales = reader(prim, time, prim_notes)
    to_world = stage_m @ world(prim)
    if not np.isfinite(to_world).all():
        ops = _nonfinite_ops(prim, time)
        where = f"its transform ops {', '.join(ops)} hold" if ops else "a parent prim's transform holds"
        raise SplatFileError(_file(prim), f"{prim.GetPath()}: {where} NaN or Inf")
    anisotropy = 0.0
    if np.array_equal(to_world, np.eye(4)) or np.array_equal(to_world, FLIP):
        cloud = cloud if to_world[1, 1] == 1 else flip_yz(cloud)  # exact: only signs change
        _READ_LINEAR[cloud] = (cloud.opacity_logits.copy(), opacities, cloud.log_scales.copy(), scales)
    else:
        try:
            anisotropy = float(geometry.anisotropy(to_world[:3, :3]))
            cloud = cloud.transformed(to_world)
        except ValueError as exc:
            raise SplatFileError(_file(prim), f"{prim.GetPath()}: cannot apply its transform: {exc}") from None
        if anisotropy > ANISOTROPY_TOLERANCE:
            angle = np.degrees(np.arctan(anisotropy / (2 * np.sqrt(1 + anisotropy))))
            prim_notes.append(
                f"its transform stretches unevenly (anisotropy {anisotropy:.3g}): positions "
                "and covariances are exact, SH colours follow its nearest rotation only "
                f"(view directions off by up to {angle:.3g} degrees)"
            )
    notes += [f"{prim.GetPath()}: {text}" for text in prim_notes]
    return SplatPrim(str(prim.GetPath()), cloud, source, to_world, anisotropy, prim_notes)


def _splat_prims(stage, time, axes, meters_per_unit, notes, unmarked="capture"):
    if unmarked not in UNMARKED:
        raise ValueError(f"unmarked must be one of {UNMARKED}, got {unmarked!r}")
    stage_m = stage_matrix(stage, axes, meters_per_unit, notes)
    capture_m = stage_m
    if unmarked == "capture":  # values are capture coordinates already: only units (and RUB) apply
        capture_m = stage_matrix(stage, None, meters_per_unit, [])
        if axes == "RUB":
            capture_m = FLIP @ capture_m
    found, skipped = [], {}
    world = stages.active.world_matrices(time)
    for prim in stages.active.traverse(stage):
        got = _read_prim(prim, time, (stage_m, capture_m), notes, world)
        if got is not None:
            found.append(got)
        elif stages.active.is_geometry(prim) or prim.GetTypeName().startswith("ParticleField"):
            skipped.setdefault(str(prim.GetTypeName()), []).append(str(prim.GetPath()))
    if skipped:
        listed = "; ".join(
            f"{t} x{len(p)} ({', '.join(p[:3])}{', ...' if len(p) > 3 else ''})" for t, p in sorted(skipped.items())
        )
        notes.append(f"skipped prims that are not splats: {listed}")
    return found


def _warn(path, notes):
    if notes:
        warnings.warn(f"{path}: " + "; ".join(notes), SplatFileWarning, stacklevel=3)


# public reading -----------------------------------------------------------------------------------


def read_stage(
    path, time=None, axes="RDF", meters_per_unit=1.0, nonfinite="raise", unmarked="capture", allow_outside=False
):
    """Every splat prim of a stage as a SplatPrim (path, world-space cloud, transform, notes).

    time: a time code (default: the earliest sample, or the default value of unanimated files).
    unmarked: how to take a ParticleField3DGaussianSplat without our upright transform (NVIDIA's
    and OpenUSD's converters copy PLY coordinates into a Y-up stage unchanged): "capture" takes its
    values as capture (3DGS PLY) coordinates, giving back the PLY's values; "stage" takes them in the
    stage's own axes like any geometry (for files authored truly Y-up).
    allow_outside: also compose sublayers, references and payloads from outside the stage's package
    (.usdz) or folder; by default they are refused, and missing ones are an error either way.
    """
    with stages.reading(path):
        return _read_stage(_open(path, allow_outside), path, time, axes, meters_per_unit, nonfinite, unmarked)


def _read_stage(stage, path, time, axes, meters_per_unit, nonfinite, unmarked="capture"):
    notes = []
    prims = _splat_prims(stage, stages.active.time_code(time), axes, meters_per_unit, notes, unmarked)
    for p in prims:
        p.cloud = apply_nonfinite_policy(f"{path}:{p.path}", p.cloud, nonfinite, "read")
    _warn(path, notes)
    return prims


def read(path, time=None, axes="RDF", meters_per_unit=1.0, nonfinite="raise", unmarked="capture", allow_outside=False):
    """All splat prims of the stage, in world space, concatenated into one SplatCloud (unmarked and
    allow_outside: see read_stage)."""
    prims = read_stage(path, time, axes, meters_per_unit, nonfinite, unmarked, allow_outside)
    if not prims:
        raise SplatFileError(path, f"no {TYPE_NAME} prims (nor UsdGeomPoints with 3DGS primvars) on the stage")
    if len(prims) == 1:
        return prims[0].cloud
    clouds = [p.cloud for p in prims]
    cloud = SplatCloud.concatenate(clouds)
    remembered = [_READ_LINEAR.get(c) for c in clouds]
    if all(r is not None for r in remembered):
        _READ_LINEAR[cloud] = tuple(np.concatenate(parts) for parts in zip(*remembered))
    return cloud


def time_codes(path, prim_path=None, allow_outside=False):
    """Sorted time codes at which the splat prims (or one of them) have samples; [] if unanimated."""
    with stages.reading(path):
        return _time_codes(_open(path, allow_outside), path, prim_path)


def _time_codes(stage, path, prim_path):
    if prim_path:
        prims = [stage.GetPrimAtPath(prim_path)]
        if not prims[0]:
            raise SplatFileError(path, f"no prim at {prim_path}")
    else:
        prims = [p for p in stages.active.traverse(stage) if _dialect(p) is not None]
    times = set()
    for prim in prims:
        for attr in prim.GetAttributes():  # transform ops included: a moving prim is animated too
            times.update(attr.GetTimeSamples())
    return sorted(times)


def read_frames(
    path, prim_path=None, axes="RDF", meters_per_unit=1.0, nonfinite="raise", unmarked="capture", allow_outside=False
):
    """[(time code, cloud)] for every time sample of the stage's splat prims (concatenated per time),
    or of the one at prim_path; one (None, cloud) entry for an unanimated file."""
    with stages.reading(path):
        return _read_frames(_open(path, allow_outside), path, prim_path, axes, meters_per_unit, nonfinite, unmarked)


def _read_frames(stage, path, prim_path, axes, meters_per_unit, nonfinite, unmarked):
    frames = []
    for t in _time_codes(stage, path, prim_path) or [None]:
        prims = _read_stage(stage, path, t, axes, meters_per_unit, nonfinite, unmarked)
        if prim_path:
            prims = [p for p in prims if p.path == prim_path]
        if not prims:
            raise SplatFileError(path, f"no splat prim at {prim_path}" if prim_path else "no splat prims")
        frames.append((t, SplatCloud.concatenate([p.cloud for p in prims]) if len(prims) > 1 else prims[0].cloud))
    return frames
