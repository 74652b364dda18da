"""Compiled projection, tile binning and compositing for core.render (numba; loaded by core.jit).

The same rules as the NumPy path in core/render.py, which stays the readable reference and the
fallback: these loops compute, per splat or per tile, what it computes with whole-array operations.
What the loops buy besides speed:
- compositing walks each tile's entries front to back over the tile's pixel state, but evaluates
  only the tile rows that an entry's alpha >= 1/255 ellipse (its box) crosses, so a sub-pixel splat
  costs a row or two of its tile, not all of it, and a tile stops within a few entries of its last
  pixel stopping;
- the image is written straight from each tile, with no per-tile accumulators (memory is the
  image, the projected splats and the tile lists).
Each kernel runs on one thread over a range of splats or tiles; core.render spreads the ranges
over the cores (the kernels release the GIL).
"""

import math

import numpy as np

from .jit import njit, prefetcher
from .render_constants import AA_MIN_RATIO, ALPHA_MAX, ALPHA_MIN, LOW_PASS, MAX_TILE_SIZE
from .sh import C0, C1, C2, C3, C4

prefetch = prefetcher()  # random reads (records by entry, rows by index) start a few items early
LOG_ALPHA_MIN = math.log(ALPHA_MIN)
LOG_ALPHA_MAX = math.log(ALPHA_MAX)
# exp(x) for x in [EXP_FLOOR, 0] (alpha >= 1/255 needs x >= -5.55) as p(x/16)^16, p the Taylor terms to
# r^7 (relative error below 2e-8 for |r| <= 3/8, 4e-7 after the squarings)
EXP_FLOOR = -6.0
SHAPE_PIECE = 4096  # splats whose shapes project_range computes at a time (80 B each: stays in cache)
EXP_TERMS = (1.0, 1.0, 1.0 / 2, 1.0 / 6, 1.0 / 24, 1.0 / 120, 1.0 / 720, 1.0 / 5040)


# projection ---------------------------------------------------------------------------------------


@njit
def band4_color(x, y, z, c):
    """sum over m of the degree-4 basis function (core.sh._band4) at the unit x, y, z times c[m + 4]."""
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    return (
        C4[0] * xy * (xx - yy) * c[0]
        + C4[1] * yz * (3 * xx - yy) * c[1]
        + C4[2] * xy * (7 * zz - 1) * c[2]
        + C4[3] * yz * (7 * zz - 3) * c[3]
        + C4[4] * (zz * (35 * zz - 30) + 3) * c[4]
        + C4[5] * xz * (7 * zz - 3) * c[5]
        + C4[6] * (xx - yy) * (7 * zz - 1) * c[6]
        + C4[7] * xz * (xx - 3 * yy) * c[7]
        + C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)) * c[8]
    )


