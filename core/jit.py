"""Compiled kernels where they pay, with NumPy doing the same work where they cannot run.

numba compiles the few scalar loops that NumPy cannot express without large temporaries (forward
kinematics of one configuration, exact contact tests of many pairs). Blender's own Python has no
numba, so every kernel has a NumPy path computing the same thing; `SPLATWRIGHT_NO_JIT=1` forces
that path (tests compare the two).
"""

import os

try:                                               # an optional dependency: absent inside Blender
    import numba
except ImportError:                                # pragma: no cover - depends on the environment
    numba = None

ENABLED = numba is not None and os.environ.get("SPLATWRIGHT_NO_JIT", "") not in ("1", "true", "yes")


def kernel(fn):
    """`fn` compiled (no Python objects, GIL released, cached on disk), or None without numba: callers
    test `if kernel is not None` and fall back to their NumPy path."""
    if not ENABLED:
        return None
    return numba.njit(cache=True, nogil=True, fastmath=False)(fn)
