"""Shrinkage depth scaling: `Σ' = s_c · Σ + k_c · d · I` with `s_c > 0`, `k_c >= 0` per class.

Detectors often over-state their spread near the ego and under-state it far away; one
additive `k` (`_depth`, the case `s = 1`) cannot fix both, a scale of `Σ` plus a
range term can. `(s_c, k_c)` minimise the mean Gaussian NLL of the class's matched residuals:
bounded Brent on `log s`, and for each `s` the depth-scaling Brent on `k`.

Each evaluation reuses depth scaling's binned statistics, built once. With `Σ = U Λ Uᵀ`,
`a = λ/d`, `b = (Uᵀr)²/d`, a term `log(sλ + kd) + q/(sλ + kd)` equals
`log d + log s + log(a + k/s) + (b/s)/(a + k/s)`, so the NLL at `(s, k)` is depth scaling's
binned NLL at `k' = k/s` with every `b` divided by `s` and `D·log s` added per sample; a
sample at `d = 0` contributes `log(sλ) + q/(sλ)`, whose `q/λ` sum is kept apart. Each step
is O(bins). `Σ = None` (`Σ = 0`) leaves `s` undefined: it is 1, and the fit is depth scaling.
Classes with fewer than `min_samples` residuals take the pooled `(s, k)`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Hashable
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from calibrators.core.checks import (
    check_bounds,
    check_min_samples,
)
from calibrators.core.errors import FieldError
from calibrators.covariance._depth import (
    add_depth_term,
    depth_dict,
    depth_from_dict,
    fit_inputs,
    per_row,
    transform_inputs,
)
from calibrators.covariance._depth_nll import DepthBins, DepthTerms, depth_bins
from calibrators.covariance._depth_search import fit_k


class ShrinkageDepthScaler:
    """Fit `(s_c, k_c)` per class so that `s_c·Σ + k_c·d·I` explains the residuals.

    Parameters
    ----------
    min_samples : a class with fewer residuals than this takes the pooled `(s, k)`.
    bounds : (low, high) search interval for `k`, 0 <= low < high (widened as in
        `DepthScaler`).
    scale_bounds : (low, high) search interval for `s`, 0 < low <= high; low == high fixes
        `s` (`(1, 1)` is `DepthScaler`).
    xtol : Brent's absolute tolerance on `log s` and on `log k`.

    Attributes set by `fit`: `s_`, `k_` (dicts class -> value), `pooled_s_`, `pooled_k_`,
    `fallback_classes_` (classes that took the pooled pair), `n_samples_` (dict class ->
    count), `n_dims_` (D), `nll_` (dict class -> exact mean NLL at its own pair, None for
    fallback classes), `pooled_nll_`.
    """

    def __init__(self, min_samples: int = 50, bounds: tuple[float, float] = (0.0, 25.0),
                 scale_bounds: tuple[float, float] = (1e-2, 1e2), xtol: float = 1e-7) -> None:
        self.min_samples = min_samples
        self.bounds = bounds
        self.scale_bounds = scale_bounds
        self.xtol = xtol

    def fit(self, residuals: np.ndarray, covariances: np.ndarray | None,
            distances: np.ndarray, classes: np.ndarray) -> ShrinkageDepthScaler:
        """Fit on `residuals [N, D]`, `covariances [N, D, D] | None`, `distances [N]` (>= 0)
        and `classes [N]` (hashable labels, e.g. ints or strs); returns self."""
        min_samples = check_min_samples(self.min_samples)
        bounds = check_bounds(self.bounds, zero_low=True)
        scale_bounds = _check_scale_bounds(self.scale_bounds)
        r, cov, d, keys, codes, terms = fit_inputs(residuals, covariances, distances, classes)
        n, dim = r.shape
        groups, pooled = depth_bins(terms, codes, len(keys))
        near_q = near_zero_q(terms, codes, len(keys))
        fit = _PairFit(bounds, (1.0, 1.0) if cov is None else scale_bounds, float(self.xtol))
        s_of, k_of = self._fit_groups(fit, groups, pooled, near_q, keys, min_samples)
        exact = _scaled_terms(terms, s_of[codes]).group_nll(k_of, codes)
        self.nll_ = {key: (None if key in self.fallback_classes_ else float(exact[g]))
                     for g, key in enumerate(keys)}
        self.pooled_nll_ = _scaled_terms(terms, np.full(n, self.pooled_s_)).nll(self.pooled_k_)
        self.n_dims_ = dim
        return self

    def fit_binned(self, groups: list[DepthBins], pooled: DepthBins, near_q: np.ndarray,
                   keys: list, n_dims: int, has_sigma: bool = True) -> ShrinkageDepthScaler:
        """Fit from binned statistics (`BinSums.finish()`) of the groups named `keys` and of
        all of them pooled, with each group's `near_q` (`near_zero_q`), as `fit` does after
        binning: the same `s_`, `k_`, fallbacks and counts (a streamed fit merges the
        statistics of chunks of the data). `has_sigma=False`: Σ = 0, s is 1. `nll_` and
        `pooled_nll_` are None (they need the data once more). Returns self."""
        min_samples = check_min_samples(self.min_samples)
        bounds = check_bounds(self.bounds, zero_low=True)
        scale_bounds = _check_scale_bounds(self.scale_bounds)
        if pooled.n == 0:
            raise FieldError("residuals", "residuals is empty: no sample to fit k on")
        fit = _PairFit(bounds, scale_bounds if has_sigma else (1.0, 1.0), float(self.xtol))
        self._fit_groups(fit, groups, pooled, np.asarray(near_q, dtype=np.float64), keys,
                         min_samples)
        self.nll_ = {key: None for key in keys}
        self.pooled_nll_ = None
        self.n_dims_ = int(n_dims)
        return self

    def _fit_groups(self, fit: _PairFit, groups: list[DepthBins], pooled: DepthBins,
                    near_q: np.ndarray, keys: list, min_samples: int
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Set `s_`, `k_`, the pooled pair, `n_samples_`, `fallback_classes_`; returns
        `(s, k)` per group."""
        pooled_s, pooled_k = fit(pooled, float(near_q.sum()), "pooled")
        s_of, k_of = np.full(len(keys), pooled_s), np.full(len(keys), pooled_k)
        self.n_samples_, self.fallback_classes_ = {}, []
        for g, (key, stats) in enumerate(zip(keys, groups, strict=True)):
            self.n_samples_[key] = stats.n
            if stats.n < min_samples:
                self.fallback_classes_.append(key)
            else:
                s_of[g], k_of[g] = fit(stats, float(near_q[g]), key)
        self.s_ = {key: float(s_of[g]) for g, key in enumerate(keys)}
        self.k_ = {key: float(k_of[g]) for g, key in enumerate(keys)}
        self.pooled_s_, self.pooled_k_ = pooled_s, pooled_k
        return s_of, k_of

    def transform(self, covariances: np.ndarray | None, distances: np.ndarray,
                  classes: np.ndarray) -> np.ndarray:
        """`s_c·Σ + k_c·d·I` `[N, D, D]`; a class never seen in fit takes the pooled pair."""
        d, cov, k = transform_inputs(self, covariances, distances, classes)
        if cov is None:
            base = np.zeros((d.shape[0], self.n_dims_, self.n_dims_))
        else:
            base = cov * per_row(self.s_, self.pooled_s_, np.asarray(classes))[:, None, None]
        return add_depth_term(base, d, k)

    def to_dict(self) -> dict[str, Any]:
        """Strict-JSON-able plain dict; `from_dict(to_dict())` transforms identically."""
        return depth_dict(self, {"min_samples": self.min_samples, "bounds": self.bounds,
                                 "scale_bounds": self.scale_bounds, "xtol": self.xtol},
                          ("s", "k"))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ShrinkageDepthScaler:
        """The fitted scaler `to_dict` wrote; ValueError naming a missing or bad key."""
        return depth_from_dict(cls, data, "shrinkage scaler", ("s", "k"))


