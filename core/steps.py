"""Long work as a generator of (done, total, label) steps, so a caller can show progress and stop
between steps (close() the generator): running one to its end, and relabelling its steps; and, for
work that reports to a progress callback instead, a part's progress placed in its share of a whole."""


def drain(steps, progress=None):
    """Run a generator of (done, total, label) steps to its end, passing each to `progress`;
    returns the generator's return value."""
    while True:
        try:
            step = next(steps)
        except StopIteration as stop:
            return stop.value
        if progress:
            progress(*step)


def mapped_steps(steps, fn):
    """A generator of (done, total, label) steps passed on as fn(done, total, label); returns the
    generator's return value (for `yield from`)."""
    while True:
        try:
            step = next(steps)
        except StopIteration as stop:
            return stop.value
        yield fn(*step)


def part_progress(progress, part, parts, label=None):
    """A progress callback (done, total, label) for part `part` of `parts` equal parts of a job that
    reports to `progress`: the part's own fraction placed in its share, under `label` when given
    (else the part's own); None without progress."""
    if progress is None:
        return None
    return lambda done, total, own: progress(part * total + done, parts * total, label or own)
