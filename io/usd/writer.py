"""Writing splats as ParticleField3DGaussianSplat prims (`write`, `write_stage`, `write_frames`).

A Y-up, metersPerUnit 1 stage holding the values as the reference converters write them (see the
package notes); one prim per cloud, and a sequence of same-count clouds (any iterable, consumed one
at a time) becomes time samples on one prim, where an attribute that never changes is authored once
as its default value. The values come from schema._frame_values; the active stage implementation
(stages.py) creates the prim, its attributes and the file.
"""

import itertools
import math
import os

import numpy as np

from ...core import SplatCloud
from ...core.splats import NORMAL_EXTRAS
from ..common import SplatFileError, apply_nonfinite_policy, atomic_path, check_nonfinite_policy
from . import stages
from .schema import (
    ANTIALIASED,
    DTYPE_KEY,
    EXTRA_TYPES,
    LAYOUTS,
    PRIM_PATH,
    SH_COEFFS,
    SH_DEGREE,
    UPRIGHT,
    UPRIGHT_OP,
    VALID_NAMESPACED,
    VT_ARRAYS,
    _frame_values,
    _Samples,
    _vt,
    _WriteOptions,
)


def _extra_primvars(path, prim, cloud):
    """[(attribute, extra name, widen to int32?)] authoring each extra as a vertex primvar."""
    out = []
    for key, values in cloud.extras.items():
        type_name = EXTRA_TYPES.get(values.dtype.name)
        if type_name is None or not VALID_NAMESPACED.fullmatch(key):
            raise SplatFileError(
                path,
                f"extra '{key}' ({values.dtype}) cannot be a USD primvar: it needs a "
                f"valid identifier and one of the dtypes {sorted(EXTRA_TYPES)}",
            )
        size = int(np.prod(values.shape[1:])) if values.ndim > 1 else -1
        attr = stages.active.vertex_primvar(prim, key, type_name + "[]", size)
        widen = type_name == "int" and values.dtype != np.int32
        if widen:
            stages.active.set_custom_data(attr, DTYPE_KEY, values.dtype.name)
        out.append((attr, key, widen))
    return out


def _author_prim(path, stage, prim_path, frames, times, options):
    """Author one prim from its frames (a cloud, or clouds one per time code), consumed one at a
    time so only the stage holds them; returns the time codes used ([] for a static prim)."""
    impl = stages.active
    prim, samples, codes, shape = None, {}, [], None
    for cloud, code in _checked_frames(path, prim_path, frames, times, options):
        shape = (len(cloud), cloud.sh.shape[1])
        if prim is None:  # the first frame sets the prim up
            prim = impl.define_splat(stage, prim_path)
            impl.attribute(prim, SH_DEGREE).Set(cloud.sh_degree)
            if cloud.antialiased:
                impl.attribute(prim, ANTIALIASED).Set(True)
            if options.layout == "upright" and options.axes == "RDF":
                _upright_op(prim)
            extras = _extra_primvars(path, prim, cloud)
        flip = options.axes == "RDF" and options.layout == "y-up"  # as _frame_values turns positions
        values = {**_frame_values(path, cloud, options, impl), **_extra_values(cloud, extras, flip)}
        for name, value in values.items():
            if name not in samples:
                samples[name] = _Samples(
                    prim.GetAttribute(name) or impl.attribute(prim, name), name != "positions", impl
                )
            samples[name].add(value, code)
        codes.append(code)
        del cloud, values  # let this frame go before the next one is made
    for attr in samples.values():
        attr.finish()
    for name in (SH_COEFFS, SH_COEFFS + "h"):  # one particle's coefficients per element, as primvars say
        if name in samples:
            impl.set_vertex_interpolation(samples[name].attr, shape[1])
    return [c for c in codes if c is not None]


def _upright_op(prim):
    """The transform standing a capture (y down, z forward) upright in the Y-up stage: a half turn
    about X, authored as an exact matrix op named for what it does."""
    stages.active.transform_op(prim, UPRIGHT_OP, UPRIGHT)


def _extra_values(cloud, extras, flip=False):
    """{primvar attribute name: Vt array} of a cloud's extras (see _extra_primvars); with `flip`
    (values turned into the Y-up stage) the normals' y and z change sign as the positions' do."""
    values = {}
    for attr, key, widen in extras:
        flat = np.ascontiguousarray(cloud.extras[key].reshape(-1))
        if flip and key in NORMAL_EXTRAS[1:]:
            flat = -flat
        flat = flat.astype(np.int32) if widen else flat
        values[attr.GetName()] = _vt(stages.active, VT_ARRAYS[flat.dtype.name], flat)
    return values


