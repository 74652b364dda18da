"""Triangle meshes from Wavefront OBJ files with their MTL materials (diffuse colour and texture).

`read_mesh(path) -> core.mesh.Mesh`. Polygons are fan-triangulated; negative (relative) indices,
`v x y z r g b` vertex colours, `usemtl`/`mtllib` and line continuations are understood. Colour
spaces follow Blender's OBJ importer: `Kd` is scene-linear, vertex colours are sRGB-encoded (and
converted to linear here), `map_Kd` images are sRGB-encoded 8/16-bit images read with Pillow; its
`-o` and `-s` options offset and scale the UVs. A texture replaces `Kd`, as in Blender. A `map_d`
image (its alpha channel, else its grey level) cuts the surface as an alpha mask (core.mesh.Material
alpha_mode "MASK", cutoff 0.5), as Blender's importer links it to the Alpha.

Malformed lines raise SplatFileError naming the file and line. A missing MTL file or texture
image is reported with a warning and the material falls back to its `Kd` (or the default grey).
MTL files and textures are read only from the OBJ's folder and below (io.policy: absolute paths,
`../` escapes and working-directory names are refused with a warning that does not say whether the
file exists) unless `allow_outside=True`, and a texture beyond policy.MAX_IMAGE_PIXELS is refused
from its header.
"""

import struct
import warnings
from pathlib import Path

import numpy as np

from ..core import color
from ..core.mesh import Material, Mesh
from .common import SplatFileError, check_file, read_text
from .policy import MAX_IMAGE_PIXELS, inside, outside_message

THE_FOLDER = "the model's folder"

# map_* options and how many numbers each takes (at most; -o/-s/-t take one to three).
_MAP_OPTIONS = {
    "-blendu": 1,
    "-blendv": 1,
    "-bm": 1,
    "-boost": 1,
    "-cc": 1,
    "-clamp": 1,
    "-imfchan": 1,
    "-mm": 2,
    "-o": 3,
    "-s": 3,
    "-t": 3,
    "-texres": 1,
    "-type": 1,
}


def read_mesh(path, allow_outside=False):
    """Read an OBJ file (and the MTL files and textures it names) into a core.mesh.Mesh.
    allow_outside: follow MTL and texture names outside the OBJ's folder too."""
    path = Path(path)
    check_file(path)
    if path.suffix.lower() != ".obj":
        raise SplatFileError(path, f"unknown mesh file extension '{path.suffix}' (known: .obj)")
    return _ObjReader(path, allow_outside).read()


