"""Typed values of an OpenUSD text layer as OpenUSD reads them, for usda_parse.py: numbers of the
attribute's type (floats rounded to it, overflowing to infinity; integers truncated towards zero and
refused outside its range; bools from true, false, yes or no in any case, or any number), tuples of exactly its shape,
and numeric arrays parsed in bulk by NumPy after their layout is checked against the type, in a few
bytes per character of the text. What OpenUSD refuses raises BadValue saying why.
"""

import math
import warnings

import numpy as np

BOOL_WORDS = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}  # any case


class BadValue(ValueError):
    """A value that is not one of its type (the parser names the line)."""


class Unregistered:
    """The value of an attribute whose type OpenUSD does not know, kept as read: like Sdf's
    UnregisteredValue it is no number nor array to the readers."""

    def __init__(self, value):
        self.value = value

    def __repr__(self):
        return f"Unregistered({self.value!r:.60})"


def shape_of(type_name, spec):
    """The shape of one element: () for a number, (n,) for a tuple, (k, k) for a matrix."""
    width = spec[1]
    base = type_name.removesuffix("[]")
    if base.startswith(("matrix", "frame")):
        k = math.isqrt(width)
        return (k, k)
    return () if width == 1 else (width,)


def describe(shape):
    """What an element of `shape` is, in words."""
    if not shape:
        return "a number"
    if len(shape) == 1:
        return f"a tuple of {shape[0]} numbers"
    return f"a tuple of {shape[0]} tuples of {shape[1]} numbers"


# one value ----------------------------------------------------------------------------------------


def scalar(type_name, dtype, value):
    """One number of `dtype` as OpenUSD reads `value` (a Python number or, for bools, a word)."""
    if dtype.kind == "b":
        if isinstance(value, str) and value.lower() in BOOL_WORDS:
            return BOOL_WORDS[value.lower()]
        if _is_number(value):
            return bool(value != 0)
        raise BadValue(f"a {type_name} is true, false or a number, not {value!r}")
    if not _is_number(value):
        raise BadValue(f"a {type_name} needs a number, found {_what(value)}")
    if dtype.kind == "f":
        with np.errstate(over="ignore"):
            return np.float64(value).astype(dtype).item()
    return _integer(type_name, dtype, value)


def typed(type_name, spec, value):
    """A non-array value of a numeric type (spec: usda.element's): a Python scalar, or a NumPy
    array of the type's shape (quaternions x, y, z, w as Vt holds them)."""
    dtype = spec[0]
    shape = shape_of(type_name, spec)
    if not shape:
        return scalar(type_name, dtype, value)
    numbers = _flatten(type_name, shape, value)
    values = np.array([scalar(type_name, dtype, v) for v in numbers], dtype).reshape(shape)
    return values[[1, 2, 3, 0]] if type_name.startswith("quat") else values


def typed_list(type_name, spec, items):
    """An array value parsed token by token (bools, which may be words; arrays with comments): a
    NumPy array as numeric_array makes it."""
    dtype = spec[0]
    shape = shape_of(type_name, spec)
    rows = [_flatten(type_name, shape, item) if shape else [item] for item in items]
    width = int(np.prod(shape)) if shape else 1
    flat = [scalar(type_name, dtype, v) for row in rows for v in row]
    values = np.array(flat, dtype).reshape((-1, width) if shape else (-1,))
    return np.ascontiguousarray(values[:, [1, 2, 3, 0]]) if type_name.startswith("quat") else values


def _flatten(type_name, shape, value):
    """The numbers of a nested tuple of exactly `shape`, in order."""
    if not isinstance(value, tuple) or len(value) != shape[0]:
        raise BadValue(f"a {type_name} needs {describe(shape)}, found {_what(value)}")
    if len(shape) == 1:
        return list(value)
    return [v for row in value for v in _flatten(type_name, shape[1:], row)]


def _is_number(value):
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _what(value):
    if isinstance(value, tuple):
        return f"a tuple of {len(value)}"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    text = repr(value)
    return text if len(text) < 40 else text[:40] + "..."


def _integer(type_name, dtype, value):
    if isinstance(value, float):
        if not math.isfinite(value):
            raise BadValue(f"a {type_name} cannot be {value}")
        value = math.trunc(value)
    info = np.iinfo(dtype)
    if not info.min <= value <= info.max:
        raise BadValue(f"{value} is outside the range of a {type_name} ({info.min}..{info.max})")
    return int(value)


# arrays in bulk -------------------------------------------------------------------------------------

