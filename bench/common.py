"""What every benchmark shares: repeated timing with spread, the machine, and result rows.

Each bench/<topic>.py defines `run(quick=False) -> list[Row]` (and runs itself when executed);
bench/run.py collects every topic into bench/REPORT.md. Speeds are always reported as a ratio
against a baseline timed in the same run, next to the error they buy.
"""

import os
import platform
import statistics
import time
from dataclasses import dataclass, field


@dataclass
class Timing:
    median: float
    spread: float  # (max - min) / 2 over the runs, seconds
    runs: int

    def __str__(self):
        return f"{self.median:.4g} s ± {self.spread:.2g} (n={self.runs})"


def timeit(fn, repeat=5, warmup=1, clock=time.perf_counter):
    """Median and spread of `repeat` timed calls of fn() after `warmup` untimed ones; `clock` may be
    time.process_time for CPU seconds (all threads of the process), which a shared machine disturbs
    less than wall time."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return Timing(statistics.median(times), (max(times) - min(times)) / 2, repeat)


@dataclass
class Row:
    """One measured configuration: what it is, how fast, against what baseline, at what error."""

    topic: str
    case: str
    timing: Timing
    baseline: Timing | None = None
    error: dict = field(default_factory=dict)  # metric name -> value
    extra: dict = field(default_factory=dict)  # anything else worth a column

    @property
    def ratio(self):
        """How many times faster than the baseline (baseline time / our time)."""
        return None if self.baseline is None else self.baseline.median / self.timing.median


def paired(baseline, ours, repeat=5, clock=time.perf_counter, warmup=True):
    """(baseline Timing, our Timing) from runs that alternate, so both meet the same load on a shared
    machine; one untimed warm-up each (unless not `warmup`: for long runs whose code is warm)."""
    pairs = _pairs(baseline, ours, repeat, clock, warmup)
    return tuple(_combine([p[side] for p in pairs]) for side in (0, 1))


def paired_ratio(baseline, ours, repeat=5, clock=time.perf_counter, warmup=True):
    """paired()'s two Timings and the median of the ratios ours / baseline of each pair: a pair's two
    runs meet the same load, so their ratio holds still where the ratio of the two medians moves
    with every load that falls on one side's median run."""
    pairs = _pairs(baseline, ours, repeat, clock, warmup)
    ratio = statistics.median(mine.median / base.median for base, mine in pairs)
    return (*(_combine([p[side] for p in pairs]) for side in (0, 1)), ratio)


def _pairs(baseline, ours, repeat, clock, warmup):
    return [
        (timeit(baseline, 1, int(i == 0 and warmup), clock), timeit(ours, 1, int(i == 0 and warmup), clock))
        for i in range(repeat)
    ]


def _combine(timings):
    times = [t.median for t in timings]
    return Timing(statistics.median(times), (max(times) - min(times)) / 2, len(times))


def fresh_file(path, write):
    """A callable writing `write(path)` to a new file each time: replacing a large file makes the
    file system flush the old one first, a cost that would swamp what is measured."""

    def run():
        if path.exists():
            path.unlink()
        write(path)

    return run


def machine():
    """A one-line description of the machine the numbers come from."""
    import numpy as np

    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, NumPy {np.__version__}, {platform.system()}"
    )


def print_rows(rows):
    for r in rows:
        ratio = f"  x{r.ratio:.3g} vs baseline ({r.baseline})" if r.baseline else ""
        err = (
            "  " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.error.items())
            if r.error
            else ""
        )
        ext = "  " + ", ".join(f"{k}={v}" for k, v in r.extra.items()) if r.extra else ""
        print(f"[{r.topic}] {r.case}: {r.timing}{ratio}{err}{ext}")
