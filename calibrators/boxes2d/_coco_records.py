"""Strict, field-by-field reading of COCO record lists (a results list, an instances file's
`annotations`, `images` and `categories`) into columns.

Each value must have the type the COCO format gives it (https://cocodataset.org/#format-data
and #format-results): ids are integers (not bools, not floats such as 1.0), `bbox` is 4
numbers `x, y, w, h` with `w, h >= 0`, `score` and `area` are numbers, `iscrowd` is 0 or 1. A
JSON file gives ints, floats and lists; a Python caller may also pass numpy scalars, tuples
and arrays. Strings, bools, NaN and infinities are refused wherever a number is due.

A bad value raises `FieldError` with `field` the key, `row` the record's index, and a message
naming both: `annotations[3].bbox must be 4 finite numbers with w, h >= 0, got [1, 2, -3, 4]`.
A record without a required key: `results[1] has no 'score'`.

The checks run on whole columns (the set of value types, then one array), and only a column
found bad is walked to name its first bad record.
"""

from __future__ import annotations

import itertools
import numbers
import operator
import reprlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from calibrators.core.errors import FieldError

__all__ = ["MISSING", "at_record", "boxes", "column", "flags", "has_key", "ints", "layer_boxes",
           "numbers_of", "records", "strings", "vectors"]

#: `column`'s default: the key is required.
MISSING: Any = object()
_SHORT = reprlib.Repr()  # values in messages: 2 levels, 6 items, 40 characters
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxtuple, _SHORT.maxstring = 2, 6, 6, 40
_BOX_TEXT = "must be 4 finite numbers with w, h >= 0"


def records(value: object, what: str) -> Sequence[Mapping[str, Any]]:
    """`value` as a list of records (objects); FieldError naming `what` otherwise."""
    if not isinstance(value, list | tuple):
        raise FieldError(what, f"{what} must be a list of objects, got {_kind(value)}")
    _first_bad(value, lambda t: issubclass(t, Mapping), what, None,
               lambda i, v: f"{what}[{i}] must be an object, got {_kind(v)}")
    return value


def has_key(rows: Sequence[Mapping[str, Any]], key: str, what: str) -> bool:
    """Whether the optional `key` is given: in every record (True), in none (False); a key in
    some records only is a FieldError naming the first without it."""
    count = sum(map(operator.contains, rows, itertools.repeat(key)))
    if count in (0, len(rows)):
        return count > 0
    have = [key in r for r in rows]
    i, j = have.index(False), have.index(True)
    raise FieldError(key, f"{what}[{i}] has no {key!r} but {what}[{j}] has one: give it in "
                          "every record or in none", row=i)


def column(rows: Sequence[Mapping[str, Any]], key: str, what: str,
           default: Any = MISSING) -> list[Any]:
    """The values of `key` `[N]`; a record without it takes `default`, or is a FieldError."""
    if default is not MISSING:
        return [r.get(key, default) for r in rows]
    try:
        return [r[key] for r in rows]
    except KeyError:
        i = next(i for i, r in enumerate(rows) if key not in r)
        raise FieldError(key, f"{what}[{i}] has no {key!r}", row=i) from None


def ints(rows: Sequence[Mapping[str, Any]], key: str, what: str,
         default: Any = MISSING) -> np.ndarray:
    """`[N]` int64 of an integer key (64-bit range)."""
    values = column(rows, key, what, default)
    _first_bad(values, _is_int, key, what, lambda i, v: f"must be an integer, got {_show(v)}")
    try:
        return np.array(values, dtype=np.int64).reshape(len(values))
    except OverflowError:
        _first_bad(values, None, key, what, "is outside the 64-bit integer range",
                   bad=lambda v: not -2**63 <= int(v) < 2**63)
        raise  # unreachable


