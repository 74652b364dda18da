"""Textured test meshes made from code, as artists' meshes are textured: hard-edged stripes and
checkerboards, one- and two-texel lines, lettering on a decal, UV seams and mirrored UVs, several
materials on one mesh and hard-edged vertex colours. Tests and the bench both use them; every mesh
is a core.mesh.Mesh with 8-bit sRGB textures, the same on every machine.

The alpha-cut leaves are RGBA textures on crossed quads, alpha-masked (core.mesh.Material's MASK):
leaf shapes with veins, cut out of a pale background that must not show.
"""

import numpy as np

from .mesh import Material, Mesh

CREAM = (235, 226, 200)
RED = (200, 24, 20)
INK = (20, 24, 40)


def _image(h, w, colour):
    return np.broadcast_to(np.asarray(colour, np.uint8), (h, w, 3)).copy()


def stripe_texture(
    width: int = 1024, height: int = 256, period: int = 64, stripe: int = 24, background=CREAM, colour=RED
) -> np.ndarray:
    """Hard vertical stripes: `stripe` texels of `colour` every `period` texels along u."""
    img = _image(height, width, background)
    img[:, (np.arange(width) % period) < stripe] = colour
    return img


def grid_texture(size: int = 1024, squares: int = 8, line_every: int = 32, line_width: int = 1) -> np.ndarray:
    """A two-colour checkerboard of `squares` x `squares` with dark lines `line_width` texels wide
    every `line_every` texels: hard edges and lines thinner than any splat a distant view needs."""
    i = np.arange(size)
    cell = size // squares
    check = ((i[:, None] // cell) + (i[None, :] // cell)) % 2 == 1
    img = np.where(check[..., None], np.array((60, 110, 170), np.uint8), np.array(CREAM, np.uint8))
    line = (i % line_every) < line_width
    img[line] = INK
    img[:, line] = INK
    return img.astype(np.uint8)


# A 5 x 7 pixel font for the decal's lettering (rows top to bottom, '#' set).
_GLYPHS = {
    "S": [" ####", "#    ", "#    ", " ### ", "    #", "    #", "#### "],
    "P": ["#### ", "#   #", "#   #", "#### ", "#    ", "#    ", "#    "],
    "L": ["#    ", "#    ", "#    ", "#    ", "#    ", "#    ", "#####"],
    "A": [" ### ", "#   #", "#   #", "#####", "#   #", "#   #", "#   #"],
    "T": ["#####", "  #  ", "  #  ", "  #  ", "  #  ", "  #  ", "  #  "],
    "4": ["   # ", "  ## ", " # # ", "#  # ", "#####", "   # ", "   # "],
    "2": [" ### ", "#   #", "    #", "   # ", "  #  ", " #   ", "#####"],
    " ": ["     "] * 7,
}


def text_texture(text: str = "SPLAT 42", scale: int = 8, margin: int = 2, background=CREAM, colour=INK) -> np.ndarray:
    """Lettering rasterised from a 5 x 7 font, each font pixel `scale` texels square, with a
    one-texel outline box round it: a decal's glyph edges and thin lines."""
    rows = [" ".join(_GLYPHS[c][r] for c in text) for r in range(7)]
    mask = np.array([[ch == "#" for ch in row] for row in rows])
    mask = np.pad(mask, margin).repeat(scale, 0).repeat(scale, 1)
    img = np.where(mask[..., None], np.array(colour, np.uint8), np.array(background, np.uint8)).astype(np.uint8)
    img[[1, -2], 1:-1] = colour
    img[1:-1, [1, -2]] = colour
    return img


def _grid(nu, nv):
    """Vertices (u, v) in [0,1]^2 of an (nu+1) x (nv+1) grid and its 2 nu nv triangles."""
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    i = (np.arange(nv)[:, None] * (nu + 1) + np.arange(nu)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + 1, i + nu + 2], 1), np.stack([i, i + nu + 2, i + nu + 1], 1)])
    return np.column_stack([u.ravel(), v.ravel()]), f


