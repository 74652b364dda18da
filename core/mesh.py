"""Triangle meshes with unlit appearance: the input of mesh-to-splats and of the mesh rasteriser.

Colour spaces (every input is stated here once, and converted once):
- `Material.base_color` and per-corner/vertex colours are scene-linear RGB, as Blender's Base Color
  socket and colour attributes (`.color`) hold them and as Blender's OBJ importer treats MTL `Kd`.
- `Material.texture` carries its own colour space: `texture_srgb=True` for sRGB-encoded images
  (8-bit PNG/JPEG, Blender colourspace 'sRGB'), False for linear data ('Linear Rec.709', float EXR).
  Texels are decoded to linear once and filtered in linear, as a renderer does.
- The surface colour is linear: (texture if the material has one, else base_color) * corner colour.
  Display sRGB (what splat SH hold) is `color.linear_to_srgb(clip(linear, 0, 1))`, which is what an
  emission shader shows under Blender's 'Standard' view transform.
"""

import functools
import warnings
from dataclasses import dataclass, field

import numpy as np

from . import color
from .material import DEFAULT_METALLIC, DEFAULT_ROUGHNESS
from .mesh_texture import (  # the texture lookups and the display conversion live there, used from here too
    EdgeField,
    footprint_average,
    sample_mipmap,  # noqa: F401
    sample_texture,
    texel_jacobians,
    to_display,  # noqa: F401
)

# A triangle whose area is below this fraction of its longest edge squared has no usable normal.
DEGENERATE_RATIO = 1e-10


@dataclass(eq=False)
class Material:
    """Unlit appearance of one material.

    base_color: scene-linear RGB (or RGBA: its alpha multiplies the texture's). texture: optional
    image (H,W,3|4), uint8/uint16 or float, row 0 at the top (v = 1), sampled bilinearly with
    repeat wrapping at texel centres.
    alpha_mode: what the alpha (the texture's 4th channel, or 2nd of grey + alpha, times the base
    colour's alpha; never sRGB-decoded) does, as glTF names it: "OPAQUE" ignores it; "MASK" cuts
    the surface where the bilinear alpha is below `alpha_cutoff` (glTF MASK, Blender's alpha clip);
    "BLEND" makes it a fractional coverage (Cycles' mix with transparent).
    uv_scale, uv_offset: the texture is looked up at uv * uv_scale + uv_offset.
    rim_color: optional scene-linear RGB seen at grazing angles: the colour is
    mix(surface, rim_color, 1 - |cos(view, normal)|), a view-dependent 'facing' blend.
    roughness, metallic: the Principled BSDF's, in [0,1], for the material splats carry for
    relighting (core.material); the unlit colour ignores them.
    """

    base_color: tuple = (0.8, 0.8, 0.8)
    texture: np.ndarray | None = None
    texture_srgb: bool = True
    uv_scale: tuple = (1.0, 1.0)
    uv_offset: tuple = (0.0, 0.0)
    rim_color: tuple | None = None
    name: str = ""
    roughness: float = DEFAULT_ROUGHNESS
    metallic: float = DEFAULT_METALLIC
    alpha_mode: str = "OPAQUE"
    alpha_cutoff: float = 0.5
    _linear: np.ndarray | None = field(default=None, repr=False)
    _mips: list | None = field(default=None, repr=False)
    _edges: object = field(default=None, repr=False)
    _alpha: np.ndarray | None = field(default=None, repr=False)
    _premultiplied: list | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.alpha_mode not in ALPHA_MODES:
            raise ValueError(f"alpha_mode must be one of {ALPHA_MODES}, got {self.alpha_mode!r}")

    @property
    def cut(self) -> bool:
        """Whether alpha cuts or thins the surface: a MASK or BLEND material with an alpha below 1
        somewhere (a texture alpha channel, or a base colour alpha)."""
        return self.alpha_mode != "OPAQUE" and (self.alpha_texture() is not None or self.base_alpha < 1)

    @property
    def base_alpha(self) -> float:
        return float(self.base_color[3]) if len(self.base_color) > 3 else 1.0

    def alpha_texture(self):
        """The texture's alpha times the base colour's, float32 (H,W,1), or None when the texture
        has no alpha channel (or there is no texture). Decoded once and cached."""
        if self.texture is None:
            return None
        if self._alpha is None:
            img = np.asarray(self.texture)
            if img.ndim != 3 or img.shape[2] not in (2, 4):
                return None
            a = img[:, :, -1:]
            if np.issubdtype(a.dtype, np.integer):
                a = a.astype(np.float32) / np.float32(np.iinfo(a.dtype).max)
            a = np.clip(np.nan_to_num(a.astype(np.float32), nan=1.0), 0.0, 1.0)
            self._alpha = np.ascontiguousarray(a * np.float32(self.base_alpha))
        return self._alpha

    def premultiplied_mipmap(self):
        """Mip levels (as mipmap()) of the linear texture premultiplied by its alpha, with the alpha
        as a 4th channel: averaged over a footprint, colour / alpha is the colour of what is there
        (a cut-out texel's colour adds nothing), and alpha its coverage. Cached."""
        if self._premultiplied is None:
            alpha = self.alpha_texture()
            if alpha is None:
                alpha = np.full(self.linear_texture().shape[:2] + (1,), self.base_alpha, np.float32)
            levels = [np.concatenate([self.linear_texture() * alpha, alpha], axis=2)]
            self._premultiplied = _reduce_mips(levels)
        return self._premultiplied

    def linear_texture(self):
        """The texture as float32 linear RGB (H,W,3), decoded once and cached."""
        if self.texture is None:
            return None
        if self._linear is None:
            self._linear = decode_texture(self.texture, self.texture_srgb)
        return self._linear

    def mipmap(self):
        """The linear texture and its 2x2 box-filtered reductions down to one texel, cached."""
        if self._mips is None:
            self._mips = _reduce_mips([self.linear_texture()])
        return self._mips

    def edge_field(self):
        """The texture's hard edges and each texel's way to the nearest (core.mesh_texture.EdgeField),
        cached; an alpha-cut material's alpha steps are edges too (where the surface ends)."""
        if self._edges is None:
            self._edges = EdgeField(self.linear_texture(), self.alpha_texture() if self.cut else None)
        return self._edges

    @property
    def view_dependent(self):
        return self.rim_color is not None