@njit
def shape_range(rotations, log_scales, logits, rows, lo, hi, out, base, widest):
    """Rows t - base of out (n, 10) for t in lo..hi-1, of splats rows[t] (of splat t where rows is
    empty): what projecting them needs that no camera changes, in float64. out[:, :9] is R S row by
    row, the rotation (the normalised quaternion; zero or non-finite norms: the identity) times the
    scales, out[:, 9] the opacity, NaN where the rotation, scales or logit is not finite. widest
    (n,), unless empty: the splat's widest scale, exp of its largest log-scale (as
    core.shadow_cameras.reach_and_gap takes it)."""
    every = rows.shape[0] == 0
    for t in range(lo, hi):
        i = t if every else rows[t]
        row = t - base
        if widest.shape[0]:
            widest[row] = math.exp(np.float64(max(max(log_scales[i, 0], log_scales[i, 1]), log_scales[i, 2])))
        finite = np.isfinite(logits[i])
        for j in range(3):
            finite &= np.isfinite(log_scales[i, j])
        for j in range(4):
            finite &= np.isfinite(rotations[i, j])
        if not finite:
            out[row, 9] = np.nan
            continue
        logit = np.float64(logits[i])
        out[row, 9] = 1.0 / (1.0 + math.exp(-logit)) if logit >= 0 else math.exp(logit) / (1.0 + math.exp(logit))
        qw, qx, qy, qz = (
            np.float64(rotations[i, 0]),
            np.float64(rotations[i, 1]),
            np.float64(rotations[i, 2]),
            np.float64(rotations[i, 3]),
        )
        norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if np.isfinite(norm) and norm > 1e-30:
            qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        else:
            qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        s0 = math.exp(np.float64(log_scales[i, 0]))
        s1 = math.exp(np.float64(log_scales[i, 1]))
        s2 = math.exp(np.float64(log_scales[i, 2]))
        out[row, 0] = (1 - 2 * (qy * qy + qz * qz)) * s0
        out[row, 1] = 2 * (qx * qy - qw * qz) * s1
        out[row, 2] = 2 * (qx * qz + qw * qy) * s2
        out[row, 3] = 2 * (qx * qy + qw * qz) * s0
        out[row, 4] = (1 - 2 * (qx * qx + qz * qz)) * s1
        out[row, 5] = 2 * (qy * qz - qw * qx) * s2
        out[row, 6] = 2 * (qx * qz - qw * qy) * s0
        out[row, 7] = 2 * (qy * qz + qw * qx) * s1
        out[row, 8] = (1 - 2 * (qx * qx + qy * qy)) * s2


