"""Temperature scaling: one `T > 0` for all classes, fit on classification NLL.

`p = sigmoid(z / T)` (sigmoid mode) or `p = softmax(z / T)` (softmax mode). `T` is found by
bounded Brent (`scipy.optimize.minimize_scalar(method="bounded")`) on `log T`, in float64
whatever the input dtype. Dividing every logit by the same positive `T` is monotone, so the
arg-max (the detection's label) never changes.

Labels:
- sigmoid: `labels [N]` in {0, 1}, 1 if the detection is a true positive of its predicted
  (arg-max) class; only that class's logit enters the NLL.
- softmax: `labels [N]` in [0, C], the target column of `logits [N, C + 1]` (C = no-object).

Speed, with the result unchanged (tests check both against the exact minimiser to 1e-6):
- sigmoid: the NLL depends on the predicted logits `s [N]` only. With more than
  `_SIGMOID_BINS` detections, `s` is binned once on a uniform grid and Brent runs on the
  bins' counts, means and spreads (`_binned_sigmoid_nll`, error third order in the bin
  width).
- softmax: every evaluation needs all `N x C'` logits. With at least `_SUBSAMPLE_MIN` rows,
  a seeded subsample is fit first and Brent on the full data searches only a bracket of
  `_BRACKET_WIDTH` in log T around it; the NLL is unimodal in log T (convex in 1/T), so an
  optimum inside that bracket is the optimum, and one at its edge is searched again on the
  full bounds.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import expit

from calibrators.checks import (
    as_float_array,
    as_int_array,
    check_choice,
    check_index,
    check_length,
)
from calibrators.exceptions import check_fitted
from calibrators.scores import class_probabilities
from calibrators.vocab import SCORE_MODES

Objective = Callable[[float], float]

_SIGMOID_BINS = 1 << 16  # sigmoid: bins of the predicted logit when N exceeds this
_SUBSAMPLE_MIN = 200_000  # softmax: from this many rows on, a subsample brackets T first
_SUBSAMPLE_ROWS = 50_000  # rows of that subsample (at least; N / 20 if larger)
_SUBSAMPLE_XTOL = 1e-4  # Brent tolerance on log T of the subsample fit
_BRACKET_WIDTH = 0.1  # in log T: the full-data search covers T_sub · exp(-0.038 .. +0.062)
_GOLDEN = (3.0 - 5.0**0.5) / 2.0  # where bounded Brent places its first point in a bracket


class TemperatureScaler:
    """Fit one temperature `T` on `logits [N, C']` and labels `[N]`; see the module docstring.

    Parameters
    ----------
    mode : "sigmoid" or "softmax" (the detector's score mode).
    bounds : (low, high) search interval for `T`, both > 0; Brent runs on `log T`.
    xtol : absolute tolerance of Brent on `log T` (so a relative tolerance on `T`).

    Attributes set by `fit`: `temperature_` (float), `n_samples_` (int), `n_columns_` (C'),
    `nll_` (exact mean NLL at `temperature_`), `nll_before_` (exact mean NLL at T = 1),
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
        low, high = _check_bounds(self.bounds)
        xtol = float(self.xtol)
        z, y = _validate(logits, labels, self.mode)
        bounds = (float(np.log(low)), float(np.log(high)))
        exact, search, bracket = _search_plan(z, y, self.mode, bounds)
        log_t, nll, n_evaluations = _brent(search, bracket, xtol)
        if bracket != bounds and _at_inner_edge(log_t, bracket, bounds, xtol):
            log_t, nll, extra = _brent(search, bounds, xtol)
            n_evaluations += extra
        if min(log_t - bounds[0], bounds[1] - log_t) < 10 * xtol:
            warnings.warn(f"temperature {np.exp(log_t):.6g} is at the edge of bounds "
                          f"{(low, high)}; widen bounds or check the labels", RuntimeWarning,
                          stacklevel=2)
        self.temperature_ = float(np.exp(log_t))
        self.nll_ = nll if search is exact else float(exact(log_t))
        self.nll_before_ = float(exact(0.0))
        self.n_evaluations_ = n_evaluations
        self.n_samples_ = int(z.shape[0])
        self.n_columns_ = int(np.shape(logits)[1])
        return self

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
    """(exact NLL, objective for Brent, first bracket on log T) for `z [N, C']`, `y [N]`.

    sigmoid: the binned NLL above `_SIGMOID_BINS` rows, searched on the full `bounds`;
    softmax: the exact NLL, searched first around a subsample's T from `_SUBSAMPLE_MIN` rows.
    """
    if mode == "sigmoid":
        s = _row_max(z)
        exact = _sigmoid_nll_1d(s, y)
        return exact, (_binned_sigmoid_nll(s, y) if len(s) > _SIGMOID_BINS else exact), bounds
    exact = _softmax_nll(z, y)
    return exact, exact, (_subsample_bracket(z, y, bounds) if len(z) >= _SUBSAMPLE_MIN
                          else bounds)


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


def _subsample_bracket(z: np.ndarray, y: np.ndarray, bounds: tuple[float, float]
                       ) -> tuple[float, float]:
    """A `_BRACKET_WIDTH` bracket on log T (within `bounds`) around `T_sub`, fit on seeded rows.

    z: [N, C'] float64 logits, y: [N] target columns. The rows are drawn with replacement
    by a fixed seed (so a fit is reproducible) and sorted (for memory locality). `log T_sub`
    is put where bounded Brent takes its first point (the lower golden section), so the
    search starts next to the optimum (about one evaluation fewer than a centred bracket).
    """
    n = z.shape[0]
    rows = np.sort(np.random.default_rng(0).integers(0, n, max(_SUBSAMPLE_ROWS, n // 20)))
    centre, _, _ = _brent(_softmax_nll(z[rows], y[rows]), bounds, _SUBSAMPLE_XTOL)
    return (max(bounds[0], centre - _GOLDEN * _BRACKET_WIDTH),
            min(bounds[1], centre + (1.0 - _GOLDEN) * _BRACKET_WIDTH))


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """`a [M] · b [M]` by numpy's own loop: a BLAS dot may start threads, which on a busy
    machine costs milliseconds per call."""
    return float(np.einsum("i,i->", a, b))


_CHUNK_FLOATS = 1 << 16  # 512 KiB of float64 per work buffer: stays in the CPU cache


def _chunks(n: int, width: int) -> list[slice]:
    """Row slices covering `range(n)` whose `[rows, width]` blocks fit the cache budget."""
    rows = max(256, _CHUNK_FLOATS // max(width, 1))
    return [slice(i, min(i + rows, n)) for i in range(0, n, rows)]


def _row_max(z: np.ndarray) -> np.ndarray:
    """`z.max(axis=1)` for `[N, C']`, as column-wise maxima over cache-sized row blocks
    (several times faster than numpy's reduction over short rows)."""
    out = np.empty(z.shape[0])
    for sl in _chunks(z.shape[0], z.shape[1]):
        block, m = z[sl], out[sl]
        np.copyto(m, block[:, 0])
        for j in range(1, z.shape[1]):
            np.maximum(m, block[:, j], out=m)
    return out


def _sigmoid_nll(z: np.ndarray, y: np.ndarray) -> Objective:
    """Exact mean binary NLL of the predicted class of `z [N, C]`, labels `y [N]` 0/1, as a
    function of `log T` (see `_sigmoid_nll_1d`)."""
    return _sigmoid_nll_1d(_row_max(z), y)


def _sigmoid_nll_1d(s: np.ndarray, y: np.ndarray) -> Objective:
    """Exact mean binary NLL of the predicted logits `s [N]`, labels `y [N]`, vs `log T`.

    `-log p(y | s/T) = softplus(s/T) - y·s/T`, where `softplus(x) = max(x, 0) +
    log1p(exp(-|x|))` is `np.logaddexp(0, x)` written out (stable for any x, and several
    times faster). `mean(y·s)` is taken once; each evaluation then runs over `s` in
    cache-sized chunks with two small buffers.
    """
    n = len(s)
    mean_ys = _dot(y.astype(np.float64), s) / n
    chunks = _chunks(n, 1)
    x_buf, t_buf = np.empty(chunks[0].stop), np.empty(chunks[0].stop)

    def nll(log_t: float) -> float:
        inv_t = float(np.exp(-log_t))
        total = 0.0
        for sl in chunks:
            x, tail = x_buf[:sl.stop - sl.start], t_buf[:sl.stop - sl.start]
            np.multiply(s[sl], inv_t, out=x)
            np.abs(x, out=tail)
            np.negative(tail, out=tail)
            np.exp(tail, out=tail)
            np.log1p(tail, out=tail)
            np.maximum(x, 0.0, out=x)
            total += float(x.sum()) + float(tail.sum())
        return total / n - mean_ys * inv_t

    return nll


def _binned_sigmoid_nll(s: np.ndarray, y: np.ndarray, n_bins: int = _SIGMOID_BINS
                        ) -> Objective:
    """`_sigmoid_nll_1d(s, y)` from sufficient statistics: O(n_bins) per evaluation.

    The linear term `mean(y·s)/T` is exact. For the softplus term, `s [N]` is binned once on
    `n_bins` equal bins of width `h` over `[min s, max s]`; a bin of `m` logits with mean `s̄`
    and squared deviations `M2 = Σ (s - s̄)²` stands for its second-order Taylor sum about
    `s̄`, `m·softplus(x) + M2/(2T²)·σ(x)(1 - σ(x))` with `x = s̄/T` (the first-order terms
    cancel about the mean). The third derivative of softplus is below 0.1 in magnitude, so
    the mean NLL is off by at most `(h/T)³ / 48`, about 1e-14 for logits spanning 30 at
    T = 1; the tests check that the minimiser is the exact one to 1e-6 even for heavy-tailed
    logits.
    """
    n = len(s)
    mean_ys = _dot(y.astype(np.float64), s) / n
    low, span = float(s.min()), float(s.max() - s.min())
    width = span / n_bins if span > 0 else 1.0
    pos = (s - low) / width  # in [0, n_bins]: integer part = bin, the rest = place in the bin
    idx = pos.astype(np.intp)
    np.minimum(idx, n_bins - 1, out=idx)
    pos -= idx  # offset from the bin's left edge, in bin widths
    count = np.bincount(idx, minlength=n_bins)
    offset = np.bincount(idx, weights=pos, minlength=n_bins)
    offset_sq = np.bincount(idx, weights=pos * pos, minlength=n_bins)
    used = count > 0
    m, offset, offset_sq = count[used].astype(np.float64), offset[used], offset_sq[used]
    mean_offset = offset / m
    centre = low + (np.flatnonzero(used) + mean_offset) * width
    half_m2 = 0.5 * np.maximum(offset_sq - m * mean_offset**2, 0.0) * width**2 / n
    weight = m / n

    def nll(log_t: float) -> float:
        inv_t = float(np.exp(-log_t))
        x = centre * inv_t
        curvature = expit(x) * expit(-x) * inv_t**2
        return (_dot(weight, np.logaddexp(0.0, x)) + _dot(half_m2, curvature)
                - mean_ys * inv_t)

    return nll


def _softmax_nll(z: np.ndarray, y: np.ndarray) -> Objective:
    """Mean categorical NLL `mean(logsumexp(z/T) - z_y/T)` as a function of `log T`.

    Rows are shifted by their maximum `m` once (`z - m <= 0`); since `T > 0`,
    `logsumexp(z/T) = m/T + log(sum(exp((z - m)/T)))`, which never overflows. Each
    evaluation scales and exponentiates cache-sized blocks of rows in one small buffer and
    sums each row with a matrix-vector product.
    """
    n, width = z.shape
    shifted = z - _row_max(z)[:, None]
    mean_shift_target = float(shifted[np.arange(n), y].mean())
    chunks = _chunks(n, width)
    buf = np.empty((chunks[0].stop, width))
    row_sums = np.empty(n)
    ones = np.ones(width)

    def nll(log_t: float) -> float:
        inv_t = float(np.exp(-log_t))
        for sl in chunks:
            block = buf[:sl.stop - sl.start]
            np.multiply(shifted[sl], inv_t, out=block)
            np.exp(block, out=block)
            np.matmul(block, ones, out=row_sums[sl])
        return float(np.log(row_sums).mean()) - mean_shift_target * inv_t

    return nll