def numbers_of(rows: Sequence[Mapping[str, Any]], key: str, what: str, *,
               low: float = -np.inf, high: float = np.inf, default: Any = MISSING) -> np.ndarray:
    """`[N]` float64 of a number key, each finite in `[low, high]`."""
    values = column(rows, key, what, default)
    text = "a finite number" if (low, high) == (-np.inf, np.inf) else \
        f"a number >= {low:g}" if high == np.inf else f"a number in [{low:g}, {high:g}]"
    _first_bad(values, _is_number, key, what, lambda i, v: f"must be {text}, got {_show(v)}")
    arr = _floats(values, key, what, f"must be {text}").reshape(len(values))
    _first_row(~(np.isfinite(arr) & (arr >= low) & (arr <= high)), values, key, what,
               f"must be {text}")
    return arr


def flags(rows: Sequence[Mapping[str, Any]], key: str, what: str,
          default: Any = MISSING) -> np.ndarray:
    """`[N]` bool of a 0 / 1 key (JSON true / false too)."""
    values = column(rows, key, what, default)
    _first_bad(values, None, key, what, lambda i, v: f"must be 0 or 1, got {_show(v)}",
               bad=lambda v: not (isinstance(v, numbers.Integral | np.bool_) and v in (0, 1)))
    return np.array(values, dtype=np.int64).reshape(len(values)) == 1


def strings(rows: Sequence[Mapping[str, Any]], key: str, what: str) -> list[str]:
    """`[N]` of a string key."""
    values = column(rows, key, what)
    _first_bad(values, lambda t: issubclass(t, str), key, what,
               lambda i, v: f"must be a string, got {_kind(v)}")
    return values


def boxes(rows: Sequence[Mapping[str, Any]], key: str, what: str) -> np.ndarray:
    """`[N, 4]` float64 of a COCO box key `[x, y, w, h]`: finite, `w, h >= 0`."""
    values = column(rows, key, what)
    return _boxes(values, lambda i: f"{what}[{i}].{key}", key)


def vectors(rows: Sequence[Mapping[str, Any]], key: str, what: str) -> np.ndarray | None:
    """`[N, C]` float64 of an optional key holding C >= 1 finite numbers (the same C in every
    record), or None when no record has it."""
    if not has_key(rows, key, what):
        return None
    values = column(rows, key, what)
    text = "must be a non-empty list of finite numbers"
    _first_bad(values, _is_sequence, key, what, lambda i, v: f"{text}, got {_kind(v)}")
    _same_length(values, key, what, text)
    if not _all_kinds(itertools.chain.from_iterable(values), _is_number):
        _first_bad(values, None, key, what, lambda i, v: f"{text}, got {_show(v)}",
                   bad=lambda v: not _all_kinds(v, _is_number))
    arr = _floats(values, key, what, text)
    _first_row(~np.isfinite(arr).all(axis=1), values, key, what, text)
    return arr


