"""Per-class Platt scaling: `p = sigmoid(a_c·z + b_c [+ g_c·d])` on the labelled logit.

`(a_c, b_c[, g_c])` minimise the binary NLL of "is a true positive" plus a light ridge
`l2/2 · ((a - 1)² + b² + g²)` towards the identity (so separable data keeps finite
parameters), by Newton's method on internally standardised columns (2 or 3 parameters).
`a_c >= min_slope > 0` is a bound, so the ranking within a class never changes; with
`range_term=True` the distance `d` (m) enters linearly and is the only thing that may
re-rank detections of one class. Classes with too few detections take the pooled fit.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.special import expit

from calibrators.core.errors import FieldError
from calibrators.scores._calibrator import ClasswiseCalibrator
from calibrators.scores._logistic import fit_logistic


class PlattScaler(ClasswiseCalibrator):
    """Per-class logistic calibration of the logit (module docstring).

    Parameters
    ----------
    range_term : add `g_c · d`; then `fit` and `transform` need `distances`.
    l2 : ridge weight (>= 0) on `(a - 1, b, g)`, against the summed (not mean) NLL.
    min_slope : lower bound of `a_c` (> 0).
    min_samples, min_each : fallback rule of `ClasswiseCalibrator` (pooled fit).

    Fitted: `coef_ [C, 3]` rows `(a, b, g)` (g = 0 without a range term), `pooled_coef_ [3]`.
    """

    method = "platt"
    _param_size = 3
    _param_text = "[a, b, g] with a > 0"
    _hyper = ("range_term", "min_samples", "min_each", "l2", "min_slope", "shrink")

    def __init__(self, range_term: bool = False, min_samples: int = 50, min_each: int = 5,
                 l2: float = 1.0, min_slope: float = 1e-6, shrink: float = 0.0) -> None:
        self.shrink = shrink
        self.range_term = range_term
        self.min_samples = min_samples
        self.min_each = min_each
        self.l2 = l2
        self.min_slope = min_slope

    @property
    def method_name(self) -> str:
        return "platt_range" if self.range_term else "platt"

    def _needs_distances(self) -> bool:
        return bool(self.range_term)

    def _check_hyper(self) -> None:
        if not isinstance(self.range_term, bool | np.bool_):
            raise FieldError("range_term", "range_term must be true or false, got "
                                           f"{self.range_term!r}")
        if not (isinstance(self.l2, numbers.Real) and 0.0 <= float(self.l2) < np.inf):
            raise FieldError("l2", f"l2 must be a finite number >= 0, got {self.l2!r}")
        if not (isinstance(self.min_slope, numbers.Real) and 0.0 < float(self.min_slope) < 1):
            raise FieldError("min_slope", "min_slope must be a number in (0, 1), got "
                                          f"{self.min_slope!r}")

    def _fit_one(self, z: np.ndarray, hit: np.ndarray, d: np.ndarray | None,
                 w: np.ndarray | None) -> np.ndarray:
        cols = [z, np.ones_like(z)] + ([d] if self.range_term else [])
        coef = np.zeros(3)
        coef[:len(cols)] = fit_logistic(cols, hit, float(self.l2), float(self.min_slope), w)
        return coef

    def _apply(self, params: np.ndarray, z: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        eta = params[0] * z + params[1]
        if self.range_term:
            eta = eta + params[2] * d
        return expit(eta)

    def _derive(self) -> None:
        self.coef_ = np.stack(self.params_)
        self.pooled_coef_ = self.pooled_params_
