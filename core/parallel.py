"""Spreading array work over the cores: NumPy, zlib and zstd release the GIL, so threads pay."""

import os
from concurrent.futures import ThreadPoolExecutor

WORKERS = os.cpu_count() or 1


def map_threads(fn, items, threads=None):
    """[fn(x) for x in items], on up to `threads` threads (default: every core), results in order;
    inline when one thread would do."""
    items = list(items)
    threads = min(len(items), int(threads or WORKERS))
    if threads <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(fn, items))


def in_chunks(n, work, chunk=1 << 13):
    """Call work(start, stop) over [0, n) in chunks of `chunk`, on every core.

    Small chunks keep float64 temporaries in cache; chunks are handed out in order, and work must
    write only its own rows.
    """
    map_threads(lambda span: work(*span), [(a, min(a + chunk, n)) for a in range(0, n, chunk)])
