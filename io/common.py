"""What every format shares: the error type and the write-then-rename rule."""

import contextlib
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np


NONFINITE_POLICIES = ("raise", "keep", "drop")

_UMASK = os.umask(0)
os.umask(_UMASK)


class SplatFileError(ValueError):
    """A splat file that cannot be read or written; the message names the file and the problem."""

    def __init__(self, path, problem):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class SplatFileWarning(UserWarning):
    """A file was read or written, but not exactly as stored (2DGS flattened, non-finite splats kept
    or dropped, view-dependent colour dropped by a format without it, ...)."""


def read_text(path):
    """A text file's contents (undecodable bytes replaced), or a SplatFileError naming why it
    cannot be read (missing, a folder, no permission)."""
    try:
        return Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None


def check_nonfinite_policy(policy):
    if policy not in NONFINITE_POLICIES:
        raise ValueError(f"nonfinite must be one of {NONFINITE_POLICIES}, got {policy!r}")


def nonfinite_counts(cloud):
    """{field: splats with NaN/Inf, or values that overflow when activated, in that field (float
    extras included)}, only the fields that have some (SplatCloud.bad_counts)."""
    return cloud.bad_counts()


def apply_nonfinite_policy(path, cloud, policy, verb, counts=None):
    """The rule every format follows for NaN/Inf: 'raise' a SplatFileError counting them per field,
    'keep' them with a warning (SplatCloud.problems() reports them), or 'drop' those splats with a
    warning. `counts` may come from a reader that tallied while parsing."""
    check_nonfinite_policy(policy)
    counts = nonfinite_counts(cloud) if counts is None else counts
    if not counts:
        return cloud
    bad = ~cloud.finite_mask()
    detail = ", ".join(f"{name} in {c}" for name, c in counts.items())
    what = (f"{int(bad.sum())} of {len(cloud)} splats have non-finite values (NaN, Inf, beyond float32, or "
            f"overflowing float32 once activated): {detail}")
    if policy == "raise":
        raise SplatFileError(path, f"{what}; {verb} with nonfinite='keep' or 'drop' to go on anyway")
    warnings.warn(f"{path}: {what}; {'kept' if policy == 'keep' else 'dropped'}", SplatFileWarning, stacklevel=3)
    return cloud if policy == "keep" else cloud[~bad]


def log_scales_from_linear(scales, notes):
    """float32 natural logs of linear scales; negative scales count by magnitude and zero ones (a
    flat axis) become the smallest normal float32, so the log stays finite. Repairs go to `notes`."""
    scales = np.array(scales, dtype=np.float32)
    negative = scales < 0
    if negative.any():
        notes.append(f"{int(negative.sum())} negative scales taken as their absolute values")
        scales = np.abs(scales)
    zero = scales == 0
    if zero.any():
        notes.append(f"{int(zero.sum())} zero scales set to {np.finfo(np.float32).tiny:g}")
        scales[zero] = np.finfo(np.float32).tiny
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(scales.astype(np.float64)).astype(np.float32)


@contextlib.contextmanager
def atomic_write(path, mode="wb"):
    """Yield a temporary file beside `path`; rename it over `path` only if the block succeeds.

    A failed or interrupted write leaves neither a partial file nor a stray temporary behind, and
    whatever was at `path` before is untouched.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path):
    """Like atomic_write, for libraries that insist on writing a file by name themselves.

    Yields a temporary path with the same extension (so extension-sniffing writers pick the right
    format) and renames it over `path` when the block succeeds.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent or ".")
    os.close(fd)
    try:
        yield tmp
        _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _publish(tmp, path):
    # mkstemp makes 0600 files; give the result the permissions a plain open() would have.
    os.chmod(tmp, 0o666 & ~_UMASK)
    os.replace(tmp, path)
