"""Per-class histogram binning: equal-mass bins of the labelled logit, smoothed frequency.

In each class the logits are cut into `n_bins` bins of about equal count (a tie is never
split, so a bin may hold more); each bin's frequency of true positives is smoothed by a
Beta(α, β) prior, `(tp + α) / (n + α + β)`, projected onto non-decreasing sequences
(weighted isotonic regression over the bins) and served like isotonic knots: a knot at each
bin's mean logit, linear in between, with the strictly increasing tie-breaker of
`_knots.serve`, so the ranking within a class never changes.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.optimize import isotonic_regression

from calibrators.core.bins import check_n_bins
from calibrators.core.errors import FieldError
from calibrators.scores._knots import KnotCalibrator, monotone_knots


class HistogramBinning(KnotCalibrator):
    """Per-class histogram binning (module docstring); serving as `IsotonicCalibrator`.

    Parameters
    ----------
    n_bins : equal-mass bins per class (>= 1).
    prior : (α, β) > 0 of the Beta prior on each bin's frequency; (1, 1) is Laplace's rule.
    min_samples, min_each, eps, tie_break : as `IsotonicCalibrator`.

    Fitted: `knots_` (list [C] of `[2, K <= n_bins]` arrays: logit, frequency).
    """

    method = "histogram"
    _hyper = ("min_samples", "min_each", "n_bins", "prior", "eps", "tie_break",
              "shrink")

    def __init__(self, min_samples: int = 50, min_each: int = 5, n_bins: int = 15,
                 prior: tuple[float, float] = (1.0, 1.0), eps: float = 1e-3,
                 tie_break: float = 1e-6, shrink: float = 0.0) -> None:
        self.shrink = shrink
        self.min_samples = min_samples
        self.min_each = min_each
        self.n_bins = n_bins
        self.prior = prior
        self.eps = eps
        self.tie_break = tie_break

    def _check_hyper(self) -> None:
        check_n_bins("n_bins", self.n_bins, minimum=1)
        _check_prior(self.prior)
        super()._check_hyper()

    def _fit_one(self, z: np.ndarray, hit: np.ndarray, d: np.ndarray | None,
                 w: np.ndarray | None) -> np.ndarray:
        n_bins = int(self.n_bins)
        alpha, beta = (float(v) for v in self.prior)
        if w is None:
            order = np.sort(z)
            edges = np.unique(order[(np.arange(1, n_bins) * order.size) // n_bins])
        else:   # the same rule on the cumulative weight: unit weights give the edges above
            order = np.argsort(z, kind="stable")
            cum = np.cumsum(w[order])
            at = np.searchsorted(cum, np.arange(1, n_bins) * cum[-1] / n_bins, side="right")
            edges = np.unique(z[order[np.minimum(at, z.size - 1)]])
        idx = np.searchsorted(edges, z, side="right")
        count = np.bincount(idx, weights=w, minlength=edges.size + 1)
        pos = np.bincount(idx, weights=hit if w is None else hit * w, minlength=edges.size + 1)
        z_sum = np.bincount(idx, weights=z if w is None else z * w, minlength=edges.size + 1)
        used = count > 0
        count, pos, z_sum = count[used].astype(np.float64), pos[used], z_sum[used]
        freq = (pos + alpha) / (count + alpha + beta)
        mono = isotonic_regression(freq, weights=count, increasing=True).x
        return monotone_knots(z_sum / count, np.clip(mono, 0.0, 1.0), count, n_bins)


def _check_prior(prior: object) -> None:
    try:
        alpha, beta = prior  # type: ignore[misc]
    except (TypeError, ValueError):
        raise FieldError("prior", f"prior must be a pair (alpha, beta), got {prior!r}") from None
    for v in (alpha, beta):
        if not (isinstance(v, numbers.Real) and 0.0 < float(v) < np.inf):
            raise FieldError("prior", f"prior must hold two finite numbers > 0, got {prior!r}")
