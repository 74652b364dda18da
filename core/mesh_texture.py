"""Texture-aware splats: what a mesh's textures and colours ask of the splats on it.

- Footprint filtering: a splat shows one colour over its Gaussian, so its colour is the texture
  averaged over that Gaussian mapped into texels (an elliptical footprint: `footprint_average`),
  not the texel under its centre nor a square mip level.
- Texture edges: where the surface colour changes hard (a stripe's edge, a one-texel line, a
  glyph, a material or vertex-colour boundary) or an alpha-cut surface ends, a splat reaching
  across the edge would smear it over its own width. `texture_edges` gives each splat its
  distance to the nearest such edge and the edge's normal in its face's frame, so sampling can
  narrow it across the edge (long along it, thin across: core/mesh_sampling.py).

Frames: a face's "local" frame is core/mesh_sampling.py's (first edge t1, normal x t1), in world
units; texel coordinates are (u w, (1 - v) h) of a material's texture, rows down, as
core.mesh.sample_texture reads them.
"""

import numpy as np

from . import color

EDGE_CONTRAST = 0.08  # display-colour step (largest channel) between neighbouring texels that can be an edge
STEP_CONTRAST = 0.1  # ... and between the two sides of an edge, blurred to a splat's scale, that it narrows across
MAX_TAPS = 9  # footprint_average's lookups along an elongated footprint, at most


def local_corners(surface) -> np.ndarray:
    """(F,3,2) the faces' corners in their local frames (corner 0 at the origin)."""
    length1 = np.linalg.norm(surface.edge1, axis=1)
    t1 = surface.edge1 / np.where(length1 > 0, length1, 1.0)[:, None]
    t2 = np.cross(surface.normal, t1)
    corners = np.zeros((len(surface.faces), 3, 2))
    corners[:, 1, 0] = length1
    corners[:, 2] = np.column_stack(
        [np.einsum("ij,ij->i", surface.edge2, t1), np.einsum("ij,ij->i", surface.edge2, t2)]
    )
    return corners


def texel_jacobians(surface, material) -> np.ndarray:
    """(F,2,2): d(texel x, y) / d(local x, y) of `material`'s texture on every face (0 where a
    face's UVs or geometry are degenerate)."""
    h, w = material.texture.shape[:2]
    uv = surface.corner_uvs * np.asarray(material.uv_scale, float)
    texel = np.stack([uv[..., 0] * w, -uv[..., 1] * h], axis=-1)  # the offset and flip's 1 - v drop out
    dt = np.stack([texel[:, 1] - texel[:, 0], texel[:, 2] - texel[:, 0]], axis=-1)  # columns: edges
    p = local_corners(surface)
    dp = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=-1)
    det = dp[:, 0, 0] * dp[:, 1, 1] - dp[:, 0, 1] * dp[:, 1, 0]
    ok = np.abs(det) > 0
    inverse = np.stack([np.stack([dp[:, 1, 1], -dp[:, 0, 1]], -1), np.stack([-dp[:, 1, 0], dp[:, 0, 0]], -1)], 1)
    inverse /= np.where(ok, det, 1.0)[:, None, None]
    return np.where(ok[:, None, None], dt @ inverse, 0.0)