def striped_cylinder(
    segments: int = 64, rings: int = 32, radius: float = 0.5, height: float = 1.0, texture=None
) -> Mesh:
    """An open cylinder of 2 x segments x rings triangles (4,096 by default), a 1024 x 256 texture
    of 24-texel red stripes every 64 texels wrapped once round it (its seam at u = 0 = 1)."""
    uv, f = _grid(segments, rings)
    angle = 2 * np.pi * uv[:, 0]
    v = np.column_stack([radius * np.cos(angle), height * (uv[:, 1] - 0.5), -radius * np.sin(angle)])
    tex = stripe_texture() if texture is None else texture
    return Mesh(v, f, uv[f], None, [Material(texture=tex)])


def grid_plane(n: int = 32, size: float = 2.0, texture=None) -> Mesh:
    """A square plane of 2 n^2 triangles (2,048 by default) in y = 0, facing up, with a checkerboard
    and one-texel grid lines."""
    uv, f = _grid(n, n)
    v = np.column_stack([size * (uv[:, 0] - 0.5), np.zeros(len(uv)), size * (0.5 - uv[:, 1])])
    tex = grid_texture() if texture is None else texture
    return Mesh(v, f, uv[f], None, [Material(texture=tex)])


def striped_cup(
    segments: int = 256,
    profile_steps: int = 57,
    radius: float = 0.04,
    height: float = 0.09,
    wall: float = 0.005,
    texture=None,
) -> Mesh:
    """A closed cup turned from a profile (outside floor, outer wall, rim, inner wall, inner floor),
    about 29k triangles by default: hard red stripes round the outside (material 0, its seam at
    u = 0 = 1), plain blue inside (material 1)."""
    inner = radius - wall
    # The profile from the outside floor's centre round to the inside floor's centre, as (r, y, outside).
    legs = [
        ((0.0, 0.0), (radius, 0.0), 0.1),
        ((radius, 0.0), (radius, height), 0.4),
        ((radius, height), (inner, height), 0.02),
        ((inner, height), (inner, wall), 0.38),
        ((inner, wall), (0.0, wall), 0.1),
    ]
    points, outside = [], []
    for k, (a, b, share) in enumerate(legs):
        n = max(2, round(share * profile_steps))
        t = np.linspace(0, 1, n, endpoint=False) if k < len(legs) - 1 else np.linspace(0, 1, n + 1)
        points += [np.array(a) + s * (np.array(b) - np.array(a)) for s in t]
        outside += [k <= 1] * len(t)
    profile = np.array(points)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(profile, axis=0), axis=1))])
    uv, f = _grid(segments, len(profile) - 1)
    row = np.round(uv[:, 1] * (len(profile) - 1)).astype(int)
    angle = 2 * np.pi * uv[:, 0]
    r, y = profile[row, 0], profile[row, 1]
    v = np.column_stack([r * np.cos(angle), y, -r * np.sin(angle)])
    uv[:, 1] = arc[row] / arc[-1]
    corners = v[f]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    f = f[area > 1e-12 * height**2]  # the fans' degenerate halves at the two centres
    below = np.array(outside)[row[f].min(axis=1)]
    material = np.where(below, 0, 1)
    tex = stripe_texture(1024, 512, period=64, stripe=24) if texture is None else texture
    tex = tex.copy()
    tex[262:280] = RED  # and a hard band round it just below the rim (v = 1 is the inside's centre)
    return Mesh(v, f, uv[f], material, [Material(texture=tex), Material(base_color=(0.05, 0.2, 0.9))])


