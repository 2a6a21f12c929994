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
per-bin counts, sums and means (`_Binned`), O(bins) per step and second order in the bin
width. The reported NLLs are exact (one pass over the data at the fitted k); the tests check
that the fitted k equal the minimisers of the exact NLL to 1e-6.
"""

from __future__ import annotations

import warnings
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from calibrators._spectral import _spectral, _spectral_2x2
from calibrators.checks import as_float_array, check_covariances, check_length
from calibrators.exceptions import FieldError, check_fitted

_LOG_2PI = float(np.log(2.0 * np.pi))
_WIDEN = 100.0  # an optimum at the upper bound is searched again once up to 100 x the bound
_CHUNK = 1 << 15  # samples per block in the NLL loop: its buffers stay in the CPU cache
_MANTISSA_BITS = 9  # bins of a = λ/d per octave: 2**9, a relative width <= 2e-3
_OCTAVES = 64  # octaves of a below its maximum that the grid covers
_BINS = _OCTAVES << _MANTISSA_BITS  # bins per class


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
        r, cov, d, keys, codes, terms = fit_inputs(residuals, covariances, distances, classes)
        n, dim = r.shape
        groups, pooled = _binned(terms, codes, len(keys))
        xtol = float(self.xtol)

        pooled_k = _fit_k(pooled, bounds, xtol, "pooled")
        k_of = np.full(len(keys), pooled_k)
        self.k_, self.n_samples_, self.fallback_classes_ = {}, {}, []
        for g, (key, stats) in enumerate(zip(keys, groups, strict=True)):
            self.n_samples_[key] = stats.n
            if stats.n < min_samples:
                self.fallback_classes_.append(key)
            else:
                k_of[g] = _fit_k(stats, bounds, xtol, key)
            self.k_[key] = float(k_of[g])
        exact = terms.group_nll(k_of, codes)
        self.nll_ = {key: (None if key in self.fallback_classes_ else float(exact[g]))
                     for g, key in enumerate(keys)}
        self.pooled_k_, self.pooled_nll_ = pooled_k, terms.nll(pooled_k)
        self.n_dims_ = dim
        return self

    def transform(self, covariances: np.ndarray | None, distances: np.ndarray,
                  classes: np.ndarray) -> np.ndarray:
        """Scaled covariances `[N, D, D]`; a class never seen in fit takes `pooled_k_`."""
        d, cov, k = transform_inputs(self, covariances, distances, classes)
        base = np.zeros((d.shape[0], self.n_dims_, self.n_dims_)) if cov is None else cov
        return add_depth_term(base, d, k)


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
    d = _check_distances(distances, n)
    keys, codes = _class_codes(classes, n)
    return r, cov, d, keys, codes, _Terms.build(r, cov, d)


def per_row(table: dict, pooled: float, classes: np.ndarray) -> np.ndarray:
    """`[N]` the value of `table` for each row's class in `classes [N]` (pooled if absent)."""
    keys, codes = _class_codes(classes, len(classes))
    values = np.array([table.get(key, pooled) for key in keys], dtype=np.float64)
    return values[codes] if len(classes) else np.zeros(0)