ALPHA_MODES = ("OPAQUE", "MASK", "BLEND")  # glTF's alphaMode values


def _reduce_mips(levels):
    """`levels` ([level 0]) extended by 2x2 box-filtered reductions down to one texel."""
    while max(levels[-1].shape[:2]) > 1:
        a = levels[-1]
        a = np.pad(a, ((0, a.shape[0] % 2), (0, a.shape[1] % 2), (0, 0)), mode="edge")
        levels.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
    return levels


def decode_texture(image, srgb=True):
    """Image array -> float32 linear RGB (H,W,3); integer images are scaled by their type's maximum."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4) or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"texture has shape {img.shape}, expected (H, W, 1..4)")
    img = img[:, :, :1].repeat(3, axis=2) if img.shape[2] <= 2 else img[:, :, :3]
    if img.dtype in (np.uint8, np.uint16):  # every value once, then a lookup: 10x faster
        return np.ascontiguousarray(_decoded_values(img.dtype, srgb)[img])
    if np.issubdtype(img.dtype, np.integer):
        rgb = img.astype(np.float32) / np.float32(np.iinfo(img.dtype).max)
    else:
        rgb = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    if srgb:
        rgb = color.srgb_to_linear(rgb).astype(np.float32)
    return np.ascontiguousarray(rgb)


@functools.cache
def _decoded_values(dtype, srgb):
    """decode_texture's value of each value of an unsigned integer `dtype`, by index."""
    rgb = np.arange(np.iinfo(dtype).max + 1).astype(np.float32) / np.float32(np.iinfo(dtype).max)
    return color.srgb_to_linear(rgb).astype(np.float32) if srgb else rgb


