"""The stage interface (stages.Stages) on OpenUSD's own Python module, pxr.

Opening: the root layer and every layer it composes (sublayers, references, payloads, value clips)
are opened with Sdf before Usd.Stage.Open composes them (_composed_layers, _LayerWalk): each must
lie in the stage's package (.usdz) or folder (see policy.py) and be a regular file, its bytes are
checked before OpenUSD parses them (layer_check.py: crate counts, text nesting), and every child a
prim spec lists must exist. The open stage may then use no layer the walk did not check.
Writing: a new layer in the format the extension names (a .usdz packages
a crate layer, see usdz.py); the splat prim is authored through pxr.UsdVol's schema class where this
pxr has it, else by type name and attributes through the generic API (an older pxr, such as one
bundled with Blender), which gives the same file. Arrays are Vt arrays, filled in place.
"""

import contextlib
import ctypes
import math
import os
import posixpath
import re

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

from .. import policy
from ..common import SplatFileError
from .layer_check import check_layer, package_names, split_packaged
from .schema import CUSTOM, SCHEMA, TYPE_NAME
from .usdz import write_usdz

# Clip templates: OpenUSD tries every time from start to end by stride (in steps of stride * 10000
# added to time * 10000, which stop moving once the time is large enough), resolving a file each.
MAX_TEMPLATE_CLIPS = 100_000
MAX_CLIP_TIME = 1e9
MIN_CLIP_STRIDE = 1e-3

try:
    from pxr import UsdVol  # the splat schema's classes (usd-core >= 26.3; not in Blender's pxr)
except ImportError:
    UsdVol = None


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
    """The root layer and every layer it composes, each checked and opened with Sdf before the
    stage is: OpenUSD would read any path a layer names (/etc/..., ../../, a URL, a FIFO) and only
    warn about missing ones. See _LayerWalk."""
    walk = _LayerWalk(path, allow_outside)
    first = walk.open(os.path.abspath(path), "", "")
    layers, todo = [first], [first]
    while todo:
        layer = todo.pop()
        named_by = "" if layer is first else f"layer {layer.identifier} "
        for asset, resolved in walk.dependencies(layer, named_by):
            if walk.key(resolved) in walk.checked:
                continue
            found = walk.open(resolved, asset, named_by)
            layers.append(found)
            todo.append(found)
    walk.check_template_times()
    return layers, walk


