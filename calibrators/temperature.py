"""Temperature scaling: one `T > 0` for all classes, fit on classification NLL.

`p = sigmoid(z / T)` (sigmoid mode) or `p = softmax(z / T)` (softmax mode). `T` is found by
bounded Brent (`scipy.optimize.minimize_scalar(method="bounded")`) on `log T`, in float64
whatever the input dtype. Dividing every logit by the same positive `T` is monotone, so the
arg-max (the detection's label) never changes.

Labels:
- sigmoid: `labels [N]` in {0, 1}, 1 if the detection is a true positive of its predicted
  (arg-max) class; only that class's logit enters the NLL.
- softmax: `labels [N]` in [0, C], the target column of `logits [N, C + 1]` (C = no-object).

Speed, with the result unchanged (tests check both against the exact minimiser to 1e-6
for T in [0.3, 5] and logit scales 0.3 to 30):
- sigmoid: the NLL depends on the predicted logits `s [N]` only. With more than
  `_SIGMOID_BINS` detections, `s` is binned once on a uniform grid and Brent runs on the
  bins' counts, means and spreads (`SigmoidBins`, error third order in the bin width),
  first in a narrow bracket around the optimum of 64x coarser bins (microseconds per
  evaluation), so the fine bins are evaluated about 8 times.
- softmax: every evaluation needs all `N x C'` logits. With at least `_SUBSAMPLE_MIN` rows,
  a seeded subsample is fit first and Brent on the full data searches only a bracket around
  it: `_BRACKET_WIDTH` in log T, widened in proportion to the subsample's standard error
  of log T where the data say little about T (small logits, large T: that case used to
  miss the bracket and search the full bounds, ~45 evaluations).
- either: the NLL is unimodal in log T (convex in 1/T), so an optimum inside the bracket is
  the optimum; one at an inner edge is searched again on a bracket five times as wide on
  that side (`search_log_t`), never on the full bounds.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from calibrators.checks import (
    as_float_array,
    as_int_array,
    check_choice,
    check_index,
    check_length,
)
from calibrators.exceptions import check_fitted
from calibrators.scores import class_probabilities
from calibrators.temperature_nll import (
    SIGMOID_BINS,
    Objective,
    SigmoidBins,
    row_max,
    sigmoid_nll,
    softmax_nll,
)
from calibrators.vocab import SCORE_MODES

_SIGMOID_BINS = SIGMOID_BINS  # sigmoid: bins of the predicted logit when N exceeds this
_SUBSAMPLE_MIN = 200_000  # softmax: from this many rows on, a subsample brackets T first
_SUBSAMPLE_ROWS = 50_000  # rows of that subsample (at least; N / 20 if larger)
_SUBSAMPLE_XTOL = 1e-4  # Brent tolerance on log T of the subsample fit
_BRACKET_WIDTH = 0.1  # in log T: the full-data search covers T_sub · exp(-0.038 .. +0.062)
_BRACKET_SE = 0.0125  # standard error of log T_sub that _BRACKET_WIDTH covers (8 times)
_GOLDEN = (3.0 - 5.0**0.5) / 2.0  # where bounded Brent places its first point in a bracket


class TemperatureScaler:
    """Fit one temperature `T` on `logits [N, C']` and labels `[N]`; see the module docstring.

    Parameters
    ----------
    mode : "sigmoid" or "softmax" (the detector's score mode).
    bounds : (low, high) search interval for `T`, both > 0; Brent runs on `log T`.
    xtol : absolute tolerance of Brent on `log T` (so a relative tolerance on `T`).

    Attributes set by `fit`: `temperature_` (float), `n_samples_` (int), `n_columns_` (C'),
    `nll_` (exact mean NLL at `temperature_`), `nll_before_` (exact mean NLL at T = 1;
    both to 1e-12 relative),
    `n_evaluations_` (objective evaluations of the final Brent search(es)).
    """

    def __init__(self, mode: str = "sigmoid", bounds: tuple[float, float] = (0.01, 100.0),
                 xtol: float = 1e-7) -> None:
        self.mode = mode
        self.bounds = bounds
        self.xtol = xtol

    def fit(self, logits: np.ndarray, labels: np.ndarray) -> TemperatureScaler:
        """Fit `T` on `logits [N, C']` (any float dtype) and `labels [N]`; returns self."""
        check_choice("mode", self.mode, SCORE_MODES)
        bounds = self._log_bounds()
        z, y = _validate(logits, labels, self.mode)
        exact, search, bracket = _search_plan(z, y, self.mode, bounds)
        log_t, nll = self._search(search, bracket, bounds)
        self.nll_ = nll if search is exact else float(exact(log_t))
        self.nll_before_ = float(exact(0.0))
        self.n_samples_ = int(z.shape[0])
        self.n_columns_ = int(np.shape(logits)[1])
        return self

    def fit_objective(self, objective: Objective, n_samples: int, n_columns: int,
                      bracket: Callable[[tuple[float, float]], tuple[float, float]] | None = None
                      ) -> TemperatureScaler:
        """Fit `T` by minimising `objective` (the mean NLL as a function of `log T`, e.g.
        merged from chunks of a dataset too large for memory: `SigmoidBins.objective()`, or
        one pass over the data per call), searching first `bracket(log bounds)` when given,
        exactly as `fit` searches its own objective. `nll_` and `nll_before_` are the
        objective's values. Returns self."""
        check_choice("mode", self.mode, SCORE_MODES)
        bounds = self._log_bounds()
        first = bounds if bracket is None else bracket(bounds)
        log_t, nll = self._search(objective, first, bounds)
        self.nll_, self.nll_before_ = nll, float(objective(0.0))
        self.n_samples_, self.n_columns_ = int(n_samples), int(n_columns)
        return self

    def _log_bounds(self) -> tuple[float, float]:
        low, high = _check_bounds(self.bounds)
        return float(np.log(low)), float(np.log(high))

    def _search(self, objective: Objective, bracket: tuple[float, float],
                bounds: tuple[float, float]) -> tuple[float, float]:
        """Set `temperature_`, `n_evaluations_`; warn at the edge; returns (log T, NLL)."""
        xtol = float(self.xtol)
        log_t, nll, self.n_evaluations_ = search_log_t(objective, bracket, bounds, xtol)
        if min(log_t - bounds[0], bounds[1] - log_t) < 10 * xtol:
            low, high = _check_bounds(self.bounds)
            warnings.warn(f"temperature {np.exp(log_t):.6g} is at the edge of bounds "
                          f"{(low, high)}; widen bounds or check the labels", RuntimeWarning,
                          stacklevel=3)
        self.temperature_ = float(np.exp(log_t))
        return log_t, nll

    def transform(self, logits: np.ndarray) -> np.ndarray:
        """Object-class probabilities `[N, C]` of `logits [N, C']` at the fitted temperature."""
        check_fitted(self, "temperature_")
        z = as_float_array("logits", logits, ndim=2)
        if z.shape[1] != self.n_columns_:
            raise ValueError(f"logits has {z.shape[1]} columns but the scaler was fit on "
                             f"{self.n_columns_}")
        return class_probabilities(z, self.mode, self.temperature_)

    def fit_transform(self, logits: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """`fit(logits, labels).transform(logits)`."""
        return self.fit(logits, labels).transform(logits)


def _check_bounds(bounds: tuple[float, float]) -> tuple[float, float]:
    try:
        low, high = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise ValueError(f"bounds must be a pair of numbers, got {bounds!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and 0 < low < high):
        raise ValueError(f"bounds must satisfy 0 < low < high (finite), got {bounds!r}")
    return low, high


def _validate(logits: np.ndarray, labels: np.ndarray, mode: str
              ) -> tuple[np.ndarray, np.ndarray]:
    """Float64 logits `[N, C']` and int64 labels `[N]`, checked for the score mode."""
    z = as_float_array("logits", logits, ndim=2)
    if z.shape[0] == 0:
        raise ValueError("logits is empty: need at least one detection to fit a temperature")
    min_cols = 2 if mode == "softmax" else 1
    if z.shape[1] < min_cols:
        raise ValueError(f"logits must have at least {min_cols} column(s) in {mode} mode, "
                         f"got shape {z.shape}")
    y = as_int_array("labels", labels)
    check_length("labels", y, z.shape[0], "logits")
    if mode == "sigmoid":
        check_index("labels", y, 2, "values (sigmoid labels are 0/1)")
    else:
        check_index("labels", y, z.shape[1], "logit columns (softmax labels are 0..C)")
    return z, y


def _search_plan(z: np.ndarray, y: np.ndarray, mode: str, bounds: tuple[float, float]
                 ) -> tuple[Objective, Objective, tuple[float, float]]:
    """(reported NLL, objective for Brent, first bracket on log T) for `z [N, C']`, `y [N]`.

    The reported NLL is exact (sigmoid bins: exact to 1e-12 relative, from the bins where
    their error bound allows, else from the data).

    sigmoid: above `_SIGMOID_BINS` rows the binned NLL, searched first around the optimum of
    its coarsened bins (`SigmoidBins.bracket`); softmax: the exact NLL, searched first around
    a subsample's T from `_SUBSAMPLE_MIN` rows.
    """
    if mode == "sigmoid":
        s = row_max(z)
        exact = sigmoid_nll(s, y)
        if len(s) <= _SIGMOID_BINS:
            return exact, exact, bounds
        bins = SigmoidBins.from_logits(s, y)
        binned = bins.objective()

        def reported(log_t: float) -> float:
            """The binned NLL where its error bound is below 1e-12 of it, else the exact."""
            value = binned(log_t)
            return value if bins.error_bound(log_t) <= 1e-12 * abs(value) else exact(log_t)

        return reported, binned, bins.bracket(bounds)
    exact = softmax_nll(z, y)
    return exact, exact, (_softmax_bracket(z, y, bounds) if len(z) >= _SUBSAMPLE_MIN
                          else bounds)


def search_log_t(objective: Objective, bracket: tuple[float, float],
                 bounds: tuple[float, float], xtol: float) -> tuple[float, float, int]:
    """Bounded Brent on `log T` in `bracket`, then, while the optimum sits at an end of the
    bracket that is not an end of `bounds`, again on a bracket five times as wide on that
    side (the NLL is unimodal in log T, so the optimum lies beyond that end).
    Returns (argmin, minimum, number of evaluations)."""
    log_t, nll, n_evaluations = _brent(objective, bracket, xtol)
    while bracket != bounds and _at_inner_edge(log_t, bracket, bounds, xtol):
        width = bracket[1] - bracket[0]
        if log_t - bracket[0] < 10 * xtol:
            bracket = (max(bounds[0], bracket[0] - 4 * width), bracket[0] + width)
        else:
            bracket = (bracket[1] - width, min(bounds[1], bracket[1] + 4 * width))
        log_t, nll, extra = _brent(objective, bracket, xtol)
        n_evaluations += extra
    return log_t, nll, n_evaluations


def _brent(objective: Objective, bracket: tuple[float, float], xtol: float
           ) -> tuple[float, float, int]:
    """Bounded Brent on `log T` in `bracket`: (argmin, minimum, number of evaluations)."""
    result = minimize_scalar(objective, bounds=bracket, method="bounded",
                             options={"xatol": xtol})
    return float(result.x), float(result.fun), int(result.nfev)


def _at_inner_edge(x: float, bracket: tuple[float, float], bounds: tuple[float, float],
                   xtol: float) -> bool:
    """Whether `x` lies at an end of `bracket` that is not also an end of `bounds`."""
    return ((x - bracket[0] < 10 * xtol and bracket[0] > bounds[0])
            or (bracket[1] - x < 10 * xtol and bracket[1] < bounds[1]))


def subsample_rows(n: int, size: int | None = None) -> np.ndarray:
    """Sorted row indices of the softmax subsample among `n` rows: `size` rows (default
    `max(_SUBSAMPLE_ROWS, n // 20)`) drawn with replacement by a fixed seed (a fit is
    reproducible, and a streamed fit draws the same rows)."""
    size = max(_SUBSAMPLE_ROWS, n // 20) if size is None else int(size)
    return np.sort(np.random.default_rng(0).integers(0, n, size))


def subsample_bracket(objective: Objective, n_rows: int, bounds: tuple[float, float]
                      ) -> tuple[float, float]:
    """A bracket on log T (within `bounds`) around `T_sub`, the optimum of `objective`, the
    softmax NLL of `n_rows` subsampled rows (`_subsample_fit`, `_bracket_around`)."""
    return _bracket_around(*_subsample_fit(objective, n_rows, bounds, bounds), bounds)


def _subsample_fit(objective: Objective, n_rows: int, bracket: tuple[float, float],
                   bounds: tuple[float, float]) -> tuple[float, float]:
    """`(log T_sub, its standard error)`: the optimum of a subsample's NLL, searched from
    `bracket` to `_SUBSAMPLE_XTOL`, and the Fisher standard error `1 / sqrt(n_rows · NLL'')`
    from the NLL's curvature there."""
    centre, value, _ = search_log_t(objective, bracket, bounds, _SUBSAMPLE_XTOL)
    step = 1e-2
    curvature = (objective(centre + step) - 2.0 * value + objective(centre - step)) / step**2
    return centre, float(1.0 / np.sqrt(n_rows * max(curvature, 1e-12)))


def _bracket_around(centre: float, se: float, bounds: tuple[float, float]
                    ) -> tuple[float, float]:
    """A bracket of `_BRACKET_WIDTH` in log T, widened in proportion where the standard error
    `se` of `centre` exceeds `_BRACKET_SE` (weakly informative data: small logits, large T),
    with `centre` where bounded Brent takes its first point (the lower golden section), so
    the search starts next to the optimum."""
    width = _BRACKET_WIDTH * max(1.0, se / _BRACKET_SE)
    return (max(bounds[0], centre - _GOLDEN * width),
            min(bounds[1], centre + (1.0 - _GOLDEN) * width))


def _softmax_bracket(z: np.ndarray, y: np.ndarray, bounds: tuple[float, float]
                     ) -> tuple[float, float]:
    """The first bracket of the full-data softmax search: around the seeded subsample's
    `T_sub` (`subsample_bracket`)."""
    rows = subsample_rows(len(z))
    return subsample_bracket(softmax_nll(z[rows], y[rows]), len(rows), bounds)

# The objectives under their historical names (the tests and benchmarks use them).
_row_max = row_max
_sigmoid_nll_1d = sigmoid_nll
_softmax_nll = softmax_nll


def _sigmoid_nll(z: np.ndarray, y: np.ndarray) -> Objective:
    """Exact mean binary NLL of the predicted class of `z [N, C]`, labels `y [N]` 0/1, as a
    function of `log T` (see `calibrators.temperature_nll.sigmoid_nll`)."""
    return sigmoid_nll(row_max(z), y)


def _binned_sigmoid_nll(s: np.ndarray, y: np.ndarray, n_bins: int = SIGMOID_BINS
                        ) -> Objective:
    """`sigmoid_nll(s, y)` from `n_bins` bins of `s [N]` (`SigmoidBins`)."""
    return SigmoidBins.from_logits(s, y, n_bins).objective()
