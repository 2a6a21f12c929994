"""Penalised logistic regression by Newton's method: the fit of Platt scaling (per class,
with or without a range term) and of any other logistic calibrator of the logit with extra
linear terms (the 2-D position calibrator of `calibrators.boxes2d`).

`fit_logistic(columns, hit, l2, min_slope, weight)`: the coefficients `θ [P]` minimising
`Σ w·(softplus(η) - y·η) + l2/2·|θ - prior|²`, `η = Σ_j θ_j·x_j`, prior the identity on the
logit (`θ_0 = 1`, the rest 0), with the slope of the logit bounded below, `θ_0 >= min_slope`
(so the ranking within a class never changes). Columns are standardised internally.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.special import expit


def fit_logistic(columns: list[np.ndarray], hit: np.ndarray, l2: float, min_slope: float,
                 weight: np.ndarray | None = None) -> np.ndarray:
    """`θ [P]` of the module docstring for `columns` (P arrays `[n]`: the logit first, the
    intercept's ones second, then any other terms), outcomes `hit [n]` and row weights
    `weight [n]` (None: 1 each)."""
    scale = np.array([_spread(c, weight) for c in columns])
    scale[1] = 1.0
    problem = _Logistic([c / s for c, s in zip(columns, scale, strict=True)],
                        hit.astype(np.float64), scale, l2, weight)
    theta = problem.newton(problem.prior * scale)
    low = min_slope * scale[0]
    if theta[0] < low:  # convex: the bounded optimum has the slope on the bound
        theta = problem.newton(np.r_[low, theta[1:]], fixed=1)
    return theta / scale


class _Logistic:
    """Penalised logistic NLL `Σ w·(softplus(η) - y·η) + l2/2·|θ/scale - prior|²` with
    `η = Σ_j θ_j·x_j` over unit-spread columns `x` (list of P arrays `[n]`) and row weights
    `w [n]` (None: 1 each), minimised by Newton's method with backtracking (strictly convex
    for l2 > 0).

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
        warnings.warn(f"logistic fit did not converge in {max_iter} Newton steps (l2 = "
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