class _LayerWalk:
    """Which layers a stage may compose, and their checks. A layer is followed when it lies in the
    stage's package (.usdz) or folder (policy.py), unless allow_outside; it must be a regular file
    (or a stored member of the package), pass layer_check.check_layer, and open with Sdf. Layers
    are named by sublayers, references and payloads (in variants too), and by value clips on any
    prim spec: assetPaths, manifestAssetPath and templateAssetPath, whose every matching file is
    checked. A layer outside is refused with the same message whether it exists or not; a missing
    one is a SplatFileError either way. After the stage opens, `verify` holds it to the layers
    checked here."""

    def __init__(self, path, allow_outside):
        self.path, self.allow_outside = path, allow_outside
        self.root = os.path.abspath(path)
        self.package = self.root if self.root.lower().endswith(".usdz") else None
        self.where = "the stage's package" if self.package else "the stage's folder"
        self.checked = set()
        self.template_times = []  # (start, end, stride) of every templated clip set

    @staticmethod
    def key(identifier):
        """`identifier` with its file's symbolic links followed, to compare layers OpenUSD names."""
        outer, bracket, rest = identifier.partition("[")
        return os.path.realpath(outer) + bracket + rest

    def open(self, resolved, asset, named_by):
        """The Sdf layer at `resolved` (a file or "pkg.usdz[inner]"), checked before OpenUSD parses it,
        re-read if an earlier open left it cached (it may be stale)."""
        try:  # regular files only: a FIFO would hang OpenUSD, /dev/zero never ends
            policy.referenced_file(self.path, resolved.split("[", 1)[0], [], allow_outside=True, what="layer")
        except SplatFileError:
            if not asset:
                raise SplatFileError(self.path, "not a regular file") from None
            raise self._unopened(asset, named_by) from None
        check_layer(self.path, resolved)
        try:
            layer = Sdf.Layer.Find(resolved)
            if layer is not None:
                layer.Reload(True)
            else:
                layer = Sdf.Layer.FindOrOpen(resolved)
        except Tf.ErrorException:
            layer = None
        if layer is None:
            if not asset:
                raise SplatFileError(self.path, "OpenUSD cannot open it")
            raise self._unopened(asset, named_by)
        _check_children(self.path, layer)
        self.checked.update((self.key(resolved), self.key(layer.identifier)))
        return layer

    def _unopened(self, asset, named_by):
        return SplatFileError(
            self.path,
            f"{named_by}refers to the layer '{asset}', which cannot be opened "
            "(missing, not a regular file, or not an OpenUSD layer)",
        )

    def dependencies(self, layer, named_by):
        """(asset, resolved identifier) of every layer `layer` names, each refused if outside."""
        for asset in layer.GetCompositionAssetDependencies():
            yield asset, self.resolve(layer, asset, named_by)
        for spec in _prim_specs(layer):
            if spec.HasInfo("clips"):
                yield from self._clips(layer, spec, named_by)

    def resolve(self, layer, asset, named_by, shown=None):
        """The identifier OpenUSD opens for `asset` named in `layer`, refused unless it lies in the
        package or folder (or allow_outside); `shown` is the name the refusal gives (default asset)."""
        if asset.startswith("`"):  # an expression of variables, evaluated by OpenUSD when composing
            raise SplatFileError(
                self.path, f"{named_by}names a layer by an expression ({asset}); only plain asset paths are read"
            )
        resolved = layer.ComputeAbsolutePath(asset)
        if not os.path.isabs(resolved.split("[", 1)[0]):  # a search path: anchored as the resolver does first
            resolved = layer.ComputeAbsolutePath("./" + asset)
        if self.package:
            ok = policy.inside_package(self.package, resolved)
        else:
            ok = policy.within(os.path.dirname(self.root), resolved.split("[", 1)[0])
        if not ok and not self.allow_outside:
            raise SplatFileError(
                self.path,
                f"{named_by}refers to a layer: {policy.outside_message(shown or asset, self.where)} "
                "(read with allow_outside=True to allow it)",
            )
        return resolved

    def _clips(self, layer, spec, named_by):
        """The layers the value clips of prim `spec` name (every clip set of its `clips`)."""
        clips = spec.GetInfo("clips")
        for clip_set in clips.values() if isinstance(clips, dict) else ():
            if not isinstance(clip_set, dict):
                continue
            paths = clip_set.get("assetPaths")
            for asset in paths if isinstance(paths, Sdf.AssetPathArray) else ():
                yield asset.path, self.resolve(layer, asset.path, named_by)
            manifest = clip_set.get("manifestAssetPath")
            if isinstance(manifest, Sdf.AssetPath) and manifest.path:
                yield manifest.path, self.resolve(layer, manifest.path, named_by)
            template = clip_set.get("templateAssetPath")
            if isinstance(template, str) and template:
                times = [clip_set.get(f"template{k}") for k in ("StartTime", "EndTime", "Stride")]
                self.template_times.append(times)
                for name in self._template_files(layer, template, named_by):
                    yield name, self.resolve(layer, name, named_by)

    def _template_files(self, layer, template, named_by):
        """Every file that a clip template ("clips/shot.###.usda") can expand to: the names in its
        folder (or package) that match it, its hashes standing for numbers. Its folder must be
        inside; the hashes may stand only in the file's name."""
        folder, _, name = template.replace("\\", "/").rpartition("/")
        if "#" in folder:
            raise SplatFileError(self.path, f"{named_by}a clip template '{template}' has hashes in its folder")
        anchor = self.resolve(layer, (folder or ".") + "/", named_by, shown=template)
        parts = [p for p in name.split(".") if p]
        pattern = re.compile(r"\.".join(r"-?\d+" if set(p) == {"#"} else re.escape(p) for p in parts), re.IGNORECASE)
        if self.package:
            outer, members = split_packaged(anchor)
            inner = posixpath.normpath(members.pop()) if members else "."
            inner = "" if inner == "." else inner + "/"
            names = [n[len(inner) :] for n in package_names(self.path, outer, members) if n.startswith(inner)]
        else:
            names = os.listdir(anchor) if os.path.isdir(anchor) else []
        prefix = folder + "/" if folder else ""
        return [prefix + n for n in names if "/" not in n and pattern.fullmatch(n)]

    def check_template_times(self):
        """Refuse clip templates whose times would make OpenUSD try too many files, or loop
        forever (a stride too small to move a time that large)."""
        times = [t for t in self.template_times if all(isinstance(v, float | int) for v in t)]
        if not times:
            return
        start, end, stride = min(t[0] for t in times), max(t[1] for t in times), min(t[2] for t in times)
        bounded = all(math.isfinite(v) and abs(v) <= MAX_CLIP_TIME for v in (start, end))
        if not bounded or not stride >= MIN_CLIP_STRIDE or (end - start) / stride > MAX_TEMPLATE_CLIPS:
            raise SplatFileError(
                self.path,
                f"a clip template spans times {start} to {end} by {stride}: at most {MAX_TEMPLATE_CLIPS} clips, "
                f"times within +-{MAX_CLIP_TIME:g} and strides of at least {MIN_CLIP_STRIDE} are read",
            )

    def verify(self, stage):
        """Every layer the open stage uses, value clips included, must be one checked before it
        opened: a backstop for any way of naming a layer that the walk does not know."""
        used = [layer.identifier for layer in stage.GetUsedLayers(True) if not layer.anonymous]
        for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
            if prim.HasAuthoredMetadata("clips"):
                clips = Usd.ClipsAPI(prim)
                for name in clips.GetClips():
                    used += [a.resolvedPath or a.path for a in clips.ComputeClipAssetPaths(name)]
        unchecked = [u for u in used if self.key(u) not in self.checked]
        if unchecked:
            raise SplatFileError(
                self.path, f"the stage composes a layer that was not checked before it opened: {unchecked[0]}"
            )