def decal_box(n: int = 8, size: float = 1.0) -> Mesh:
    """A box of 6 x 2 n^2 triangles and three materials: painted wood-red sides (a base colour),
    a lettered decal on the front, and a stripe texture mirrored about the middle of the top (its
    UVs run back at u = 0.5, as artists mirror a symmetric texture) and on the back (a UV seam)."""
    uv, quad = _grid(n, n)
    s = size / 2
    sides = {  # (origin, u axis, v axis): outward-facing when wound (u, v)
        "front": ((-s, -s, s), (1, 0, 0), (0, 1, 0)),
        "back": ((s, -s, -s), (-1, 0, 0), (0, 1, 0)),
        "left": ((-s, -s, -s), (0, 0, 1), (0, 1, 0)),
        "right": ((s, -s, s), (0, 0, -1), (0, 1, 0)),
        "top": ((-s, s, s), (1, 0, 0), (0, 0, -1)),
        "bottom": ((-s, -s, -s), (1, 0, 0), (0, 0, 1)),
    }
    vertices, faces, corner_uvs, material = [], [], [], []
    for name, (origin, du, dv) in sides.items():
        pts = np.asarray(origin) + size * (uv[:, :1] * np.asarray(du) + uv[:, 1:] * np.asarray(dv))
        faces.append(quad + sum(len(p) for p in vertices))
        vertices.append(pts)
        side_uv = uv[quad].copy()
        if name in ("top", "back"):
            side_uv[..., 0] = 1 - np.abs(2 * side_uv[..., 0] - 1)  # mirrored about the middle
        corner_uvs.append(side_uv)
        material.append(np.full(len(quad), {"front": 1, "top": 2, "back": 2}.get(name, 0)))
    stripes = stripe_texture(256, 256, period=32, stripe=10, colour=(30, 120, 60))
    stripes[:, :2] = INK  # a two-texel line on the mirror's fold side
    return Mesh(
        np.concatenate(vertices),
        np.concatenate(faces),
        np.concatenate(corner_uvs),
        np.concatenate(material),
        [
            Material(base_color=(0.45, 0.08, 0.04)),
            Material(texture=text_texture()),
            Material(texture=stripes),
        ],
    )


def vertex_coloured_sphere(segments: int = 48, rings: int = 24) -> Mesh:
    """A UV sphere coloured by corner colours only (no texture): flat-coloured bands, each face one
    colour, so colour changes hard along triangle edges, and a smooth blend on the lower half."""
    uv, f = _grid(segments, rings)
    theta, phi = np.pi * (1 - uv[:, 1]), 2 * np.pi * uv[:, 0]
    v = np.column_stack([np.sin(theta) * np.cos(phi), np.cos(theta), -np.sin(theta) * np.sin(phi)])
    corners = v[f]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    f = f[area > 1e-12]
    palette = np.array([[0.8, 0.1, 0.05], [0.9, 0.75, 0.1], [0.05, 0.3, 0.8], [0.05, 0.5, 0.1]])
    centre = v[f].mean(axis=1)
    band = (np.floor((np.arctan2(-centre[:, 2], centre[:, 0]) / (2 * np.pi) % 1) * 8)).astype(int) % 4
    flat = np.repeat(palette[band][:, None, :], 3, axis=1)
    smooth = 0.5 + 0.4 * v[f] * np.array([1.0, 0.0, -1.0])  # per corner, blended across faces
    colours = np.where((centre[:, 1] > 0)[:, None, None], flat, np.clip(smooth, 0.0, 1.0))
    return Mesh(v, f, None, None, [Material(base_color=(1.0, 1.0, 1.0))], colours)


LEAF = (52, 120, 38)
VEIN = (170, 200, 90)
LEAF_BACKGROUND = (235, 235, 225)  # the cut-out texels' colour: pale, so showing it is an error


