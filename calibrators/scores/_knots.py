"""Knot tables of monotone step calibrators (isotonic, histogram) and how they are served.

A knot table is `[2, K]` float64: increasing knot positions `x` (logits, strictly) and
non-decreasing frequencies `y` in [0, 1]. It is served as

    p(z) = (1 - δ) · clip(interp(z; x, y), eps, 1 - eps) + δ · sigmoid(z),

linear between knots and flat beyond the ends, with a tiny `δ` (`tie_break`): flat stretches
of `interp` would give tied scores, and ties re-rank detections and can lower mAP. The
`sigmoid(z)` term makes `p` strictly increasing in `z` (wherever float64 resolves
`sigmoid`, |z| < ~36) and keeps `p` in (0, 1).
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.optimize import isotonic_regression
from scipy.special import expit

from calibrators.core.errors import FieldError
from calibrators.scores._calibrator import ClasswiseCalibrator


class KnotCalibrator(ClasswiseCalibrator):
    """A `ClasswiseCalibrator` whose per-class parameters are a knot table `[2, K]`, served
    by `serve` with the hyper-parameters `eps` and `tie_break`; fitted `knots_` (list [C])."""

    _param_ndim = 2
    eps: float
    tie_break: float

    def _check_hyper(self) -> None:
        if not (isinstance(self.eps, numbers.Real) and 0.0 < float(self.eps) < 0.5):
            raise FieldError("eps", f"eps must be a number in (0, 0.5), got {self.eps!r}")
        if not (isinstance(self.tie_break, numbers.Real) and 0.0 < float(self.tie_break) <= 1e-3):
            raise FieldError("tie_break", "tie_break must be a number in (0, 1e-3], got "
                                          f"{self.tie_break!r}")

    def _apply(self, params: np.ndarray, z: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        return serve(params, z, float(self.eps), float(self.tie_break))

    def _param_array(self, name: str, value: object) -> np.ndarray:
        arr = super()._param_array(name, value)
        check_knot_table(name, arr)
        return arr

    def _derive(self) -> None:
        self.knots_ = self.params_


def serve(knots: np.ndarray, z: np.ndarray, eps: float, tie_break: float) -> np.ndarray:
    """Calibrated probabilities `[N]` of logits `z [N]` under `knots [2, K]` (docstring)."""
    p = np.clip(np.interp(z, knots[0], knots[1]), eps, 1.0 - eps)
    return (1.0 - tie_break) * p + tie_break * expit(z)


def isotonic_knots(z: np.ndarray, hit: np.ndarray, max_knots: int,
                   weight: np.ndarray | None = None) -> np.ndarray:
    """Knots `[2, K <= max_knots]` of the isotonic regression of `hit [N]` on `z [N]` (rows
    weighted by `weight [N]` > 0 when given).

    Equal logits are pooled first (so a block boundary never splits a tie), then each
    isotonic block becomes one knot at its mean logit (`compact`).
    """
    ux, inverse, counts = np.unique(z, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    if weight is not None:
        counts = np.bincount(inverse, weights=weight, minlength=ux.size)
        hit = hit * weight
    mean_hit = np.bincount(inverse, weights=hit, minlength=ux.size) / counts
    fit = isotonic_regression(mean_hit, weights=counts.astype(np.float64), increasing=True)
    return monotone_knots(ux, fit.x, counts, max_knots)


def monotone_knots(x: np.ndarray, y: np.ndarray, weight: np.ndarray, max_knots: int
                   ) -> np.ndarray:
    """Knots from points `x [M]` (strictly increasing) with non-decreasing `y [M]` and
    weights `[M]` > 0: runs of equal `y` become one knot at their weighted mean `x`, then
    `compact` keeps at most `max_knots`."""
    start = np.flatnonzero(np.r_[True, y[1:] != y[:-1]])
    w = np.add.reduceat(weight.astype(np.float64), start)
    bx = np.add.reduceat(weight * x, start) / w
    return compact(bx, y[start], w, max_knots)


def compact(x: np.ndarray, y: np.ndarray, weight: np.ndarray, max_knots: int) -> np.ndarray:
    """At most `max_knots` knots `[2, K]`: adjacent points are merged into groups of about
    equal weight, each group a knot at its weighted mean `x` and `y`. Weighted means of
    contiguous groups keep `x` strictly increasing and `y` non-decreasing."""
    if x.size > max_knots:
        before = np.cumsum(weight) - weight
        group = np.floor(before / weight.sum() * max_knots).astype(np.int64)
        start = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        w = np.add.reduceat(weight, start)
        x = np.add.reduceat(weight * x, start) / w
        y = np.minimum(np.add.reduceat(weight * y, start) / w, 1.0)
        y = np.maximum.accumulate(y)  # rounding of the means must not break monotonicity
    return np.stack([x, y]).astype(np.float64)


def check_knot_table(name: str, knots: np.ndarray) -> None:
    """Raise unless `knots` is `[2, K]` with strictly increasing x and non-decreasing y in
    [0, 1] (what `serve` assumes)."""
    if knots.shape[0] != 2:
        raise ValueError(f"{name} must have shape [2, K], got {knots.shape}")
    x, y = knots
    if (np.diff(x) <= 0).any() or (np.diff(y) < 0).any() or (y < 0).any() or (y > 1).any():
        raise ValueError(f"{name} must have increasing x and non-decreasing y in [0, 1]")
