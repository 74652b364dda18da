"""Large working arrays on memory this process has written before.

Memory fresh from the system costs a page fault per page, in which the system zeroes it: a lit
1920x1080 frame of 410k splats took a fifth of its CPU time there (its shadow maps, shading and
picture each taking tens of MB and giving them back), where C's allocator, keeping freed blocks
for the next request, serves a loop of one kind of work from warm memory but returns the large
ones to the system between the kinds. empty() and zeros() hand out views of kept buffers instead.

A buffer is free again when nothing else holds it: every array made from it (a view, a result
that kept it) holds a reference to it, so the references decide, and an array handed out can be
kept, returned or dropped like any other. Requests round up to a size class (an eighth of a
power of two) so that work whose sizes change a little from call to call (a moving camera's
visible splats) still meets its buffers. At most KEPT_LIMIT bytes are kept, the least recently used
free buffers given back first to make room; release() gives all the free ones back (a job done).
"""

import sys
import threading

import numpy as np

MIN_BYTES = 1 << 20  # smaller requests come from the allocator, which keeps such blocks itself
# Bytes of buffers kept at most, in use or free: what one frame or job leaves behind is bounded by
# it even when nothing asks for memory again. A lit 1920x1080 frame of 410k splats takes about 280
# MB of them; a 500k-splat conversion ran 5% slower with 1 GiB kept idle (memory its other work
# would have reused) and as fast as without at this limit. Beyond it requests get plain arrays.
KEPT_LIMIT = 384 << 20
_ALIGN = 64  # a cache line: kernels that lay records on cache lines rely on it

_lock = threading.Lock()
_buffers: list[np.ndarray] = []  # uint8 buffers, the most recently handed out last


def _count_alone() -> int:
    """What sys.getrefcount says, in _free's own words, of an array that only a list holds: 2 on the
    CPythons of today (the list and the call's argument), but an interpreter that lends the
    argument would say 1, and comparing with a fixed 2 would then hand out arrays in use."""
    probe = [np.empty(1, np.uint8)]
    return [sys.getrefcount(probe[i]) for i in range(1)][0]


_ALONE = _count_alone()


def empty(shape, dtype=np.float64) -> np.ndarray:
    """np.empty(shape, dtype), on kept memory when the request is large enough to be worth it."""
    dtype = np.dtype(dtype)
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(s) for s in shape)
    need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if need < MIN_BYTES:
        return np.empty(shape, dtype)
    buffer = _take(_size_class(need))
    start = -buffer.ctypes.data % _ALIGN
    return buffer[start : start + need].view(dtype).reshape(shape)


def zeros(shape, dtype=np.float64) -> np.ndarray:
    """np.zeros(shape, dtype), on kept memory when large enough (zeroing warm memory costs a tenth
    of faulting in fresh pages)."""
    out = empty(shape, dtype)
    out.fill(0)
    return out


def release() -> None:
    """Give every free buffer back to the system."""
    with _lock:
        _buffers[:] = [b for b, free in zip(_buffers, _free()) if not free]


def kept_bytes() -> tuple[int, int]:
    """(bytes in use, bytes free) of the kept buffers."""
    with _lock:
        free = _free()
        return (
            sum(b.nbytes for b, f in zip(_buffers, free) if not f),
            sum(b.nbytes for b, f in zip(_buffers, free) if f),
        )


def _free() -> list[bool]:
    """Whether each kept buffer is free: held by the list alone (_ALONE)."""
    return [sys.getrefcount(_buffers[i]) == _ALONE for i in range(len(_buffers))]


def _size_class(need: int) -> int:
    """need + alignment, rounded up to an eighth of its power of two."""
    need += _ALIGN
    step = 1 << max(need.bit_length() - 4, 0)
    return -(-need // step) * step


def _take(size: int) -> np.ndarray:
    """A free kept buffer of `size` bytes (marked most recently used), or a new one, kept when room
    can be made for it under KEPT_LIMIT by dropping free buffers, the least recently used first."""
    with _lock:
        free = _free()
        for i in range(len(_buffers) - 1, -1, -1):
            if free[i] and _buffers[i].nbytes == size:
                buffer = _buffers.pop(i)
                _buffers.append(buffer)
                return buffer
        buffer = np.empty(size, np.uint8)
        if sum(b.nbytes for b, f in zip(_buffers, free) if not f) + size > KEPT_LIMIT:
            return buffer  # no room even without the free ones: not kept
        kept, dropped = sum(b.nbytes for b in _buffers), set()
        for i in (i for i, f in enumerate(free) if f):  # the least recently used first
            if kept + size <= KEPT_LIMIT:
                break
            kept -= _buffers[i].nbytes
            dropped.add(i)
        _buffers[:] = [b for i, b in enumerate(_buffers) if i not in dropped]
        _buffers.append(buffer)
        return buffer
