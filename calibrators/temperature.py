"""Temperature scaling: one `T > 0` for all classes, fit on classification NLL.

`p = sigmoid(z / T)` (sigmoid mode) or `p = softmax(z / T)` (softmax mode). `T` is found by
bounded Brent (`scipy.optimize.minimize_scalar(method="bounded")`) on `log T`, in float64
whatever the input dtype. Dividing every logit by the same positive `T` is monotone, so the
arg-max (the detection's label) never changes.

Labels:
- sigmoid: `labels [N]` in {0, 1}, 1 if the detection is a true positive of its predicted
  (arg-max) class; only that class's logit enters the NLL.
- softmax: `labels [N]` in [0, C], the target column of `logits [N, C + 1]` (C = no-object).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from calibrators._checks import (
    as_float_array,
    as_int_array,
    check_choice,
    check_index,
    check_length,
)
from calibrators.exceptions import check_fitted
from calibrators.scores import SCORE_MODES, class_probabilities

Objective = Callable[[float], float]


class TemperatureScaler:
    """Fit one temperature `T` on `logits [N, C']` and labels `[N]`; see the module docstring.

    Parameters
    ----------
    mode : "sigmoid" or "softmax" (the detector's score mode).
    bounds : (low, high) search interval for `T`, both > 0; Brent runs on `log T`.
    xtol : absolute tolerance of Brent on `log T` (so a relative tolerance on `T`).

    Attributes set by `fit`: `temperature_` (float), `n_samples_` (int), `n_columns_` (C'),
    `nll_` (mean NLL at `temperature_`), `nll_before_` (mean NLL at T = 1), `n_evaluations_`.
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
        z, y = _validate(logits, labels, self.mode)
        objective = _sigmoid_nll(z, y) if self.mode == "sigmoid" else _softmax_nll(z, y)
        result = minimize_scalar(objective, bounds=(np.log(low), np.log(high)), method="bounded",
                                 options={"xatol": float(self.xtol)})
        log_t = float(result.x)
        if min(log_t - np.log(low), np.log(high) - log_t) < 10 * float(self.xtol):
            warnings.warn(f"temperature {np.exp(log_t):.6g} is at the edge of bounds "
                          f"{(low, high)}; widen bounds or check the labels", RuntimeWarning,
                          stacklevel=2)
        self.temperature_ = float(np.exp(log_t))
        self.nll_ = float(result.fun)
        self.nll_before_ = float(objective(0.0))
        self.n_evaluations_ = int(result.nfev)
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
    """Mean binary NLL of the predicted class as a function of `log T`.

    With `s` the predicted class's logit, `-log p(y | s/T) = softplus(s/T) - y·s/T`, where
    `softplus(x) = max(x, 0) + log1p(exp(-|x|))` is `np.logaddexp(0, x)` written out (stable
    for any x, and several times faster). The 1-D vector `s` and `mean(y·s)` are taken once;
    each evaluation then runs over `s` in cache-sized chunks with two small buffers.
    """
    s = _row_max(z)
    n = len(s)
    mean_ys = float(np.dot(y.astype(np.float64), s)) / n
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