@dataclass(eq=False)
class Mesh:
    """A triangle mesh and its appearance, as `mesh_to_splats` and `render_mesh` take them.

    vertices (V,3); faces (F,3) int; corner_uvs (F,3,2) or None; face_materials (F,) int or None
    (index into materials; out of range means the default material); materials: list of Material;
    corner_colors (F,3,3) per corner or (V,3) per vertex, scene-linear, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    corner_uvs: np.ndarray | None = None
    face_materials: np.ndarray | None = None
    materials: list = field(default_factory=list)
    corner_colors: np.ndarray | None = None

    def appearance(self):
        """The keyword arguments mesh_to_splats and render_mesh take besides vertices and faces."""
        return dict(
            corner_uvs=self.corner_uvs,
            face_materials=self.face_materials,
            materials=self.materials,
            corner_colors=self.corner_colors,
        )


class Surface:
    """A validated mesh ready for sampling: float64 geometry, per-face areas, normals and materials.

    Degenerate faces (zero or numerically zero area, non-finite vertices) are kept in the arrays
    but marked in `valid`; `report` counts what was skipped or repaired.
    """

    def __init__(self, vertices, faces, corner_uvs=None, face_materials=None, materials=None, corner_colors=None):
        self.report, self._cache = {}, {}
        self.vertices = _as_array(vertices, "vertices", (None, 3), np.float64)
        self.faces = _faces(faces, len(self.vertices))
        f = len(self.faces)
        corners = self.vertices[self.faces]  # (F,3,3)
        self.origin = corners[:, 0]
        self.edge1 = corners[:, 1] - corners[:, 0]
        self.edge2 = corners[:, 2] - corners[:, 0]
        with np.errstate(invalid="ignore", over="ignore"):
            cross = np.cross(self.edge1, self.edge2)
            double_area = np.linalg.norm(cross, axis=1)
            longest2 = np.max(
                np.stack([np.einsum("ij,ij->i", e, e) for e in (self.edge1, self.edge2, self.edge2 - self.edge1)]),
                axis=0,
            )
            finite = np.isfinite(corners).all(axis=(1, 2)) & np.isfinite(double_area) & np.isfinite(longest2)
            self.valid = finite & (double_area > DEGENERATE_RATIO * 2 * longest2) & (double_area > 0)
        self.area = np.where(self.valid, 0.5 * double_area, 0.0)
        safe = np.where(self.valid, double_area, 1.0)[:, None]
        self.normal = np.where(self.valid[:, None], cross / safe, 0.0)
        self.normal[~self.valid, 2] = 1.0
        self._count("non-finite vertices", ~finite)
        self._count("zero-area faces", finite & ~self.valid)
        self.materials = list(materials) if materials else [Material()]
        self.face_materials = self._face_materials(face_materials, f)
        self.corner_uvs = self._uvs(corner_uvs, f)
        self.corner_colors = self._corner_colors(corner_colors, f)
        if self.corner_uvs is None and any(m.texture is not None for m in self.materials):
            self.report["textured faces without UVs (base colour used)"] = int(self.valid.sum())
            warnings.warn("mesh has textured materials but no UVs: using the materials' base colours", stacklevel=2)

    # validation helpers -------------------------------------------------------------------------

    def _count(self, what, mask):
        n = int(np.count_nonzero(mask))
        if n:
            self.report[what] = n

    def _face_materials(self, face_materials, f):
        if face_materials is None:
            return np.zeros(f, np.int64)
        fm = _as_array(face_materials, "face_materials", (f,), np.int64)
        bad = (fm < 0) | (fm >= len(self.materials))
        self._count("faces with an unknown material (default used)", bad)
        return np.where(bad, 0, fm)

    def _uvs(self, corner_uvs, f):
        if corner_uvs is None:
            return None
        uv = _as_array(corner_uvs, "corner_uvs", (f, 3, 2), np.float64)
        bad = ~np.isfinite(uv).all(axis=(1, 2))
        self._count("faces with non-finite UVs (set to 0)", bad)
        return np.where(np.isfinite(uv), uv, 0.0)

    def _corner_colors(self, corner_colors, f):
        if corner_colors is None:
            return None
        c = np.asarray(corner_colors, np.float64)
        if c.ndim == 2 and c.shape[0] == len(self.vertices) and c.shape[1] in (3, 4):
            c = c[self.faces]  # per vertex -> per corner
        if c.ndim != 3 or c.shape[:2] != (f, 3) or c.shape[2] not in (3, 4):
            raise ValueError(
                f"corner_colors has shape {c.shape}, expected ({f}, 3, 3) per corner "
                f"or ({len(self.vertices)}, 3) per vertex"
            )
        c = c[:, :, :3]
        self._count("faces with non-finite colours (set to 0)", ~np.isfinite(c).all(axis=(1, 2)))
        return np.where(np.isfinite(c), np.maximum(c, 0.0), 0.0)

    # queries ----------------------------------------------------------------------------------

    @property
    def view_dependent(self):
        return any(m.view_dependent for m in self.materials)

    @property
    def centroids(self):
        """(F,3) the faces' centroids."""
        return self.origin + (self.edge1 + self.edge2) / 3

    def points(self, tri, bary):
        """World positions (n,3) float64 of barycentric points (n,3) on faces tri (n,)."""
        return self.origin[tri] + bary[:, 1:2] * self.edge1[tri] + bary[:, 2:3] * self.edge2[tri]

    def linear_colors(self, tri, bary, footprint=None, covariance=None):
        """Scene-linear surface colour (n,3) float64 at barycentric points on faces tri.

        `footprint` (n,) is the world-space width each point stands for (a splat's share of the
        surface); textures are then averaged over it (trilinear mipmap lookup), so a splat
        covering many texels shows their mean rather than whichever texel its centre hits.
        `covariance` (n,2,2), in each face's local frame (core.mesh_texture), is a Gaussian
        footprint instead: the texture averaged over that Gaussian (an ellipse in texels).
        """
        out = np.empty((len(tri), 3))
        mat = self.face_materials[tri]
        uv = None
        if self.corner_uvs is not None:
            uv = np.einsum("nk,nkc->nc", bary, self.corner_uvs[tri])
        for m, material in enumerate(self.materials):
            sel = np.flatnonzero(mat == m) if len(self.materials) > 1 else slice(None)
            if material.texture is not None and uv is not None:
                scale = np.asarray(material.uv_scale, float)
                lookup = uv[sel] * scale + np.asarray(material.uv_offset, float)
                if covariance is not None:
                    jac = self.texel_jacobians(m)[tri[sel]]
                    texel_cov = jac @ covariance[sel] @ jac.transpose(0, 2, 1)
                    if material.cut:  # the colour of what is there: cut-out texels' colours left out
                        rgba = footprint_average(material.premultiplied_mipmap(), lookup, texel_cov)
                        out[sel] = rgba[:, :3] / np.maximum(rgba[:, 3:], 1e-6)
                    else:
                        out[sel] = footprint_average(material.mipmap(), lookup, texel_cov)
                elif footprint is None:
                    out[sel] = sample_texture(material.linear_texture(), lookup)
                else:
                    texels = footprint[sel] * self._texel_density(material, scale)[tri[sel]]
                    out[sel] = sample_mipmap(material.mipmap(), lookup, np.log2(np.maximum(texels, 1.0)))
            else:
                out[sel] = np.asarray(material.base_color, np.float64)[:3]
        if self.corner_colors is not None:
            out *= np.einsum("nk,nkc->nc", bary, self.corner_colors[tri])
        return np.maximum(out, 0.0)

    @property
    def cut(self) -> bool:
        """Whether any material's alpha cuts or thins the surface (Material.cut)."""
        return any(m.cut for m in self.materials)

    def occluding_arrays(self) -> list[np.ndarray]:
        """What decides where this surface stops a ray (rasterize, hit_alpha): its triangles and, where
        alpha cuts it, the face materials, the corners' uvs and each material's alpha texture, mode,
        cutoff, base alpha and uv transform. Equal arrays, equal shadows (core.relight.KeptVisibilities)."""
        arrays = [self.vertices, self.faces]
        if not self.cut:
            return arrays
        arrays += [self.face_materials, np.zeros(0) if self.corner_uvs is None else self.corner_uvs]
        for material in self.materials:  # a loop over materials
            rules = [ALPHA_MODES.index(material.alpha_mode) if material.cut else 0, material.alpha_cutoff]
            rules.append(material.base_alpha)
            texture = material.alpha_texture() if material.cut else None
            arrays += [np.array(rules + list(material.uv_scale) + list(material.uv_offset), np.float64)]
            arrays.append(np.zeros(0, np.float32) if texture is None else texture)
        return arrays

    def coverage(self, tri, bary, covariance=None):
        """(n,) float64 the alpha at barycentric points on faces tri: 1 on materials whose alpha
        does not cut (Material.cut), else the bilinear alpha, or with `covariance` (n,2,2), as in
        linear_colors, the alpha averaged over that Gaussian footprint."""
        out = np.ones(len(tri))
        mat = self.face_materials[tri]
        for m, material in enumerate(self.materials):
            sel = np.flatnonzero(mat == m)
            if not material.cut or not len(sel):
                continue
            if material.alpha_texture() is None or self.corner_uvs is None:
                out[sel] = material.base_alpha
                continue
            uv = np.einsum("nk,nkc->nc", bary[sel], self.corner_uvs[tri[sel]])
            lookup = uv * np.asarray(material.uv_scale, float) + np.asarray(material.uv_offset, float)
            if covariance is None:
                out[sel] = sample_texture(material.alpha_texture(), lookup)[:, 0]
            else:
                jac = self.texel_jacobians(m)[tri[sel]]
                texel_cov = jac @ covariance[sel] @ jac.transpose(0, 2, 1)
                out[sel] = footprint_average(material.premultiplied_mipmap(), lookup, texel_cov)[:, 3]
        return out

    def hit_alpha(self, tri, bary):
        """(n,) float64 how much of a ray hitting faces tri at `bary` the surface stops, as a
        renderer's alpha test does: 1 on opaque materials, 0 or 1 on MASK ones (alpha >=
        alpha_cutoff, glTF's rule), the alpha itself on BLEND ones."""
        alpha = self.coverage(tri, bary)
        mode = np.array([m.alpha_mode if m.cut else "OPAQUE" for m in self.materials])[self.face_materials[tri]]
        cutoff = np.array([m.alpha_cutoff for m in self.materials])[self.face_materials[tri]]
        return np.where(mode == "MASK", (alpha >= cutoff).astype(np.float64), np.where(mode == "BLEND", alpha, 1.0))

    def texel_jacobians(self, m):
        """(F,2,2) d(texel) / d(local frame) of material m's texture on every face, cached."""
        key = ("jacobians", m)
        if key not in self._cache:
            self._cache[key] = texel_jacobians(self, self.materials[m])
        return self._cache[key]

    def _texel_density(self, material, uv_scale):
        """Texels per world unit on each face for a material's texture (square root of the ratio
        of the face's areas in texels and in world units)."""
        h, w = material.texture.shape[:2]
        uv = self.corner_uvs * uv_scale
        d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        texel_area = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) * w * h
        return np.sqrt(texel_area / np.where(self.area > 0, self.area, np.inf))

    def welded_faces(self):
        """Faces with vertices that coincide in position merged (UV and normal seams closed)."""
        if "welded" not in self._cache:
            _, weld = np.unique(_weld_keys(self.vertices), axis=0, return_inverse=True)
            self._cache["welded"] = weld.reshape(-1)[self.faces]
        return self._cache["welded"]

    def edge_neighbours(self):
        """(f, g): every pair of faces sharing an edge (vertices welded by position), both ways round."""
        if "neighbours" not in self._cache:
            _, _, edge = _edge_keys(self.welded_faces())
            order = np.argsort(edge, kind="stable")
            twin = np.flatnonzero(edge[order][1:] == edge[order][:-1])
            f, g = order[twin] // 3, order[twin + 1] // 3
            self._cache["neighbours"] = np.concatenate([f, g]), np.concatenate([g, f])
        return self._cache["neighbours"]

    def sharp_edges(self, angle_deg=25.0):
        """(F,3) bool: edge k of a face (opposite corner k) is an outline edge: on the boundary,
        shared by more than two faces, or a crease whose faces turn by more than `angle_deg`."""
        key = ("_sharp", angle_deg)
        if key not in self._cache:
            self._cache[key] = self._sharp_edges(angle_deg)
        return self._cache[key]

    def _sharp_edges(self, angle_deg):
        # Edge k opposite corner k is the edge from corner k + 1 to k + 2.
        _, _, key = _edge_keys(self.welded_faces()[:, [1, 2, 0]])
        _, inverse = np.unique(key, return_inverse=True)
        uses = np.bincount(inverse, weights=np.repeat(self.valid, 3))
        normals = np.where(self.valid[:, None], self.normal, 0.0)
        total = np.zeros((len(uses), 3))
        np.add.at(total, inverse, np.repeat(normals, 3, axis=0))
        other = total[inverse] - np.repeat(normals, 3, axis=0)  # the neighbour across the edge
        turn = np.einsum("ij,ij->i", other, np.repeat(normals, 3, axis=0))
        sharp = (uses[inverse] != 2) | (turn < np.cos(np.radians(angle_deg)))
        return sharp.reshape(-1, 3) & self.valid[:, None]

    def outward_signs(self):
        """Per face +1 or -1 so that sign * normal points out of the solid, 0 where there is no solid.

        Computed per connected part (faces sharing an edge, vertices welded by position): a part is
        a solid when it is consistently wound (each edge used at most twice, once in each
        direction; at most NON_MANIFOLD_SHARE of its edges used more often) and encloses a clear
        volume: closed, or open like a head with eye holes, whose signed volume around its centre
        is at least OPEN_VOLUME times its area^1.5 (a sphere has 0.094, a hemisphere 0.067, a flat
        sheet 0).
        The sign of that volume tells outward from inward. Faces wound against most of their
        neighbours (`_misoriented`) count turned round, and get the opposite sign.
        """
        if "outward" not in self._cache:
            signs = self._outward_signs()
            signs.flags.writeable = False
            self._cache["outward"] = signs
        return self._cache["outward"]

    def _outward_signs(self):
        welded = self.welded_faces()
        flipped = _misoriented(welded)
        faces = np.where(flipped[:, None], welded[:, ::-1], welded)
        part = _connected_parts(faces)
        n_parts = part.max() + 1 if len(part) else 0
        a, b, uses, same_way = _edge_uses(faces)
        edge_part = np.repeat(part, 3)
        manifold = uses <= 2
        wound = ~manifold | (~same_way & (a != b))
        closed = manifold & wound & (uses == 2)
        per_part = lambda mask: np.bincount(edge_part, weights=mask, minlength=n_parts)  # noqa: E731
        edges = np.bincount(edge_part, minlength=n_parts)
        consistent = (per_part(~wound) == 0) & (per_part(~manifold) <= NON_MANIFOLD_SHARE * edges)
        watertight = per_part(~closed) == 0
        corners = self.vertices[np.where(flipped[:, None], self.faces[:, ::-1], self.faces)]
        finite = np.isfinite(corners).all(axis=(1, 2))
        count = np.maximum(np.bincount(part, weights=finite, minlength=n_parts), 1)
        centers = (
            np.stack(
                [
                    np.bincount(part, weights=np.where(finite, corners[:, :, k].mean(axis=1), 0.0), minlength=n_parts)
                    for k in range(3)
                ],
                axis=1,
            )
            / count[:, None]
        )
        c = np.where(np.isfinite(corners), corners - centers[part][:, None, :], 0.0)
        volume = np.bincount(
            part, weights=np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])) / 6, minlength=n_parts
        )
        area = np.bincount(part, weights=np.where(self.valid, self.area, 0.0), minlength=n_parts)
        enclosing = (watertight | (np.abs(volume) >= OPEN_VOLUME * area**1.5)) & consistent
        sign = np.where(enclosing & (volume != 0), np.sign(volume), 0.0)
        return sign[part] * self.valid * np.where(flipped, -1.0, 1.0)

    def rim_colors(self, tri):
        """Per-point rim colour (n,3) and a mask of points whose material has one."""
        rims = np.array([m.rim_color if m.view_dependent else (0, 0, 0) for m in self.materials], np.float64)
        has = np.array([m.view_dependent for m in self.materials])
        mat = self.face_materials[tri]
        return rims[mat, :3], has[mat]


