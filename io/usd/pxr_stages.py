"""The stage interface (stages.Stages) on OpenUSD's own Python module, pxr.

Opening: the root layer and every layer it composes are opened with Sdf before Usd.Stage.Open
composes them (_composed_layers): each must lie in the stage's package (.usdz) or folder (see
policy.py), crate layers are checked against their own sizes first (crate.py), and every child a
prim spec lists must exist. Writing: a new layer in the format the extension names (a .usdz packages
a crate layer, see usdz.py); the splat prim is authored through pxr.UsdVol's schema class where this
pxr has it, else by type name and attributes through the generic API (an older pxr, such as one
bundled with Blender), which gives the same file. Arrays are Vt arrays, filled in place.
"""

import contextlib
import ctypes
import os

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

from ..common import SplatFileError
from ..policy import inside_package, outside_message, within
from .crate import check_crate
from .schema import CUSTOM, SCHEMA, TYPE_NAME
from .usdz import write_usdz

try:
    from pxr import UsdVol  # the splat schema's classes (usd-core >= 26.3; not in Blender's pxr)
except ImportError:
    UsdVol = None


def _layer(path, identifier):
    """The Sdf layer at `identifier` (a file, or "pkg.usdz[inner]"), re-read if an earlier open left it
    cached (it may be stale); crate files are checked before OpenUSD parses them. None if missing."""
    check_crate(path, identifier)
    layer = Sdf.Layer.Find(identifier)
    if layer is not None:
        layer.Reload(True)
    else:
        layer = Sdf.Layer.FindOrOpen(identifier)
    if layer is not None:
        _check_children(path, layer)
    return layer


def _names(path, spec, key, where=""):
    """The list of names a spec's field `key` holds ([] if unauthored); a damaged crate file can make
    it any other type, which is a SplatFileError."""
    if not spec.HasInfo(key):
        return []
    names = spec.GetInfo(key)
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise SplatFileError(
            path, f"{where}{spec.path}: its {key} hold a {type(names).__name__}, not a list of names (corrupt?)"
        )
    return names


def _check_children(path, layer):
    """Every prim and property a prim spec lists as its children must exist: OpenUSD composes a
    stage by those lists and aborts the process ("Dereferenced an invalid SdfPrimSpec") on a name
    without a spec, which one damaged token index in a crate file makes."""
    where = "" if layer.identifier == os.path.abspath(path) else f"layer {layer.identifier}: "
    todo = [layer.pseudoRoot]
    while todo:
        prim = todo.pop()
        for name in _names(path, prim, "primChildren", where):
            child = layer.GetPrimAtPath(prim.path.AppendChild(name)) if Sdf.Path.IsValidIdentifier(name) else None
            if child is None:
                raise SplatFileError(
                    path, f"{where}prim {prim.path} lists a child {name!r} that the layer does not hold (corrupt?)"
                )
            todo.append(child)
        for name in _names(path, prim, "properties", where):
            ok = (
                Sdf.Path.IsValidNamespacedIdentifier(name)
                and layer.GetPropertyAtPath(prim.path.AppendProperty(name)) is not None
            )
            if not ok:
                raise SplatFileError(
                    path, f"{where}prim {prim.path} lists a property {name!r} that the layer does not hold (corrupt?)"
                )