def _checked_frames(path, prim_path, frames, times, options):
    """(cloud, time code) pairs, each cloud checked as it comes: the same splat count, SH degree and
    extras in every frame, one time code per cloud, the non-finite policy applied."""
    if isinstance(frames, SplatCloud):
        frames, codes = [frames], iter([None])  # None: the default value
    else:
        codes = (float(t) for t in (itertools.count() if times is None else times))
    shape, count = None, 0
    for cloud in frames:
        code = next(codes, "none left")
        if code == "none left":
            raise SplatFileError(path, f"{prim_path}: more clouds than time codes ({count})")
        cloud = apply_nonfinite_policy(f"{path}:{prim_path}", cloud, options.nonfinite, "write")
        this = (len(cloud), cloud.sh_degree, tuple(sorted(cloud.extras)))
        if shape is not None and this != shape:
            raise SplatFileError(
                path,
                f"{prim_path}: time samples need the same splat count, SH degree and "
                f"extras in every frame; frame {count} has (count, degree, extras) "
                f"{this}, the first {shape}",
            )
        shape, count = this, count + 1
        yield cloud, code
        del cloud
    if count == 0:
        raise SplatFileError(path, f"{prim_path}: no clouds to write")
    if times is not None and next(codes, "none left") != "none left":
        raise SplatFileError(path, f"{prim_path}: more time codes than clouds ({count})")


def write_stage(
    path,
    prims,
    times=None,
    half=False,
    half_positions=False,
    exact=True,
    axes="RDF",
    nonfinite="raise",
    fps=None,
    layout="upright",
):
    """Write {prim path: cloud, or clouds one per time code} as a Y-up, metre stage.

    The clouds of an animated prim may come from any iterable (a generator, say): each is authored
    and let go before the next is asked for. An attribute that holds the same values in every frame
    is authored once rather than per frame (positions always get a sample per frame).
    times: time codes for the frames of animated prims (every sequence in `prims` must match it;
    default 0, 1, 2, ...).
    fps: time codes per second for players (OpenUSD assumes 24 when the stage does not say).
    half: orientations, scales, opacities and SH as half floats; half_positions: positions too.
    exact: also store the model's float32 logits and log scales, so reading back is exact.
    axes: "RDF" (the model's convention) or "RUB" (clouds already in Y-up axes: written as they are).
    layout, for RDF clouds: "upright" (the capture's coordinates, as the reference converters write
    them, under a prim transform standing them upright in the Y-up stage), "y-up" (values flipped
    into the Y-up stage, no transform: for viewers that ignore prim transforms) or "as-is" (the
    capture's coordinates and no transform, as NVIDIA's converter writes: upside down in Y-up viewers).
    """
    stages.active.check_writable(path)
    if axes not in ("RDF", "RUB"):
        raise ValueError(f"axes must be 'RDF' or 'RUB', got {axes!r}")
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    check_nonfinite_policy(nonfinite)
    options = _WriteOptions(half, half_positions, exact, axes, nonfinite, layout)
    path = os.fspath(path)
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    if not prims:
        raise SplatFileError(path, "no prims to write")
    for prim_path in prims:
        if not PRIM_PATH.fullmatch(prim_path):
            raise SplatFileError(path, f"'{prim_path}' is not an absolute prim path")
    if times is not None:
        times = list(times)
    with atomic_path(path) as tmp:
        stages.active.save(
            path,
            tmp,
            prims,
            lambda stage, prim_path, frames: _author_prim(path, stage, prim_path, frames, times, options),
            fps,
        )


def write(
    path,
    cloud,
    prim_path="/Splats",
    half=False,
    half_positions=False,
    exact=True,
    axes="RDF",
    nonfinite="raise",
    layout="upright",
):
    """Write one cloud as one ParticleField3DGaussianSplat prim (options as write_stage's)."""
    if not isinstance(cloud, SplatCloud):
        raise TypeError(f"write takes one SplatCloud, got {type(cloud).__name__}; write_frames takes a sequence")
    write_stage(path, {prim_path: cloud}, None, half, half_positions, exact, axes, nonfinite, layout=layout)


def write_frames(path, clouds, times=None, prim_path="/Splats", **options):
    """Write same-count clouds (any iterable, consumed one at a time) as time samples of one prim;
    times default to 0, 1, 2, ...; options as write_stage's (fps among them)."""
    write_stage(path, {prim_path: clouds}, times, **options)
