"""core.parallel: the shared pool's maps keep order, bound their threads, never deadlock when
nested or called from several threads at once, and stop handing out work on an error."""

import multiprocessing
import sys
import threading
import time

import pytest

from splatwright.core import parallel
from splatwright.core.parallel import Pool, in_chunks, map_threads


def finishes(fn, timeout=30.0):
    """fn's result, run on a thread of its own: a deadlock fails the test instead of hanging it."""
    out = {}
    thread = threading.Thread(target=lambda: out.setdefault("value", fn()), daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), "the map did not finish: deadlock"
    return out["value"]


def test_results_come_in_order_as_a_serial_loop_gives_them():
    items = list(range(200))
    assert map_threads(lambda x: x * x - 3, items, threads=2) == [x * x - 3 for x in items]
    assert map_threads(lambda x: x, []) == []


def test_in_chunks_covers_every_row_once():
    n = 100_003
    seen = bytearray(n)

    def work(lo, hi):
        for i in range(lo, hi):
            seen[i] += 1

    in_chunks(n, work, chunk=4096)
    assert bytes(seen) == b"\x01" * n


def test_nested_maps_finish_and_run_inline():
    """Every pool thread busy with an outer item that maps again: the inner maps run in place."""

    def outer(x):
        inner_threads = set(map_threads(lambda y: threading.get_ident(), range(8)))
        return x, inner_threads == {threading.get_ident()}

    results = finishes(lambda: map_threads(outer, range(4 * parallel.WORKERS + 1)))
    assert [x for x, _ in results] == list(range(4 * parallel.WORKERS + 1))
    assert all(inline for _, inline in results)


def test_threads_bounds_how_many_items_run_at_once():
    running, most = 0, 0
    lock = threading.Lock()

    def item(_):
        nonlocal running, most
        with lock:
            running += 1
            most = max(most, running)
        time.sleep(0.002)
        with lock:
            running -= 1

    map_threads(item, range(40), threads=2)
    assert 1 <= most <= 2
    caller = threading.get_ident()
    assert set(map_threads(lambda _: threading.get_ident(), range(10), threads=1)) == {caller}


def test_two_callers_at_once_both_finish():
    """A viewport thread and a render thread sharing the pool: neither waits on the other's work."""
    results = {}

    def call(name, offset):
        results[name] = map_threads(lambda x: (time.sleep(0.001), x + offset)[1], range(60))

    threads = [threading.Thread(target=call, args=(name, k * 1000)) for k, name in enumerate(("a", "b"))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert results == {"a": list(range(60)), "b": [x + 1000 for x in range(60)]}


@pytest.mark.parametrize("error", [ValueError("bad item"), KeyboardInterrupt()])
def test_an_error_stops_the_handing_out_and_is_raised(error):
    started = []

    def item(x):
        started.append(x)
        if x == 3:
            raise error
        time.sleep(0.002)
        return x

    with pytest.raises(type(error)):
        map_threads(item, range(100), threads=2)
    count = len(started)
    assert 4 <= count <= 6  # items 0-3 and at most what the other taker had started
    time.sleep(0.05)
    assert len(started) == count  # nothing runs on after the map returned


def test_leaving_a_pool_stops_its_unread_stream():
    """A render that stops reading its tiles on a cancel: leaving the Pool stops the rest."""
    started = []

    def item(x):
        started.append(x)
        time.sleep(0.002)
        return x

    with Pool(2) as pool:
        stream = pool.imap(item, range(200))
        assert [next(stream), next(stream)] == [0, 1]
    count = len(started)
    assert count < 200
    time.sleep(0.05)
    assert len(started) == count


@pytest.mark.skipif(
    sys.platform == "win32" or "fork" not in multiprocessing.get_all_start_methods(), reason="no fork here"
)
def test_a_forked_child_makes_its_own_pool():
    map_threads(lambda x: x, range(8))  # the parent's pool has threads now
    context = multiprocessing.get_context("fork")
    with context.Pool(1) as children:
        assert finishes(lambda: children.apply(_squares_in_child), timeout=60) == [x * x for x in range(50)]


def _squares_in_child():
    return map_threads(lambda x: x * x, range(50))
