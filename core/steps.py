"""Long work as a generator of (done, total, label) steps, so a caller can show progress and stop
between steps (close() the generator): running one to its end, and relabelling its steps."""


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
