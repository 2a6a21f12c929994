"""Temperature scaling: one `T > 0` for all classes, fit on classification NLL.

`p = sigmoid(z / T)` (sigmoid mode) or `p = softmax(z / T)` (softmax mode), in float64
whatever the input dtype. The optimiser is Brent's method: Brent's root finder
(`scipy.optimize.brentq`, `search_root`) on `d NLL / d log T` for softmax and for binned
sigmoid logits, bounded Brent minimisation (`minimize_scalar(method="bounded")`,
`search_log_t`) on the NLL for small sigmoid fits and `fit_objective`. The NLL is convex in
`1/T`, so its derivative in log T changes sign once; the derivative stays well resolved
where the NLL is too flat for a minimiser (small logits: float64 cancellation in the mean).
Dividing every logit by the same positive `T` is monotone: the arg-max never changes.

Labels:
- sigmoid: `labels [N]` in {0, 1}, 1 if the detection is a true positive of its predicted
  (arg-max) class; only that class's logit enters the NLL.
- softmax: `labels [N]` in [0, C], the target column of `logits [N, C + 1]` (C = no-object).

Speed, with the result unchanged (tests check both against the exact minimiser to 1e-6
for T in [0.3, 5] and logit scales 0.3 to 30):
- sigmoid: the NLL depends on the predicted logits `s [N]` only. With more than
  `SIGMOID_BINS` detections, `s` is binned once (`SigmoidBins`, error fourth order in the
  bin width); the root is found first on 64x coarser bins, then on bins as coarse as the
  derivative's error bound allows there (`fit_bins`).
- softmax: each evaluation is one cache-blocked pass over the `N x C'` logits giving the
  NLL and its derivative (`SoftmaxSums`). From `SUBSAMPLE_MIN` rows a seeded subsample's
  root and curvature (`subsample_start`) give the first bracket: that point and 1.5 Newton
  steps from it; a bracket without a sign change moves to the root's side, four times as
  wide (never blindly to the bounds). About five passes in all.
- validation reads nothing twice: float64 logits are not copied; their finiteness is
  checked by the pass that reads them anyway, with the errors of `calibrators.core.checks`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from calibrators.core.bins import check_n_bins
from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_bounds,
    check_choice,
    check_finite,
    check_fitted,
    check_index,
    check_length,
    check_positive,
)
from calibrators.core.json_safe import to_jsonable
from calibrators.core.vocab import SCORE_MODES
from calibrators.scores._calibrator import dict_key, unfitted
from calibrators.scores._probabilities import class_probabilities
from calibrators.scores._temperature_nll import (
    SIGMOID_BINS,
    Objective,
    SigmoidBins,
    ValueGrad,
    row_max,
    sigmoid_nll,
    softmax_value_grad,
)
from calibrators.scores._temperature_search import search_log_t

SUBSAMPLE_MIN = 200_000  # softmax: from this many rows on, a subsample brackets T first
_SUBSAMPLE_ROWS = 50_000  # rows of that subsample (at least; N / 20 if larger)
_SUBSAMPLE_XTOL = 1e-4  # Brent tolerance on log T of the subsample fit
_TINY_STEP = 10  # the subsample's own start: every 10th of its rows, searched from the bounds
_NEWTON_MARGIN = 1.5  # first bracket: the start and 1.5 Newton steps from it
_COARSEN = 64  # sigmoid: the first search runs on bins this many times as wide
_COARSE_XTOL = 1e-3  # Brent tolerance on log T of that first search
_ROOT_SHARE = 0.1  # sigmoid: the bins' error may move the root by this much of xtol at most
_NLL_RTOL = 1e-9  # sigmoid: the reported NLL is the bins' where their error is below this
_FITTED = ("temperature", "n_samples", "n_columns", "nll", "n_evaluations")  # of `to_dict`


class TemperatureScaler:
    """Fit one temperature `T` on `logits [N, C']` and labels `[N]`; see the module docstring.

    Parameters
    ----------
    mode : "sigmoid" or "softmax" (the detector's score mode).
    bounds : (low, high) search interval for `T`, both > 0; Brent runs on `log T`.
    xtol : absolute tolerance of Brent on `log T` (so a relative tolerance on `T`).

    Attributes set by `fit`: `temperature_` (float), `n_samples_` (int), `n_columns_` (C'),
    `nll_` (mean NLL at `temperature_`: exact, or from the sigmoid bins where their error
    bound is below 1e-9 of it), `n_evaluations_` (objective evaluations of the final
    search, each a pass over the data).
    """

    def __init__(self, mode: str = "sigmoid", bounds: tuple[float, float] = (0.01, 100.0),
                 xtol: float = 1e-7) -> None:
        self.mode = mode
        self.bounds = bounds
        self.xtol = xtol

    def fit(self, logits: np.ndarray, labels: np.ndarray) -> TemperatureScaler:
        """Fit `T` on `logits [N, C']` (any float dtype) and `labels [N]`; returns self."""
        check_choice("mode", self.mode, SCORE_MODES)
        bounds = self.log_bounds()
        z, y = _validate(logits, labels, self.mode)
        if self.mode == "softmax":
            start = None
            if len(z) >= SUBSAMPLE_MIN:
                rows = subsample_rows(len(z))
                z_sub = z[rows]
                if not np.isfinite(z_sub).all():
                    check_finite("logits", z)
                start = subsample_start(z_sub, y[rows], bounds)
            return self.fit_gradient(softmax_value_grad(z, y), len(z), z.shape[1], start)
        s, span = _predicted(z)
        if len(s) > SIGMOID_BINS:
            bins = SigmoidBins.from_logits(s, y, span=span, clip=False)   # span: s's own

            def exact(log_t: float) -> float:   # built only if the bins are not exact enough
                return sigmoid_nll(s, y)(log_t)

            return self.fit_bins(bins, z.shape[1], exact)
        log_t, self.nll_ = self._search(sigmoid_nll(s, y), bounds, bounds)
        self.n_samples_, self.n_columns_ = int(z.shape[0]), int(z.shape[1])
        return self

    def fit_bins(self, bins: SigmoidBins, n_columns: int, exact: Objective | None = None
                 ) -> TemperatureScaler:
        """Fit `T` (sigmoid) on the binned predicted logits `bins` (in memory, or summed over
        the parts of a dataset): Brent's root finder on the binned `d NLL / d log T`, first
        on bins `_COARSEN` times as wide from the bounds (to `_COARSE_XTOL`), then from there
        on the bins coarsened as far as the derivative's error bound allows
        (`_fine_factor`). `nll_` is the bins' NLL where its error bound is below
        `_NLL_RTOL` of it, else `exact(log T)` when given. Returns self."""
        check_choice("mode", self.mode, SCORE_MODES)
        bounds, xtol = self.log_bounds(), float(self.xtol)
        factor = _COARSEN if len(bins.count) % _COARSEN == 0 else 1
        coarse = search_root(bins.coarsen(factor).value_grad(), bounds, _COARSE_XTOL)
        factor = _fine_factor(bins, coarse, xtol)
        fine = bins.coarsen(factor) if factor > 1 else bins
        found = search_root(fine.value_grad(), bounds, xtol, (coarse.log_t, coarse.curvature))
        self._set_temperature(found.log_t, found.n_evaluations, bounds)
        nll = found.nll
        if fine.error_bound(found.log_t) > _NLL_RTOL * abs(nll) and factor > 1:
            nll = bins.value_grad()(found.log_t)[0]
        if bins.error_bound(found.log_t) > _NLL_RTOL * abs(nll) and exact is not None:
            nll = exact(found.log_t)
        self.nll_ = float(nll)
        self.n_samples_, self.n_columns_ = int(bins.n), int(n_columns)
        return self

    def fit_gradient(self, value_grad: ValueGrad, n_samples: int, n_columns: int,
                     start: tuple[float, float] | None = None) -> TemperatureScaler:
        """Fit `T` as the root of `d NLL / d log T` (`value_grad`: `log T -> (mean NLL, its
        derivative)`, e.g. summed over the parts of a dataset too large for memory) by
        Brent's root finder (`search_root`), from `start = (log T_0, NLL'' there)` (a
        subsample's optimum and curvature, `subsample_start`) or from the bounds. Returns
        self."""
        check_choice("mode", self.mode, SCORE_MODES)
        bounds = self.log_bounds()
        found = search_root(value_grad, bounds, float(self.xtol), start)
        self._set_temperature(found.log_t, found.n_evaluations, bounds)
        self.nll_ = found.nll
        self.n_samples_, self.n_columns_ = int(n_samples), int(n_columns)
        return self

    def fit_objective(self, objective: Objective, n_samples: int, n_columns: int,
                      bracket: Callable[[tuple[float, float]], tuple[float, float]] | None = None
                      ) -> TemperatureScaler:
        """Fit `T` by minimising `objective` (the mean NLL as a function of `log T`, e.g.
        merged from chunks of a dataset too large for memory: `SigmoidBins.objective()`, or
        one pass over the data per call), searching first `bracket(log bounds)` when given,
        by bounded Brent (`search_log_t`). `nll_` is the objective's value. Returns self."""
        check_choice("mode", self.mode, SCORE_MODES)
        bounds = self.log_bounds()
        first = bounds if bracket is None else bracket(bounds)
        log_t, nll = self._search(objective, first, bounds)
        self.nll_ = nll
        self.n_samples_, self.n_columns_ = int(n_samples), int(n_columns)
        return self

    def log_bounds(self) -> tuple[float, float]:
        """The search bounds on log T (checked)."""
        low, high = check_bounds(self.bounds)
        return float(np.log(low)), float(np.log(high))

    def _search(self, objective: Objective, bracket: tuple[float, float],
                bounds: tuple[float, float]) -> tuple[float, float]:
        """Set `temperature_`, `n_evaluations_`; warn at the edge; returns (log T, NLL)."""
        log_t, nll, n_evaluations = search_log_t(objective, bracket, bounds, float(self.xtol))
        self._set_temperature(log_t, n_evaluations, bounds)
        return log_t, nll

    def _set_temperature(self, log_t: float, n_evaluations: int,
                         bounds: tuple[float, float]) -> None:
        """Set `temperature_`, `n_evaluations_`; warn when `log_t` is at the edge of bounds."""
        if min(log_t - bounds[0], bounds[1] - log_t) < 10 * float(self.xtol):
            low, high = check_bounds(self.bounds)
            warnings.warn(f"temperature {np.exp(log_t):.6g} is at the edge of bounds "
                          f"{(low, high)}; widen bounds or check the labels", RuntimeWarning,
                          stacklevel=4)
        self.temperature_ = float(np.exp(log_t))
        self.n_evaluations_ = int(n_evaluations)

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

    def to_dict(self) -> dict:
        """Strict-JSON-able plain dict; `from_dict(to_dict())` transforms identically."""
        check_fitted(self, "temperature_")
        hyper = {"mode": self.mode, "bounds": self.bounds, "xtol": self.xtol}
        return to_jsonable({"method": "temperature", "hyper": hyper,
                            **{key: getattr(self, f"{key}_") for key in _FITTED}})

    @classmethod
    def from_dict(cls, data: dict) -> TemperatureScaler:
        """The fitted scaler `to_dict` wrote; ValueError naming a missing or bad key."""
        self = unfitted(cls, data, "temperature scaler")
        got = {key: dict_key(data, key, "temperature scaler") for key in ("method", *_FITTED)}
        check_choice("method", got["method"], ("temperature",))
        check_choice("mode", self.mode, SCORE_MODES)
        self.temperature_ = check_positive("temperature", got["temperature"])
        for key in ("n_samples", "n_columns", "n_evaluations"):
            setattr(self, f"{key}_", check_n_bins(key, got[key], minimum=0))
        self.nll_ = float("nan") if got["nll"] is None else float(got["nll"])
        return self


def _validate(logits: np.ndarray, labels: np.ndarray, mode: str
              ) -> tuple[np.ndarray, np.ndarray]:
    """C-contiguous float64 logits `[N, C']` and int64 labels `[N]`, checked for the score
    mode. Float64 logits are not copied, and their finiteness is left to the one pass that
    reads them anyway (sigmoid: the predicted logits' range; softmax: the search's first
    pass); the errors are those of `calibrators.core.checks`."""
    if isinstance(logits, np.ndarray) and logits.dtype == np.float64 and logits.ndim == 2:
        z = np.ascontiguousarray(logits)
        if mode == "sigmoid" and z.shape[1] > 1:
            check_finite("logits", z)
    else:
        z = np.ascontiguousarray(as_float_array("logits", logits, ndim=2))
    if z.shape[0] == 0:
        raise ValueError("logits is empty: need at least one detection to fit a temperature")
    min_cols = 2 if mode == "softmax" else 1
    if z.shape[1] < min_cols:
        raise ValueError(f"logits must have at least {min_cols} column(s) in {mode} mode, "
                         f"got shape {z.shape}")
    if isinstance(labels, np.ndarray) and labels.dtype == np.int64 and labels.ndim == 1:
        y = labels
    else:
        y = as_int_array("labels", labels)
    check_length("labels", y, z.shape[0], "logits")
    upper = 2 if mode == "sigmoid" else z.shape[1]
    if int(y.min()) < 0 or int(y.max()) >= upper:
        check_index("labels", y, upper, "values (sigmoid labels are 0/1)" if mode == "sigmoid"
                    else "logit columns (softmax labels are 0..C)")
    return z, y


def _predicted(z: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """The predicted logits `s [N]` of `z [N, C]` (sigmoid) and their range, which also
    checks that `s` is finite (`z` with more columns was checked by `_validate`)."""
    s = row_max(z)
    span = (float(s.min()), float(s.max()))
    if not (np.isfinite(span[0]) and np.isfinite(span[1])):
        check_finite("logits", z)
    return s, span


def _fine_factor(bins: SigmoidBins, coarse: Root, xtol: float) -> int:
    """The widest coarsening of `bins` (a power of 2 up to `_COARSEN`) whose bound on the
    derivative's error, divided by the NLL's curvature, moves the root by at most
    `_ROOT_SHARE · xtol` within 10 % below the coarse search's T; 1 when that search ended
    at a bound."""
    if not (np.isfinite(coarse.curvature) and coarse.curvature > 0):
        return 1
    allowed = _ROOT_SHARE * xtol * coarse.curvature / bins.gradient_bound(coarse.log_t - 0.1)
    factor = _COARSEN
    while factor > 1 and (len(bins.count) % factor or factor**4 > allowed):
        factor //= 2
    return factor


@dataclass(frozen=True)
class Root:
    """The result of `search_root`: `log_t`, the mean NLL there, the number of
    evaluations, and `curvature`, `d² NLL / d(log T)²` from the last bracket (NaN when the
    optimum is at a bound)."""

    log_t: float
    nll: float
    n_evaluations: int
    curvature: float


def search_root(value_grad: ValueGrad, bounds: tuple[float, float], xtol: float,
                start: tuple[float, float] | None = None) -> Root:
    """Brent's root finder (`scipy.optimize.brentq`) on `d NLL / d log T` to `xtol` in log T.

    The NLL is convex in `1/T`, so its derivative in log T changes sign once, from - to +.
    The first bracket: `bounds` without `start`; with `start = (u0, c)` (a guess of log T
    and of the curvature there), `u0` and the Newton step from it, lengthened by
    `_NEWTON_MARGIN`. A bracket without a sign change is moved to the side of the root,
    four times as wide, until it has one (or the root is a bound, then returned). Every
    point is evaluated once (value and derivative in one call)."""
    memo: dict[float, tuple[float, float]] = {}

    def grad(u: float) -> float:
        if u not in memo:
            memo[u] = value_grad(u)
        return memo[u][1]

    lo, hi = _first_bracket(grad, bounds, xtol, start)
    while not (grad(lo) <= 0.0 <= grad(hi)):
        width = hi - lo
        if grad(lo) > 0.0:    # NLL rising at lo: the optimum lies below
            if lo <= bounds[0]:
                hi = lo
                break
            lo, hi = max(bounds[0], lo - 4.0 * width), lo
        elif grad(hi) < 0.0:  # NLL falling at hi: the optimum lies above
            if hi >= bounds[1]:
                lo = hi
                break
            lo, hi = hi, min(bounds[1], hi + 4.0 * width)
        else:
            raise ValueError("the NLL's derivative is not finite")
    root = lo if lo == hi else float(brentq(grad, lo, hi, xtol=xtol))
    nll = memo[root][0] if root in memo else value_grad(root)[0]
    return Root(root, float(nll), len(memo), _curvature(memo, root))


def _first_bracket(grad: Callable[[float], float], bounds: tuple[float, float], xtol: float,
                   start: tuple[float, float] | None) -> tuple[float, float]:
    """`bounds`, or `start`'s guess and its Newton step lengthened by `_NEWTON_MARGIN`
    (at least `xtol`), within `bounds`."""
    if start is None or not (np.isfinite(start[1]) and start[1] > 0):
        return bounds
    u0 = min(max(float(start[0]), bounds[0]), bounds[1])
    step = -grad(u0) / float(start[1]) * _NEWTON_MARGIN
    step = float(np.copysign(max(abs(step), xtol), step))
    other = min(max(u0 + step, bounds[0]), bounds[1])
    return (u0, other) if other > u0 else (other, u0) if other < u0 else bounds


def _curvature(memo: dict[float, tuple[float, float]], root: float) -> float:
    """Slope of the derivative between the evaluated points nearest `root` on either side
    of it (NaN unless there is one on each side)."""
    below = [u for u in memo if u < root]
    above = [u for u in memo if u > root]
    if not below or not above:
        return float("nan")
    lo, hi = max(below), min(above)
    return (memo[hi][1] - memo[lo][1]) / (hi - lo)


def subsample_rows(n: int, size: int | None = None) -> np.ndarray:
    """Sorted row indices of the softmax subsample among `n` rows: `size` rows (default
    `max(_SUBSAMPLE_ROWS, n // 20)`) drawn with replacement by a fixed seed (a fit is
    reproducible, and a streamed fit draws the same rows)."""
    size = max(_SUBSAMPLE_ROWS, n // 20) if size is None else int(size)
    return np.sort(np.random.default_rng(0).integers(0, n, size))


def subsample_start(z_sub: np.ndarray, y_sub: np.ndarray, bounds: tuple[float, float]
                    ) -> tuple[float, float]:
    """`(log T, curvature)` of the softmax NLL of subsampled rows `z_sub [M, C']`, `y_sub [M]`
    (`subsample_rows`): the full-data search's start. Found on every `_TINY_STEP`-th row
    from the bounds (to 1e-3), then on all `M` from there (to `_SUBSAMPLE_XTOL`)."""
    z_sub = np.ascontiguousarray(z_sub, dtype=np.float64)
    tiny = search_root(softmax_value_grad(np.ascontiguousarray(z_sub[::_TINY_STEP]),
                                          y_sub[::_TINY_STEP]), bounds, 1e-3)
    sub = search_root(softmax_value_grad(z_sub, y_sub), bounds, _SUBSAMPLE_XTOL,
                      (tiny.log_t, tiny.curvature))
    return sub.log_t, sub.curvature
