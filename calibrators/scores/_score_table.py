"""A mergeable table of (labelled logit, distance, outcome) counts: what a per-class score
calibrator is fit on when its data arrive in parts (the streamed and Dask fits).

Each detection falls in a cell keyed by its class, its logit `z` on a grid of `Z_WIDTH`
logits, its distance on a grid of `D_WIDTH` metres and its outcome (true positive or not);
a cell keeps its count and the sums of its `z` and distances. Tables of disjoint parts of the
data add (`+`), in any order and grouping, to the table of the whole. `rows()` gives one
weighted row per cell at the cell's mean `z` and mean distance, and a calibrator fit on those
rows with `sample_weight` is the fit of the data with every logit moved by less than
`Z_WIDTH` (and every distance by less than `D_WIDTH`) to its cell's mean; the linear terms of
the logistic likelihoods (Σ y·z, Σ y·d per class and outcome) stay exact.

The table's size is bounded by the occupied cells, not by the detections: at most
classes × (logit span / Z_WIDTH) × distance cells × 2. A fit small enough to hold its rows
(`exact=True`) keeps them instead: `rows()` then gives every detection as it is, unweighted,
and a calibrator fit on them is the in-memory fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.core.checks import as_float_array, as_int_array, check_length

#: The logit grid of a cell (1/256: served probabilities move by < 0.001 across a cell).
Z_WIDTH = 1.0 / 256.0
#: The distance grid of a cell, metres.
D_WIDTH = 1.0
#: A fit of at most this many detections keeps them all (an exact table, 28 bytes each).
EXACT_ROWS = 1 << 20

_Z_HALF = 1 << 30   # logit cells in [-2^30, 2^30): |z| beyond ~4e6 shares an end cell
_D_CELLS = 1 << 16  # distance cells: beyond 65 km shares the last one
_MAX_CLASSES = 1 << 14


@dataclass(frozen=True)
class ScoreRows:
    """One weighted row per occupied cell: mean logit `z [K]`, class `labels [K]`, outcome
    `hit [K]` (bool), mean distance `distances [K]` (m) and `weight [K]` (its count; None
    for an exact table's rows, one detection each)."""

    z: np.ndarray
    labels: np.ndarray
    hit: np.ndarray
    distances: np.ndarray
    weight: np.ndarray | None


@dataclass(frozen=True)
class ScoreTable:
    """Cells `keys [K]` (int64, ascending, unique) with their `count [K]`, `sum_z [K]` and
    `sum_d [K]` (float64), for `n_classes` classes (module docstring). An exact table has no
    `keys`: its `sum_z`, `sum_d` are the rows' own logits and distances, `labels [K]` and
    `hit [K]` their classes and outcomes, in the order added."""

    n_classes: int
    keys: np.ndarray | None
    count: np.ndarray
    sum_z: np.ndarray
    sum_d: np.ndarray
    labels: np.ndarray | None = None
    hit: np.ndarray | None = None

    @property
    def exact(self) -> bool:
        """Whether the table holds its rows as they are."""
        return self.keys is None

    @classmethod
    def empty(cls, n_classes: int, exact: bool = False) -> ScoreTable:
        """The table of no detections."""
        zero = np.zeros(0)
        if exact:
            return cls(int(n_classes), None, zero, zero, zero, np.zeros(0, dtype=np.int64),
                       np.zeros(0, dtype=bool))
        return cls(int(n_classes), np.zeros(0, dtype=np.int64), zero, zero, zero)

    @classmethod
    def build(cls, z: np.ndarray, labels: np.ndarray, hit: np.ndarray,
              distances: np.ndarray, n_classes: int, exact: bool = False) -> ScoreTable:
        """The table of detections with labelled logits `z [N]` (finite), classes
        `labels [N]` in [0, n_classes), outcomes `hit [N]` (bool or 0/1) and distances
        `distances [N]` (m, >= 0); `exact`: keep the rows themselves."""
        if not 0 < n_classes <= _MAX_CLASSES:
            raise ValueError(f"n_classes must be in [1, {_MAX_CLASSES}], got {n_classes}")
        x = as_float_array("z", z, ndim=1)
        y = as_int_array("labels", labels)
        d = as_float_array("distances", distances, ndim=1)
        t = np.asarray(hit).astype(bool).reshape(-1)
        for name, arr in (("labels", y), ("distances", d), ("hit", t)):
            check_length(name, arr, x.shape[0], "z")
        if exact:
            return cls(int(n_classes), None, np.ones(x.size), x, d, y.astype(np.int64), t)
        if not x.size:
            return cls.empty(n_classes)
        zi = np.clip(np.floor(x / Z_WIDTH), -_Z_HALF, _Z_HALF - 1).astype(np.int64) + _Z_HALF
        di = np.clip(np.floor(d / D_WIDTH), 0, _D_CELLS - 1).astype(np.int64)
        keys = ((y.astype(np.int64) * (2 * _Z_HALF) + zi) * _D_CELLS + di) * 2 + t
        return cls._aggregate(int(n_classes), keys, np.ones(x.size), x, d)

    def __add__(self, other: ScoreTable) -> ScoreTable:
        if self.n_classes != other.n_classes or self.exact != other.exact:
            raise ValueError(f"cannot add score tables of {self.n_classes} and "
                             f"{other.n_classes} classes, exact {self.exact} and "
                             f"{other.exact}")
        if not other.count.size:
            return self
        if not self.count.size:
            return other
        if self.exact:
            return ScoreTable(self.n_classes, None, *(
                np.concatenate([getattr(self, f), getattr(other, f)])
                for f in ("count", "sum_z", "sum_d", "labels", "hit")))
        return self._aggregate(self.n_classes, np.concatenate([self.keys, other.keys]),
                               np.concatenate([self.count, other.count]),
                               np.concatenate([self.sum_z, other.sum_z]),
                               np.concatenate([self.sum_d, other.sum_d]))

    @property
    def n(self) -> int:
        """The detections counted."""
        return int(self.count.sum())

    def rows(self) -> ScoreRows:
        """One weighted row per cell (`ScoreRows`), ordered by class, logit cell, distance
        cell and outcome; an exact table's rows as they are (no weights)."""
        if self.exact:
            return ScoreRows(self.sum_z, self.labels, self.hit, self.sum_d, None)
        hit = (self.keys & 1).astype(bool)
        labels = self.keys // (2 * _D_CELLS * 2 * _Z_HALF)
        return ScoreRows(self.sum_z / self.count, labels.astype(np.int64), hit,
                         self.sum_d / self.count, self.count.copy())

    @classmethod
    def _aggregate(cls, n_classes: int, keys: np.ndarray, count: np.ndarray,
                   sum_z: np.ndarray, sum_d: np.ndarray) -> ScoreTable:
        unique, inverse = np.unique(keys, return_inverse=True)
        inverse = inverse.reshape(-1)
        size = unique.size
        return cls(n_classes, unique,
                   np.bincount(inverse, weights=count, minlength=size),
                   np.bincount(inverse, weights=sum_z, minlength=size),
                   np.bincount(inverse, weights=sum_d, minlength=size))
