"""The stage interface: how the readers and the writer reach an OpenUSD stage, and the one place
that asks whether OpenUSD's Python module (pxr) exists.

Two implementations answer it: PXR (pxr_stages.PxrStages: OpenUSD itself, every layer format) and
TEXT (text_stages.TextStages: text layers parsed and written by NumPy, for a Python without pxr,
such as Blender 4.2's). `active` is the one in use: PXR where pxr imports, else TEXT. It is the single
switch; tests set it to TEXT to run the text path where pxr is installed too.

The interface has two levels. A Stages object (below) opens, creates and saves stages and does
what differs between the two: traversal, primvars, transforms, time codes, array types, authoring
attributes by schema name. The stages, prims and attributes it hands out answer one shared subset
of pxr's calls (stages: GetPrimAtPath, GetRootLayer().identifier; prims: GetAttribute,
GetAttributes, GetTypeName, GetPath, GetStage; attributes: Get, Set, HasAuthoredValue,
GetTimeSamples, GetTypeName, GetName, GetCustomDataByKey; primvars, from `primvars(prim)`:
GetPrimvar, HasPrimvar, GetPrimvarsWithAuthoredValues, and on each GetAttr, GetPrimvarName,
GetTypeName, GetInterpolation, GetElementSize, HasAuthoredValue, ComputeFlattened), so each reader
and the writer is written once for both.
"""

import contextlib
from typing import Protocol, runtime_checkable

from ..common import SplatFileError
from . import text_stages

try:  # the one question whether pxr exists
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdUtils, Vt  # noqa: F401
except ImportError:
    PXR = None
else:
    from . import pxr_stages

    PXR = pxr_stages.PxrStages()
TEXT = text_stages.TextStages()
active = PXR if PXR is not None else TEXT


@runtime_checkable
class Stages(Protocol):
    """What an implementation provides. Times are the implementation's own (see time_code); arrays
    are filled in its own array type (see filled)."""

    name: str  # "pxr" or "text"
    errors: tuple  # exception types its calls raise on a damaged file

    def message(self, exc):
        """One line saying what went wrong in `exc`, one of `errors`."""

    # reading

    def open(self, path, allow_outside):
        """The stage of the file at `path` (its header already checked against its extension), with
        what it composes; layers outside its package or folder refused unless allow_outside."""

    def time_code(self, time):
        """The time to read values at: `time` (a number), or None for the earliest sample (the
        default value of an unanimated attribute)."""

    def traverse(self, stage):
        """Every prim of the stage, parents before children (instance proxies included)."""

    def metadata(self, stage, key):
        """The stage's layer metadata `key` as authored ("upAxis", "metersPerUnit"), or None."""

    def primvars(self, prim):
        """The prim's primvars (pxr's UsdGeom.PrimvarsAPI calls)."""

    def is_points(self, prim):
        """Whether the prim is a UsdGeomPoints."""

    def is_geometry(self, prim):
        """Whether the prim is geometry (a Gprim), so that skipping it is worth a warning."""

    def world_matrices(self, time):
        """A function prim -> its 4x4 (column vectors) local-to-world transform at `time`, sharing the
        parents' transforms among the prims of one read (a parent's ops read once, not once a child)."""

    # writing

    def check_writable(self, path):
        """A SplatFileError when this implementation cannot write the layer format `path` names."""

    def filled(self, kind, shape, dtype, fill):
        """A new array of Vt type `kind` ("Vec3fArray" ...) of NumPy `shape` and `dtype`, in the
        implementation's own array type, its values written by fill(ndarray)."""

    def define_splat(self, stage, prim_path):
        """A new ParticleField3DGaussianSplat prim at prim_path."""

    def attribute(self, prim, name):
        """The attribute `name` of schema.SCHEMA or schema.CUSTOM, created with its type."""

    def vertex_primvar(self, prim, name, type_name, element_size):
        """The attribute of a new vertex-interpolated primvar (element_size -1: left unauthored)."""

    def set_custom_data(self, attr, key, value):
        """Custom data `key` (namespaced: "splatwright:dtype") of an attribute."""

    def set_vertex_interpolation(self, attr, element_size):
        """Primvar metadata on an attribute: vertex interpolation, `element_size` values each."""

    def transform_op(self, prim, name, matrix):
        """A matrix transform op `name` holding `matrix` (4x4, column vectors), the prim's only op."""

    def set_value(self, attr, value, code):
        """Author `value` at time code `code` (a number), or as the default value (None)."""

    def save(self, path, partial, prims, author, fps):
        """Write a Y-up, metre stage for `path` to the file `partial`: author(stage, prim_path,
        frames) authors each of `prims` ({prim path: frames}) and returns its time codes, which set
        the stage's time range; `fps` (None: unsaid) its time codes and frames per second."""


@contextlib.contextmanager
def reading(path):
    """OpenUSD parses a layer lazily: a damaged one can fail while prims and values are read, not only
    when it is opened. The active implementation's errors (and undecodable strings it hands back)
    become a SplatFileError naming the file."""
    try:
        yield
    except active.errors as exc:
        raise SplatFileError(path, f"OpenUSD cannot read it (truncated or corrupt?): {active.message(exc)}") from None
    except UnicodeDecodeError:
        raise SplatFileError(
            path, "OpenUSD cannot read it: it holds names or strings that are not UTF-8 (corrupt?)"
        ) from None
