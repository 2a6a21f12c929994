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
import warnings

import numpy as np
from scipy.special import expit

from calibrators.core.errors import FieldError
from calibrators.scores._calibrator import ClasswiseCalibrator


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
        scale = np.array([_spread(c, w) for c in cols])
        scale[1] = 1.0
        problem = _Logistic([c / s for c, s in zip(cols, scale, strict=True)],
                            hit.astype(np.float64), scale, float(self.l2), w)
        theta = problem.newton(problem.prior * scale)
        low = float(self.min_slope) * scale[0]
        if theta[0] < low:  # convex: the bounded optimum has a on the bound
            theta = problem.newton(np.r_[low, theta[1:]], fixed=1)
        coef = np.zeros(3)
        coef[:len(cols)] = theta / scale
        return coef

    def _apply(self, params: np.ndarray, z: np.ndarray, d: np.ndarray | None) -> np.ndarray:
        eta = params[0] * z + params[1]
        if self.range_term:
            eta = eta + params[2] * d
        return expit(eta)

    def _derive(self) -> None:
        self.coef_ = np.stack(self.params_)
        self.pooled_coef_ = self.pooled_params_


class _Logistic:
    """Penalised logistic NLL `Σ w·(softplus(η) - y·η) + l2/2·|θ/scale - prior|²` with
    `η = Σ_j θ_j·x_j` over unit-spread columns `x` (list of P arrays `[n]`) and row weights
    `w [n]` (None: 1 each), minimised by Newton's method with backtracking (strictly convex
    for l2 > 0; P <= 3).

    Columns are combined one by one with einsum: a BLAS matmul may start threads, which costs
    milliseconds per call on a busy machine."""

    def __init__(self, x: list[np.ndarray], y: np.ndarray, scale: np.ndarray, l2: float,
                 w: np.ndarray | None = None) -> None:
        self.x, self.y, self.scale, self.l2, self.w = x, y, scale, l2, w
        self.wy = y if w is None else w * y
        self.prior = np.zeros(len(x))
        self.prior[0] = 1.0  # the identity: a = 1, b = 0, g = 0

    def value(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        eta = theta[0] * self.x[0]
        for j in range(1, len(self.x)):
            eta += theta[j] * self.x[j]
        gap = theta / self.scale - self.prior
        soft = np.logaddexp(0.0, eta)
        nll = (float(soft.sum()) if self.w is None else _dot(self.w, soft)) - _dot(self.wy, eta)
        return nll + 0.5 * self.l2 * float(np.sum(gap * gap)), eta

    def newton(self, theta: np.ndarray, fixed: int = 0, max_iter: int = 100) -> np.ndarray:
        """The minimiser over `theta[fixed:]` (the first `fixed` entries held), from `theta`."""
        theta = theta.astype(np.float64)
        f, eta = self.value(theta)
        free = slice(fixed, len(theta))
        for _ in range(max_iter):
            p = expit(eta)
            w = p * (1.0 - p)
            resid = p - self.y
            if self.w is not None:
                w, resid = w * self.w, resid * self.w
            gap = theta / self.scale - self.prior
            grad = np.array([_dot(c, resid) for c in self.x]) + self.l2 * gap / self.scale
            hess = np.array([[_dot(w * a, b) for b in self.x] for a in self.x])
            hess += np.diag(self.l2 / self.scale**2)
            step = np.zeros_like(theta)
            step[free] = np.linalg.solve(hess[free, free], grad[free])
            t = 1.0
            while True:
                f_new, eta_new = self.value(theta - t * step)
                if f_new <= f - 1e-4 * t * float(grad @ step) or t < 1e-10:
                    break
                t *= 0.5
            theta, converged = theta - t * step, float(np.abs(t * step).max()) < 1e-10
            f, eta = f_new, eta_new
            if converged:
                return theta
        warnings.warn(f"Platt fit did not converge in {max_iter} Newton steps (l2 = "
                      f"{self.l2}); the data may be separable", RuntimeWarning, stacklevel=5)
        return theta


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.einsum("i,i->", a, b))


def _spread(col: np.ndarray, w: np.ndarray | None = None) -> float:
    """A positive scale of a column: its (weighted) standard deviation, 1 when that is 0 or
    tiny."""
    if w is None:
        s = float(np.std(col))
    else:
        mean = float(np.dot(w, col)) / float(w.sum())
        s = float(np.sqrt(np.dot(w, (col - mean) ** 2) / float(w.sum())))
    return s if s > 1e-12 else 1.0
