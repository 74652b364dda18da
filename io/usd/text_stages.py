"""The stage interface (stages.Stages) on text layers, where OpenUSD's Python module is missing
(Blender 4.2 bundles none): usda.Layer is the stage and its prims answer the pxr calls the readers
make; arrays are NumPy arrays, which the layer formats itself. Crate (.usdc) layers and composition
need OpenUSD and are refused by name.
"""

import os

import numpy as np

from ..common import SplatFileError
from . import usda, usda_parse
from .schema import CUSTOM, SCHEMA, TYPE_NAME


def _shown(prim):
    """Whether a stage traversal visits the prim (and so its children), as Usd.Stage.Traverse's
    default predicate decides: defined (`def`, not `over` or an abstract `class`) and active."""
    return prim.specifier == "def" and prim.metadata.get("active", True) is not False


class TextStages:
    """stages.Stages on usda.Layer."""

    name = "text"
    errors = ()  # its failures are SplatFileErrors already

    def message(self, exc):
        return str(exc)

    # reading

    def open(self, path, allow_outside):
        return usda_parse.read_layer(path)  # composes nothing: nothing outside to refuse

    def time_code(self, time):
        return None if time is None else float(time)

    def traverse(self, stage):
        return stage.traverse(_shown)

    def metadata(self, stage, key):
        return stage.metadata.get(key)

    def primvars(self, prim):
        return usda.PrimvarsAPI(prim)

    def is_points(self, prim):
        return prim.GetTypeName() == "Points"

    def is_geometry(self, prim):
        return prim.GetTypeName() not in ("", "Xform", "Scope")

    def world_matrices(self, time):
        return lambda prim: prim.world_matrix(time, prim.layer.read_matrices)  # the layer caches parents

    # writing

    def check_writable(self, path):
        if os.fspath(path).lower().endswith(".usdc"):
            raise SplatFileError(
                path,
                "binary OpenUSD (.usdc) needs OpenUSD's Python module (pxr), which this "
                "Python lacks (Blender 4.4 and later bundle it); write .usda, .usd or .usdz",
            )

    def filled(self, kind, shape, dtype, fill):
        out = np.empty(shape, dtype)
        fill(out)
        return out

    def define_splat(self, stage, prim_path):
        return stage.define(prim_path, TYPE_NAME)

    def attribute(self, prim, name):
        type_name, uniform = (CUSTOM[name], False) if name in CUSTOM else SCHEMA[name][:2]
        return prim.attribute(name, type_name, uniform, custom=name in CUSTOM)

    def vertex_primvar(self, prim, name, type_name, element_size):
        attr = prim.attribute(f"primvars:{name}", type_name)
        attr.metadata["interpolation"] = "vertex"
        if element_size > 0:
            attr.metadata["elementSize"] = element_size
        return attr

    def set_custom_data(self, attr, key, value):
        """A namespaced key ("splatwright:dtype") nests a dictionary per part, as OpenUSD writes it."""
        *parents, last = key.split(":")
        data = attr.metadata.setdefault("customData", {})
        for part in parents:
            data = data.setdefault(part, {})
        data[last] = value

    def set_vertex_interpolation(self, attr, element_size):
        attr.metadata.update(interpolation="vertex", elementSize=element_size)

    def transform_op(self, prim, name, matrix):
        prim.attribute(name, "matrix4d").Set(matrix.T.copy())
        prim.attribute("xformOpOrder", "token[]", uniform=True).Set([name])

    def set_value(self, attr, value, code):
        attr.Set(value, code)

    def save(self, path, partial, prims, author, fps):
        """The same prims and metadata as PxrStages.save, in a text layer (a .usdz of one)."""
        layer = usda.Layer(partial)
        layer.metadata.update(upAxis="Y", metersPerUnit=1.0)
        all_times = []
        for prim_path, frames in prims.items():
            all_times += author(layer, prim_path, frames)
        layer.metadata["defaultPrim"] = next(iter(prims)).split("/")[1]
        if all_times:
            layer.metadata.update(startTimeCode=float(min(all_times)), endTimeCode=float(max(all_times)))
        if fps is not None:
            layer.metadata.update(timeCodesPerSecond=float(fps), framesPerSecond=float(fps))
        layer.save(partial, os.path.splitext(os.path.basename(path))[0] + ".usda", usdz=path.lower().endswith(".usdz"))
