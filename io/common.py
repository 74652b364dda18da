"""What every format shares: the error type and the write-then-rename rule."""

import contextlib
import os
import tempfile
from pathlib import Path

_UMASK = os.umask(0)
os.umask(_UMASK)


class SplatFileError(ValueError):
    """A splat file that cannot be read or written; the message names the file and the problem."""

    def __init__(self, path, problem):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


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
