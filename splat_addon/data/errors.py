"""What can go wrong reading splat objects, and the warnings passed on to Blender's reports."""

import contextlib
import warnings

from ...core import SplatValidationError
from ...io import SplatFileError


class SplatModeWarning(UserWarning):
    """Splats made for antialiased rendering shown or written classic beside classic ones."""


class RelightWarning(UserWarning):
    """Something of the scene that relighting cannot shade as Cycles would (the engine reports it)."""


@contextlib.contextmanager
def reported_warnings(report):
    """Python warnings raised inside (a format's notes, mixed render modes) passed on to `report`, an
    operator's or render engine's, as Blender warnings, each message once (a thousand instances of
    one light say the same)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for message in dict.fromkeys(str(w.message) for w in caught):
        report({"WARNING"}, message)


class SplatObjectError(ValueError):
    """A Blender object that cannot be read as a splat cloud; the message names it and the problem."""


# What a failed read or write can raise; anything else is a bug and should surface as one.
EXPECTED_ERRORS = (SplatFileError, SplatValidationError, SplatObjectError, OSError, ValueError)
