"""Between projection and compositing (core/render.py's notes): the projected splats, one 64-byte
record each, front to back (Projected); the screen-space covariance and frustum clamp that the
projection and the backward pass (core/render_grad.py) share; and the NumPy path's binning of the
records into square tiles, each tile's entries front to back."""

from dataclasses import dataclass

import numpy as np

from . import scratch
from .parallel import Pool
from .render_constants import FRUSTUM_MARGIN
from .spatial import ramp


@dataclass
class Projected:
    """Visible splats in front-to-back order (ties by index), in pixel space.

    Each splat is one 64-byte record (a cache line, so the compositor fetches it with one read):
    float64 u, v (pixel-space mean) and conic a, b, c (inverse of Sigma2D + 0.3 I), then float32
    log opacity, r, g, b, camera z and 1. The last record is padding whose alpha is exactly 0.
    """

    index: np.ndarray  # (n,) index into the input cloud
    records: np.ndarray  # (n+1, 8) float64, laid out as above
    r2: np.ndarray  # (n,) squared Mahalanobis extent: alpha >= 1/255 inside
    bbox: np.ndarray  # (n, 4) int64 inclusive pixel box x0, y0, x1, y1 (clipped to the image)
    skipped_nonfinite: int

    def __len__(self):
        return len(self.index)

    @property
    def mean_conic(self):
        """(n+1, 5) float64 view: u, v, conic a, b, c."""
        return self.records[:, :5]


def new_records(n):
    """Room for n records plus the padding record, each record on one cache line (64-byte aligned:
    NumPy's large arrays start 16 bytes past a page, which would put every record across two).
    Only the padding record is set: every projection writes each field of the records it keeps."""
    raw = scratch.empty((n + 2) * 64, np.uint8)
    start = -raw.ctypes.data % 64
    rec = raw[start : start + (n + 1) * 64].view(np.float64).reshape(n + 1, 8)
    rec[n] = 0.0
    record_floats(rec[n:])[:, 0] = -1e30  # padding: exp(-1e30) = 0
    return rec


def record_floats(records):
    """The float32 part of records: (m, 6) log opacity, r, g, b, camera z, 1."""
    return records[:, 5:].view(np.float32)


# screen geometry, shared with the backward pass ---------------------------------------------------


def _dot3(p, q):
    return p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1] + p[:, 2] * q[:, 2]


def _cross3(p, q):
    return np.stack(
        [
            p[:, 1] * q[:, 2] - p[:, 2] * q[:, 1],
            p[:, 2] * q[:, 0] - p[:, 0] * q[:, 2],
            p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0],
        ],
        axis=1,
    )


def screen_covariance(m0, m1, rs):
    """Sigma2D = V V^T with V = J W R S (2x3, rows m0 rs and m1 rs): V's rows, Sigma2D's entries a, b,
    c, and its determinant. V V^T is exactly symmetric and PSD, and its determinant is the squared
    cross product of V's rows, free of the cancellation in a c - b^2 for needles."""
    v0 = np.einsum("nj,njk->nk", m0, rs)
    v1 = np.einsum("nj,njk->nk", m1, rs)
    return v0, v1, _dot3(v0, v0), _dot3(v0, v1), _dot3(v1, v1), _dot3(*(_cross3(v0, v1),) * 2)


def clamped_ratios(tx, ty, camera):
    """x/z and y/z clamped where the Jacobian is taken: the reference clamps them to 1.3 x tan(half
    fov) around the centre; with an off-centre principal point the same 30% margin is kept beyond
    each image edge."""
    mx, my = (FRUSTUM_MARGIN - 1) / 2 * camera.width, (FRUSTUM_MARGIN - 1) / 2 * camera.height
    return (
        np.minimum(np.maximum(tx, (-camera.cx - mx) / camera.fx), (camera.width - camera.cx + mx) / camera.fx),
        np.minimum(np.maximum(ty, (-camera.cy - my) / camera.fy), (camera.height - camera.cy + my) / camera.fy),
    )


def screen_rows(cam, camera):
    """Pixel-space means and the rows of J W (the projection's Jacobian at each camera-space point
    times the world-to-camera rotation), each (n,3)."""
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    rot = camera.rotation
    if camera.is_orthographic:
        u, v = camera.fx * x + camera.cx, camera.fy * y + camera.cy
        return u, v, np.broadcast_to(camera.fx * rot[0], cam.shape), np.broadcast_to(camera.fy * rot[1], cam.shape)
    tx, ty = x / z, y / z
    u, v = camera.fx * tx + camera.cx, camera.fy * ty + camera.cy
    tx, ty = clamped_ratios(tx, ty, camera)
    # J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]]; each row times W
    fz, gz = camera.fx / z, camera.fy / z
    m0, m1 = np.empty_like(cam), np.empty_like(cam)
    for k in range(3):
        m0[:, k] = fz * (rot[0, k] - tx * rot[2, k])
        m1[:, k] = gz * (rot[1, k] - ty * rot[2, k])
    return u, v, m0, m1


# tile binning ---------------------------------------------------------------------------------


@dataclass
class Bins:
    tile_size: int
    tiles_x: int
    tiles_y: int
    entry_splat: np.ndarray  # (E,) splat per entry, grouped by tile, front to back within a tile
    offsets: np.ndarray  # (tiles+1,) entries of tile t are entry_splat[offsets[t]:offsets[t+1]]

    @property
    def n_tiles(self):
        return self.tiles_x * self.tiles_y