def _prim_specs(layer):
    """Every prim spec of the layer, variants' included."""
    paths = []
    layer.Traverse(Sdf.Path.absoluteRootPath, paths.append)
    for path in paths:
        if path.IsPrimPath() or path.IsPrimVariantSelectionPath():
            spec = layer.GetPrimAtPath(path)
            if spec is not None:
                yield spec


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
            layers, walk = _composed_layers(path, allow_outside)  # held open until the stage uses them
            stage = Usd.Stage.Open(layers[0], Usd.Stage.LoadAll)
            if stage is not None:
                walk.verify(stage)
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

    def world_matrices(self, time):
        """A prim's own ops are read with GetLocalTransformation: a pxr without the splat schema
        (Blender's) does not count the prim as Xformable, and ComputeLocalToWorldTransform would
        skip them. One XformCache serves every prim of the read: a cache per prim evaluated a parent's
        ops once per child (a 1 MB layer of 6,000 ops over 1,500 children took 25 s)."""
        cache = UsdGeom.XformCache(time)

        def world(prim):
            xformable = UsdGeom.Xformable(prim)
            local = np.array(xformable.GetLocalTransformation(time), dtype=np.float64).T
            if xformable.GetResetXformStack():
                return local
            return np.array(cache.GetParentToWorldTransform(prim), dtype=np.float64).T @ local

        return world

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
