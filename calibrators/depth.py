"""Depth scaling (thesis Eq. 4-5 to 4-7): `Σ' = Σ + k_c · d · I` with one `k_c >= 0` per class.

`k_c` minimises the mean Gaussian NLL of the matched residuals of class `c`, found by bounded
Brent. `Σ` is eigendecomposed once, `Σ = U Λ Uᵀ`, so `Σ' = U (Λ + k d) Uᵀ` and with the
projected squared residuals `q = (Uᵀ r)²` (taken once) the NLL is

    NLL(k) = 1/N Σ_i 1/2 Σ_j [log(λ_ij + k d_i) + q_ij / (λ_ij + k d_i)] + D/2 log 2π,

O(N·D) per Brent step, with no matrix inverse. `Σ = None` means `Σ = 0` (`λ = 0`, `q = r²`).
Classes with fewer than `min_samples` residuals take the pooled `k` (fit on all residuals).
"""

from __future__ import annotations

import warnings
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from calibrators._checks import as_float_array, check_covariances, check_length
from calibrators.exceptions import check_fitted

_LOG_2PI = float(np.log(2.0 * np.pi))
_WIDEN = 100.0  # an optimum at the upper bound is searched again once up to 100 x the bound
_CHUNK = 1 << 15  # samples per block in the NLL loop: its buffers stay in the CPU cache


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
        min_samples = _check_min_samples(self.min_samples)
        bounds = _check_bounds(self.bounds)
        r = as_float_array("residuals", residuals, ndim=2)
        if r.shape[0] == 0 or r.shape[1] == 0:
            raise ValueError(f"residuals is empty (shape {r.shape}): need [N, D] with N, D >= 1")
        n, dim = r.shape
        cov = _check_cov(covariances, n, dim, full=False)
        d = _check_distances(distances, n)
        keys, codes = _class_codes(classes, n)
        terms = _Terms.build(r, cov, d)

        pooled_k, pooled_nll = _fit_k(terms, bounds, float(self.xtol), "pooled")
        self.k_, self.nll_, self.n_samples_, self.fallback_classes_ = {}, {}, {}, []
        for key, members in zip(keys, _groups(codes, len(keys)), strict=True):
            self.n_samples_[key] = len(members)
            if len(members) < min_samples:
                self.k_[key], self.nll_[key] = pooled_k, None
                self.fallback_classes_.append(key)
            else:
                self.k_[key], self.nll_[key] = _fit_k(terms.take(members), bounds,
                                                      float(self.xtol), key)
        self.pooled_k_, self.pooled_nll_ = pooled_k, pooled_nll
        self.n_dims_ = dim
        return self

    def transform(self, covariances: np.ndarray | None, distances: np.ndarray,
                  classes: np.ndarray) -> np.ndarray:
        """Scaled covariances `[N, D, D]`; a class never seen in fit takes `pooled_k_`."""
        check_fitted(self, "k_")
        d = _check_distances(distances, None)
        n = d.shape[0]
        cov = _check_cov(covariances, n, self.n_dims_)
        keys, codes = _class_codes(classes, n)
        k_rows = np.array([self.k_.get(key, self.pooled_k_) for key in keys], dtype=np.float64)
        base = np.zeros((n, self.n_dims_, self.n_dims_)) if cov is None else cov
        return add_depth_term(base, d, k_rows[codes] if n else np.zeros(0))


def add_depth_term(covariances: np.ndarray, distances: np.ndarray, k: np.ndarray
                   ) -> np.ndarray:
    """`covariances [N, D, D] + (k [N] · distances [N]) · I` as a new float64 array."""
    out = np.array(covariances, dtype=np.float64, copy=True)
    diag = np.einsum("nii->ni", out)
    diag += (np.asarray(k, dtype=np.float64) * distances)[:, None]
    return out


