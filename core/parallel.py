"""Spreading array work over the cores: NumPy releases the GIL inside its loops, so threads pay."""

import os
from concurrent.futures import ThreadPoolExecutor

WORKERS = os.cpu_count() or 1


def in_chunks(n, work, chunk=1 << 13):
    """Call work(start, stop) over [0, n) in chunks of `chunk`, on every core.

    Small chunks keep float64 temporaries in cache; chunks are handed out in order, and work must
    write only its own rows.
    """
    spans = [(a, min(a + chunk, n)) for a in range(0, n, chunk)]
    workers = min(len(spans), WORKERS)
    if workers <= 1:
        for span in spans:
            work(*span)
        return
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda span: work(*span), spans))
