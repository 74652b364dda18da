"""Space partitions shared by the converters, the file writers and collision: the Morton order of
points, and a uniform grid of cubic cells whose points are sorted by cell.

Morton (Z-order): each point's box-relative coordinates quantised to `bits` bits per axis and
interleaved, bit b of axis a at bit 3 b + a of the code (axis 0 the least significant of each
triple); points sort by code, ties in their given order. Non-finite points get code 0.

Grid: cell (i, j, k) covers origin + h [i, i + 1) x [j, j + 1) x [k, k + 1); a cell's key runs
x-major, then y, then z, so the cells of one (x, y) column are consecutive keys and a run of
points sorted by key. Queries find a cell's points either from a table of every cell's first
sorted position (`cell_start`, for grids with a bounded number of cells) or by binary search of
the sorted keys (`runs`, for grids of any size). `ramp` numbers the places within runs."""

from dataclasses import dataclass

import numpy as np

MORTON_BITS = 21  # the most that three axes interleave into 64 bits
# The 27 cells around a cell, itself included: (dx, dy, dz), dx slowest.
NEIGHBOURS = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)]


def morton_order(points, bits=MORTON_BITS):
    """Indices sorting points (N,3) along a 3D Morton curve over their finite points' bounding box,
    `bits` bits per axis (at most 21)."""
    if not 1 <= bits <= MORTON_BITS:
        raise ValueError(f"bits must be 1 to {MORTON_BITS}, got {bits}")
    p = np.asarray(points, np.float64)
    finite = np.isfinite(p).all(axis=1)
    if not finite.any():
        return np.arange(len(p))
    top = 2**bits - 1
    lo, hi = p[finite].min(axis=0), p[finite].max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    q = np.where(finite[:, None], (p - lo) / span, 0.0)
    q = np.clip(q * top, 0, top).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | (_spread_bits(q[:, 2]) << np.uint64(2))
    return np.argsort(code, kind="stable")


def _spread_bits(x):
    """Insert two zero bits between each of the low 21 bits (the classic magic-number sequence)."""
    x = x & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


@dataclass
class Grid:
    """A uniform grid: cells `h` wide from `origin` (3,), `dims` (3,) cells a side."""

    origin: np.ndarray
    h: float
    dims: np.ndarray

    def cells(self, points):
        """The integer cells (N,3) holding points (N,3), unclipped."""
        return np.floor((points - self.origin) / self.h).astype(np.int64)

    def keys(self, cells):
        """The keys of integer cells (N,3) inside the grid."""
        return (cells[:, 0] * self.dims[1] + cells[:, 1]) * self.dims[2] + cells[:, 2]

    def step(self, dx, dy, dz):
        """What a key gains from a cell to the cell (dx, dy, dz) away."""
        return (dx * self.dims[1] + dy) * self.dims[2] + dz

    @property
    def size(self):
        """The number of cells."""
        return int(np.prod(self.dims))


def sort_by_cell(keys):
    """(order, sorted keys): the stable order sorting points by their cells' keys."""
    order = np.argsort(keys, kind="stable")
    return order, keys[order]


def cell_start(keys, size):
    """(size + 1,) int64: the first position of each of `size` cells among points sorted by their
    keys (and, last, the number of points); cell c holds sorted points cell_start[c]:cell_start[c+1]."""
    start = np.zeros(size + 1, np.int64)
    np.cumsum(np.bincount(keys, minlength=size), out=start[1:])
    return start


def ramp(counts):
    """0, 1, ..., c-1 for each count c, concatenated (int64): the places within runs of those lengths,
    as the rasterisers walk a splat's tiles or a face's pixels along a row."""
    counts = np.asarray(counts, np.int64)
    return np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)


def runs(sorted_keys, keys):
    """(lo, hi): where each of `keys` runs among `sorted_keys` (empty where no point has it)."""
    return np.searchsorted(sorted_keys, keys, "left"), np.searchsorted(sorted_keys, keys, "right")