def layer_boxes(rows: Sequence[Mapping[str, Any]], key: str, what: str) -> np.ndarray | None:
    """`[N, L, 4]` float64 of an optional key holding L >= 1 COCO boxes (the same L in every
    record, each as `boxes`), or None when no record has it."""
    if not has_key(rows, key, what):
        return None
    values = column(rows, key, what)
    text = "must be a non-empty list of boxes [x, y, w, h]"
    _first_bad(values, _is_sequence, key, what, lambda i, v: f"{text}, got {_kind(v)}")
    n_layers = _same_length(values, key, what, text)
    flat = list(itertools.chain.from_iterable(values))
    out = _boxes(flat, lambda k: f"{what}[{k // n_layers}].{key}[{k % n_layers}]", key,
                 lambda k: k // n_layers)
    return out.reshape(len(values), n_layers, 4)


def at_record(error: FieldError, what: str) -> FieldError:
    """A container's FieldError on row r of field f (`f[r] has ...`) as one on record r of
    the list `what` (`what[r].f has ...`); other errors as they are."""
    prefix = f"{error.field}[{error.row}]"
    text = str(error)
    if error.row is None or not text.startswith(prefix):
        return error
    return FieldError(error.field, f"{what}[{error.row}].{error.field}{text[len(prefix):]}",
                      row=error.row)


# -- helpers -----------------------------------------------------------------------------------
def _boxes(values: list[Any], where: Callable[[int], str], key: str,
           row_of: Callable[[int], int] = lambda i: i) -> np.ndarray:
    """`[N, 4]` boxes of `values`, each named by `where(i)` and reported at `row_of(i)`."""
    def fail(i: int) -> None:
        raise FieldError(key, f"{where(i)} {_BOX_TEXT}, got {_show(values[i])}", row=row_of(i))

    kinds = set(map(type, values))
    if not all(_is_sequence(t) for t in kinds) or set(map(len, values)) - {4} \
            or not _all_kinds(itertools.chain.from_iterable(values), _is_number):
        fail(next(i for i, v in enumerate(values) if not (
            _is_sequence(type(v)) and len(v) == 4 and _all_kinds(v, _is_number))))
    try:
        arr = np.array(values, dtype=np.float64).reshape(len(values), 4)
    except OverflowError:  # an int beyond the float range
        fail(next(i for i, v in enumerate(values) if not _converts(v)))
    bad = ~np.isfinite(arr).all(axis=1) | (arr[:, 2] < 0) | (arr[:, 3] < 0)
    if bad.any():
        fail(int(np.argmax(bad)))
    return arr


def _floats(values: list[Any], key: str, what: str, text: str) -> np.ndarray:
    try:
        return np.array(values, dtype=np.float64)
    except OverflowError:  # an int beyond the float range
        i = next(i for i, v in enumerate(values) if not _converts(v))
        raise FieldError(key, f"{what}[{i}].{key} {text}, got {_show(values[i])}",
                         row=i) from None


def _same_length(values: list[Any], key: str, what: str, text: str) -> int:
    """The common length (>= 1) of the sequences `values`, or a FieldError."""
    lengths = list(map(len, values))
    if 0 in lengths:
        i = lengths.index(0)
        raise FieldError(key, f"{what}[{i}].{key} {text}, got []", row=i)
    i = next((i for i, n in enumerate(lengths) if n != lengths[0]), None)
    if i is not None:
        raise FieldError(key, f"{what}[{i}].{key} has {lengths[i]} entries but "
                              f"{what}[0].{key} has {lengths[0]}", row=i)
    return lengths[0] if lengths else 0


def _first_bad(values: Sequence[Any], kind_ok: Callable[[type], bool] | None, key: str,
               what: str | None, message: Any, bad: Callable[[Any], bool] | None = None
               ) -> None:
    """Raise for the first value whose type fails `kind_ok` (tested once per distinct type) or,
    without it, for which `bad(value)` holds. `message(i, v)` (or a fixed text) follows
    `what[i].key` (or is the whole message when `what` is None)."""
    if kind_ok is not None:
        if all(kind_ok(t) for t in set(map(type, values))):
            return
        i = next(i for i, v in enumerate(values) if not kind_ok(type(v)))
    else:
        assert bad is not None
        i = next((i for i, v in enumerate(values) if bad(v)), None)
        if i is None:
            return
    text = message(i, values[i]) if callable(message) else message
    raise FieldError(key, text if what is None else f"{what}[{i}].{key} {text}", row=i)


def _first_row(bad: np.ndarray, values: list[Any], key: str, what: str, text: str) -> None:
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError(key, f"{what}[{i}].{key} {text}, got {_show(values[i])}", row=i)


def _is_int(t: type) -> bool:
    return issubclass(t, numbers.Integral) and not issubclass(t, bool | np.bool_)


def _is_number(t: type) -> bool:
    return issubclass(t, numbers.Real) and not issubclass(t, bool | np.bool_)


def _is_sequence(t: type) -> bool:
    return issubclass(t, list | tuple | np.ndarray)


def _all_kinds(values: Any, ok: Callable[[type], bool]) -> bool:
    return all(ok(t) for t in set(map(type, values)))


def _converts(value: Any) -> bool:
    try:
        np.array(value, dtype=np.float64)
    except OverflowError:
        return False
    return True


def _show(value: Any) -> str:
    return _SHORT.repr(value.tolist() if isinstance(value, np.ndarray) else value)


def _kind(value: Any) -> str:
    """A short description of a value for messages (never the whole value)."""
    if isinstance(value, Mapping):
        return "an object"
    if isinstance(value, list | tuple):
        return "a list"
    if value is None:
        return "null"
    return f"{type(value).__name__} {_show(value)}"
