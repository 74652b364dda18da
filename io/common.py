"""What every format shares: the error type and the write-then-rename rule."""

import contextlib
import contextvars
import errno
import itertools
import os
import re
import stat
import time
import warnings
from pathlib import Path

import numpy as np

NONFINITE_POLICIES = ("raise", "keep", "drop")


class SplatFileError(ValueError):
    """A splat file that cannot be read or written; the message names the file and the problem."""

    def __init__(self, path, problem):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class SplatFileWarning(UserWarning):
    """A file was read or written, but not exactly as stored (2DGS flattened, non-finite splats kept
    or dropped, view-dependent colour dropped by a format without it, ...)."""


def check_file(path):
    """SplatFileError unless `path` is a regular file (symbolic links followed): "no such file" when
    nothing is there, "not a regular file" for a folder, FIFO, device or socket, whose read would fail,
    hang or never end."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        raise SplatFileError(path, "no such file") from None
    if not stat.S_ISREG(mode):
        raise SplatFileError(path, "not a regular file (a folder, pipe or device); only files are read")


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
    what = (
        f"{int(bad.sum())} of {len(cloud)} splats have non-finite values (NaN, Inf, beyond float32, or "
        f"overflowing float32 once activated): {detail}"
    )
    if policy == "raise":
        raise SplatFileError(path, f"{what}; {verb} with nonfinite='keep' or 'drop' to go on anyway")
    warnings.warn(f"{path}: {what}; {'kept' if policy == 'keep' else 'dropped'}", SplatFileWarning, stacklevel=3)
    return cloud if policy == "keep" else cloud[~bad]


def reduced_sh(cloud, degree, what, notes):
    """The cloud with its SH cut to `degree` where the format `what` stores no higher band; a note
    says so when the bands dropped held anything."""
    if cloud.sh_degree <= degree:
        return cloud
    if np.any(cloud.sh[:, (degree + 1) ** 2 :]):
        notes.append(
            f"{what} stores SH up to degree {degree}: SH degree {cloud.sh_degree} reduced to {degree} "
            "(the higher bands' view-dependent colour dropped)"
        )
    return cloud.with_sh_degree(degree)


def warn_notes(path, notes, stacklevel=3):
    """One SplatFileWarning for a writer's or reader's notes, if any."""
    if notes:
        warnings.warn(f"{path}: " + "; ".join(notes), SplatFileWarning, stacklevel=stacklevel)


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
    """Yield an open file for `path`'s new contents; `path` gets them only if the block succeeds.

    The file is a partial, `<path>.splatwright-partial-<pid>` beside the target (never a name with
    the target's extension, never a temporary folder). On success it is fsynced, given the
    permissions of the file it replaces (a new file gets what open() makes under the umask),
    renamed over the target, and the folder fsynced (not on Windows). A symlink at `path` is
    written through: the file it points to is replaced and the link stays; a dangling link gets
    its target made. Any failure removes the partial and leaves the target as it was, and every
    OSError, the block's own writes included, becomes a SplatFileError naming `path` (disk full,
    no permission, missing folder, a folder in the way). A killed process leaves the target whole
    and at most its partial, which the next write into that folder removes (_sweep_partials).
    Inside publish_together() the rename waits for the end of the group.
    """
    with _partial(path) as (fd, _):
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())


@contextlib.contextmanager
def atomic_path(path):
    """Like atomic_write, for libraries that insist on writing a file by name themselves (pxr,
    OpenEXR). The name yielded does not end in `path`'s extension: tell the library the format."""
    with _partial(path) as (fd, tmp):
        os.close(fd)
        yield tmp
        fd = os.open(tmp, os.O_RDWR if os.name == "nt" else os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


PARTIAL_TAG = ".splatwright-partial-"
STALE_AFTER = 24 * 3600  # seconds: a partial this old is swept whoever wrote it
_PARTIAL_NAME = re.compile(re.escape(PARTIAL_TAG) + r"(\d+)")


@contextlib.contextmanager
def _partial(path):
    """atomic_write's rule, for both helpers: yields (open fd, name) of a new partial file, then
    (once the caller has fsynced it) publishes it or, on any failure, removes it."""
    target = _write_target(path)
    _sweep_partials(target.parent)
    mode = _existing_mode(target)
    try:
        fd, tmp = _create_partial(target, 0o666 if mode is None else mode | 0o600)  # the writer may reopen it
    except OSError as exc:
        raise SplatFileError(path, _write_problem(exc, target)) from None
    try:
        yield fd, tmp
        if mode is not None:  # exactly the replaced file's, whatever the umask
            os.chmod(tmp, mode)
        group = _together.get()
        if group is not None:
            group.append((path, tmp, target))
            return
        os.replace(tmp, target)
    except BaseException as exc:
        _remove_partial(tmp)
        if isinstance(exc, OSError):
            raise SplatFileError(path, _write_problem(exc, target)) from exc
        raise
    _fsync_folder(target.parent)


_together = contextvars.ContextVar("splatwright_publish_together", default=None)


@contextlib.contextmanager
def publish_together():
    """Hold back the renames of every atomic write in the block until it ends: the files appear
    together when the block succeeds (one after another, each whole), and none does when it fails
    (every partial is removed)."""
    if _together.get() is not None:  # inside another group: its renames decide
        yield
        return
    group = []
    token = _together.set(group)
    try:
        yield
        _together.reset(token)
        token = None
        while group:
            path, tmp, target = group[0]
            try:
                os.replace(tmp, target)
            except OSError as exc:
                raise SplatFileError(path, _write_problem(exc, target)) from exc
            group.pop(0)
            _fsync_folder(target.parent)
    finally:
        if token is not None:
            _together.reset(token)
        for _, tmp, _ in group:
            _remove_partial(tmp)


def _write_target(path):
    """The file a write to `path` replaces (through symlinks), or a SplatFileError when there is
    none to write: a folder, a device or pipe, a symlink loop, or a folder that does not exist."""
    path = Path(path)
    target = Path(os.path.realpath(path))
    if target.is_symlink():
        raise SplatFileError(path, "is a symbolic link that loops; nothing to write to")
    if target.is_dir():
        raise SplatFileError(path, "is a folder, not a file")
    if target.exists() and not target.is_file():
        raise SplatFileError(path, "is not a regular file (a device or a pipe?); write to a file")
    if not target.parent.is_dir():
        raise SplatFileError(path, f"cannot write: the folder {target.parent} does not exist")
    return target


def _create_partial(target, mode):
    """A new partial file for `target`, made with `mode` under the umask as open() makes files."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    base = f"{target}{PARTIAL_TAG}{os.getpid()}"
    for n in itertools.count():
        tmp = base if n == 0 else f"{base}-{n}"  # another thread writing the same target
        try:
            return os.open(tmp, flags, mode), tmp
        except FileExistsError:
            continue


def _remove_partial(tmp):
    """Remove a partial and whatever its writer made from its name (a .usdz's layer, pxr's own
    `<name>.XXXXXX` temporary when its save fails)."""
    folder, name = os.path.split(tmp)
    with contextlib.suppress(OSError):
        os.unlink(tmp)
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder or "."):
            if entry.name.startswith(name + ".") and entry.is_file(follow_symlinks=False):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)


def _sweep_partials(folder):
    """Remove the partials a killed write left in `folder`: those whose process is gone (on this
    machine; where that cannot be told, Windows, only by age) and any older than STALE_AFTER."""
    try:
        entries = [e for e in os.scandir(folder) if PARTIAL_TAG in e.name]
    except OSError:
        return
    now = time.time()
    for entry in entries:
        match = _PARTIAL_NAME.search(entry.name)
        with contextlib.suppress(OSError):  # gone already, or not ours to remove
            if (
                match
                and entry.is_file(follow_symlinks=False)
                and (
                    not _process_alive(int(match.group(1)))
                    or now - entry.stat(follow_symlinks=False).st_mtime > STALE_AFTER
                )
            ):
                os.unlink(entry.path)


def _process_alive(pid):
    if os.name == "nt" or pid <= 0:
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # alive, another user's
        return True
    return True


def _existing_mode(target):
    try:
        return stat.S_IMODE(os.stat(target).st_mode)
    except FileNotFoundError:
        return None


def _fsync_folder(folder):
    """Make the rename itself durable; folders cannot be opened on Windows, and some file systems
    refuse to sync one (nothing more to do there)."""
    if os.name == "nt":
        return
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


_WRITE_HINTS = {
    errno.ENOSPC: "the disk is full",
    getattr(errno, "EDQUOT", -1): "the disk quota is used up",
    errno.EROFS: "the folder {folder} is on a read-only file system",
    errno.EACCES: "no permission to write in the folder {folder}",
    errno.EPERM: "no permission to write in the folder {folder}",
    errno.ENOENT: "the folder {folder} does not exist",
}


def _write_problem(exc, target):
    if exc.errno == errno.EISDIR:
        return "is a folder, not a file"
    hint = _WRITE_HINTS.get(exc.errno)
    return f"cannot write: {exc.strerror or exc}" + (f" ({hint.format(folder=target.parent)})" if hint else "")
