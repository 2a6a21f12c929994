"""Depth scaling (thesis Eq. 4-5 to 4-7): `Σ' = Σ + k_c · d · I` with one `k_c >= 0` per class.

`k_c` minimises the mean Gaussian NLL of the matched residuals of class `c`, found by bounded
Brent. `Σ` is eigendecomposed once, `Σ = U Λ Uᵀ`, so `Σ' = U (Λ + k d) Uᵀ` and with the
projected squared residuals `q = (Uᵀ r)²` (taken once) the NLL is

    NLL(k) = 1/N Σ_i 1/2 Σ_j [log(λ_ij + k d_i) + q_ij / (λ_ij + k d_i)] + D/2 log 2π,

O(N·D) per Brent step, with no matrix inverse. `Σ = None` means `Σ = 0` (`λ = 0`, `q = r²`).
Classes with fewer than `min_samples` residuals take the pooled `k` (fit on all residuals).

Brent does not even need O(N·D) steps: for `d_i > 0`, with `a = λ/d` and `b = q/d`, each term
is `log d + log(a + k) + b/(a + k)`, a function of `(a, b)` alone. The pairs `(i, j)` are
binned once on a fine logarithmic grid of `a` (relative bin width 2e-3, one grid for all
classes, so the pooled statistics are the sums of the per-class ones) and Brent runs on
per-bin counts, sums and means (`_depth_nll`), O(bins) per step and second order
in the bin width. The reported NLLs are exact (one pass over the data at the fitted k); the
tests check that the fitted k equal the minimisers of the exact NLL to 1e-6.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_bounds,
    check_covariances,
    check_distances,
    check_fitted,
    check_min_samples,
    class_codes,
)
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable
from calibrators.covariance._depth_nll import DepthBins, DepthTerms, depth_bins
from calibrators.covariance._depth_search import fit_k


class DepthScaler:
    """Fit `k_c` per class so that `Σ + k_c · d · I` explains the residuals (module docstring).

    Parameters
    ----------
    min_samples : a class with fewer residuals than this takes the pooled `k`.
    bounds : (low, high) search interval for `k`, 0 <= low < high. If an optimum lies at
        `high`, the search is repeated once on (low, 100·high); a `RuntimeWarning` is raised
        if it is still at the edge.
    xtol : absolute tolerance of Brent on `log k` (a relative tolerance on k).

    Attributes set by `fit`: `k_` (dict class -> k), `pooled_k_`, `fallback_classes_` (classes
    that took `pooled_k_`), `n_samples_` (dict class -> count), `n_dims_` (D), `nll_` (dict
    class -> mean NLL at its own k, None for fallback classes), `pooled_nll_`.
    `to_dict()` / `from_dict` as `ShrinkageDepthScaler`'s, without `s`.
    """

    def __init__(self, min_samples: int = 50, bounds: tuple[float, float] = (0.0, 25.0),
                 xtol: float = 1e-7) -> None:
        self.min_samples = min_samples
        self.bounds = bounds
        self.xtol = xtol

    def fit(self, residuals: np.ndarray, covariances: np.ndarray | None,
            distances: np.ndarray, classes: np.ndarray) -> DepthScaler:
        """Fit on `residuals [N, D]`, `covariances [N, D, D] | None`, `distances [N]` (>= 0)
        and `classes [N]` (any hashable labels, e.g. ints or strs); returns self."""
        min_samples = check_min_samples(self.min_samples)
        bounds = check_bounds(self.bounds, zero_low=True)
        r, cov, d, keys, codes, terms = fit_inputs(residuals, covariances, distances, classes)
        n, dim = r.shape
        groups, pooled = depth_bins(terms, codes, len(keys))
        k_of, pooled_k = self._fit_binned(groups, pooled, keys, min_samples, bounds)
        exact, pooled_nll = terms.fitted_nll(k_of, codes, pooled_k,
                                             np.array([g.n for g in groups]))
        self.nll_ = {key: (None if key in self.fallback_classes_ else float(exact[g]))
                     for g, key in enumerate(keys)}
        self.pooled_k_, self.pooled_nll_ = pooled_k, pooled_nll
        self.n_dims_ = dim
        return self

    def fit_binned(self, groups: list[DepthBins], pooled: DepthBins, keys: list, n_dims: int
                   ) -> DepthScaler:
        """Fit from binned statistics (`_depth_nll.BinSums.finish()`) of the
        groups named `keys` and of all of them pooled, as `fit` does after binning: the same
        `k_`, `pooled_k_`, `fallback_classes_`, `n_samples_` (a streamed fit merges the
        statistics of chunks of the data). `nll_` and `pooled_nll_` are None here (they need
        the data once more). Returns self."""
        min_samples = check_min_samples(self.min_samples)
        bounds = check_bounds(self.bounds, zero_low=True)
        if pooled.n == 0:
            raise FieldError("residuals", "residuals is empty: no sample to fit k on")
        _, self.pooled_k_ = self._fit_binned(groups, pooled, keys, min_samples, bounds)
        self.nll_ = {key: None for key in keys}
        self.pooled_nll_ = None
        self.n_dims_ = int(n_dims)
        return self

    def _fit_binned(self, groups: list[DepthBins], pooled: DepthBins, keys: list, min_samples: int,
                    bounds: tuple[float, float]) -> tuple[np.ndarray, float]:
        """Set `k_`, `n_samples_`, `fallback_classes_`; returns (k per group, pooled k)."""
        xtol = float(self.xtol)
        pooled_k = fit_k(pooled, bounds, xtol, "pooled")
        k_of = np.full(len(keys), pooled_k)
        self.k_, self.n_samples_, self.fallback_classes_ = {}, {}, []
        for g, (key, stats) in enumerate(zip(keys, groups, strict=True)):
            self.n_samples_[key] = stats.n
            if stats.n < min_samples:
                self.fallback_classes_.append(key)
            else:
                k_of[g] = fit_k(stats, bounds, xtol, key)
            self.k_[key] = float(k_of[g])
        return k_of, pooled_k

    def transform(self, covariances: np.ndarray | None, distances: np.ndarray,
                  classes: np.ndarray) -> np.ndarray:
        """Scaled covariances `[N, D, D]`; a class never seen in fit takes `pooled_k_`."""
        d, cov, k = transform_inputs(self, covariances, distances, classes)
        base = np.zeros((d.shape[0], self.n_dims_, self.n_dims_)) if cov is None else cov
        return add_depth_term(base, d, k)

    def to_dict(self) -> dict[str, Any]:
        """Strict-JSON-able plain dict; `from_dict(to_dict())` transforms identically."""
        return depth_dict(self, {"min_samples": self.min_samples, "bounds": self.bounds,
                                 "xtol": self.xtol})

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DepthScaler:
        """The fitted scaler `to_dict` wrote; ValueError naming a missing or bad key."""
        return depth_from_dict(cls, data, "depth scaler", ("k",))


def depth_dict(scaler: Any, hyper: dict[str, Any], tables: tuple[str, ...] = ("k",)
               ) -> dict[str, Any]:
    """The strict-JSON-able dict of a fitted depth-type scaler: `hyper`, its `classes` and,
    in their order, each per-class table of `tables` (`k`; shrinkage: `s`, `k`) with its
    pooled value, `fallback_classes`, `n_samples`, `n_dims`, `nll` and `pooled_nll`."""
    check_fitted(scaler, "k_")
    keys = list(scaler.k_)
    out: dict[str, Any] = {"hyper": hyper, "classes": keys}
    out.update({name: [getattr(scaler, f"{name}_")[c] for c in keys] for name in tables})
    out.update({f"pooled_{name}": getattr(scaler, f"pooled_{name}_") for name in tables})
    out.update(fallback_classes=scaler.fallback_classes_, n_samples=[
        scaler.n_samples_[c] for c in keys], n_dims=scaler.n_dims_,
        nll=[scaler.nll_[c] for c in keys], pooled_nll=scaler.pooled_nll_)
    return to_jsonable(out)


def depth_from_dict(cls: Any, data: dict[str, Any], what: str, tables: tuple[str, ...]) -> Any:
    """The fitted depth-type scaler `cls` that `depth_dict` wrote (`what` names it in
    errors): a ValueError names a missing or bad key; `s` must be > 0 and `k` >= 0."""
    if not isinstance(data, dict):
        raise ValueError(f"a {what} must be a dict, got {type(data).__name__}")
    pooled = tuple(f"pooled_{name}" for name in tables)
    missing = [k for k in ("hyper", "classes", *tables, *pooled, "fallback_classes",
                           "n_samples", "n_dims") if k not in data]
    if missing:
        raise ValueError(f"{what} dict lacks {missing[0]!r}")
    hyper = {k: tuple(v) if isinstance(v, list) else v for k, v in data["hyper"].items()}
    try:
        self = cls(**hyper)
    except TypeError as exc:
        raise ValueError(f"hyper has a bad key: {exc}") from None
    keys = list(data["classes"])
    arrays = {name: as_float_array(name, data[name], ndim=1) for name in tables}
    n_samples = as_int_array("n_samples", data["n_samples"])
    for name, arr in (*arrays.items(), ("n_samples", n_samples)):
        if arr.shape[0] != len(keys):
            raise ValueError(f"{name} has {arr.shape[0]} entries but classes has {len(keys)}")
    if (arrays.get("s", np.ones(1)) <= 0).any() or (arrays["k"] < 0).any():
        raise ValueError("k must be >= 0 (and s > 0) for every class")
    for name, key in zip(tables, pooled, strict=True):
        setattr(self, f"{name}_", dict(zip(keys, arrays[name].tolist(), strict=True)))
        setattr(self, f"{key}_", float(as_float_array(key, data[key], ndim=0)))
    self.fallback_classes_ = list(data["fallback_classes"])
    self.n_samples_ = dict(zip(keys, n_samples.tolist(), strict=True))
    self.n_dims_ = int(data["n_dims"])
    self.nll_ = dict(zip(keys, data.get("nll") or [None] * len(keys), strict=True))
    self.pooled_nll_ = data.get("pooled_nll")
    return self


def fit_inputs(residuals: np.ndarray, covariances: np.ndarray | None, distances: np.ndarray,
               classes: np.ndarray) -> tuple[Any, ...]:
    """Checked `(residuals [N, D], covariances [N, D, D] | None, distances [N], class keys,
    class codes [N], the NLL terms)` of a depth-type scaler's `fit`."""
    r = as_float_array("residuals", residuals, ndim=2)
    if r.shape[0] == 0 or r.shape[1] == 0:
        raise FieldError("residuals", f"residuals is empty (shape {r.shape}): need [N, D] "
                                      "with N, D >= 1")
    n, dim = r.shape
    cov = _check_cov(covariances, n, dim, full=False)
    d = check_distances(distances, n)
    keys, codes = class_codes(classes, n)
    return r, cov, d, keys, codes, DepthTerms.build(r, cov, d)


