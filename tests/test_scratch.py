"""core.scratch: working arrays on kept memory, handed out again only when nothing holds them; and
core.memory's switch of NumPy's huge-page advice, the other cost of fresh memory."""

import threading

import numpy as np
import pytest

from splatwright.core import memory, scratch
from splatwright.core.camera import Camera
from splatwright.core.render import render
from splatwright.core.splats import SplatCloud

MB = 1 << 20


@pytest.fixture(autouse=True)
def _own_buffers(monkeypatch):
    """Each test starts from no kept buffers (and leaves none behind)."""
    monkeypatch.setattr(scratch, "_buffers", [])
    yield


def _address(a):
    return a.__array_interface__["data"][0]


def test_a_dropped_array_serves_the_next_request_of_its_size_class():
    first = scratch.empty((3 * MB,), np.float32)
    where = _address(first)
    del first
    # a little smaller, another dtype and shape: the same size class, the same memory
    again = scratch.empty((1600, 1000), np.float64)  # 12.8e6 bytes against 12.6e6: both under 13 MiB
    assert _address(again) == where
    assert scratch.kept_bytes()[0] >= again.nbytes


def test_a_held_array_is_never_handed_out_and_keeps_its_values():
    held = scratch.empty(2 * MB, np.uint8)
    held[:] = 7
    view = held[10:20]  # a view holds the buffer as well
    del held
    other = scratch.empty(2 * MB, np.uint8)
    other[:] = 9
    assert np.all(view == 7)
    assert not np.shares_memory(view, other)


def test_zeros_are_zero_on_reused_memory():
    dirty = scratch.empty(MB, np.float64)
    dirty[:] = np.nan
    del dirty
    clean = scratch.zeros(MB, np.float64)
    assert np.count_nonzero(clean) == 0


def test_small_requests_and_alignment():
    small = scratch.empty(1000, np.float64)  # under MIN_BYTES: a plain allocation, not kept
    assert scratch.kept_bytes() == (0, 0) and small.shape == (1000,)
    for n in (MB + 8, 3 * MB + 24):
        assert _address(scratch.empty(n, np.uint8)) % 64 == 0


def test_at_most_the_limit_is_kept_least_recently_used_free_buffers_dropped_first(monkeypatch):
    monkeypatch.setattr(scratch, "KEPT_LIMIT", 10 * MB)
    arrays = [scratch.empty(3 * MB, np.uint8) for _ in range(3)]  # 9+ MiB kept, all in use
    over = scratch.empty(3 * MB, np.uint8)  # no room: a plain array, not kept
    busy, free = scratch.kept_bytes()
    assert busy == sum(a.base.nbytes for a in arrays) <= 10 * MB and free == 0
    assert not any(np.shares_memory(over, a) for a in arrays)
    oldest, newest = id(arrays[0].base), id(arrays[2].base)
    del arrays, over
    assert scratch.kept_bytes() == (0, sum(b.nbytes for b in scratch._buffers))  # all free, none new
    big = scratch.empty(5 * MB, np.uint8)  # room made: the least recently used free ones go
    kept = {id(b) for b in scratch._buffers}
    assert sum(b.nbytes for b in scratch._buffers) <= 10 * MB and id(big.base) in kept
    assert oldest not in kept and newest in kept
    scratch.release()
    assert scratch.kept_bytes() == (big.base.nbytes, 0)


def test_threads_never_share_a_buffer():
    errors = []

    def work(tag):
        for _ in range(200):
            a = scratch.empty(MB // 8 + 1, np.float64)  # just over MIN_BYTES
            a.fill(tag)
            if not np.all(a == tag):
                errors.append(tag)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert scratch.kept_bytes()[0] == 0  # every one given back


def test_a_kept_render_result_survives_the_next_render():
    """The render's images come from kept memory: a result the caller holds must not be written by
    the next render (a shared buffer would show the second picture in the first)."""
    rng = np.random.default_rng(3)
    n = 4000

    def cloud(shift):
        sh = np.zeros((n, 1, 3), np.float32)
        sh[:, 0] = rng.uniform(-1, 1, (n, 3))
        return SplatCloud(rng.normal(0, 0.4, (n, 3)) + [shift, 0, 4], np.tile([1, 0, 0, 0], (n, 1)),
                          np.full((n, 3), -3.5), np.full(n, 2.0), sh)  # fmt: skip

    camera = Camera.look_at((0, 0, 0), (0, 0, 4), up=(0, -1, 0), fov_deg=50, width=900, height=700)
    first = render(cloud(0.0), camera)
    copy = (first.color.copy(), first.alpha.copy(), first.depth.copy())
    second = render(cloud(0.3), camera)
    assert not np.array_equal(second.color, copy[0])
    assert np.array_equal(first.color, copy[0]) and np.array_equal(first.alpha, copy[1])
    assert np.array_equal(first.depth, copy[2], equal_nan=True)
    del first, second
    third = render(cloud(0.0), camera)  # on the buffers the first two gave back
    assert scratch.kept_bytes()[1] > 0
    np.testing.assert_array_equal(third.color.shape, copy[0].shape)


def test_numpy_huge_pages_switches_numpys_setting_and_tells_the_previous_one():
    """(What the advice costs is a benchmark's business: bench/relight.py, docs/DESIGN.md.)"""
    before = memory.numpy_huge_pages(False)
    assert before is not None  # this NumPy can be told
    try:
        assert memory.numpy_huge_pages(True) is False and memory.numpy_huge_pages(False) is True
    finally:
        memory.numpy_huge_pages(before)
