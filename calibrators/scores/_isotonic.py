"""Per-class isotonic regression of "is a true positive" on the labelled logit.

`scipy.optimize.isotonic_regression` (scipy >= 1.12) fits the non-decreasing step function
closest in squared error to the outcomes; its blocks become knots at their mean logit (at
most `max_knots` per class, adjacent blocks merged by equal mass) and are served by linear
interpolation with a strictly increasing tie-breaker (`_knots.serve`), so the ranking within
a class never changes.
"""

from __future__ import annotations

import numpy as np

from calibrators.core.bins import check_n_bins
from calibrators.scores._knots import KnotCalibrator, isotonic_knots


class IsotonicCalibrator(KnotCalibrator):
    """Per-class isotonic calibration of the labelled logit `z [N]` (module docstring).

    Parameters
    ----------
    min_samples, min_each : fallback rule of `ClasswiseCalibrator` (pooled isotonic fit).
    max_knots : knots kept per class (>= 2).
    eps : served probabilities are clipped to [eps, 1 - eps] before the tie-breaker.
    tie_break : weight `δ` of the strictly increasing `sigmoid(z)` term (0 < δ <= 1e-3).

    Fitted: `knots_` (list [C] of `[2, K]` arrays: logit, frequency) besides the base ones.
    """

    method = "isotonic"
    _hyper = ("min_samples", "min_each", "max_knots", "eps", "tie_break", "shrink")

    def __init__(self, min_samples: int = 50, min_each: int = 5, max_knots: int = 200,
                 eps: float = 1e-3, tie_break: float = 1e-6, shrink: float = 0.0) -> None:
        self.shrink = shrink
        self.min_samples = min_samples
        self.min_each = min_each
        self.max_knots = max_knots
        self.eps = eps
        self.tie_break = tie_break

    def _check_hyper(self) -> None:
        check_n_bins("max_knots", self.max_knots, minimum=2)
        super()._check_hyper()

    def _fit_one(self, z: np.ndarray, hit: np.ndarray, d: np.ndarray | None,
                 w: np.ndarray | None) -> np.ndarray:
        return isotonic_knots(z, hit.astype(np.float64), int(self.max_knots), w)