def shade(base_linear, rim_linear, has_rim, cos_view):
    """Linear colour seen at |cos(view, normal)| = cos_view: the facing blend for rim materials."""
    facing = np.where(has_rim, 1.0 - np.abs(cos_view), 0.0)[..., None]
    return base_linear * (1.0 - facing) + rim_linear * facing


OPEN_VOLUME = 0.03  # enclosed volume / area^1.5 above which an open part counts as a solid
NON_MANIFOLD_SHARE = 0.01  # a solid's edges may be shared by more than two faces up to this share (fins, seams)
REWIND_PASSES = 8  # _misoriented's passes: a patch of wrongly wound faces turns a ring per pass


def _edge_keys(faces):
    """Per face edge (corner k to k + 1, flattened): its two vertices and a key naming the edge
    whichever way it is run (the same for every face that shares it)."""
    n = np.int64(faces.max() + 1 if faces.size else 0)
    a, b = faces.ravel().astype(np.int64), faces[:, [1, 2, 0]].ravel().astype(np.int64)
    return a, b, np.minimum(a, b) * n + np.maximum(a, b)


def _edge_uses(faces):
    """Per face edge (corner k to k+1, flattened): its two vertices, how many faces use the edge
    (either way), and whether another face runs it the same way."""
    a, b, key = _edge_keys(faces)
    n = np.int64(faces.max() + 1 if faces.size else 0)
    directed, dcount = np.unique(a * n + b, return_counts=True)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return a, b, counts[inverse], dcount[np.searchsorted(directed, a * n + b)] > 1