def bin_tiles(proj, camera, tile_size, pool=None):
    """Every (tile, splat) pair whose alpha >= 1/255 ellipse reaches the rectangle spanned by the
    tile's pixel centres, grouped by tile and front to back within each tile.

    Runs on depth-ordered chunks of splats in parallel; each chunk's entries are sorted by tile,
    then the chunks' per-tile runs are laid out one after the other, which keeps depth order.
    """
    pool = pool or Pool(1)
    ts = tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    n_tiles = tiles_x * tiles_y
    n = len(proj)
    bounds = np.linspace(0, n, 2 * pool.threads + 1 if n > 10000 else 2).astype(np.int64)
    parts = pool.map(
        lambda k: _bin_chunk(proj, bounds[k], bounds[k + 1], ts, tiles_x, n_tiles), list(range(len(bounds) - 1))
    )
    counts = np.stack([c for _, c in parts])  # (chunks, tiles)
    offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    np.cumsum(counts.sum(axis=0), out=offsets[1:])
    starts = offsets[:-1] + np.cumsum(counts, axis=0) - counts  # where each chunk's run begins
    entry_splat = np.empty(int(offsets[-1]), dtype=np.int32)

    def place(k):
        splat, count = parts[k]
        local = np.cumsum(count) - count
        entry_splat[np.repeat(starts[k] - local, count) + np.arange(len(splat))] = splat

    pool.map(place, list(range(len(parts))))
    return Bins(ts, tiles_x, tiles_y, entry_splat, offsets)


def _bin_chunk(proj, lo, hi, ts, tiles_x, n_tiles):
    """Entries of splats lo..hi-1 sorted by tile (stable): (splat ids, entries per tile)."""
    box = proj.bbox[lo:hi]
    row0 = box[:, 1] // ts
    rows = box[:, 3] // ts - row0 + 1
    splat = np.repeat(np.arange(lo, hi, dtype=np.int32), rows)
    row = np.repeat(row0, rows) + ramp(rows)
    col0, col1 = np.repeat(box[:, 0] // ts, rows), np.repeat(box[:, 2] // ts, rows)
    # A box one tile high or wide meets every tile it covers; only larger ones need the ellipse.
    big = np.flatnonzero((rows > 1) & (box[:, 2] // ts > box[:, 0] // ts))
    if len(big):
        fit = np.repeat(np.cumsum(rows)[big] - rows[big], rows[big]) + ramp(rows[big])
        col0[fit], col1[fit] = _row_extent(proj, lo + big, rows[big], row[fit], ts)
    cols = np.maximum(col1 - col0 + 1, 0)
    splat = np.repeat(splat, cols)
    tile = np.repeat(row * tiles_x + col0, cols) + ramp(cols)
    order = stable_argsort(tile, n_tiles)
    return splat[order], np.bincount(tile, minlength=n_tiles)


def _row_extent(proj, ids, rows, row, ts):
    """First and last tile column that the splat's ellipse reaches within a tile row (its band of
    pixel-centre rows, cut to the splat's box). The right edge of the ellipse, x(dy), is concave in
    dy with its maximum at the ellipse's rightmost point, so over a band of dy it peaks there or at
    the band end nearest to it; the left edge mirrors this. `ids` are splats spanning `rows` tile
    rows each; `row` lists those rows, splat by splat."""
    u, v, a, b, c = proj.mean_conic[ids].T
    r2 = proj.r2[ids]
    det = a * c - b * b
    sxx = c / det  # covariance entries
    half_x = np.sqrt(r2 * sxx)
    peak = np.sqrt(r2 / sxx) * (-b / det)  # dy of the rightmost point (leftmost: -peak)
    box = proj.bbox[ids]
    u, v, a, b, r2, det, half_x, peak = (np.repeat(x, rows) for x in (u, v, a, b, r2, det, half_x, peak))
    box = np.repeat(box, rows, axis=0)
    lo = np.maximum(row * ts, box[:, 1]) + 0.5 - v
    hi = np.minimum(row * ts + ts - 1, box[:, 3]) + 0.5 - v

    def edge(dy, sign):
        return (-b * dy + sign * np.sqrt(np.maximum(a * r2 - det * dy * dy, 0.0))) / a

    right = np.where((peak >= lo) & (peak <= hi), half_x, edge(np.minimum(np.maximum(peak, lo), hi), 1.0))
    left = np.where((-peak >= lo) & (-peak <= hi), -half_x, edge(np.minimum(np.maximum(-peak, lo), hi), -1.0))
    x0 = np.maximum(np.ceil(u + left - 0.5), box[:, 0]).astype(np.int64)
    x1 = np.minimum(np.floor(u + right - 0.5), box[:, 2]).astype(np.int64)
    return x0 // ts, np.where(x1 >= x0, x1 // ts, x0 // ts - 1)


def stable_argsort(keys, n_keys):
    """Stable argsort of non-negative integers below n_keys <= 2^32: NumPy radix-sorts 16-bit
    keys, and two 16-bit passes (low half, then high half) sort larger ones."""
    if n_keys <= 1 << 16:
        return np.argsort(keys.astype(np.uint16), kind="stable")
    low = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    high = np.argsort((keys[low] >> 16).astype(np.uint16), kind="stable")
    return low[high]