def per_row(table: dict, pooled: float, classes: np.ndarray) -> np.ndarray:
    """`[N]` the value of `table` for each row's class in `classes [N]` (pooled if absent)."""
    keys, codes = class_codes(classes, len(classes))
    values = np.array([table.get(key, pooled) for key in keys], dtype=np.float64)
    return values[codes] if len(classes) else np.zeros(0)


def transform_inputs(scaler: Any, covariances: np.ndarray | None, distances: np.ndarray,
                     classes: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Checked `(distances [N], covariances [N, D, D] | None, k per row [N])` for the
    `transform` of a fitted depth-type scaler (`k_`, `pooled_k_`, `n_dims_`)."""
    check_fitted(scaler, "k_")
    d = check_distances(distances, None)
    cov = _check_cov(covariances, d.shape[0], scaler.n_dims_)
    class_codes(classes, d.shape[0])          # checks the length and the labels
    return d, cov, per_row(scaler.k_, scaler.pooled_k_, np.asarray(classes))


def add_depth_term(covariances: np.ndarray, distances: np.ndarray, k: np.ndarray
                   ) -> np.ndarray:
    """`covariances [N, D, D] + (k [N] · distances [N]) · I` as a new float64 array."""
    out = np.array(covariances, dtype=np.float64, copy=True)
    diag = np.einsum("nii->ni", out)
    diag += (np.asarray(k, dtype=np.float64) * distances)[:, None]
    return out


def _check_cov(covariances: np.ndarray | None, n: int, dim: int, full: bool = True
               ) -> np.ndarray | None:
    """Float64 `[n, dim, dim]` covariances or None. `full=False` checks shape and finiteness
    only: fit tests symmetry and PSD on the decomposition it needs anyway (`DepthTerms.build`)."""
    if covariances is None:
        return None
    cov = as_float_array("covariances", covariances, ndim=3)
    check_covariances("covariances", cov if full else cov[:0], n=n if full else None, dim=dim)
    if cov.shape[0] != n:
        raise ValueError(f"covariances has {cov.shape[0]} matrices but {n} were expected")
    return cov