class _ObjReader:
    def __init__(self, path, allow_outside=False):
        self.path, self.allow_outside = path, allow_outside
        self.positions, self.colors, self.uvs = [], [], []
        self.corner_v, self.corner_t, self.face_sizes, self.face_mat = [], [], [], []
        self.materials, self.material_index, self.library = [], {}, {}
        self.current = -1

    def read(self):
        text = read_text(self.path)
        text = text.replace("\\\r\n", " ").replace("\\\n", " ")  # line continuations
        for number, line in enumerate(text.splitlines(), 1):
            parts = line.split("#", 1)[0].split()
            if parts:
                try:
                    self._line(parts)
                except (ValueError, IndexError) as exc:
                    raise SplatFileError(self.path, f"line {number}: {exc}: '{line.strip()[:80]}'") from None
        return self._mesh()

    def _line(self, parts):
        key = parts[0]
        if key == "v":
            values = [float(p) for p in parts[1:]]
            if len(values) < 3:
                raise ValueError("a vertex needs x y z")
            self.positions.append(values[:3])
            self.colors.append(values[3:6] if len(values) >= 6 else None)
        elif key == "vt":
            values = [float(p) for p in parts[1:3]]
            if not values:
                raise ValueError("a texture coordinate needs u [v]")
            self.uvs.append(values + [0.0] * (2 - len(values)))
        elif key == "f":
            self._face(parts[1:])
        elif key == "usemtl":
            self.current = self._material(" ".join(parts[1:]))
        elif key == "mtllib":
            self._library(" ".join(parts[1:]))

    def _face(self, corners):
        if len(corners) < 3:
            raise ValueError(f"a face needs at least 3 corners, got {len(corners)}")
        for corner in corners:
            fields = corner.split("/")
            self.corner_v.append(_index(fields[0], len(self.positions), "vertex"))
            has_uv = len(fields) > 1 and fields[1] != ""
            self.corner_t.append(_index(fields[1], len(self.uvs), "texture coordinate") if has_uv else -1)
        self.face_sizes.append(len(corners))
        self.face_mat.append(self.current)

    def _material(self, name):
        if name not in self.material_index:
            self.material_index[name] = len(self.materials)
            self.materials.append(self.library.get(name) or Material(name=name))
        return self.material_index[name]

    def _library(self, names):
        folder = self.path.parent
        candidates = [names] + names.split()
        allowed = [_named(folder, folder, n, self.allow_outside) for n in candidates]
        found = next((p for p in allowed if p is not None and p.is_file()), None)
        if found is None:
            refused = [n for n, p in zip(candidates, allowed) if p is None]
            why = (
                f"material library {outside_message(refused[0], THE_FOLDER)}"
                if refused
                else f"material library '{names}' not found"
            )
            warnings.warn(f"{self.path}: {why}; using default colours", stacklevel=2)
            return
        self.library.update(read_mtl(found, root=folder, allow_outside=self.allow_outside))
        # Materials used before their library was named pick up its definitions.
        for name, i in self.material_index.items():
            if name in self.library:
                self.materials[i] = self.library[name]

    def _mesh(self):
        if not self.positions:
            raise SplatFileError(self.path, "no vertices")
        if not self.face_sizes:
            raise SplatFileError(self.path, "no faces")
        positions = _finite_rows(self.path, np.asarray(self.positions, np.float64), "vertex")
        sizes = np.asarray(self.face_sizes)
        corner_v, corner_t = np.asarray(self.corner_v), np.asarray(self.corner_t)
        # Fan triangulation, vectorised: polygon corners (0, k, k+1) for k = 1 .. n-2.
        starts = np.cumsum(sizes) - sizes
        tri_poly = np.repeat(np.arange(len(sizes)), sizes - 2)
        k = np.arange(len(tri_poly)) - np.repeat(np.cumsum(sizes - 2) - (sizes - 2), sizes - 2) + 1
        base = starts[tri_poly]
        corner_ids = np.stack([base, base + k, base + k + 1], axis=1)
        faces = corner_v[corner_ids]
        uv_ids = corner_t[corner_ids]
        corner_uvs = None
        if self.uvs and (uv_ids >= 0).any():
            uvs = _finite_rows(self.path, np.asarray(self.uvs, np.float64), "texture coordinate")
            corner_uvs = np.where((uv_ids >= 0)[..., None], uvs[np.maximum(uv_ids, 0)], 0.0)
        face_mat = np.asarray(self.face_mat)[tri_poly]
        materials = list(self.materials)
        if (face_mat < 0).any():  # faces before any usemtl get the default material
            face_mat = np.where(face_mat < 0, len(materials), face_mat)
            materials.append(Material(name="default"))
        return Mesh(positions, faces, corner_uvs, face_mat, materials, self._vertex_colors())

    def _vertex_colors(self):
        if all(c is None for c in self.colors):
            return None
        rgb = np.array([c if c is not None else (1.0, 1.0, 1.0) for c in self.colors], np.float64)
        _finite_rows(self.path, rgb, "vertex colour")
        return color.srgb_to_linear(np.clip(rgb, 0.0, 1.0))


def _finite_rows(path, values, what):
    """`values` (one row per OBJ entry), or a SplatFileError naming the first with NaN or Inf."""
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise SplatFileError(path, f"{what} {first + 1} holds NaN or infinite values ({int(bad.sum())} {what}s in all)")
    return values


