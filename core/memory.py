"""Memory budgets: how much memory this machine has and has free, and a default share of it for work
whose size depends on its input (a conversion's splats, an image's buffers).

Work that grows with its input predicts its memory before allocating and keeps within a budget:
past it, it stops with what it reached and says why, rather than being ended by the OOM killer.
"""

import os

# The default budget: this share of the memory free when the work starts. Half leaves room for
# Blender's own data, the scene being converted and a second job, on a machine in use.
DEFAULT_SHARE = 0.5
# A budget below this is refused: the fixed costs of a conversion (views, meshes, the interpreter's
# own data) alone are of this order.
MIN_BUDGET = 64 << 20


def physical_memory() -> int | None:
    """This machine's memory in bytes, or None where it cannot be told."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        pass
    status = _windows_memory_status()
    return None if status is None else int(status.total)


def available_memory() -> int | None:
    """Bytes this machine can give a new allocation without swapping (Linux MemAvailable, Windows
    ullAvailPhys, elsewhere the free pages), or None where it cannot be told."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    status = _windows_memory_status()
    if status is not None:
        return int(status.available)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def default_budget() -> int:
    """The budget a job gets unless told otherwise: DEFAULT_SHARE of the memory free now (of the
    machine's memory where the free memory cannot be told; 4 GiB where neither can)."""
    have = available_memory() or physical_memory() or 8 << 30
    return max(MIN_BUDGET, int(have * DEFAULT_SHARE))


def check_budget(budget: int | None) -> int:
    """`budget` in bytes (None: default_budget()); ValueError for one too small to do any work in."""
    if budget is None:
        return default_budget()
    budget = int(budget)
    if budget < MIN_BUDGET:
        raise ValueError(f"a memory budget must be at least {MIN_BUDGET >> 20} MiB, got {budget / 2**20:.1f} MiB")
    return budget


def numpy_huge_pages(enabled: bool) -> bool | None:
    """Set whether NumPy asks Linux for transparent huge pages for its large arrays (it madvises
    every array of 4 MiB or more); the previous setting, or None where this NumPy cannot be told.

    Where the system compacts memory for such a request on the spot (THP defrag "madvise", the
    default of Ubuntu among others), a fault in a fresh array can stall for that, and fresh arrays
    are most of a frame's and a conversion's: measured on a 2-core Linux machine, a lit 1920x1080
    frame of 410k splats 378 -> 262 ms and a 500k-splat conversion 36-37 -> 30-32 s (system time
    10 -> 3.5 s) with it off. The setting is the process's: the Blender extension turns it off
    while it is enabled, and the command line for its run; a library user may do the same."""
    import importlib

    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):  # NumPy 2, then 1.x
        try:
            toggle = getattr(importlib.import_module(name), "_set_madvise_hugepage", None)
        except ImportError:
            continue
        if toggle is not None:
            return bool(toggle(bool(enabled)))
    return None


def human_bytes(n: float) -> str:
    """A byte count for people: 1536 -> '1.5 KiB', 3 << 30 -> '3.0 GiB'."""
    for unit in ("B", "KiB", "MiB"):
        if n < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _windows_memory_status():
    try:
        import ctypes

        class Status(ctypes.Structure):
            _fields_ = [
                ("length", ctypes.c_ulong),
                ("load", ctypes.c_ulong),
                ("total", ctypes.c_ulonglong),
                ("available", ctypes.c_ulonglong),
                ("page_total", ctypes.c_ulonglong),
                ("page_available", ctypes.c_ulonglong),
                ("virtual_total", ctypes.c_ulonglong),
                ("virtual_available", ctypes.c_ulonglong),
                ("extended", ctypes.c_ulonglong),
            ]

        status = Status()
        status.length = ctypes.sizeof(Status)
        if ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status)):  # type: ignore[attr-defined]
            return status
    except Exception:  # noqa: BLE001 - not Windows, or no kernel32: the memory cannot be told this way
        pass
    return None