@dataclass(frozen=True)
class _Terms:
    """Per-sample NLL terms, dims first: `eig [D, N]` of Σ, `sq [D, N] = (Uᵀ r)²`, `dist [N]`."""

    eig: np.ndarray
    sq: np.ndarray
    dist: np.ndarray

    @classmethod
    def build(cls, r: np.ndarray, cov: np.ndarray | None, d: np.ndarray) -> _Terms:
        """Terms of residuals `r [N, D]` under `cov [N, D, D]` (None = 0) at distances `d`;
        checks that Σ is symmetric PSD and that Σ + k·d·I can be regular."""
        if cov is None:
            eig, sq = np.zeros((r.shape[1], r.shape[0])), np.ascontiguousarray((r * r).T)
        elif r.shape[1] == 2:
            eig, sq = _spectral_2x2(cov, r)
        else:
            eig, sq = _spectral(cov, r)
        singular = (d == 0) & (eig.min(axis=0) == 0)
        if singular.any():
            i = int(np.argmax(singular))
            what = "covariances is None" if cov is None else f"covariances[{i}] is singular"
            raise ValueError(f"distances[{i}] is 0 and {what}: Σ + k·d·I is singular for every k")
        return cls(eig, sq, d)

    def take(self, idx: np.ndarray) -> _Terms:
        return _Terms(self.eig[:, idx], self.sq[:, idx], self.dist[idx])

    def nll(self, k: float) -> float:
        """Mean Gaussian NLL of the residuals under `Σ + k d I`, in cache-sized blocks."""
        n_dims, n = self.eig.shape
        var = np.empty(min(n, _CHUNK))
        total = 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            for start in range(0, n, _CHUNK):
                sl = slice(start, min(start + _CHUNK, n))
                v = var[:sl.stop - start]
                for j in range(n_dims):
                    np.multiply(self.dist[sl], k, out=v)
                    v += self.eig[j, sl]
                    total += float(np.log(v).sum())
                    np.divide(self.sq[j, sl], v, out=v)
                    total += float(v.sum())
        value = 0.5 * total / n + 0.5 * n_dims * _LOG_2PI
        return value if np.isfinite(value) else np.inf


def _spectral(cov: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues `[D, N]` of Σ = U Λ Uᵀ and `(Uᵀ r)² [D, N]`, by `np.linalg.eigh`."""
    scale = np.maximum(np.abs(cov).reshape(len(cov), -1).max(axis=1), 1.0)
    _check_symmetric(np.abs(cov - np.swapaxes(cov, 1, 2)).reshape(len(cov), -1).max(axis=1),
                     scale)
    eig, vecs = np.linalg.eigh(cov)
    _check_psd(eig[:, 0], scale)
    sq = np.einsum("nij,ni->jn", vecs, r) ** 2
    return _zero_tiny(np.ascontiguousarray(eig.T)), np.ascontiguousarray(sq)


def _spectral_2x2(cov: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_spectral` in closed form for D = 2, with no eigenvectors and no trigonometry.

    For Σ = [[a, b], [b, c]]: λ = (a + c)/2 ∓ hypot((a - c)/2, b). With p_lo + p_hi = |r|²
    and rᵀΣr = λ_lo·p_lo + λ_hi·p_hi, the projection onto the major axis is
    p_hi = (rᵀΣr - λ_lo |r|²) / (λ_hi - λ_lo); for λ_hi = λ_lo any split gives the same NLL.
    """
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), np.maximum(np.abs(c), 1.0))
    _check_symmetric(np.abs(b - cov[:, 1, 0]), scale)
    half_gap = np.hypot(0.5 * (a - c), b)
    mean = 0.5 * (a + c)
    eig = np.stack([mean - half_gap, mean + half_gap])
    _check_psd(eig[0], scale)
    x, y = r[:, 0], r[:, 1]
    rr = x * x + y * y
    quad = a * x * x + 2.0 * b * x * y + c * y * y
    distinct = half_gap > 1e-12 * np.maximum(np.abs(eig[1]), np.finfo(np.float64).tiny)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_hi = np.where(distinct, (quad - eig[0] * rr) / (2.0 * half_gap), 0.5 * rr)
    p_hi = np.clip(p_hi, 0.0, rr)
    return _zero_tiny(eig), np.stack([rr - p_hi, p_hi])


def _zero_tiny(eig: np.ndarray) -> np.ndarray:
    """Eigenvalues `[D, N]` (ascending) below 1e-12 of each matrix's largest set to 0."""
    top = np.maximum(eig[-1], np.finfo(np.float64).tiny)
    return np.where(eig <= 1e-12 * top, 0.0, eig)


def _check_symmetric(gap: np.ndarray, scale: np.ndarray, tol: float = 1e-9) -> None:
    """The symmetry test of `_checks.check_covariances` on `max |Σ - Σᵀ|` per matrix."""
    asym = gap > tol * scale
    if asym.any():
        raise ValueError(f"covariances[{int(np.argmax(asym))}] is not symmetric")