def _finite(texts):
    """Numbers from text; NaN and infinities are refused (ValueError, reported with the line)."""
    values = [float(t) for t in texts]
    if not all(np.isfinite(values)):
        raise ValueError("numbers must be finite")
    return values


def _index(text, count, what):
    i = int(text)
    if i == 0:
        raise ValueError(f"{what} index 0 (OBJ indices start at 1)")
    resolved = i - 1 if i > 0 else count + i
    if not 0 <= resolved < count:
        raise ValueError(f"{what} index {i} out of range ({count} defined so far)")
    return resolved


def read_mtl(path, root=None, allow_outside=False):
    """Materials of an MTL file: name -> Material with Kd (scene-linear), map_Kd image, map_d mask
    (_with_mask) and the PBR extension's Pr (roughness) and Pm (metallic), clamped to [0, 1]. Textures
    are read only from the folder `root` (default: the MTL's own) and below, unless allow_outside."""
    path = Path(path)
    root = path.parent if root is None else Path(root)
    materials, current, masks = {}, None, {}
    for number, line in enumerate(read_text(path).splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        key = parts[0].lower()
        try:
            if key == "newmtl":
                current = Material(name=" ".join(parts[1:]))
                materials[current.name] = current
            elif current is None:
                continue
            elif key == "kd":
                values = _finite(parts[1:4])
                current.base_color = tuple(values + [values[-1]] * (3 - len(values)))
            elif key == "map_kd":
                _texture(current, parts[1:], path, root, allow_outside)
            elif key == "map_d":
                image_path, _ = _map(current, parts[1:], path, root, allow_outside)
                if image_path is not None:
                    masks[current.name] = load_image(image_path, alpha=True)
            elif key in ("pr", "pm"):  # PBR extension: roughness, metallic (as Blender's importer maps them)
                value = min(max(_finite(parts[1:2])[0], 0.0), 1.0)
                setattr(current, "roughness" if key == "pr" else "metallic", value)
        except (ValueError, IndexError) as exc:
            raise SplatFileError(path, f"line {number}: {exc}: '{line.strip()[:80]}'") from None
    for name, alpha in masks.items():  # after the file: map_d may come before map_Kd
        _with_mask(materials[name], alpha)
    return materials


def _with_mask(material, alpha):
    """Give `material` the alpha (H,W) of a map_d image as its texture's alpha channel, alpha_mode
    MASK: beside its map_Kd texture (the mask resampled to its size, nearest texel), or beside its
    Kd colour as a linear texture of the mask's size."""
    a = alpha.astype(np.float32) / np.float32(np.iinfo(alpha.dtype).max)
    if material.texture is None:
        rgb = np.broadcast_to(np.asarray(material.base_color[:3], np.float32), a.shape + (3,))
        material.texture_srgb = False
    else:
        rgb = material.texture
        rgb = rgb.astype(np.float32) / np.float32(np.iinfo(rgb.dtype).max)
        h, w = rgb.shape[:2]
        rows = (np.arange(h) + 0.5) * a.shape[0] // h
        cols = (np.arange(w) + 0.5) * a.shape[1] // w
        a = a[rows.astype(np.int64)][:, cols.astype(np.int64)]
    material.texture = np.concatenate([rgb, a[:, :, None]], axis=2)
    material.alpha_mode = "MASK"


def _texture(material, args, mtl_path, root, allow_outside=False):
    image_path, options = _map(material, args, mtl_path, root, allow_outside)
    if image_path is None:
        return
    material.texture = load_image(image_path)
    material.texture_srgb = True
    material.uv_offset = _pair(options.get("-o"), 0.0)
    material.uv_scale = _pair(options.get("-s"), 1.0)


def _map(material, args, mtl_path, root, allow_outside=False):
    """(image path or None, {option: values}) of a map_* statement's arguments."""
    options, i = {}, 0
    while i < len(args) and args[i].lower() in _MAP_OPTIONS:
        name, most = args[i].lower(), _MAP_OPTIONS[args[i].lower()]
        values = []
        i += 1
        numeric_only = name in ("-o", "-s", "-t")  # these take one to three numbers
        while len(values) < most and i < len(args) and (_is_number(args[i]) or not numeric_only):
            values.append(args[i])
            i += 1
        options[name] = values
    if i >= len(args):
        raise ValueError("map statement without a file name")
    return _find_image(mtl_path, material, " ".join(args[i:]), root, allow_outside), options


def _pair(values, default):
    values = _finite((values or [])[:2])
    return tuple(values + [default] * (2 - len(values)))


def load_image(path, alpha=False):
    """An image file as a uint8/uint16 array (H,W,3), row 0 at the top; with `alpha`, its alpha
    channel (H,W) uint8, or its grey level where it has none (a mask image). An image of more than
    policy.MAX_IMAGE_PIXELS is refused from its header, before any pixel is decoded."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our limit is lower
            img = Image.open(path)  # reads the header only; pixels are decoded on use
        with img:
            width, height = img.size
            if width * height > MAX_IMAGE_PIXELS:
                raise SplatFileError(
                    path,
                    f"image of {width} x {height} pixels, more than the "
                    f"{MAX_IMAGE_PIXELS} ({_side(MAX_IMAGE_PIXELS)}) textures may have",
                )
            if alpha:
                transparent = "A" in img.getbands() or "transparency" in img.info
                return np.asarray(img.convert("RGBA").getchannel("A") if transparent else img.convert("L"))
            if img.mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.asarray(img, dtype=np.uint32)
                return np.repeat(np.clip(a, 0, 65535).astype(np.uint16)[:, :, None], 3, axis=2)
            return np.asarray(img.convert("RGB"))
    except (OSError, ValueError, EOFError, SyntaxError, struct.error, Image.DecompressionBombError) as exc:
        if isinstance(exc, SplatFileError):
            raise
        # Pillow reports a corrupt or hostile file (a header claiming 10^10 pixels) in all of these.
        raise SplatFileError(path, f"cannot read image: {exc}") from None


def _side(pixels):
    side = int(round(pixels**0.5))
    return f"{side} x {side}" if side * side == pixels else f"{pixels} pixels"


def _find_image(mtl_path, material, name, root, allow_outside=False):
    """The texture `name` names (relative to the MTL's folder), or the file of that name beside the
    MTL (exporters write absolute paths of the machine they ran on); only inside `root`. Refusals
    and misses are warned about, and the material keeps its Kd colour."""
    name = name.strip().strip('"').replace("\\", "/")
    folder = mtl_path.parent
    named = _named(root, folder, name, allow_outside)
    if named is not None and named.is_file():
        return named
    beside = _named(root, folder, Path(name).name, allow_outside)
    use = beside if beside is not None and beside.is_file() else None
    if named is None:
        instead = f"; read '{Path(name).name}' beside the MTL instead" if use else "; using its Kd colour"
        warnings.warn(
            f"{mtl_path}: texture of material '{material.name}' {outside_message(name, THE_FOLDER)}{instead}",
            stacklevel=2,
        )
    elif use is None:
        warnings.warn(
            f"{mtl_path}: texture '{name}' of material '{material.name}' not found; using its Kd colour", stacklevel=2
        )
    return use


def _named(root, base, name, allow_outside):
    """The path `name` gives relative to the folder `base`: only inside `root` (policy.inside)
    unless allow_outside; None for an empty or refused name."""
    if not allow_outside:
        return inside(root, base, name)
    text = str(name).strip().strip('"').replace("\\", "/")
    return (Path(base) / text).resolve() if text else None


def _is_number(text):
    try:
        float(text)
        return True
    except ValueError:
        return False