def _misoriented(faces):
    """(F,) bool: faces wound against more of their neighbours (across edges two faces share) than
    along with them, as exported meshes have a few. Turned round a ring at a time, so a small
    patch of them turns whole; two large halves wound against each other stay as they are."""
    flipped = np.zeros(len(faces), bool)
    for _ in range(REWIND_PASSES):
        _, _, uses, same_way = _edge_uses(np.where(flipped[:, None], faces[:, ::-1], faces))
        pair = (uses == 2).reshape(-1, 3)
        against = (pair & same_way.reshape(-1, 3)).sum(axis=1)
        wrong = against > pair.sum(axis=1) - against
        if not wrong.any():
            break
        flipped ^= wrong
    return flipped


def _weld_keys(vertices, tolerance=1e-9):
    """Integer keys equal for vertices that coincide to `tolerance` times the mesh size."""
    finite = np.isfinite(vertices).all(axis=1)
    if not finite.any():
        return np.zeros((len(vertices), 3), np.int64)
    lo, hi = vertices[finite].min(axis=0), vertices[finite].max(axis=0)
    step = tolerance * max(float(np.max(hi - lo)), 1e-300)
    keys = np.round((np.where(finite[:, None], vertices, lo) - lo) / step)
    return np.where(finite[:, None], keys, -1 - np.arange(len(vertices))[:, None]).astype(np.int64)