def _composed_layers(path, allow_outside):
    """The root layer and every layer it composes (sublayers, references, payloads, recursively),
    each opened with Sdf before the stage is: OpenUSD would read any path a layer names (/etc/...,
    ../../, a URL) and only warn about missing ones. A layer outside the stage's package (.usdz) or
    folder is refused unless allow_outside, with the same message whether it exists or not; a
    missing one is a SplatFileError either way."""
    root = os.path.abspath(path)
    package = root if root.lower().endswith(".usdz") else None
    where = "the stage's package" if package else "the stage's folder"
    first = _layer(path, root)
    if first is None:
        raise SplatFileError(path, "OpenUSD cannot open it")
    layers, todo, seen = [first], [first], {first.identifier}
    while todo:
        layer = todo.pop()
        named_by = "" if layer is first else f"layer {layer.identifier} "
        for asset in layer.GetCompositionAssetDependencies():
            resolved = layer.ComputeAbsolutePath(asset)
            if not os.path.isabs(resolved.split("[", 1)[0]):  # a search path: anchored as the resolver does first
                resolved = layer.ComputeAbsolutePath("./" + asset)
            ok = (
                inside_package(package, resolved)
                if package
                else within(os.path.dirname(root), resolved.split("[", 1)[0])
            )
            if not ok and not allow_outside:
                raise SplatFileError(
                    path,
                    f"{named_by}refers to a layer: {outside_message(asset, where)} "
                    "(read with allow_outside=True to allow it)",
                )
            if resolved in seen:
                continue
            try:
                found = _layer(path, resolved)
            except Tf.ErrorException:
                found = None
            if found is None:
                raise SplatFileError(
                    path,
                    f"{named_by}refers to the layer '{asset}', which cannot be opened "
                    "(missing, or not an OpenUSD layer)",
                )
            seen.add(found.identifier)
            seen.add(resolved)
            layers.append(found)
            todo.append(found)
    return layers


def _tf_message(exc):
    try:
        text = str(exc)
    except UnicodeDecodeError:  # OpenUSD quoting bytes of the file that are not UTF-8
        return "it holds bytes that are not UTF-8 text"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0].split(" : ", 1)[-1] if lines else "unknown error"


def _vt_filled(cls, length, shape, dtype, fill):
    """A new Vt array (cls, e.g. Vt.Vec3fArray) of `length` elements, filled by fill(ndarray).

    cls.FromNumpy converts element by element and needs a finished NumPy copy first; for 16M SH
    triples that costs more than the whole file write. A fresh Vt array owns its storage alone, so
    we let NumPy write straight into it. Falls back to FromNumpy if the storage is not laid out
    exactly as expected.
    """
    out = cls(length)
    view = np.asarray(out)
    if view.shape != shape or view.dtype != dtype or not view.flags.c_contiguous or not view.size:
        data = np.empty(shape, dtype)
        fill(data)
        return cls.FromNumpy(data)
    raw = (ctypes.c_char * view.nbytes).from_address(view.ctypes.data)
    fill(np.frombuffer(raw, dtype).reshape(shape))
    return out


def _schema_class():
    return getattr(UsdVol, TYPE_NAME, None) if UsdVol is not None else None


