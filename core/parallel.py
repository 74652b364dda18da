"""Spreading array work over the cores: NumPy, zlib, zstd and the compiled kernels release the GIL,
so threads pay.

One pool of WORKERS threads serves the whole process. Starting and joining threads for every call
cost 2-4 ms (a lit frame made eight such calls), as much as a kernel pass over 400k splats; the
shared threads cost nothing between calls. A map hands its items out one at a time to at most
`threads` takers: the calling thread itself and helpers from the pool, so a map whose helpers wait
behind another caller's work still runs, in the caller, and a map's `threads` bounds its cores
whatever the pool's size. Inside a map (on a pool thread, or in a caller running items), a nested
map runs inline: the outer map already holds the cores, and a pool thread waiting for work queued
behind it could wait for ever. An error or interrupt (Ctrl-C, a cancel raised by a progress
callback) in any item stops the handing out; the map waits for the items already running and
raises it.
"""

import os
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor

WORKERS = os.cpu_count() or 1

_local = threading.local()  # .inside: this thread is running a map's items
_lock = threading.Lock()
_executor: ThreadPoolExecutor | None = None


def map_threads(fn, items, threads=None):
    """[fn(x) for x in items], on up to `threads` threads (default: every core), results in order;
    inline when one thread would do, or inside another map."""
    return Pool(threads).map(fn, items)


def in_chunks(n, work, chunk=1 << 13):
    """Call work(start, stop) over [0, n) in chunks of `chunk`, on every core.

    Small chunks keep float64 temporaries in cache; chunks are handed out in order, and work must
    write only its own rows.
    """
    map_threads(lambda span: work(*span), [(a, min(a + chunk, n)) for a in range(0, n, chunk)])


class Pool:
    """Up to `threads` threads (default: all cores) of the shared pool; with one thread, or inside
    another map, map() and imap() run inline. As a context manager, leaving it stops what its
    imap() calls left unread (a caller that stopped reading on a cancel) and waits for their
    running items."""

    def __init__(self, threads=None):
        self.threads = max(1, int(threads or WORKERS))
        self._streams: list = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for stream in self._streams:
            stream.close()
        self._streams.clear()

    def map(self, fn, items):
        return list(self._stream(fn, items))

    def imap(self, fn, items):
        """fn over items, results yielded in order in the calling thread as they come (it runs
        items itself while the next result is not ready)."""
        stream = self._stream(fn, items)
        self._streams.append(stream)
        return stream

    def _stream(self, fn, items):
        items = list(items)
        takers = min(self.threads, len(items))
        if takers <= 1 or getattr(_local, "inside", False):
            return (fn(item) for item in items)
        return _Run(fn, items).results(takers - 1)


class _Run:
    """One map's items, handed out one at a time under a lock to whichever taker asks next."""

    def __init__(self, fn: Callable, items: list):
        self.fn, self.items = fn, items
        self.values: list = [None] * len(items)
        self.ready = [False] * len(items)
        self.taken = 0
        self.error: BaseException | None = None
        self.changed = threading.Condition()

    def take(self) -> int | None:
        """The next item's index, or None when all are handed out or an item failed."""
        with self.changed:
            if self.error is not None or self.taken >= len(self.items):
                return None
            self.taken += 1
            return self.taken - 1

    def run(self, index: int) -> None:
        was_inside = getattr(_local, "inside", False)
        _local.inside = True
        try:
            value = self.fn(self.items[index])
        except BaseException as exc:  # a cancel or Ctrl-C too: the caller re-raises it
            with self.changed:
                self.error = self.error or exc
                self.changed.notify_all()
            return
        finally:
            _local.inside = was_inside
        with self.changed:
            self.values[index], self.ready[index] = value, True
            self.changed.notify_all()

    def drain(self) -> None:
        """A helper's work: take and run items until none are left."""
        while (index := self.take()) is not None:
            self.run(index)

    def results(self, helpers: int) -> Iterator:
        """The values in order, the caller running items while the next one is not ready."""
        futures = [_shared().submit(self.drain) for _ in range(helpers)]
        try:
            for index in range(len(self.items)):
                yield self._value(index)
        finally:
            self._stop(futures)

    def _value(self, index: int):
        while True:
            with self.changed:
                if self.error is not None:
                    raise self.error
                if self.ready[index]:
                    value, self.values[index] = self.values[index], None
                    return value
                if self.taken >= len(self.items):  # all handed out: wait for the one running it
                    self.changed.wait()
                    continue
            mine = self.take()
            if mine is not None:
                self.run(mine)

    def _stop(self, futures: Iterable[Future]) -> None:
        """Hand out nothing more and wait for the items already running (a helper not started yet
        is cancelled: it may sit behind another caller's work)."""
        with self.changed:
            self.taken = len(self.items)
        for future in futures:
            if not future.cancel():
                future.result()


def _shared() -> ThreadPoolExecutor:
    global _executor
    with _lock:
        if _executor is None:
            _executor = ThreadPoolExecutor(WORKERS, thread_name_prefix="splatwright")
        return _executor


def _forget_pool() -> None:
    """In a forked child the pool's threads do not exist: make a new pool when one is needed."""
    global _executor, _lock
    _executor, _lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