def footprint_average(
    levels: list[np.ndarray], uv: np.ndarray, cov: np.ndarray, max_taps: int = MAX_TAPS
) -> np.ndarray:
    """The texture averaged over Gaussian footprints: (n,3) float64 for texel-space covariances
    cov (n,2,2) centred at uv (n,2) (v up, as sample_texture takes them); `levels` a mipmap
    (core.mesh.Material.mipmap).

    A trilinear lookup at the mip level whose blur matches the ellipse's minor axis (a level of
    texels s wide, read bilinearly, blurs by a variance of s^2 / 4: its box and the tent), and for
    an elongated ellipse more such lookups along its major axis, Gaussian-weighted, for the rest
    of its variance there: one lookup for a round footprint, up to `max_taps` (odd) for a long one,
    no further apart than the level's own blur (their spacing grows past `max_taps`)."""
    xx, xy, yy = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    mean, radius = (xx + yy) / 2, np.hypot((xx - yy) / 2, xy)
    minor = np.maximum(mean - radius, 0.0)
    angle = 0.5 * np.arctan2(2 * xy, xx - yy)
    blur = np.maximum(np.sqrt(minor), 0.5)  # the level's blur (std); level 0 read bilinearly: 0.5
    level = np.log2(2 * blur)
    rest = np.sqrt(np.maximum(2 * radius, 0.0))  # major - minor: what the taps add along the major axis
    # one lookup where the level's own blur covers what the major axis adds (sub-texel splats:
    # bilinear, as the reference reads the texture)
    half = np.where(rest > blur, np.clip(np.ceil(2 * rest / blur), 1, (max_taps - 1) // 2), 0).astype(np.int64)
    h, w = levels[0].shape[:2]
    direction = np.column_stack([np.cos(angle) / w, -np.sin(angle) / h])  # one texel along the major axis, in uv
    out = np.empty((len(uv), levels[0].shape[2]))
    for k in np.unique(half):
        sel = np.flatnonzero(half == k)
        if k == 0:
            out[sel] = sample_mipmap(levels, uv[sel], level[sel])
            continue
        t = np.arange(-k, k + 1) / k * 2.0  # -2 .. 2 standard deviations of the rest
        weights = np.exp(-0.5 * t**2)
        weights /= weights.sum()
        offset = t[None, :, None] * (rest[sel, None, None] * direction[sel, None, :])
        taps = (uv[sel, None, :] + offset).reshape(-1, 2)
        values = sample_mipmap(levels, taps, np.repeat(level[sel], 2 * k + 1))
        out[sel] = np.einsum("t,ntc->nc", weights, values.reshape(len(sel), 2 * k + 1, -1))
    return out


def _hard_steps(steps, axis):
    """Which of the colour steps between neighbouring texels (along `axis`) are hard edges: above
    EDGE_CONTRAST and over twice the smaller of the steps beside them along the same axis (a smooth
    ramp steps as much at every texel; a stripe's edge or a thin line stands out from its
    neighbours on at least one side)."""
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 1)
    around = np.pad(steps, pad, mode="wrap")  # textures repeat
    before = np.take(around, np.arange(0, steps.shape[axis]), axis=axis)
    after = np.take(around, np.arange(2, steps.shape[axis] + 2), axis=axis)
    return (steps > EDGE_CONTRAST) & (steps > 2 * np.minimum(before, after))


class EdgeField:
    """Where a texture changes hard, and how far each texel is from there: per texel, the offset
    (dx, dy) in texels from its centre to the nearest hard step between neighbouring texels
    (_hard_steps), the way round the repeating texture if shorter, and that edge's normal (nx,
    ny; texel space, not normalised: the signed steps around it). Computed once per texture
    (core.mesh.Material.edge_field); `any` is False for a texture without hard steps."""

    def __init__(self, linear_texture: np.ndarray, alpha: np.ndarray | None = None):
        display = to_display(linear_texture.astype(np.float64))
        if alpha is not None:  # an alpha-cut texture (H,W,1): where the surface ends is an edge too
            display = np.concatenate([display, alpha.astype(np.float64)], axis=2)
        # the steps between columns j and j + 1, and rows i and i + 1, the last and first included
        step_x = _hard_steps(np.abs(np.roll(display, -1, axis=1) - display).max(axis=2), 1)
        step_y = _hard_steps(np.abs(np.roll(display, -1, axis=0) - display).max(axis=2), 0)
        self.any = bool(step_x.any() or step_y.any())
        if not self.any:
            return
        h, w = display.shape[:2]
        # The texels beside each hard step start with its midpoint as their nearest edge point, and
        # the step's signed size (summed over the channels) as its normal.
        seed = np.zeros((h, w), bool)
        point = np.zeros((2, h, w))  # (y, x) of the nearest edge point, texel centres at integers
        grad = np.zeros((2, h, w))  # (x, y) signed steps around each texel: the edges' normals
        total = display.sum(axis=2)
        for axis, steps in ((1, step_x), (0, step_y)):
            r, c = np.nonzero(steps)
            size = (np.roll(total, -1, axis=axis) - total)[r, c]
            for rr, cc in ((r, c), ((r + (axis == 0)) % h, (c + (axis == 1)) % w)):
                seed[rr, cc] = True
                point[0, rr, cc] = r + 0.5 * (axis == 0)
                point[1, rr, cc] = c + 0.5 * (axis == 1)
                np.add.at(grad[1 - axis], (rr, cc), size)
        box = sum(np.roll(grad, (dy, dx), axis=(1, 2)) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        normal = np.where(seed, box, 0.0)
        point, normal = _jump_flood(seed, point, normal)
        rows, cols = np.mgrid[0:h, 0:w]
        self.dy = (point[0] - rows + h / 2) % h - h / 2  # textures repeat: the way round if shorter
        self.dx = (point[1] - cols + w / 2) % w - w / 2
        self.nx, self.ny = normal

    def at(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset (n,2), normal (n,2)) in texels at texture coordinates uv (n,2), wrapped."""
        h, w = self.dx.shape
        fx, fy = uv[:, 0] * w, (1.0 - uv[:, 1]) * h
        x, y = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        # from the point itself: its texel's way to the edge, less the point's place in the texel
        offset = np.column_stack([self.dx[y % h, x % w] - (fx - x - 0.5), self.dy[y % h, x % w] - (fy - y - 0.5)])
        x, y = x % w, y % h
        normal = np.column_stack([self.nx[y, x], self.ny[y, x]])
        # Where the edge's own orientation is ambiguous (a corner), the way to it stands in.
        length = np.linalg.norm(normal, axis=1)
        way = np.linalg.norm(offset, axis=1)
        normal = np.where(
            (length > 0)[:, None], normal / np.maximum(length, 1e-12)[:, None], offset / np.maximum(way, 1e-12)[:, None]
        )
        return offset, normal


def _jump_flood(seed, point, normal):
    """Every texel's nearest of the seeds' points, and that seed's `normal`, on a repeating grid:
    jump flooding (each texel takes a neighbour's point where nearer, at steps of half the size,
    a quarter, ... 1, then 1 again), in NumPy: every texel at once, a shift at a time."""
    h, w = seed.shape
    rows, cols = np.mgrid[0:h, 0:w]

    def distance2(p):
        dy = (p[0] - rows + h / 2) % h - h / 2
        dx = (p[1] - cols + w / 2) % w - w / 2
        return dy * dy + dx * dx

    best = np.where(seed, distance2(point), np.inf)
    step = 1 << max(int(np.log2(max(h, w))) - 1, 0)
    steps = []
    while step >= 1:
        steps.append(step)
        step //= 2
    for step in steps + [1]:
        for dy in (-step, 0, step):
            for dx in (-step, 0, step):
                if not (dy or dx):
                    continue
                has = np.roll(seed, (dy, dx), axis=(0, 1))
                p = np.roll(point, (dy, dx), axis=(1, 2))
                d = np.where(has, distance2(p), np.inf)
                nearer = d < best
                if nearer.any():
                    best = np.where(nearer, d, best)
                    seed = seed | nearer
                    point = np.where(nearer, p, point)
                    normal = np.where(nearer, np.roll(normal, (dy, dx), axis=(1, 2)), normal)
    return point, normal


def texture_edges(
    surface, tri: np.ndarray, bary: np.ndarray, sigma: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(distance (n,), across (n,2)): each point's distance (world units) to the nearest texture
    edge of its material (a colour step, or where an alpha-cut material's alpha steps), and that
    edge's unit normal in the face's local frame; inf and 0 where its material has no texture (or
    no edges).

    With `sigma` (n,), a splat's standard deviation (world), only steps at that scale count: the
    texture blurred to sigma / 2 and read sigma either side of the edge must differ by more than
    STEP_CONTRAST. A line thinner than the splat
    has the same colour either side: a splat narrowed to it would show a dot of the line, or none,
    where its centre happens to fall; left round, it shows the line's share of its footprint, as a
    pixel filter does."""
    distance = np.full(len(tri), np.inf)
    across = np.zeros((len(tri), 2))
    if surface.corner_uvs is None:
        return distance, across
    mat = surface.face_materials[tri]
    uv = np.einsum("nk,nkc->nc", bary, surface.corner_uvs[tri])
    for m, material in enumerate(surface.materials):
        field = material.edge_field() if material.texture is not None else None
        sel = np.flatnonzero(mat == m)
        if field is None or not field.any or not len(sel):
            continue
        jac = surface.texel_jacobians(m)[tri[sel]]
        lookup = uv[sel] * np.asarray(material.uv_scale, float) + np.asarray(material.uv_offset, float)
        offset, normal = field.at(lookup)
        # A texel-space edge with normal n: its normal in the local frame is J^T n (a covector),
        # and the distance to it there is (n . offset) / |J^T n|.
        local = np.einsum("nji,nj->ni", jac, normal)
        scale = np.linalg.norm(local, axis=1)
        ok = scale > 0
        if sigma is not None:
            ok &= _is_step(material, lookup, offset, normal, sigma[sel] * scale)
        # Read bilinearly, a step between texels is a ramp a texel wide: no edge is nearer than
        # half a texel.
        away = np.maximum(np.abs(np.einsum("ij,ij->i", offset, normal)), 0.5)
        distance[sel[ok]] = away[ok] / scale[ok]
        across[sel[ok]] = local[ok] / scale[ok, None]
    return distance, across


def _is_step(material, uv, offset, normal, reach):
    """(n,) bool: whether the texture, blurred to `reach` / 2 texels, differs by more than
    STEP_CONTRAST (display) `reach` texels either side of the edge at `offset` texels from uv
    across `normal`, or its alpha does on an alpha-cut material (an alpha edge: the surface ends)."""
    levels = material.mipmap()
    h, w = levels[0].shape[:2]
    edge = uv + offset * np.array([1.0 / w, -1.0 / h])
    way = normal * reach[:, None] * np.array([1.0 / w, -1.0 / h])
    level = np.log2(np.maximum(reach, 1.0))
    near, far = (to_display(sample_mipmap(levels, edge + sign * way, level)) for sign in (-1.0, 1.0))
    step = np.abs(near - far).max(axis=1) > STEP_CONTRAST
    if material.cut:
        alpha = material.premultiplied_mipmap()
        near, far = (sample_mipmap(alpha, edge + sign * way, level)[:, 3] for sign in (-1.0, 1.0))
        step |= np.abs(near - far) > STEP_CONTRAST
    return step


def face_detail(surface) -> np.ndarray:
    """(F,) bool: faces with colour detail, a texture edge within their reach (the distance from
    their centroid to the nearest edge below their size) or a colour seam along them."""
    detail = colour_seams(surface).any(axis=1)
    tri = np.arange(len(surface.faces))
    distance, _ = texture_edges(surface, tri, np.full((len(tri), 3), 1.0 / 3))
    size = np.sqrt(2 * surface.area)
    return (detail | (distance < size)) & surface.valid


def colour_seams(surface, contrast: float = EDGE_CONTRAST) -> np.ndarray:
    """(F,3) bool: edge k of a face (opposite corner k) where the surface colour changes hard
    across it: another material, or corner colours that differ from the neighbour's on the shared
    edge by more than `contrast` (display). Welded by position, like core.mesh's outline edges."""
    welded = surface.welded_faces()
    a, b = welded[:, [1, 2, 0]].ravel().astype(np.int64), welded[:, [2, 0, 1]].ravel().astype(np.int64)
    key = np.minimum(a, b) * np.int64(welded.max() + 1) + np.maximum(a, b)  # edge k: corners k+1, k+2
    order = np.argsort(key, kind="stable")
    pair = np.flatnonzero(key[order][1:] == key[order][:-1])
    a, b = order[pair], order[pair + 1]  # flat (face * 3 + k) of two uses of one edge
    fa, ka, fb, kb = a // 3, a % 3, b // 3, b % 3
    differs = surface.face_materials[fa] != surface.face_materials[fb]
    if surface.corner_colors is not None:
        display = to_display(surface.corner_colors)

        def ends(f, k):  # the edge's two corner colours, in the order of their welded vertices
            c1, c2 = display[f, (k + 1) % 3], display[f, (k + 2) % 3]
            v1, v2 = welded[f, (k + 1) % 3], welded[f, (k + 2) % 3]
            swap = (v1 > v2)[:, None]
            return np.where(swap, c2, c1), np.where(swap, c1, c2)

        a1, a2 = ends(fa, ka)
        b1, b2 = ends(fb, kb)
        step = np.maximum(np.abs(a1 - b1).max(axis=1), np.abs(a2 - b2).max(axis=1))
        differs |= step > contrast
    seams = np.zeros(len(surface.faces) * 3, bool)
    seams[a[differs]] = True
    seams[b[differs]] = True
    return seams.reshape(-1, 3) & surface.valid[:, None]


def to_display(linear: np.ndarray) -> np.ndarray:
    """Scene-linear -> display sRGB as an emission shader shows it under the 'Standard' view."""
    return color.linear_to_srgb(np.clip(linear, 0.0, 1.0))


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with repeat wrapping: (H,W,C) texture, (n,2) uv with v up -> (n,C) float64."""
    h, w = texture.shape[:2]
    x = np.asarray(uv[:, 0], np.float64) * w - 0.5
    y = (1.0 - np.asarray(uv[:, 1], np.float64)) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    texels = texture.reshape(h * w, -1)  # flat lookups: much faster than 2D fancy indexing
    row0, row1 = y0 * w, y1 * w
    gx = 1 - fx
    top = texels.take(row0 + x0, axis=0) * gx + texels.take(row0 + x1, axis=0) * fx
    bottom = texels.take(row1 + x0, axis=0) * gx + texels.take(row1 + x1, axis=0) * fx
    return top * (1 - fy) + bottom * fy


def sample_mipmap(levels: list[np.ndarray], uv: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Trilinear lookup: bilinear in the two mip levels around `level` (n,), blended."""
    level = np.clip(level, 0.0, len(levels) - 1.0)
    lo = np.floor(level).astype(np.int64)
    frac = level - lo
    out = np.empty((len(uv), levels[0].shape[2]))
    present = np.flatnonzero(np.bincount(lo, minlength=len(levels)))
    for k in present:
        sel = slice(None) if len(present) == 1 else np.flatnonzero(lo == k)
        value = sample_texture(levels[k], uv[sel])
        blend = np.flatnonzero(frac[sel] > 0)  # only where the footprint is between levels
        if len(blend):
            f = frac[sel][blend, None]
            above = sample_texture(levels[min(k + 1, len(levels) - 1)], uv[sel][blend])
            value[blend] = value[blend] * (1 - f) + above * f
        out[sel] = value
    return out