class PxrStages:
    """stages.Stages on pxr: Usd stages, prims and attributes, Vt arrays."""

    name = "pxr"
    errors = (Tf.ErrorException,)

    def message(self, exc):
        return _tf_message(exc)

    # reading

    def open(self, path, allow_outside):
        try:
            layers = _composed_layers(path, allow_outside)  # held open until the stage uses them
            stage = Usd.Stage.Open(layers[0], Usd.Stage.LoadAll)
        except Tf.ErrorException as exc:
            raise SplatFileError(path, f"OpenUSD cannot open it (truncated or corrupt?): {_tf_message(exc)}") from None
        if stage is None:
            raise SplatFileError(path, "OpenUSD cannot open it")
        return stage

    def time_code(self, time):
        return Usd.TimeCode.EarliestTime() if time is None else Usd.TimeCode(float(time))

    def traverse(self, stage):
        return stage.Traverse(Usd.TraverseInstanceProxies())

    def metadata(self, stage, key):
        return stage.GetMetadata(key) if stage.HasAuthoredMetadata(key) else None

    def primvars(self, prim):
        return UsdGeom.PrimvarsAPI(prim)

    def is_points(self, prim):
        return prim.IsA(UsdGeom.Points)

    def is_geometry(self, prim):
        return prim.IsA(UsdGeom.Gprim)

    def world_matrix(self, prim, time):
        """Its own ops are read with GetLocalTransformation: a pxr without the splat schema
        (Blender's) does not count the prim as Xformable, and ComputeLocalToWorldTransform would
        skip them."""
        xformable = UsdGeom.Xformable(prim)
        local = np.array(xformable.GetLocalTransformation(time), dtype=np.float64).T
        if xformable.GetResetXformStack():
            return local
        return np.array(UsdGeom.XformCache(time).GetParentToWorldTransform(prim), dtype=np.float64).T @ local

    # writing

    def check_writable(self, path):
        pass  # every layer format OpenUSD knows

    def filled(self, kind, shape, dtype, fill):
        return _vt_filled(getattr(Vt, kind), shape[0], shape, dtype, fill)

    def define_splat(self, stage, prim_path):
        schema = _schema_class()
        if schema is not None:
            return schema.Define(stage, prim_path).GetPrim()
        return stage.DefinePrim(prim_path, TYPE_NAME)

    def attribute(self, prim, name):
        """Created through the schema class when pxr has it, else by name."""
        if name in CUSTOM:
            return prim.CreateAttribute(name, Sdf.ValueTypeNames.Find(CUSTOM[name]), True)
        type_name, uniform, creator = SCHEMA[name]
        schema = _schema_class()
        if schema is not None:
            return getattr(schema(prim), creator)()
        variability = Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying
        return prim.CreateAttribute(name, Sdf.ValueTypeNames.Find(type_name), False, variability)

    def vertex_primvar(self, prim, name, type_name, element_size):
        pv = UsdGeom.PrimvarsAPI(prim).CreatePrimvar(
            name, Sdf.ValueTypeNames.Find(type_name), UsdGeom.Tokens.vertex, element_size
        )
        return pv.GetAttr()

    def set_custom_data(self, attr, key, value):
        attr.SetCustomDataByKey(key, value)

    def set_vertex_interpolation(self, attr, element_size):
        UsdGeom.Primvar(attr).SetInterpolation(UsdGeom.Tokens.vertex)
        UsdGeom.Primvar(attr).SetElementSize(element_size)

    def transform_op(self, prim, name, matrix):
        op = prim.CreateAttribute(name, Sdf.ValueTypeNames.Matrix4d, False)
        op.Set(Gf.Matrix4d(*matrix.T.reshape(-1).tolist()))
        prim.CreateAttribute("xformOpOrder", Sdf.ValueTypeNames.TokenArray, False, Sdf.VariabilityUniform).Set([name])

    def set_value(self, attr, value, code):
        if code is None:
            attr.Set(value)
        else:
            attr.Set(value, Usd.TimeCode(code))

    def save(self, path, partial, prims, author, fps):
        if path.lower().endswith(".usdz"):
            layer_path = partial + ".layer"  # a partial too: swept with it after a kill
            try:
                self._save_stage(path, layer_path, "usdc", prims, author, fps)
                write_usdz(partial, os.path.splitext(os.path.basename(path))[0] + ".usdc", layer_path)
            finally:
                with contextlib.suppress(OSError):
                    os.remove(layer_path)
        else:
            self._save_stage(path, partial, os.path.splitext(path)[1][1:].lower(), prims, author, fps)

    def _save_stage(self, path, layer_path, file_format, prims, author, fps):
        """Author the prims in a new layer of `file_format` ("usda", "usdc", "usd") saved at layer_path
        (a partial, so the format is named rather than taken from its extension)."""
        try:
            self._author_stage(path, layer_path, file_format, prims, author, fps)
        except Tf.ErrorException as exc:
            raise SplatFileError(path, f"OpenUSD could not write it: {_tf_message(exc)}") from None

    def _author_stage(self, path, layer_path, file_format, prims, author, fps):
        layer = Sdf.Layer.New(Sdf.FileFormat.FindByExtension(file_format), layer_path)
        stage = Usd.Stage.Open(layer)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        all_times = []
        for prim_path, frames in prims.items():
            for ancestor in Sdf.Path(prim_path).GetParentPath().GetPrefixes():
                if not stage.GetPrimAtPath(ancestor):
                    stage.DefinePrim(ancestor, "Xform")
            all_times += author(stage, prim_path, frames)
        root = Sdf.Path(next(iter(prims))).GetPrefixes()[0]
        stage.SetDefaultPrim(stage.GetPrimAtPath(root))
        if all_times:
            stage.SetStartTimeCode(float(min(all_times)))
            stage.SetEndTimeCode(float(max(all_times)))
        if fps is not None:
            stage.SetTimeCodesPerSecond(float(fps))
            stage.SetFramesPerSecond(float(fps))
        if not layer.Save():
            raise SplatFileError(path, "OpenUSD could not save the layer")