def transform_inputs(scaler: Any, covariances: np.ndarray | None, distances: np.ndarray,
                     classes: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Checked `(distances [N], covariances [N, D, D] | None, k per row [N])` for the
    `transform` of a fitted depth-type scaler (`k_`, `pooled_k_`, `n_dims_`)."""
    check_fitted(scaler, "k_")
    d = _check_distances(distances, None)
    cov = _check_cov(covariances, d.shape[0], scaler.n_dims_)
    _class_codes(classes, d.shape[0])          # checks the length and the labels
    return d, cov, per_row(scaler.k_, scaler.pooled_k_, np.asarray(classes))


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

    def group_nll(self, k: np.ndarray, codes: np.ndarray) -> np.ndarray:
        """Exact mean NLL `[G]` of each group `g` (samples with `codes == g`, `codes [N]`)
        under `Σ + k[g] d I`, `k [G]`; inf for a group whose NLL is not finite."""
        n_dims, n = self.eig.shape
        totals = np.zeros(len(k))
        buf, var = np.empty(min(n, _CHUNK)), np.empty(min(n, _CHUNK))
        with np.errstate(divide="ignore", invalid="ignore"):
            for start in range(0, n, _CHUNK):
                sl = slice(start, min(start + _CHUNK, n))
                b, v = buf[:sl.stop - start], var[:sl.stop - start]
                kd = k[codes[sl]] * self.dist[sl]
                b.fill(0.0)
                for j in range(n_dims):
                    np.add(self.eig[j, sl], kd, out=v)
                    b += np.log(v)
                    b += self.sq[j, sl] / v
                totals += np.bincount(codes[sl], weights=b, minlength=len(k))
            counts = np.bincount(codes, minlength=len(k))
            value = 0.5 * totals / counts + 0.5 * n_dims * _LOG_2PI
        return np.where(np.isfinite(value), value, np.inf)


@dataclass(frozen=True)
class _Binned:
    """Sufficient statistics of one group's NLL as a function of k (module docstring).

    With `n` samples of `D` dims, pairs with `d > 0` and `a = λ/d > 0` binned by `a`:

        NLL(k) = (const + Σ_bins [count·log(ā + k) + b_sum/(ā_b + k)]
                  + n_zero·log k + b_zero/k) / (2n) + D/2 log 2π,

    `ā [B]` the mean `a` of a bin, `ā_b [B]` its `b`-weighted mean (so both first-order
    errors vanish), `n_zero`/`b_zero` the count and `Σ b` of pairs with `a = 0` (exact), and
    `const` the sum of `log d` over pairs with `d > 0` plus the k-free terms of `d = 0`.
    """

    n: int
    n_dims: int
    const: float
    count: np.ndarray
    a_mean: np.ndarray
    b_sum: np.ndarray
    a_bmean: np.ndarray
    n_zero: float
    b_zero: float

    @classmethod
    def from_sums(cls, n: int, n_dims: int, const: float, count: np.ndarray, sum_a: np.ndarray,
                  sum_b: np.ndarray, sum_ab: np.ndarray) -> _Binned:
        """From per-bin sums `[1 + B]` of 1, a, b and a·b; bin 0 holds the pairs with
        `a = 0`, empty bins are dropped."""
        n_zero, b_zero = float(count[0]), float(sum_b[0])
        used = count[1:] > 0
        count, sum_a, sum_b, sum_ab = (x[1:][used] for x in (count, sum_a, sum_b, sum_ab))
        a_mean = sum_a / count
        with np.errstate(divide="ignore", invalid="ignore"):
            a_bmean = np.where(sum_b > 0, sum_ab / sum_b, a_mean)
        return cls(n, n_dims, const, count.astype(np.float64), a_mean, sum_b, a_bmean,
                   n_zero, b_zero)

    def nll(self, k: float) -> float:
        """The mean Gaussian NLL at `k`, from the bins (inf where it is not finite).

        Dot products use `np.einsum`, numpy's own loop: a BLAS dot may start threads, which
        costs milliseconds per call on a busy machine (this runs ~15 times per class)."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            total = (self.const + float(np.einsum("i,i->", self.count, np.log(self.a_mean + k)))
                     + float(np.einsum("i,i->", self.b_sum, 1.0 / (self.a_bmean + k))))
            if self.n_zero:
                total += self.n_zero * np.log(k) + np.divide(self.b_zero, k)
            value = 0.5 * total / self.n + 0.5 * self.n_dims * _LOG_2PI
        return float(value) if np.isfinite(value) else np.inf


def _binned(terms: _Terms, codes: np.ndarray, n_groups: int) -> tuple[list[_Binned], _Binned]:
    """`_Binned` statistics of every group `g` (`codes [N] == g`) and of all samples pooled,
    on one logarithmic grid of `a = λ/d` (`_log_bin`)."""
    n_dims = terms.eig.shape[0]
    near = terms.dist == 0
    with np.errstate(divide="ignore"):
        row_const = n_dims * np.log(terms.dist)
    if near.any():  # d = 0: Σ is regular there (checked in build); its terms are k-free
        eig, sq = terms.eig[:, near], terms.sq[:, near]
        row_const[near] = (np.log(eig) + sq / eig).sum(axis=0)
        far = ~near
        eig, sq, dist, far_codes = terms.eig[:, far], terms.sq[:, far], terms.dist[far], codes[far]
    else:
        eig, sq, dist, far_codes = terms.eig, terms.sq, terms.dist, codes
    const = np.bincount(codes, weights=row_const, minlength=n_groups)
    n = np.bincount(codes, minlength=n_groups)

    a, b = eig / dist, sq / dist  # [D, M]
    key, n_bins = _log_bin(a)  # bin 0 holds a = 0 (Σ None or singular): log k + b/k, exact
    key += (far_codes * (n_bins + 1))[None, :]
    key, a, b = key.ravel(), a.ravel(), b.ravel()
    size = n_groups * (n_bins + 1)
    sums = [np.bincount(key, weights=w, minlength=size).reshape(n_groups, n_bins + 1)
            for w in (None, a, b, a * b)]
    groups = [_Binned.from_sums(int(n[g]), n_dims, float(const[g]), *(x[g] for x in sums))
              for g in range(n_groups)]
    pooled = _Binned.from_sums(int(n.sum()), n_dims, float(const.sum()),
                               *(x.sum(axis=0) for x in sums))
    return groups, pooled