_SPACE, _DIGIT, _OPEN, _CLOSE, _COMMA = 1, 2, 3, 4, 5
_CLASS = np.zeros(256, np.uint8)  # 0: a character no number array holds
_CLASS[list(b" \t\r\n")] = _SPACE
_CLASS[list(b"0123456789.-+eEinfa")] = _DIGIT
_CLASS[[ord("("), ord(")"), ord(",")]] = _OPEN, _CLOSE, _COMMA


def _template(shape):
    """The layout of one element with every number written `n`: b"(n,n,n)" for a float3."""
    if not shape:
        return b"n"
    inner = _template(shape[1:])
    return b"(" + b",".join([inner] * shape[0]) + b")"


def numeric_array(type_name, spec, body):
    """The array between `[` and `]` (`body`) of a numeric array type, in bulk: a NumPy array of
    (count,) or (count, numbers per element), quaternions x, y, z, w."""
    dtype = spec[0]
    shape = shape_of(type_name, spec)
    per = int(np.prod(shape)) if shape else 1
    raw = np.frombuffer(body.encode("utf-8"), np.uint8)
    kinds = _CLASS[raw]
    if not kinds.all():
        raise BadValue(f"a {type_name} array holds something other than numbers")
    digit = kinds == _DIGIT
    starts = digit.copy()
    starts[1:] &= ~digit[:-1]
    count = _check_layout(type_name, shape, per, raw, kinds, starts)
    longest = 0
    if dtype.kind in "iu" and count:
        ends = digit.copy()
        ends[:-1] &= ~digit[1:]
        longest = int((np.flatnonzero(ends) - np.flatnonzero(starts)).max()) + 1
        del ends
    del starts
    plus = np.flatnonzero(raw == ord("+"))
    if len(plus) and not np.isin(raw[plus - 1], list(b"eE")).all():
        raise BadValue(f"a {type_name} array holds a number with a leading '+'")
    text = np.where(digit, raw, ord(" ")).astype(np.uint8).tobytes()
    del digit, kinds
    if dtype.kind == "f":
        values = _parse(type_name, text, np.float64, count * per)
        with np.errstate(over="ignore"):
            values = values.astype(dtype)
    else:
        values = _integers(type_name, dtype, text, count * per, raw, longest)
    values = values.reshape((-1, per) if shape else (-1,))
    if type_name.startswith("quat"):
        values = np.ascontiguousarray(values[:, [1, 2, 3, 0]])  # w first in text, x, y, z, w held
    return values


def _check_layout(type_name, shape, per, raw, kinds, starts):
    """The number of elements, once the array's punctuation and numbers are laid out exactly as the
    type's elements are, separated by commas (a trailing comma allowed, also inside tuples)."""
    keep = starts | (kinds >= _OPEN)
    layout_bytes = np.where(starts, ord("n"), raw)[keep].astype(np.uint8).tobytes()
    del keep
    layout_bytes = layout_bytes.replace(b",)", b")")
    if layout_bytes.endswith(b","):
        layout_bytes = layout_bytes[:-1]
    count = layout_bytes.count(b"n") // per
    element = _template(shape)
    if layout_bytes + b"," != (element + b",") * count and not (count == 0 and not layout_bytes):
        raise BadValue(f"a {type_name} array is not a list of elements each {describe(shape)}")
    return count


def _parse(type_name, text, dtype, expected):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        try:
            values = np.fromstring(text, dtype, sep=" ") if expected else np.zeros(0, dtype)
        except (DeprecationWarning, ValueError):
            raise BadValue(f"a {type_name} array holds text that is not a number") from None
    if len(values) != expected:
        raise BadValue(f"a {type_name} array holds text that is not a number")
    return values


def _integers(type_name, dtype, text, expected, raw, longest):
    """Integers as OpenUSD reads them: written as floats they are truncated; out of range refused."""
    info = np.iinfo(dtype)
    if longest > 15:  # beyond float64's exact integers: each number on its own, exactly
        values = [_integer(type_name, dtype, _number(word)) for word in text.decode().split()]
        return np.array(values, dtype)
    if np.isin(raw, list(b".eEinfa")).any():
        values = _parse(type_name, text, np.float64, expected)
        if not np.isfinite(values).all():
            raise BadValue(f"a {type_name} array holds inf or nan")
        values = np.trunc(values)
    else:
        values = _parse(type_name, text, np.int64, expected)
    if len(values) and (values.min() < info.min or values.max() > info.max):
        raise BadValue(f"a {type_name} array holds a number outside {info.min}..{info.max}")
    return values.astype(dtype)


def _number(word):
    try:
        return float(word) if any(c in word for c in ".eEin") else int(word)
    except ValueError:
        raise BadValue(f"{word[:40]!r} is not a number") from None
