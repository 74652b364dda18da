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


class Pool:
    """A thread pool of `threads` workers (default: all cores) as a context manager; with one
    thread, map() runs inline."""

    def __init__(self, threads=None):
        self.threads = max(1, int(threads or os.cpu_count() or 1))
        self.executor = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.executor is not None:
            self.executor.shutdown()

    def map(self, fn, items):
        return list(self.imap(fn, items))

    def imap(self, fn, items):
        """fn over items, results yielded in order in the calling thread as they come."""
        if self.executor is None or len(items) < 2:
            return (fn(item) for item in items)
        return self.executor.map(fn, items)