@dataclasses.dataclass(frozen=True)
class _PairFit:
    """Fits `(s, k)` of one group's binned statistics: Brent on log s outside, depth
    scaling's `fit_k` on `k' = k/s` inside (module docstring)."""

    bounds: tuple[float, float]
    scale_bounds: tuple[float, float]
    xtol: float

    def __call__(self, stats: DepthBins, near_q: float, label: Hashable) -> tuple[float, float]:
        low, high = self.scale_bounds
        if low == high:
            return low, self._k(stats, near_q, low, label)

        def profile(log_s: float) -> float:
            s = float(np.exp(log_s))
            scaled = _at_scale(stats, near_q, s)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return scaled.nll(fit_k(scaled, self._k_bounds(s), self.xtol, label))

        result = minimize_scalar(profile, bounds=(np.log(low), np.log(high)), method="bounded",
                                 options={"xatol": self.xtol})
        log_s = float(result.x)
        if min(log_s - np.log(low), np.log(high) - log_s) < 10 * self.xtol:
            warnings.warn(f"shrinkage s for class {label!r} is at the edge of scale_bounds "
                          f"{self.scale_bounds}", RuntimeWarning, stacklevel=3)
        s = float(np.exp(log_s))
        return s, self._k(stats, near_q, s, label)

    def _k(self, stats: DepthBins, near_q: float, s: float, label: Hashable) -> float:
        """The NLL-optimal k at scale `s` (warnings of `fit_k` shown)."""
        return s * fit_k(_at_scale(stats, near_q, s), self._k_bounds(s), self.xtol, label)

    def _k_bounds(self, s: float) -> tuple[float, float]:
        return self.bounds[0] / s, self.bounds[1] / s


def _at_scale(stats: DepthBins, near_q: float, s: float) -> DepthBins:
    """Binned statistics whose `nll(k / s)` is the NLL under `s·Σ + k·d·I`."""
    if s == 1.0:
        return stats
    const = stats.const + stats.n * stats.n_dims * np.log(s) + near_q * (1.0 / s - 1.0)
    return dataclasses.replace(stats, const=float(const), b_sum=stats.b_sum / s,
                               b_zero=stats.b_zero / s)


def near_zero_q(terms: DepthTerms, codes: np.ndarray, n_groups: int) -> np.ndarray:
    """Per group `[G]`, the sum of `q/λ` over the samples at `d = 0` (regular Σ there)."""
    near = terms.dist == 0
    if not near.any():
        return np.zeros(n_groups)
    ratio = (terms.sq[:, near] / terms.eig[:, near]).sum(axis=0)
    return np.bincount(codes[near], weights=ratio, minlength=n_groups)


def _scaled_terms(terms: DepthTerms, s_rows: np.ndarray) -> DepthTerms:
    """`terms` with the eigenvalues of row i multiplied by `s_rows [N]`."""
    return DepthTerms(terms.eig * s_rows[None, :], terms.sq, terms.dist)


def _check_scale_bounds(bounds: tuple[float, float]) -> tuple[float, float]:
    try:
        low, high = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise FieldError("scale_bounds", "scale_bounds must be a pair of numbers, got "
                                         f"{bounds!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and 0 < low <= high):
        raise FieldError("scale_bounds", "scale_bounds must satisfy 0 < low <= high (finite), "
                                         f"got {bounds!r}")
    return low, high
