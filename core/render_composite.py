"""The NumPy path's compositing (core/render.py's reference and fallback): every tile's entries
front to back, in waves of at most `wave` entries per tile, each wave a dense (entries, tiles,
pixels) block (see core/render.py's notes); and where each pixel crosses a Layer."""

import math
import threading

import numpy as np

from .render_constants import ALPHA_MAX, ALPHA_MIN
from .render_tiles import record_floats, stable_argsort

# OpenBLAS runs larger products on its own threads, which fights our pool and is slower for these
# thin products; it stays single-threaded below m*n*k = 65536 * 4 (its SMP threshold).
_BLAS_SINGLE_THREAD_MNK = 65536 * 4
_BATCH_EVALS = 1 << 18  # splat-pixel evaluations per batch (measured sweet spot)


class Compositor:
    """Front-to-back compositing of every tile, in waves of at most `wave` entries per tile."""

    def __init__(
        self,
        proj,
        bins,
        camera,
        dtype,
        wave,
        t_min,
        pool,
        want_counts=False,
        want_weights=False,
        crossing=None,
        gather=None,
    ):
        self.proj, self.bins, self.dtype, self.wave, self.pool = proj, bins, dtype, wave, pool
        self.crossing = crossing
        self.width, self.height = camera.width, camera.height
        self.t_min = dtype(t_min)
        ts = bins.tile_size
        self.pixels = ts * ts
        e = np.arange(ts) + 0.5 - ts / 2  # pixel-centre offsets from the tile centre
        ey, ex = np.repeat(e, ts), np.tile(e, ts)  # row-major pixels within a tile
        self.basis = np.stack([np.ones_like(ex), ex, ey, ex * ex, ex * ey, ey * ey]).astype(dtype)
        n_tiles = bins.n_tiles
        self.acc = np.zeros((n_tiles, self.pixels, 5), dtype=dtype)  # sum w * (r, g, b, z, 1)
        self.trans = self._inside_image(bins, camera).astype(dtype)  # T, or 0 once a pixel stopped
        self.counts = np.zeros((n_tiles, self.pixels), dtype=np.int32) if want_counts else None
        self.order, self.records, self.entry_splat = self._by_locality(proj, bins)
        # largest weight of each (renumbered) splat; the last slot takes the padding entries
        self.best = np.zeros(len(proj) + 1, np.float32) if want_weights else None
        self.best_lock = threading.Lock()
        # the gather image in tile layout, and each (renumbered) splat's sum of weight x image
        self.gather_tiles = None if gather is None else tiled(gather, bins, 0.0).astype(dtype)
        self.sums = None if gather is None else np.zeros((len(proj) + 1, gather.shape[2]))
        self.evaluated = 0

    @staticmethod
    def _inside_image(bins, camera):
        """(tiles, pixels) bool: which pixels of the edge tiles lie inside the image. Those beyond
        start with T = 0, so they take no weight and never keep a tile alive."""
        ts, k = bins.tile_size, np.arange(bins.tile_size**2)
        tiles = np.arange(bins.n_tiles)[:, None]
        return ((tiles % bins.tiles_x) * ts + k % ts < camera.width) & (
            (tiles // bins.tiles_x) * ts + k // ts < camera.height
        )

    @staticmethod
    def _by_locality(proj, bins):
        """Records renumbered by the tile of their box's top-left corner, so that the entries of
        neighbouring tiles read neighbouring records (cache hits) instead of depth-scattered ones.
        Returns the order (new number -> old), the records and the entries renumbered."""
        n = len(proj)
        first_tile = (proj.bbox[:, 1] // bins.tile_size) * bins.tiles_x + proj.bbox[:, 0] // bins.tile_size
        order = stable_argsort(first_tile, bins.n_tiles)
        renumber = np.empty(n + 1, dtype=np.int32)
        renumber[order] = np.arange(n, dtype=np.int32)
        renumber[n] = n
        records = proj.records.take(np.append(order, n), axis=0)
        return order, records, renumber.take(bins.entry_splat)

    def max_weight(self, n_cloud):
        """(n_cloud,) float32: the largest weight of every input splat, 0 for those not projected."""
        out = np.zeros(n_cloud, np.float32)
        out[self.proj.index[self.order]] = self.best[:-1]
        return out

    def gathered(self, n_cloud):
        """(n_cloud, C) float64: the gather image's weighted sum of every input splat."""
        out = np.zeros((n_cloud, self.sums.shape[1]))
        out[self.proj.index[self.order]] = self.sums[:-1]
        return out

    def images(self, progress=None):
        """Composite every tile; returns (colour sums (H,W,3), weights, depth sums, counts or None)
        in image layout."""
        acc, counts = self.run(progress)
        acc = self._image(acc)  # (H, W, 5): the one copy out of tile order
        return acc[..., :3], acc[..., 4], acc[..., 3], None if counts is None else self._image(counts).copy()

    def _image(self, a):
        """(tiles, pixels, ...) -> (H, W, ...)."""
        bins, ts = self.bins, self.bins.tile_size
        a = a.reshape(bins.tiles_y, bins.tiles_x, ts, ts, *a.shape[2:]).swapaxes(1, 2)
        return a.reshape(bins.tiles_y * ts, bins.tiles_x * ts, *a.shape[4:])[: self.height, : self.width]

    def layer_transmittance(self, weight):
        """(H, W) T where each pixel reached the layer (see LayerCrossing.transmittance)."""
        return self.crossing.transmittance(
            self._image(self.crossing.t), self._image(self.crossing.pending), np.clip(weight, 0.0, 1.0)
        )

    def run(self, progress=None):
        bins = self.bins
        total = np.diff(bins.offsets)
        cursor = self._cursor = np.zeros(bins.n_tiles, dtype=np.int64)
        alive = np.flatnonzero(total > 0)
        done_tiles = bins.n_tiles - len(alive)
        while len(alive):
            take = np.minimum(total[alive] - cursor[alive], self.wave)
            batches = self._batches(alive, take)
            self.evaluated += sum(len(t) * d for t, _, d in batches) * self.pixels
            finished = self.pool.map(lambda b: self._composite(*b), batches)
            cursor[alive] += take
            stopped = np.zeros(bins.n_tiles, bool)
            for tiles, flags in finished:
                stopped[tiles] = flags
            still = (cursor[alive] < total[alive]) & ~stopped[alive]
            done_tiles += int((~still).sum())
            alive = alive[still]
            if progress is not None:
                progress(done_tiles, bins.n_tiles, "render")
        return self.acc, self.counts

    def _batches(self, alive, take):
        """Split the alive tiles into batches of similar entry counts, ~_BATCH_EVALS evaluations each."""
        order = np.argsort(-take, kind="stable")
        tiles, take = alive[order], take[order]
        out, i = [], 0
        while i < len(tiles):
            depth = int(take[i])
            g = max(1, _BATCH_EVALS // (depth * self.pixels))
            out.append((tiles[i : i + g], take[i : i + g], depth))
            i += g
        return out

    def _composite(self, tiles, take, depth):
        """Composite the next `take` entries of each tile (padded to `depth`); returns the tiles
        and whether each has stopped at every pixel."""
        bins, dtype = self.bins, self.dtype
        g, p = len(tiles), self.pixels
        slot = np.arange(depth)[:, None]
        pos = (bins.offsets[tiles] + self._cursor[tiles])[None, :] + slot
        splat = np.where(
            slot < take[None, :], self.entry_splat.take(pos, mode="clip"), len(self.proj)
        ).ravel()  # (depth * g), padding -> no-op row
        rec = self.records.take(splat, axis=0)  # one cache line per entry
        log_o = record_floats(rec)[:, 0]
        power = self._exponent(rec, tiles)  # (depth * g, p) log alpha
        bright = np.flatnonzero(log_o > math.log(ALPHA_MAX))
        if len(bright):  # clamp alpha at 0.99
            power[bright] = np.minimum(power[bright], dtype(math.log(ALPHA_MAX)))
        visible = power >= dtype(math.log(ALPHA_MIN))  # (multiplying by a mask beats masked stores)
        alpha = np.exp(power, out=power)
        alpha *= visible
        alpha = alpha.reshape(depth, g, p)

        trans = np.empty((depth + 1, g, p), dtype=dtype)  # T before each entry
        trans[0] = self.trans[tiles]
        keep = np.subtract(1, alpha, dtype=dtype)
        first = None if self.crossing is None else self.crossing.enter(tiles, record_floats(rec)[:, 4], alpha, keep)
        for k in range(depth):
            np.multiply(trans[k], keep[k], out=trans[k + 1])
        if first is not None:
            self.crossing.record(tiles, first, trans, self.t_min)
        weight = np.multiply(trans[:-1], alpha, out=keep)  # w = T alpha
        crossed = trans[-1] < self.t_min
        if (crossed & (trans[0] >= self.t_min)).any():  # a pixel stops in this wave
            weight *= trans[1:] >= self.t_min
        feat = record_floats(rec)[:, 1:].astype(dtype, copy=False).reshape(depth, g, 5)
        self.acc[tiles] += np.matmul(weight.transpose(1, 2, 0), feat.transpose(1, 0, 2))
        if self.counts is not None:
            self.counts[tiles] += np.count_nonzero(weight, axis=0).astype(np.int32)
        if self.best is not None:
            self._keep_best(splat, weight)
        if self.sums is not None:
            self._gather(tiles, splat, weight)
        last = trans[-1]
        last *= ~crossed
        self.trans[tiles] = last
        return tiles, ~last.any(axis=1)

    def _keep_best(self, splat, weight):
        """Fold each entry's largest weight over its pixels into the per-splat maximum."""
        rows = weight.reshape(len(splat), -1)  # slot-major, like `splat`
        peak = rows[np.arange(len(rows)), rows.argmax(axis=1)]  # (argmax is ~3x faster than max)
        hit = np.flatnonzero(peak)
        with self.best_lock:  # batches run in parallel threads
            np.maximum.at(self.best, splat[hit], peak[hit].astype(np.float32))

    def _gather(self, tiles, splat, weight):
        """Add each entry's sum over its tile's pixels of weight x gather image to its splat."""
        per_entry = np.matmul(weight.transpose(1, 0, 2), self.gather_tiles[tiles])  # (g, depth, C)
        per_entry = per_entry.transpose(1, 0, 2).reshape(len(splat), -1)  # slot-major, like splat
        with self.best_lock:
            np.add.at(self.sums, splat, per_entry.astype(np.float64))

    def _exponent(self, rec, tiles):
        """log(o) - q/2 at every pixel of every entry (records `rec`, slot-major over `tiles`).
        q is a quadratic in the pixel's offset e from the tile centre, q = q0 + 2 g.e + e^T Q e,
        expanded in float64 around the tile centre (so large pixel coordinates never meet in
        float32) and evaluated as coefficients @ basis."""
        ts, g = self.bins.tile_size, len(tiles)
        u, v, a, b, c = rec[:, :5].T
        reps = len(rec) // g
        dx = np.tile((tiles % self.bins.tiles_x) * ts + ts / 2, reps) - u
        dy = np.tile((tiles // self.bins.tiles_x) * ts + ts / 2, reps) - v
        gx, gy = a * dx + b * dy, b * dx + c * dy
        coef = np.empty((len(rec), 6), dtype=self.dtype)
        coef[:, 0] = record_floats(rec)[:, 0] - 0.5 * (gx * dx + gy * dy)
        coef[:, 1], coef[:, 2] = -gx, -gy
        coef[:, 3], coef[:, 4], coef[:, 5] = -0.5 * a, -b, -0.5 * c
        out = np.empty((len(rec), self.pixels), dtype=self.dtype)
        step = max(1, _BLAS_SINGLE_THREAD_MNK // (6 * self.pixels) - 1)
        for i in range(0, len(rec), step):
            np.matmul(coef[i : i + step], self.basis, out=out[i : i + step])
        return out


def tiled(a, bins, fill):
    """(H, W, ...) image -> (tiles, pixels, ...), pixels beyond the image edge set to `fill`."""
    ts, rest = bins.tile_size, a.shape[2:]
    padded = np.full((bins.tiles_y * ts, bins.tiles_x * ts, *rest), fill, dtype=np.float64)
    padded[: a.shape[0], : a.shape[1]] = a
    return (
        padded.reshape(bins.tiles_y, ts, bins.tiles_x, ts, *rest).swapaxes(1, 2).reshape(bins.n_tiles, ts * ts, *rest)
    )


class LayerCrossing:
    """Where each pixel meets the Layer, in tile layout (tiles, pixels): the layer's depth and
    1 - alpha, whether the pixel still waits for it, and the T it was reached with."""

    def __init__(self, layer, bins, dtype):
        self.layer = layer
        self.depth = tiled(layer.depth, bins, np.inf).astype(dtype)
        self.keep = tiled(1.0 - layer.alpha, bins, 1.0).astype(dtype)
        self.pending = np.ones(self.depth.shape, bool)
        self.t = np.zeros(self.depth.shape, dtype)
        # the nearest layer depth of each tile: a wave whose splats all lie in front skips the test
        self.nearest = self.depth.min(axis=1)

    def enter(self, tiles, z, alpha, keep):
        """Put the layer into a wave: `z` (depth * g,) are the entries' camera depths, slot-major;
        alpha and keep (depth, g, p) are scaled by the layer's 1 - alpha at the entry where each
        waiting pixel crosses it: the first entry not in front of it (entries are sorted by z; the
        padding, z = 0, counts as behind everything). Returns where that happens for record(), or
        None if no pixel crosses in this wave. Only tiles and entries that can cross are looked at."""
        depth, g = alpha.shape[:2]
        z = z.reshape(depth, g)
        z = np.where(z > 0, z, np.inf)
        nearest = self.nearest[tiles]  # inf: no surface left to cross (finish() adds the rest)
        reach = (z >= nearest) & np.isfinite(nearest)  # (depth, g): at or past the tile's nearest waiting pixel
        cross = np.flatnonzero(reach.any(axis=0))
        if not len(cross):
            return None
        k0 = int(reach[:, cross].any(axis=1).argmax())  # every entry before k0 is in front of every waiting pixel
        sel = tiles[cross]
        slot = k0 + (z[k0:, cross, None] < self.depth[sel][None]).sum(axis=0, dtype=np.int32)
        hit_g, hit_p = np.nonzero(self.pending[sel] & (slot < depth))
        if not len(hit_g):
            return None
        at_slot, at_tile = slot[hit_g, hit_p], cross[hit_g]
        factor = self.keep[sel[hit_g], hit_p]
        alpha[at_slot, at_tile, hit_p] *= factor
        keep[at_slot, at_tile, hit_p] *= factor
        return at_slot, at_tile, hit_p, sel[hit_g]

    def record(self, tiles, crossing, trans, t_min):
        """Keep T where each pixel reached the layer. A pixel that had already stopped (T below
        t_min) keeps waiting: it gives the layer the T it stopped with (see transmittance)."""
        at_slot, at_tile, pixel, tile = crossing
        t = trans[at_slot, at_tile, pixel]
        ok = t >= t_min
        self.t[tile[ok], pixel[ok]] = t[ok]
        self.pending[tile[ok], pixel[ok]] = False
        changed = np.unique(tile[ok])
        self.nearest[changed] = np.where(self.pending[changed], self.depth[changed], np.inf).min(axis=1)

    @staticmethod
    def transmittance(t, pending, splat_alpha):
        """(H, W) T at the layer: where the pixel never crossed it (no splat behind, or stopped
        first), what the splats left."""
        return np.where(pending, 1.0 - splat_alpha, t).astype(np.float32)