def _check_psd(eig_min: np.ndarray, scale: np.ndarray, tol: float = 1e-9) -> None:
    """The PSD test of `_checks.check_covariances` on the smallest eigenvalues `[N]`."""
    bad = eig_min < -tol * scale
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"covariances[{i}] is not positive semi-definite (smallest eigenvalue "
                         f"{eig_min[i]:.3g})")


def _fit_k(terms: _Terms, bounds: tuple[float, float], xtol: float, label: Hashable
           ) -> tuple[float, float]:
    """Minimise `terms.nll` over k in `bounds`: Brent on log k (see `_brent`), widened once if
    the optimum is at the upper bound, then compared with k = low itself (k = 0 is valid)."""
    low, high = bounds
    k, nll = _brent(terms, low, high, xtol)
    if _at_edge(k, high, xtol):
        k, nll = _brent(terms, low, high * _WIDEN, xtol)
        if _at_edge(k, high * _WIDEN, xtol):
            warnings.warn(f"depth k for class {label!r} is at the search edge {high * _WIDEN}; "
                          "the residuals may not grow with distance", RuntimeWarning,
                          stacklevel=3)
    at_low = terms.nll(low)
    if at_low <= nll:
        k, nll = low, at_low
    return float(k), float(nll)


def _at_edge(k: float, high: float, xtol: float) -> bool:
    return np.log(high) - np.log(k) < 10 * xtol


def _brent(terms: _Terms, low: float, high: float, xtol: float) -> tuple[float, float]:
    """Bounded Brent on log k in [log max(low, 1e-9·high), log high]; `xtol` is on log k.

    Log k reaches the scale of k (1e-3 .. 1 m²/m) in a few steps where a linear search from
    [0, 25] spends a dozen golden-section steps; values below 1e-9·high are covered by the
    k = low check in `_fit_k`.
    """
    lo = np.log(max(low, 1e-9 * high))
    result = minimize_scalar(lambda u: terms.nll(float(np.exp(u))), bounds=(lo, np.log(high)),
                             method="bounded", options={"xatol": xtol})
    return float(np.exp(result.x)), float(result.fun)


def _check_min_samples(value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"min_samples must be an integer >= 1, got {value!r}")
    return int(value)


def _check_bounds(bounds: tuple[float, float]) -> tuple[float, float]:
    try:
        low, high = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise ValueError(f"bounds must be a pair of numbers, got {bounds!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and 0 <= low < high):
        raise ValueError(f"bounds must satisfy 0 <= low < high (finite), got {bounds!r}")
    return low, high


def _check_cov(covariances: np.ndarray | None, n: int, dim: int, full: bool = True
               ) -> np.ndarray | None:
    """Float64 `[n, dim, dim]` covariances or None. `full=False` checks shape and finiteness
    only: fit tests symmetry and PSD on the decomposition it needs anyway (`_Terms.build`)."""
    if covariances is None:
        return None
    cov = as_float_array("covariances", covariances, ndim=3)
    check_covariances("covariances", cov if full else cov[:0], n=n if full else None, dim=dim)
    if cov.shape[0] != n:
        raise ValueError(f"covariances has {cov.shape[0]} matrices but {n} were expected")
    return cov


def _check_distances(distances: np.ndarray, n: int | None) -> np.ndarray:
    d = as_float_array("distances", distances, ndim=1)
    if n is not None:
        check_length("distances", d, n, "residuals")
    negative = d < 0
    if negative.any():
        i = int(np.argmax(negative))
        raise ValueError(f"distances[{i}] = {d[i]} is negative")
    return d


def _groups(codes: np.ndarray, n_keys: int) -> list[np.ndarray]:
    """Indices of each code `0 .. n_keys - 1` in `codes [N]` (one stable sort for all)."""
    order = np.argsort(codes, kind="stable")
    bounds = np.cumsum(np.bincount(codes, minlength=n_keys))[:-1]
    return np.split(order, bounds)


def _class_codes(classes: np.ndarray, n: int) -> tuple[list, np.ndarray]:
    """Distinct class labels (as Python scalars, sorted) and the code `[N]` of each entry."""
    arr = np.asarray(classes)
    if arr.ndim != 1:
        raise ValueError(f"classes must have 1 dimension, got shape {arr.shape}")
    check_length("classes", arr, n, "distances")
    if n == 0:
        return [], np.zeros(0, dtype=np.int64)
    try:
        keys, codes = np.unique(arr, return_inverse=True)
    except TypeError:
        raise ValueError("classes must be labels of one comparable type (all ints or all strs)"
                         ) from None
    return keys.tolist(), codes.reshape(-1).astype(np.int64)
