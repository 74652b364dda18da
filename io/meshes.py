"""Triangle meshes from any common file: OBJ (with MTL) by io.mesh, everything else trimesh reads
(STL, Collada .dae, glTF/GLB, OFF, PLY meshes, ...) through trimesh.

`read_mesh_file(path) -> core.mesh.Mesh`, in the file's own units and axes. A Collada scene is
flattened with its node transforms (and its `<unit>` scale, as trimesh applies it). Colours follow
the rules of io.mesh: material colours are scene-linear as stored, vertex colours and texture
images are sRGB-encoded. trimesh is needed only for the formats other than OBJ; without it they
are refused with a SplatFileError saying so.

Files a mesh names (a glTF's buffers and images, a Collada's textures) follow io.policy's reading
rule: regular files in the mesh's folder and below, unless `allow_outside=True`. A refused or
missing texture is warned about (the same words either way) and the material keeps its colour; a
texture beyond policy.MAX_IMAGE_PIXELS, embedded or referenced, is refused from its header before
it is decoded.
"""

import os
import struct
import warnings
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ..core import color
from ..core.mesh import Material, Mesh
from ..core.robot import join_meshes
from .common import SplatFileError, SplatFileWarning, check_file
from .image import check_image_size, header_size
from .mesh import read_mesh
from .policy import referenced_file

OWN_FORMATS = (".obj",)


def read_mesh_file(path: str | os.PathLike, allow_outside: bool = False) -> Mesh:
    """Read a triangle mesh file of any format trimesh knows (OBJ natively) into a core.mesh.Mesh.
    allow_outside: follow the names of other files outside the mesh's folder too."""
    path = Path(path)
    check_file(path)
    if path.suffix.lower() in OWN_FORMATS:
        return read_mesh(path, allow_outside=allow_outside)
    try:
        import trimesh
    except ImportError:
        raise SplatFileError(
            path, f"reading '{path.suffix}' meshes needs the trimesh and pycollada packages, which this Python lacks"
        ) from None
    resolver = _Resolver(path, path.parent, allow_outside)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # trimesh's own chatter about optional extras
            scene = trimesh.load(str(path), force="scene", process=False, resolver=resolver)
    except SplatFileError:
        raise
    except Exception as exc:  # trimesh raises many kinds; name the file
        raise SplatFileError(path, f"cannot read the mesh: {type(exc).__name__}: {exc}") from None
    resolver.report()
    parts = [_part(path, geometry, transform) for geometry, transform in _flattened(scene)]
    parts = [p for p in parts if p is not None]
    if not parts:
        raise SplatFileError(path, "no triangles")
    mesh = join_meshes(parts)
    if not np.isfinite(mesh.vertices).all():
        bad = int((~np.isfinite(mesh.vertices).all(axis=1)).sum())
        raise SplatFileError(path, f"{bad} vertices are NaN or infinite")
    return mesh


def _flattened(scene):
    """(geometry, its node's (4,4) transform) for every triangle geometry of a trimesh Scene. The
    geometries are not copied: trimesh's copy decodes every texture of the material (normal maps,
    roughness, ...), which this reader never uses and has not checked."""
    out = []
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geometry = scene.geometry[name]
        if hasattr(geometry, "faces") and len(geometry.faces):
            out.append((geometry, np.asarray(transform, np.float64)))
    return out


class _Resolver:
    """What trimesh asks for by name, read under io.policy's rule, images checked against the
    texture limit from their header before trimesh gets their bytes. trimesh skips a texture it
    cannot get without a word, so refusals are kept here and reported once it is done."""

    def __init__(self, mesh, folder, allow_outside):
        self.mesh, self.folder, self.allow_outside = mesh, Path(folder), allow_outside
        self.refused, self.too_big = [], []

    def get(self, name):
        try:
            found = referenced_file(self.mesh, unquote(str(name)), self.mesh.parent, self.folder, self.allow_outside)
        except SplatFileError as exc:
            self.refused.append(exc.problem)
            raise
        data = found.read_bytes()
        size = header_size(data)
        if size is not None:
            try:
                check_image_size(self.mesh, *size, what=f"texture '{name}'")
            except SplatFileError as exc:
                self.too_big.append(exc)
                raise
        return data

    __getitem__ = get

    def namespaced(self, namespace):
        twin = _Resolver(self.mesh, self.folder / namespace, self.allow_outside)
        twin.refused, twin.too_big = self.refused, self.too_big
        return twin

    def report(self):
        """Raise the first texture over the limit; warn about every name refused or missing."""
        if self.too_big:
            raise self.too_big[0]
        for problem in dict.fromkeys(self.refused):
            warnings.warn(f"{self.mesh}: {problem}; left out", SplatFileWarning, stacklevel=3)


def _part(path, geometry, transform):
    """One trimesh.Trimesh moved by `transform` as a Mesh with its material, UVs or vertex colours."""
    vertices = np.asarray(geometry.vertices, np.float64) @ transform[:3, :3].T + transform[:3, 3]
    faces = np.asarray(geometry.faces, np.int64)
    if np.linalg.det(transform[:3, :3]) < 0:  # a mirror: keep the faces turned outward
        faces = faces[:, ::-1]
    if not len(faces):
        return None
    visual = getattr(geometry, "visual", None)
    kind = getattr(visual, "kind", None)
    if kind == "texture" and getattr(visual, "material", None) is not None:
        material = _material(path, visual.material)
        uv = getattr(visual, "uv", None)
        corner_uvs = None if uv is None or len(uv) != len(vertices) else np.asarray(uv, np.float64)[faces]
        return Mesh(vertices, faces, corner_uvs, np.zeros(len(faces), np.int64), [material])
    if kind == "vertex":
        rgb = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255.0
        return Mesh(
            vertices, faces, corner_colors=color.srgb_to_linear(rgb), materials=[Material(base_color=(1, 1, 1))]
        )
    if kind == "face":
        rgb = np.asarray(visual.face_colors, np.float64)[:, :3] / 255.0
        corner = np.repeat(color.srgb_to_linear(rgb)[:, None], 3, axis=1)
        return Mesh(vertices, faces, corner_colors=corner, materials=[Material(base_color=(1, 1, 1))])
    return Mesh(vertices, faces, materials=[Material(name="default")])


def _material(path, material):
    """A trimesh material (PBR or simple) as a core Material: base colour and texture."""
    base = getattr(material, "baseColorFactor", None)
    if base is None:
        base = getattr(material, "diffuse", None)
    image = getattr(material, "baseColorTexture", None)
    if image is None:
        image = getattr(material, "image", None)
    rgb = (0.8, 0.8, 0.8) if base is None else tuple(np.asarray(base, np.float64)[:3] / 255.0)
    texture = None if image is None else _pixels(path, image)
    return Material(base_color=rgb, texture=texture, name=str(getattr(material, "name", "") or "material"))


def _pixels(path, image):
    """The RGB pixels of a texture trimesh left undecoded (its size is its header's), once the size
    is within the limit; a damaged image is a SplatFileError naming the mesh."""
    check_image_size(path, *image.size, what="embedded texture")
    try:
        return np.asarray(image.convert("RGB"))
    except (OSError, ValueError, EOFError, SyntaxError, struct.error) as exc:  # Pillow's for damaged data
        raise SplatFileError(path, f"cannot decode a texture: {exc}") from None


def has_own_colours(mesh):
    """True when a mesh carries colours of its own (a textured or coloured material, vertex
    colours), False when its materials are all the default grey."""
    if mesh.corner_colors is not None:
        return True
    default = Material()
    return any(m.texture is not None or tuple(m.base_color) != default.base_color for m in mesh.materials)