def _connected_parts(faces):
    """Part label per face: faces sharing an edge (_edge_keys) belong to one part (label
    propagation with pointer jumping, vectorised over faces). Edges, not vertices: a ball resting
    on a floor with its pole on a floor vertex is still a solid of its own."""
    if not len(faces):
        return np.zeros(0, np.int64)
    _, edge = np.unique(_edge_keys(faces)[2], return_inverse=True)
    edge = edge.reshape(-1)
    owner = np.repeat(np.arange(len(faces)), 3)
    label = np.arange(len(faces))
    while True:
        edge_min = np.full(edge.max() + 1, len(faces))
        np.minimum.at(edge_min, edge, label[owner])
        new = label.copy()
        np.minimum.at(new, owner, edge_min[edge])
        new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    return np.unique(label, return_inverse=True)[1].reshape(-1)


def _as_array(value, name, shape, dtype):
    a = np.asarray(value)
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} has shape {a.shape}, expected {want}")
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise ValueError(f"{name} has dtype {a.dtype}, expected numbers")
    if np.issubdtype(dtype, np.integer) and not np.issubdtype(a.dtype, np.integer):
        if a.size and not np.array_equal(a, np.round(a)):
            raise ValueError(f"{name} holds non-integer values")
    return a.astype(dtype)


def _faces(faces, n_vertices):
    f = _as_array(faces, "faces", (None, 3), np.int64)
    bad = (f < 0) | (f >= n_vertices)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        raise ValueError(
            f"faces: face {row} refers to vertex {int(f[row][bad[row]][0])}, but there are "
            f"{n_vertices} vertices ({int(bad.any(axis=1).sum())} faces out of range)"
        )
    return f
