"""A mergeable table of (labelled logit, distance, outcome) counts: what a per-class score
calibrator is fit on when its data arrive in parts (the streamed and Dask fits).

A detection is counted in two grids, each cell keeping its count and the sums of its logits
`z` and distances:

- by logit: its class, outcome (true positive or not) and `z` on a grid of `Z_WIDTH`
  logits. Calibrators of the logit alone (temperatures, Platt, isotonic, histogram binning)
  are fit on these cells.
- by range: its class, outcome, `z` on the coarser `RANGE_Z_WIDTH` and its distance on
  `D_WIDTH` metres: what a calibrator with a range term (`platt_range`) is fit on.

Both grids have a bounded number of cells per class whatever the number of detections
(logit span / width, times distance span / `D_WIDTH` for the second), so the table's size
does not grow with the data. Tables of disjoint parts add (`+`), in any order and grouping,
to the table of the whole. `rows(by_range)` gives one weighted row per cell at its mean `z`
and mean distance; a calibrator fit on them with `sample_weight` is the exact fit of data
whose logits moved by less than a cell's width to their cell's mean (the linear terms of the
logistic likelihoods, Σ y·z and Σ y·d per class and outcome, stay exact).

A fit small enough to hold its rows (`exact=True`) keeps them instead: `rows()` then gives
every detection as it is, unweighted, and a calibrator fit on them is the in-memory fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.core.checks import as_float_array, as_int_array, check_length

#: The logit grid of the by-logit cells.
Z_WIDTH = 1.0 / 1024.0
#: The logit and distance grids of the by-range cells (a range term varies slowly in both).
RANGE_Z_WIDTH = 1.0 / 16.0
D_WIDTH = 2.0
#: A fit of at most this many detections keeps them all (an exact table, 28 bytes each).
EXACT_ROWS = 1 << 20

_Z_HALF = 1 << 30   # logit cells in [-2^30, 2^30): |z| beyond a grid's reach shares an end cell
_D_CELLS = 1 << 16  # distance cells: beyond them shares the last one
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
class _Cells:
    """One grid's occupied cells: `keys [K]` (int64, ascending, unique), `count [K]`,
    `sum_z [K]`, `sum_d [K]` (float64)."""

    keys: np.ndarray
    count: np.ndarray
    sum_z: np.ndarray
    sum_d: np.ndarray

    @classmethod
    def build(cls, z: np.ndarray, labels: np.ndarray, hit: np.ndarray, d: np.ndarray,
              z_width: float, d_width: float | None) -> _Cells:
        zi = np.clip(np.floor(z / z_width), -_Z_HALF, _Z_HALF - 1).astype(np.int64) + _Z_HALF
        di = (np.zeros(z.size, dtype=np.int64) if d_width is None else
              np.clip(np.floor(d / d_width), 0, _D_CELLS - 1).astype(np.int64))
        keys = ((labels.astype(np.int64) * (2 * _Z_HALF) + zi) * _D_CELLS + di) * 2 + hit
        return cls.aggregate(keys, np.ones(z.size), z, d)

    @classmethod
    def aggregate(cls, keys: np.ndarray, count: np.ndarray, sum_z: np.ndarray,
                  sum_d: np.ndarray) -> _Cells:
        unique, inverse = np.unique(keys, return_inverse=True)
        inverse = inverse.reshape(-1)
        size = unique.size
        return cls(unique, np.bincount(inverse, weights=count, minlength=size),
                   np.bincount(inverse, weights=sum_z, minlength=size),
                   np.bincount(inverse, weights=sum_d, minlength=size))

    def __add__(self, other: _Cells) -> _Cells:
        if not other.keys.size:
            return self
        if not self.keys.size:
            return other
        return self.aggregate(*(np.concatenate([getattr(self, f), getattr(other, f)])
                                for f in ("keys", "count", "sum_z", "sum_d")))

    def rows(self) -> ScoreRows:
        labels = self.keys // (2 * _D_CELLS * 2 * _Z_HALF)
        return ScoreRows(self.sum_z / self.count, labels.astype(np.int64),
                         (self.keys & 1).astype(bool), self.sum_d / self.count,
                         self.count.copy())


_NO_CELLS = _Cells(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros(0))


@dataclass(frozen=True)
class ScoreTable:
    """The counts of detections of `n_classes` classes in the two grids of the module
    docstring (`by_logit`, `by_range`), or, exact, the rows themselves (`rows_`)."""

    n_classes: int
    by_logit: _Cells | None
    by_range: _Cells | None
    rows_: ScoreRows | None = None

    @property
    def exact(self) -> bool:
        """Whether the table holds its rows as they are."""
        return self.rows_ is not None

    @classmethod
    def empty(cls, n_classes: int, exact: bool = False) -> ScoreTable:
        """The table of no detections."""
        if exact:
            zero = np.zeros(0)
            return cls(int(n_classes), None, None, ScoreRows(
                zero, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), zero, None))
        return cls(int(n_classes), _NO_CELLS, _NO_CELLS)

    @classmethod
    def build(cls, z: np.ndarray, labels: np.ndarray, hit: np.ndarray,
              distances: np.ndarray, n_classes: int, exact: bool = False) -> ScoreTable:
        """The table of detections with labelled logits `z [N]` (finite), classes
        `labels [N]` in [0, n_classes), outcomes `hit [N]` (bool or 0/1) and distances
        `distances [N]` (m, >= 0); `exact`: keep the rows themselves."""
        if not 0 < n_classes <= _MAX_CLASSES:
            raise ValueError(f"n_classes must be in [1, {_MAX_CLASSES}], got {n_classes}")
        x = as_float_array("z", z, ndim=1)
        y = as_int_array("labels", labels).astype(np.int64)
        d = as_float_array("distances", distances, ndim=1)
        t = np.asarray(hit).astype(bool).reshape(-1)
        for name, arr in (("labels", y), ("distances", d), ("hit", t)):
            check_length(name, arr, x.shape[0], "z")
        if exact:
            return cls(int(n_classes), None, None, ScoreRows(x, y, t, d, None))
        if not x.size:
            return cls.empty(n_classes)
        return cls(int(n_classes), _Cells.build(x, y, t, d, Z_WIDTH, None),
                   _Cells.build(x, y, t, d, RANGE_Z_WIDTH, D_WIDTH))

    def __add__(self, other: ScoreTable) -> ScoreTable:
        if self.n_classes != other.n_classes or self.exact != other.exact:
            raise ValueError(f"cannot add score tables of {self.n_classes} and "
                             f"{other.n_classes} classes, exact {self.exact} and "
                             f"{other.exact}")
        if self.rows_ is not None and other.rows_ is not None:
            a, b = self.rows_, other.rows_
            return ScoreTable(self.n_classes, None, None, ScoreRows(
                *(np.concatenate([getattr(a, f), getattr(b, f)])
                  for f in ("z", "labels", "hit", "distances")), None))
        assert self.by_logit is not None and other.by_logit is not None
        assert self.by_range is not None and other.by_range is not None
        return ScoreTable(self.n_classes, self.by_logit + other.by_logit,
                          self.by_range + other.by_range)

    @property
    def n(self) -> int:
        """The detections counted."""
        if self.rows_ is not None:
            return int(self.rows_.z.size)
        assert self.by_logit is not None
        return int(self.by_logit.count.sum())

    def rows(self, by_range: bool = False) -> ScoreRows:
        """One weighted row per cell of the by-logit grid, or of the by-range grid for a
        calibrator with a range term (`ScoreRows`, ordered by class, logit cell, distance
        cell and outcome); an exact table's rows as they are (no weights)."""
        if self.rows_ is not None:
            return self.rows_
        cells = self.by_range if by_range else self.by_logit
        assert cells is not None
        return cells.rows()