@njit
def project_range(
    positions,
    rotations,
    log_scales,
    logits,
    sh,
    shapes,
    rows,
    lo,
    hi,
    center,
    rot,
    intrinsics,
    size,
    clip,
    ortho,
    antialiased,
    max_r2,
    rec64,
    rec32,
    index,
    depth,
    r2_out,
    bbox,
):
    """Cull and project splats rows[lo..hi-1] (splats lo..hi-1 where rows is empty), writing the
    visible ones (in that order) to rows lo.. of the outputs. Returns (visible count, skipped for
    non-finite values).

    shapes: shape_range's rows of every splat (index = splat), or an empty (0, 10) array to compute
    them here a piece at a time. intrinsics: fx, fy, cx, cy; size: width, height; clip: near, far,
    then the tangent clamp x/z in [clip[2], clip[3]], y/z in [clip[4], clip[5]]. rec64/rec32 are
    two views of the same (n, 8) float64 records (u, v, conic a, b, c | float32 log o, r, g, b, z, 1)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    width, height = size[0], size[1]
    near, far = clip[0], clip[1]
    k = sh.shape[1]
    out = lo
    skipped = 0
    m0 = np.empty(3)
    m1 = np.empty(3)
    own = shapes.shape[0] == 0
    every = rows.shape[0] == 0
    rs = np.empty((SHAPE_PIECE, 10)) if own else shapes  # R S and opacity: of the piece's t - start, or of splat i
    no_widest = np.empty(0)
    for start in range(lo, hi, SHAPE_PIECE):
        stop = min(start + SHAPE_PIECE, hi)
        if own:
            shape_range(rotations, log_scales, logits, rows, start, stop, rs, start, no_widest)
        for t in range(start, stop):
            i = t if every else rows[t]
            s = t - start if own else i
            opacity = rs[s, 9]
            finite = np.isfinite(opacity)
            for j in range(3):
                finite &= np.isfinite(positions[i, j])
            for j in range(k):
                for ch in range(3):
                    finite &= np.isfinite(sh[i, j, ch])
            if not finite:
                skipped += 1
                continue
            # camera space, relative to the eye in float64
            px = positions[i, 0] - center[0]
            py = positions[i, 1] - center[1]
            pz = positions[i, 2] - center[2]
            x = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz
            y = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz
            z = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz
            if not (z > near and z <= far and opacity >= ALPHA_MIN):
                continue
            if ortho:
                u, v = fx * x + cx, fy * y + cy
                for j in range(3):
                    m0[j] = fx * rot[0, j]
                    m1[j] = fy * rot[1, j]
            else:
                tx, ty = x / z, y / z
                u, v = fx * tx + cx, fy * ty + cy
                tx = min(max(tx, clip[2]), clip[3])
                ty = min(max(ty, clip[4]), clip[5])
                for j in range(3):
                    m0[j] = fx / z * (rot[0, j] - tx * rot[2, j])
                    m1[j] = fy / z * (rot[1, j] - ty * rot[2, j])
            # Sigma2D = V V^T, V = (J W) (R S): rows v0, v1
            v00 = m0[0] * rs[s, 0] + m0[1] * rs[s, 3] + m0[2] * rs[s, 6]
            v01 = m0[0] * rs[s, 1] + m0[1] * rs[s, 4] + m0[2] * rs[s, 7]
            v02 = m0[0] * rs[s, 2] + m0[1] * rs[s, 5] + m0[2] * rs[s, 8]
            v10 = m1[0] * rs[s, 0] + m1[1] * rs[s, 3] + m1[2] * rs[s, 6]
            v11 = m1[0] * rs[s, 1] + m1[1] * rs[s, 4] + m1[2] * rs[s, 7]
            v12 = m1[0] * rs[s, 2] + m1[1] * rs[s, 5] + m1[2] * rs[s, 8]
            a = v00 * v00 + v01 * v01 + v02 * v02
            b = v00 * v10 + v01 * v11 + v02 * v12
            c = v10 * v10 + v11 * v11 + v12 * v12
            c0 = v01 * v12 - v02 * v11
            c1 = v02 * v10 - v00 * v12
            c2 = v00 * v11 - v01 * v10
            det0 = c0 * c0 + c1 * c1 + c2 * c2
            det = det0 + LOW_PASS * (a + c) + LOW_PASS * LOW_PASS
            if antialiased:
                opacity = opacity * math.sqrt(max(AA_MIN_RATIO, det0 / det))
            r2 = 2.0 * math.log(max(255.0 * opacity, 1e-300))
            r2 = min(r2, max_r2)
            a += LOW_PASS
            c += LOW_PASS
            if not (np.isfinite(det) and np.isfinite(u) and np.isfinite(v)):
                skipped += 1
                continue
            half_x, half_y = math.sqrt(r2 * a), math.sqrt(r2 * c)
            x0 = max(math.ceil(min(max(u - half_x - 0.5, -1.0), width)), 0.0)
            y0 = max(math.ceil(min(max(v - half_y - 0.5, -1.0), height)), 0.0)
            x1 = min(math.floor(min(max(u + half_x - 0.5, -1.0), width)), width - 1.0)
            y1 = min(math.floor(min(max(v + half_y - 0.5, -1.0), height)), height - 1.0)
            if not (r2 > 0 and x0 <= x1 and y0 <= y1):
                continue
            # view-dependent colour, float64 (the direction only where SH have bands beyond the DC)
            dx, dy, dz = 0.0, 0.0, 0.0
            if k > 1:
                if ortho:
                    dx, dy, dz = rot[2, 0], rot[2, 1], rot[2, 2]
                else:
                    dx, dy, dz = px, py, pz
                dn = math.sqrt(dx * dx + dy * dy + dz * dz)
                if dn > 0:
                    dx, dy, dz = dx / dn, dy / dn, dz / dn
            for ch in range(3):
                col = 0.5 + C0 * sh[i, 0, ch]
                if k > 1:
                    col += C1 * (-dy * sh[i, 1, ch] + dz * sh[i, 2, ch] - dx * sh[i, 3, ch])
                if k > 4:
                    xx, yy, zz = dx * dx, dy * dy, dz * dz
                    col += (
                        C2[0] * dx * dy * sh[i, 4, ch]
                        + C2[1] * dy * dz * sh[i, 5, ch]
                        + C2[2] * (2 * zz - xx - yy) * sh[i, 6, ch]
                        + C2[3] * dx * dz * sh[i, 7, ch]
                        + C2[4] * (xx - yy) * sh[i, 8, ch]
                    )
                    if k > 9:
                        col += (
                            C3[0] * dy * (3 * xx - yy) * sh[i, 9, ch]
                            + C3[1] * dx * dy * dz * sh[i, 10, ch]
                            + C3[2] * dy * (4 * zz - xx - yy) * sh[i, 11, ch]
                            + C3[3] * dz * (2 * zz - 3 * xx - 3 * yy) * sh[i, 12, ch]
                            + C3[4] * dx * (4 * zz - xx - yy) * sh[i, 13, ch]
                            + C3[5] * dz * (xx - yy) * sh[i, 14, ch]
                            + C3[6] * dx * (xx - 3 * yy) * sh[i, 15, ch]
                        )
                        if k > 16:
                            col += band4_color(dx, dy, dz, sh[i, 16:25, ch])
                rec32[out, 11 + ch] = max(0.0, col)
            rec64[out, 0], rec64[out, 1] = u, v
            rec64[out, 2], rec64[out, 3], rec64[out, 4] = c / det, -b / det, a / det
            rec32[out, 10] = math.log(opacity)
            rec32[out, 14] = z
            rec32[out, 15] = 1.0
            index[out] = i
            depth[out] = z
            r2_out[out] = r2
            bbox[out, 0], bbox[out, 1], bbox[out, 2], bbox[out, 3] = x0, y0, x1, y1
            out += 1
    return out - lo, skipped


@njit
def stable_order(keys, rows, out):
    """out = rows sorted by keys[rows] (uint32), equal keys in the order of rows: a least significant
    digit radix sort, a byte a pass, skipping the bytes every key shares (a view's depths share their
    sign and most of their exponent). Twice as fast as NumPy's two 16-bit argsorts and the gathers
    between them (the hand's 400k visible splats: 7 ms, not 13)."""
    n = len(rows)
    sorted_keys, spare_keys = np.empty(n, np.uint32), np.empty(n, np.uint32)
    counts = np.zeros((4, 256), np.int64)
    for i in range(n):
        k = keys[rows[i]]
        sorted_keys[i] = k
        for d in range(4):
            counts[d, (k >> (8 * d)) & 255] += 1
    source, target = rows.copy(), out
    for d in range(4):
        shift = 8 * d
        if n == 0 or counts[d, (sorted_keys[0] >> shift) & 255] == n:
            continue
        starts = np.empty(256, np.int64)
        total = 0
        for b in range(256):
            starts[b] = total
            total += counts[d, b]
        for i in range(n):
            k = sorted_keys[i]
            b = (k >> shift) & 255
            spare_keys[starts[b]] = k
            target[starts[b]] = source[i]
            starts[b] += 1
        sorted_keys, spare_keys = spare_keys, sorted_keys
        source, target = target, source
    if source is not out:
        out[:] = source


# tile binning -------------------------------------------------------------------------------------


@njit
def count_tiles(rec64, r2, bbox, lo, hi, ts, tiles_x, first_row, spans, counts):
    """counts[tile] += the number of splats lo..hi-1 whose ellipse reaches that tile; each splat's
    first and last tile column in each of its tile rows go to spans[first_row[s] + row], for
    fill_tiles.

    Within a tile row (its band of pixel-centre rows, cut to the box) the ellipse reaches from its
    smallest to its largest x there (as core.render._row_extent): the right edge x(dy) is concave
    with its maximum at the ellipse's rightmost point, so over the band it peaks there or at the
    band end nearest to it; the left edge mirrors this. A box one tile high or wide meets every
    tile it covers."""
    for s in range(lo, hi):
        at = first_row[s]
        x0, y0, x1, y1 = bbox[s, 0], bbox[s, 1], bbox[s, 2], bbox[s, 3]
        whole = y1 // ts == y0 // ts or x1 // ts == x0 // ts
        u, v, a, b, c = rec64[s, 0], rec64[s, 1], rec64[s, 2], rec64[s, 3], rec64[s, 4]
        rr = r2[s]
        det = a * c - b * b
        sxx = c / det  # the covariance's x variance
        half = math.sqrt(rr * sxx)
        peak = math.sqrt(rr / sxx) * (-b / det)  # dy of the rightmost point (leftmost: -peak)
        inv_a, ar = 1.0 / a, a * rr
        for row in range(y0 // ts, y1 // ts + 1):
            if whole:
                c0, c1 = x0 // ts, x1 // ts
            else:
                lo_dy = max(row * ts, y0) + 0.5 - v
                hi_dy = min(row * ts + ts - 1, y1) + 0.5 - v
                if lo_dy <= peak <= hi_dy:
                    right = half
                else:
                    dy = min(max(peak, lo_dy), hi_dy)
                    right = (-b * dy + math.sqrt(max(ar - det * dy * dy, 0.0))) * inv_a
                if lo_dy <= -peak <= hi_dy:
                    left = -half
                else:
                    dy = min(max(-peak, lo_dy), hi_dy)
                    left = (-b * dy - math.sqrt(max(ar - det * dy * dy, 0.0))) * inv_a
                first = max(np.int64(math.ceil(u + left - 0.5)), x0)
                last = min(np.int64(math.floor(u + right - 0.5)), x1)
                c0, c1 = first // ts, (last // ts if last >= first else first // ts - 1)
            spans[at, 0], spans[at, 1] = c0, c1
            at += 1
            for col in range(c0, c1 + 1):
                counts[row * tiles_x + col] += 1


@njit
def fill_tiles(bbox, lo, hi, ts, tiles_x, first_row, spans, number, cursor, entry_splat):
    """Entries of splats lo..hi-1 (in this order, so front to back), as number[splat], at
    cursor[tile], which advances; the tiles from count_tiles' spans."""
    for s in range(lo, hi):
        at = first_row[s]
        for row in range(bbox[s, 1] // ts, bbox[s, 3] // ts + 1):
            for col in range(spans[at, 0], spans[at, 1] + 1):
                tile = row * tiles_x + col
                entry_splat[cursor[tile]] = number[s]
                cursor[tile] += 1
            at += 1


GATHER_AHEAD = 16  # rows ahead whose source gather() starts loading


@njit
def gather(rows, lo, hi, records, bbox, r2, index, records_out, bbox_out, r2_out, index_out):
    """Rows lo..hi-1 of the outputs from rows[lo..hi-1] of records and bbox, and of r2 and index
    unless their outputs are empty."""
    rest = len(r2_out) > 0
    for j in range(lo, hi):
        ahead = rows[min(j + GATHER_AHEAD, hi - 1)]
        prefetch(records, ahead * 8)
        prefetch(bbox, ahead * 4)
        if rest:
            prefetch(r2, ahead)
            prefetch(index, ahead)
        r = rows[j]
        for c in range(8):
            records_out[j, c] = records[r, c]
        for c in range(4):
            bbox_out[j, c] = bbox[r, c]
        if rest:
            r2_out[j] = r2[r]
            index_out[j] = index[r]


# compositing --------------------------------------------------------------------------------------


def exp_constants(dtype):
    """Constants of the compositor in its working precision (scalars read from an array of that
    dtype keep the pixel loop in it): the Taylor terms 1/2! .. 1/7!, the limits log(1/255),
    log(0.99) and -6 of the alpha exponent, then 1/16."""
    return np.array([*EXP_TERMS[2:], LOG_ALPHA_MIN, LOG_ALPHA_MAX, EXP_FLOOR, 1.0 / 16], dtype=dtype)


# The compositor keeps a tile's pixel state in one flat array, one channel of MAX_PIXELS values
# after another, and indexes it with unsigned integers: constant channel offsets and no negative
# index wrap-around are what let the compiler prove the channels apart and vectorise the pixel loop.
# (A channel is MAX_PIXELS values and one cache line more: at a power-of-two stride every channel
# of a pixel would fall in the same cache set.)
MAX_PIXELS = MAX_TILE_SIZE * MAX_TILE_SIZE
STRIDE = MAX_PIXELS + 16
CHANNELS = (
    "trans",
    "r",
    "g",
    "b",
    "z",
    "w",
    "count",
    "peak",
    "layer_depth",
    "layer_keep",
    "layer_t",
    "x_offset",
    "y_offset",
)
R_, G_, B_, Z_, W_, N_, PK, LD, LK, LT, EX, EY = (np.uint64(k * STRIDE) for k in range(1, len(CHANNELS)))
PREFETCH = 8  # entries ahead whose record and box the compositor starts loading
ALIVE_CHECK = 8  # entries between checks for the tile rows whose every pixel has stopped
LANES = 8  # tile rows are padded to a multiple of this many pixels (a vector of
# float32), so an entry's rows are whole vectors


@njit(contract=True)
def composite_tiles(
    tiles,
    offsets,
    entry_splat,
    rec64,
    rec32,
    bbox,
    ts,
    tiles_x,
    width,
    height,
    t_min,
    k,
    color,
    weight,
    depth,
    counts,
    peaks,
    layer_depth,
    layer_keep,
    layer_t,
    gather_image,
    entry_sums,
):
    """Composite every tile in `tiles` front to back and write its pixels into the image arrays
    color (H,W,3), weight (H,W) = sum of T alpha, depth (H,W) = sum of T alpha z; counts (H,W)
    and peaks (entries,) = each entry's largest T alpha are written when they are not empty.
    With a layer (layer_t not empty), a pixel meets it before the first entry whose z is not in
    front of layer_depth: T *= layer_keep (1 - its alpha), and layer_t gets the T it met it with (the
    T a stopped pixel stopped with; what is left for one that never met it).
    With a gather image (H,W,C) (entry_sums not empty), entry_sums (entries, C) gets each entry's
    sum over its pixels of T alpha x the image (float64, outside the pixel loop).
    `k` holds exp_constants in the precision of the per-pixel work. Returns the number of
    splat-pixel pairs evaluated.

    Each entry is evaluated on the whole tile rows that its box crosses, less the rows at the
    tile's top and bottom whose pixels have all stopped. (Cutting the rows to the ellipse within
    the tile's columns saves 12% of the pixels and costs more than that, measured.)
    The exponent is a quadratic in the pixel's offset (ex, ey) from the tile centre, its
    coefficients reduced in float64 per entry and the offsets read from the tile state, so the
    entry's rows are one branch-free loop over contiguous pixels (one loop per row, with the row's
    terms in float64, was 20% slower; the float32 exponent is within a few units in the last place,
    measured). alpha = exp(x) = p(x / 16)^16 with p a Taylor polynomial (x in [-6, 0], relative
    error below 1e-6; Estrin's scheme instead of Horner's was slower)."""
    typ = k.dtype.type
    e2, e3, e4, e5, e6, e7 = k[0], k[1], k[2], k[3], k[4], k[5]
    log_min, log_max, floor, sixteenth = k[6], k[7], k[8], k[9]
    one, zero, tmin = typ(1.0), typ(0.0), typ(t_min)
    row_len = -(-ts // LANES) * LANES  # a tile row, padded
    pixels = ts * row_len
    st = np.zeros(len(CHANNELS) * STRIDE, k.dtype)
    centre = ts / 2.0
    for p in range(pixels):  # each pixel's x and y offsets from the tile centre
        st[np.uint64(p) + EX] = typ(p % row_len + 0.5 - centre)
        st[np.uint64(p) + EY] = typ(p // row_len + 0.5 - centre)
    want_counts = counts.size > 0
    want_peaks = peaks.size > 0
    use_layer = layer_t.size > 0
    want_gather = entry_sums.size > 0
    n_gather = gather_image.shape[2]
    tile_image = np.zeros((pixels, n_gather))  # the tile's gather image, 0 beyond the image edge
    far = typ(np.inf)
    evaluated = 0
    for t in tiles:
        tx0, ty0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        tw, th = min(ts, width - tx0), min(ts, height - ty0)
        for p in range(pixels):
            up = np.uint64(p)
            inside = p % row_len < tw and p // row_len < th
            st[up] = one if inside else zero
            st[up + R_], st[up + G_], st[up + B_], st[up + Z_], st[up + W_], st[up + N_] = 0, 0, 0, 0, 0, 0
        near = far  # the nearest layer depth a pixel still waits for
        if use_layer:
            for p in range(pixels):
                up = np.uint64(p)
                col, row = p % row_len, p // row_len
                inside = col < tw and row < th
                st[up + LD] = typ(layer_depth[ty0 + row, tx0 + col]) if inside else far
                st[up + LK] = typ(layer_keep[ty0 + row, tx0 + col]) if inside else one
                st[up + LT] = -one  # still waiting
                near = min(near, st[up + LD])
        if want_gather:
            for row in range(th):
                for col in range(tw):
                    for ch in range(n_gather):
                        tile_image[row * row_len + col, ch] = gather_image[ty0 + row, tx0 + col, ch]
        cx, cy = tx0 + centre, ty0 + centre
        first, last = offsets[t], offsets[t + 1]
        top, bottom = 0, th - 1  # the rows with pixels still going
        for e in range(first, last):
            if t_min > 0 and (e - first) % ALIVE_CHECK == ALIVE_CHECK - 1:
                while top <= bottom and not _row_alive(st, top, row_len):
                    top += 1
                while bottom >= top and not _row_alive(st, bottom, row_len):
                    bottom -= 1
                if top > bottom:
                    break
            # the record and box of an entry a few ahead start loading: their misses overlap this one's work
            ahead = entry_splat[min(e + PREFETCH, last - 1)]
            prefetch(rec32, ahead * 16)
            prefetch(bbox, ahead * 4)
            s = entry_splat[e]
            row0 = max(bbox[s, 1] - ty0, top)
            row1 = min(bbox[s, 3] - ty0, bottom)
            if row1 < row0:
                continue
            u, v, a, b, c = rec64[s, 0], rec64[s, 1], rec64[s, 2], rec64[s, 3], rec64[s, 4]
            cz = typ(rec32[s, 14])
            if use_layer and cz >= near:  # some pixels meet the layer before this entry
                near = far
                for p in range(pixels):
                    up = np.uint64(p)
                    if st[up + LT] < zero:
                        if cz >= st[up + LD]:
                            st[up + LT] = st[up] if st[up] >= tmin else one - st[up + W_]
                            st[up] *= st[up + LK]
                        else:
                            near = min(near, st[up + LD])
            # power = log o - q / 2, q = (d + e)^T Q (d + e), d = tile centre - mean, e = pixel offset
            dx, dy = cx - u, cy - v
            gx, gy = a * dx + b * dy, b * dx + c * dy
            k0 = rec32[s, 10] - 0.5 * (gx * dx + gy * dy)
            cr, cg, cb = typ(rec32[s, 11]), typ(rec32[s, 12]), typ(rec32[s, 13])
            evaluated += (row1 - row0 + 1) * tw
            # power = k0 + kx ex + ky ey + kxx ex^2 + kxy ex ey + kyy ey^2, over the rows as one run of pixels
            k0f, kx, ky = typ(k0), typ(-gx), typ(-gy)
            kxx, kxy, kyy = typ(-0.5 * a), typ(-b), typ(-0.5 * c)
            for i in range(row0 * row_len, (row1 + 1) * row_len):
                p = np.uint64(i)
                ex, ey = st[p + EX], st[p + EY]
                power = k0f + ex * (kx + kxx * ex) + ey * (ky + kyy * ey + kxy * ex)
                # alpha = exp(power) at most 0.99, as p(x / 16)^16
                x = min(max(power, floor), log_max) * sixteenth
                alpha = one + x * (one + x * (e2 + x * (e3 + x * (e4 + x * (e5 + x * (e6 + x * e7))))))
                alpha *= alpha
                alpha *= alpha
                alpha *= alpha
                alpha *= alpha
                alpha = alpha if power >= log_min else zero
                t_before = st[p]
                t_after = t_before * (one - alpha)
                ok = t_after >= tmin
                w = t_before * alpha if ok else zero
                st[p] = t_after if ok else zero
                st[p + R_] += w * cr
                st[p + G_] += w * cg
                st[p + B_] += w * cb
                st[p + Z_] += w * cz
                st[p + W_] += w
                st[p + N_] += one if w > zero else zero
                st[p + PK] = w
            if want_peaks:
                peak = zero
                for i in range(row0 * row_len, (row1 + 1) * row_len):
                    peak = max(peak, st[np.uint64(i) + PK])
                peaks[e] = peak
            if want_gather:
                _gather_entry(st, tile_image, row0, row1, tw, row_len, entry_sums, e)
        for row in range(th):
            for col in range(tw):
                p = np.uint64(row * row_len + col)
                y, x = ty0 + row, tx0 + col
                color[y, x, 0] = st[p + R_]
                color[y, x, 1] = st[p + G_]
                color[y, x, 2] = st[p + B_]
                weight[y, x] = st[p + W_]
                depth[y, x] = st[p + Z_]
                if want_counts:
                    counts[y, x] = np.int32(st[p + N_])
                if use_layer:
                    met = st[p + LT]
                    layer_t[y, x] = met if met >= zero else (st[p] if st[p] >= tmin else one - st[p + W_])
    return evaluated


@njit
def _gather_entry(st, tile_image, row0, row1, tw, row_len, entry_sums, e):
    """entry_sums[e] = sum over the entry's pixels (rows row0..row1, weights in the peak channel)
    of weight x the tile's gather image."""
    for row in range(row0, row1 + 1):
        for col in range(tw):
            p = row * row_len + col
            w = np.float64(st[np.uint64(p) + PK])
            for ch in range(tile_image.shape[1]):
                entry_sums[e, ch] += w * tile_image[p, ch]


@njit
def _row_alive(st, row, row_len):
    """Whether any pixel of the tile row still goes on (T > 0)."""
    alive = False
    for i in range(row * row_len, (row + 1) * row_len):
        alive |= st[np.uint64(i)] > 0
    return alive


@njit
def finish_rows(color, weight, depth_sum, bg, lo, hi, alpha, depth, layer_t, layer_color, layer_alpha):
    """Rows lo..hi-1 of core.render._finish, with NumPy's float32 roundings: alpha = weight clipped
    to [0, 1]; with a layer (layer_t not empty) colour += layer_t layer_color and alpha = clip(alpha
    + layer_t layer_alpha); colour += (1 - alpha) bg unless bg is empty; depth = depth_sum / weight
    where weight > 0, else 0."""
    use_bg = bg.size == 3
    use_layer = layer_t.size > 0
    zero, one = np.float32(0.0), np.float32(1.0)
    for y in range(lo, hi):
        for x in range(weight.shape[1]):
            w = weight[y, x]
            a = min(max(w, zero), one)
            if use_layer:
                t = layer_t[y, x]
                for ch in range(3):
                    color[y, x, ch] += t * layer_color[y, x, ch]
                a = min(max(a + t * layer_alpha[y, x], zero), one)
            alpha[y, x] = a
            if use_bg:
                for ch in range(3):
                    color[y, x, ch] += (one - a) * bg[ch]
            depth[y, x] = depth_sum[y, x] / w if w > zero else zero


@njit
def sum_per_splat(entry_splat, entry_sums, sums):
    """sums[splat] += the sums of its entries."""
    for e in range(len(entry_splat)):
        s = entry_splat[e]
        for ch in range(entry_sums.shape[1]):
            sums[s, ch] += entry_sums[e, ch]


@njit
def peak_per_splat(entry_splat, peaks, best):
    """best[splat] = the largest peak of its entries."""
    for e in range(len(entry_splat)):
        s = entry_splat[e]
        if peaks[e] > best[s]:
            best[s] = peaks[e]
