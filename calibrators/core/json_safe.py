"""The one rule for JSON-safe values: library results in plain, strict JSON types.

numpy scalars and arrays become Python numbers and lists, tuples become lists, dict keys
become strings. JSON has no NaN or infinity: by default a non-finite number becomes None
(results, metrics, served ellipse axes where a region is unbounded); with `strict=True` it
is a ValueError naming where it sits (profile fields, client data echoed back), and so is a
value of no JSON type (a TypeError).
"""

from __future__ import annotations

import json
import math
import numbers
from typing import Any

import numpy as np

__all__ = ["to_jsonable"]

_Path = tuple[str | int, ...]


def to_jsonable(value: Any, *, strict: bool = False) -> Any:
    """`value` in plain JSON types (a new container for every dict, list, tuple or array).

    Non-finite numbers become None, or with `strict` raise ValueError
    (`"at ['a'][0]: NaN is not a finite number ..."`); with `strict` a value of no JSON type
    (not a dict, list, tuple, array, str, number, bool or None) raises TypeError.
    """
    return _convert(value, strict, ())


def _convert(value: Any, strict: bool, path: _Path) -> Any:
    if isinstance(value, dict):
        return {str(k): _convert(v, strict, (*path, k)) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        if value.ndim == 1 and value.dtype.kind == "f":
            return _float_list(value, strict, path)
        return _convert(value.tolist(), strict, path)
    if isinstance(value, list | tuple):
        return [_convert(v, strict, (*path, i)) for i, v in enumerate(value)]
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        x = float(value)
        return x if math.isfinite(x) else _non_finite(x, strict, path)
    if strict and not (value is None or isinstance(value, str)):
        raise TypeError(f"{_where(path)}{type(value).__name__} is not JSON-able")
    return value


def _float_list(values: np.ndarray, strict: bool, path: _Path) -> list[float | None]:
    """A 1-D float array `[N]` as a list, element for element as `_convert` (vectorised)."""
    out: list[float | None] = values.tolist()
    for i in np.flatnonzero(~np.isfinite(values)).tolist():
        out[i] = _non_finite(float(values[i]), strict, (*path, i))
    return out


def _non_finite(x: float, strict: bool, path: _Path) -> None:
    """None for the non-finite `x`, or with `strict` a ValueError naming `path`."""
    if strict:
        number = "NaN" if math.isnan(x) else "Infinity" if x > 0 else "-Infinity"
        raise ValueError(f"{_where(path)}{number} is not a finite number (JSON has none; a "
                         f"number beyond the float range is one)")
    return None


def _where(path: _Path) -> str:
    return f"at {''.join(f'[{k!r}]' for k in path)}: " if path else ""


def parse_json(text: str | bytes, what: str = "profile") -> Any:
    """`json.loads(text)`; a ValueError saying `what` is not valid JSON otherwise."""
    try:
        return json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError) as exc:
        raise ValueError(f"{what} is not valid JSON: {exc}") from None