def leaf_texture(size: int = 512, leaves: int = 5, seed: int = 0) -> np.ndarray:
    """RGBA uint8 (size, size, 4): `leaves` pointed leaves fanning out from a stem at the bottom
    centre, each with a midrib and side veins (lighter, alpha 1), on a pale background of alpha 0."""
    rng = np.random.default_rng(seed)
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    inside, vein = np.zeros((size, size), bool), np.zeros((size, size), bool)
    shade = np.zeros((size, size))
    angles = np.linspace(-0.9, 0.9, leaves) + rng.uniform(-0.1, 0.1, leaves)
    for k, angle in enumerate(angles):
        length = rng.uniform(0.55, 0.75)
        base = np.array([0.5, 0.97]) + np.array([np.sin(angle), -np.cos(angle)]) * 0.08
        along, across = np.array([np.sin(angle), -np.cos(angle)]), np.array([np.cos(angle), np.sin(angle)])
        s = ((x - base[0]) * along[0] + (y - base[1]) * along[1]) / length  # 0 .. 1 base to tip
        t = ((x - base[0]) * across[0] + (y - base[1]) * across[1]) / length
        half = 0.22 * np.sin(np.pi * np.clip(s, 0, 1)) ** 0.8 * (1 - 0.3 * s)  # widest before the middle
        leaf = (s > 0) & (s < 1) & (np.abs(t) < half)
        midrib = np.abs(t) < 0.012 + 0.01 * (1 - s)
        side = np.abs(((s - 1.4 * np.abs(t)) * 9) % 1 - 0.5) < 0.06  # veins slanting out to the tip
        inside |= leaf
        vein |= leaf & (midrib | (side & (np.abs(t) < 0.8 * half)))
        shade = np.where(leaf, 0.85 + 0.3 * k / max(leaves - 1, 1) - 0.2 * np.abs(t) / np.maximum(half, 1e-9), shade)
    stem = (np.abs(x - 0.5) < 0.012) & (y > 0.88)
    inside |= stem
    vein |= stem
    rgb = np.clip(np.asarray(LEAF, float) * shade[..., None], 0, 255)
    rgb = np.where(vein[..., None], np.asarray(VEIN, float), rgb)
    rgb = np.where(inside[..., None], rgb, np.asarray(LEAF_BACKGROUND, float))
    alpha = np.where(inside, 255, 0)
    return np.concatenate([rgb, alpha[..., None]], axis=2).round().astype(np.uint8)


def alpha_cut_leaves(cards: int = 3, n: int = 4, size: float = 1.0, texture_size: int = 512) -> Mesh:
    """A small plant: `cards` upright square quads of 2 n^2 triangles crossed about their common
    vertical axis (turned 180 / cards degrees apart), each with its own leaf_texture, alpha-masked
    (MASK at 0.5): the rays between the leaves pass through to the cards behind."""
    uv, quad = _grid(n, n)
    vertices, faces, material = [], [], []
    for k in range(cards):
        angle = np.pi * k / cards
        across = np.array([np.cos(angle), 0.0, -np.sin(angle)])
        pts = size * ((uv[:, :1] - 0.5) * across + uv[:, 1:] * np.array([0.0, 1.0, 0.0]))
        faces.append(quad + len(vertices) * len(uv))
        vertices.append(pts)
        material.append(np.full(len(quad), k))
    materials = [
        Material(texture=leaf_texture(texture_size, seed=k), alpha_mode="MASK", name=f"leaf {k}") for k in range(cards)
    ]
    return Mesh(
        np.concatenate(vertices),
        np.concatenate(faces),
        np.tile(uv[quad], (cards, 1, 1)),
        np.concatenate(material),
        materials,
    )


def textured_corpus(small: bool = False) -> dict[str, Mesh]:
    """name -> Mesh: the textured meshes mesh-to-splats is measured on. `small` gives coarser
    meshes and textures of the same kinds, for tests."""
    if small:
        return {
            "striped cylinder": striped_cylinder(16, 8, texture=stripe_texture(256, 64, 16, 6)),
            "grid plane": grid_plane(8, texture=grid_texture(256, 4, 16, 1)),
            "alpha-cut leaves": alpha_cut_leaves(3, 2, texture_size=128),
        }
    return {
        "striped cylinder": striped_cylinder(),
        "striped cup": striped_cup(),
        "grid plane": grid_plane(),
        "decal box": decal_box(),
        "vertex-coloured sphere": vertex_coloured_sphere(),
        "alpha-cut leaves": alpha_cut_leaves(),
    }