def _log_bin(a: np.ndarray) -> tuple[np.ndarray, int]:
    """Bins of the floats `a >= 0` (any shape): `(bin [same shape], B)` with bins `1 .. B` for
    `a > 0` (increasing with `a`, B <= `_BINS`) and bin 0 for `a == 0`; no logarithm taken.

    The bits of a positive float64 read as an int64 grow with its value: dropping all but the
    top `_MANTISSA_BITS` mantissa bits splits every octave into `2**_MANTISSA_BITS` equal
    bins (relative width <= 2**-_MANTISSA_BITS). The grid spans the observed `a`, at most
    `_OCTAVES` octaves below the largest; anything smaller shares the lowest bin (such `a` are
    below 1e-19 of the largest, negligible next to any k Brent tries).
    """
    key = a.view(np.int64) >> (52 - _MANTISSA_BITS)
    positive = a > 0
    if not positive.any():
        return np.zeros(a.shape, dtype=np.int64), 0
    top = int(key.max())
    low = max(int(key[positive].min()), top - _BINS + 1)
    key -= low - 1
    np.maximum(key, 1, out=key)
    key[~positive] = 0
    return key, top - low + 1


def _fit_k(stats: _Binned | _Terms, bounds: tuple[float, float], xtol: float,
           label: Hashable) -> float:
    """Minimise `stats.nll` over k in `bounds`: Brent on log k (see `_brent`), widened once if
    the optimum is at the upper bound, then compared with k = low itself (k = 0 is valid)."""
    low, high = bounds
    k, nll = _brent(stats, low, high, xtol)
    if _at_edge(k, high, xtol):
        k, nll = _brent(stats, low, high * _WIDEN, xtol)
        if _at_edge(k, high * _WIDEN, xtol):
            warnings.warn(f"depth k for class {label!r} is at the search edge {high * _WIDEN}; "
                          "the residuals may not grow with distance", RuntimeWarning,
                          stacklevel=3)
    return float(low) if stats.nll(low) <= nll else float(k)


def _at_edge(k: float, high: float, xtol: float) -> bool:
    return np.log(high) - np.log(k) < 10 * xtol


def _brent(stats: _Binned | _Terms, low: float, high: float, xtol: float
           ) -> tuple[float, float]:
    """Bounded Brent on log k in [log max(low, 1e-9·high), log high]; `xtol` is on log k.

    Log k reaches the scale of k (1e-3 .. 1 m²/m) in a few steps where a linear search from
    [0, 25] spends a dozen golden-section steps; values below 1e-9·high are covered by the
    k = low check in `_fit_k`.
    """
    lo = np.log(max(low, 1e-9 * high))
    result = minimize_scalar(lambda u: stats.nll(float(np.exp(u))), bounds=(lo, np.log(high)),
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


def _class_codes(classes: np.ndarray, n: int) -> tuple[list, np.ndarray]:
    """Distinct class labels (as Python scalars, sorted) and the code `[N]` of each entry."""
    arr = np.asarray(classes)
    if arr.ndim != 1:
        raise ValueError(f"classes must have 1 dimension, got shape {arr.shape}")
    check_length("classes", arr, n, "distances")
    if n == 0:
        return [], np.zeros(0, dtype=np.int64)
    if arr.dtype.kind in "iu":
        low, high = int(arr.min()), int(arr.max())
        if high - low <= 4 * n:  # small integer labels: a counting pass, no sort
            present = np.bincount(arr - low, minlength=high - low + 1) > 0
            code_of = np.cumsum(present) - 1
            return (np.flatnonzero(present) + low).tolist(), code_of[arr - low]
    try:
        keys, codes = np.unique(arr, return_inverse=True)
    except TypeError:
        raise ValueError("classes must be labels of one comparable type (all ints or all strs)"
                         ) from None
    return keys.tolist(), codes.reshape(-1).astype(np.int64)
