"""Validation and binning helpers shared by the metrics, plus the JSON view of result objects."""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any

import numpy as np

from calibrators.core.checks import as_float_array, check_length, check_probabilities
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable


def check_n_bins(name: str, value: object, minimum: int = 1) -> int:
    """Return `value` as an int >= `minimum`, or raise a ValueError naming `name`."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if int(value) < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {int(value)}")
    return int(value)


def check_nonempty(name: str, arr: np.ndarray) -> None:
    """Raise unless `arr` has at least one row."""
    if arr.shape[0] == 0:
        raise ValueError(f"{name} is empty")


def as_binary(name: str, value: object, n: int, other: str) -> np.ndarray:
    """`[N]` bool from bools or 0/1 numbers; raise naming `name` for anything else."""
    arr = np.asarray(value)
    if arr.ndim != 1:
        raise ValueError(f"{name} must have 1 dimensions, got shape {arr.shape}")
    check_length(name, arr, n, other)
    if arr.dtype == bool:
        return arr
    arr = as_float_array(name, arr, ndim=1)
    bad = (arr != 0.0) & (arr != 1.0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{name} must be 0/1 or bool; entry {i} is {arr[i]}")
    return arr == 1.0


def confidences_and_correct(confidences: object, correct: object
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Validated `confidences [N]` in [0, 1] (N >= 1) and `correct [N]` bool."""
    conf = as_float_array("confidences", confidences, ndim=1)
    check_nonempty("confidences", conf)
    check_probabilities("confidences", conf)
    hit = as_binary("correct", correct, conf.shape[0], "confidences")
    return conf, hit


def bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Index `[N]` of the equal-width bin of each value: `[e_m, e_{m+1})`, last bin closed.

    Values below the first edge go to bin 0, above the last edge to the last bin.
    """
    idx = np.searchsorted(edges, values, side="right") - 1
    return np.clip(idx, 0, len(edges) - 2)


def calibration_bins(conf: np.ndarray, hit: np.ndarray, n_bins: int,
                     weight: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Equal-width bins on [0, 1]: edges `[M+1]`, count `[M]`, sum of conf `[M]`, sum of hits
    (each row counted `weight [N]` times when given: the counts are then weighted sums)."""
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    idx = bin_index(conf, edges)
    h = hit.astype(np.float64)
    if weight is not None:
        conf, h = conf * weight, h * weight
    count = np.bincount(idx, weights=weight, minlength=n_bins)
    conf_sum = np.bincount(idx, weights=conf, minlength=n_bins)
    hit_sum = np.bincount(idx, weights=h, minlength=n_bins)
    return edges, count, conf_sum, hit_sum


def check_weights(weight: object, n: int, other: str = "confidences") -> np.ndarray:
    """Row weights `[n]` (as many as `other`): finite float64 >= 0 with a positive sum;
    FieldError naming `sample_weight` otherwise."""
    w = as_float_array("sample_weight", weight, ndim=1)
    check_length("sample_weight", w, n, other)
    if (w < 0).any() or not w.sum() > 0:
        raise FieldError("sample_weight", "sample_weight must be >= 0 with a positive sum")
    return w


class ResultMixin:
    """`to_dict()` for the frozen result dataclasses: JSON-able, NaN becomes None."""

    def to_dict(self) -> dict[str, Any]:
        return {f.name: to_jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}
