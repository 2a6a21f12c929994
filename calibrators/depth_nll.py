"""The Gaussian NLL of depth scaling as a function of `k`, exact (`_Terms`) and binned
(`_Binned`), and the bounded Brent search on it (`_fit_k`); used by `DepthScaler` and
`ShrinkageDepthScaler`. The math is in the docstring of `calibrators.depth`.
"""

from __future__ import annotations

import warnings
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from calibrators._spectral import _spectral, _spectral_2x2

_LOG_2PI = float(np.log(2.0 * np.pi))
_WIDEN = 100.0  # an optimum at the upper bound is searched again once up to 100 x the bound
_CHUNK = 1 << 15  # samples per block in the NLL loop: its buffers stay in the CPU cache
_MANTISSA_BITS = 9  # bins of a = λ/d per octave: 2**9, a relative width <= 2e-3
_OCTAVES = 64  # octaves of a below its maximum that the grid covers
_BINS = _OCTAVES << _MANTISSA_BITS  # bins per class


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


@dataclass(frozen=True)
class BinSums:
    """Additive per-group sums behind `_Binned` (module docstring of `calibrators.depth`).

    `n [G]` samples and `const [G]` (sum of the k-free terms) per group, and `sums [4, G,
    1 + B]`: the sums of 1, a, b and a·b per group and bin; column 0 holds the pairs with
    `a = 0`, column `i >= 1` the raw log-bin key `low - 1 + i` (`_raw_key`). Sums over disjoint
    parts of the data add up (`+`, which also re-applies the grid's floor of `_OCTAVES`
    octaves below the largest key), so a dataset can be binned chunk by chunk; `finish()`
    gives exactly the statistics of binning all of it at once.
    """

    n_dims: int
    n: np.ndarray
    const: np.ndarray
    low: int
    sums: np.ndarray

    @property
    def top(self) -> int:
        return self.low + self.sums.shape[2] - 2

    @classmethod
    def build(cls, terms: _Terms, codes: np.ndarray, n_groups: int) -> BinSums:
        """Sums of the terms of samples in groups `codes [N]` (0 .. n_groups - 1)."""
        n_dims = terms.eig.shape[0]
        near = terms.dist == 0
        with np.errstate(divide="ignore"):
            row_const = n_dims * np.log(terms.dist)
        if near.any():  # d = 0: Σ is regular there (checked in build); its terms are k-free
            eig, sq = terms.eig[:, near], terms.sq[:, near]
            row_const[near] = (np.log(eig) + sq / eig).sum(axis=0)
            far = ~near
            eig, sq, dist, far_codes = (terms.eig[:, far], terms.sq[:, far], terms.dist[far],
                                        codes[far])
        else:
            eig, sq, dist, far_codes = terms.eig, terms.sq, terms.dist, codes
        const = np.bincount(codes, weights=row_const, minlength=n_groups)[:n_groups]
        n = np.bincount(codes, minlength=n_groups)[:n_groups]
        a, b = eig / dist, sq / dist  # [D, M]
        key, n_bins, low = _log_bin_low(a)
        key += (far_codes * (n_bins + 1))[None, :]
        key, a, b = key.ravel(), a.ravel(), b.ravel()
        size = n_groups * (n_bins + 1)
        sums = np.stack([np.bincount(key, weights=w, minlength=size).reshape(n_groups, n_bins + 1)
                         for w in (None, a, b, a * b)])
        return cls(n_dims, n, const, low, sums)

    @classmethod
    def build_empty(cls, n_dims: int, n_groups: int) -> BinSums:
        """The sums of no sample."""
        return cls(n_dims, np.zeros(n_groups, dtype=np.int64), np.zeros(n_groups), 0,
                   np.zeros((4, n_groups, 1)))

    def __add__(self, other: BinSums) -> BinSums:
        if self.n_dims != other.n_dims or self.n.shape != other.n.shape:
            raise ValueError("BinSums of different dimensions or groups cannot be added")
        parts = [p for p in (self, other) if p.sums.shape[2] > 1]
        if not parts:
            return BinSums(self.n_dims, self.n + other.n, self.const + other.const, 0,
                           self.sums + other.sums)
        top = max(p.top for p in parts)
        low = max(min(p.low for p in parts), top - _BINS + 1)
        sums = np.zeros((4, len(self.n), top - low + 2))
        for p in (self, other):
            sums[:, :, 0] += p.sums[:, :, 0]
            if p.sums.shape[2] > 1:  # key -> column, keys under the floor into its bin
                cols = np.maximum(np.arange(p.low, p.top + 1), low) - low + 1
                np.add.at(sums, (slice(None), slice(None), cols), p.sums[:, :, 1:])
        return BinSums(self.n_dims, self.n + other.n, self.const + other.const, low, sums)

    def finish(self) -> tuple[list[_Binned], _Binned]:
        """`_Binned` statistics of every group and of all groups pooled."""
        groups = [_Binned.from_sums(int(self.n[g]), self.n_dims, float(self.const[g]),
                                    *self.sums[:, g]) for g in range(len(self.n))]
        pooled = _Binned.from_sums(int(self.n.sum()), self.n_dims, float(self.const.sum()),
                                   *self.sums.sum(axis=1))
        return groups, pooled


def _binned(terms: _Terms, codes: np.ndarray, n_groups: int) -> tuple[list[_Binned], _Binned]:
    """`_Binned` statistics of every group `g` (`codes [N] == g`) and of all samples pooled,
    on one logarithmic grid of `a = λ/d` (`_log_bin`)."""
    return BinSums.build(terms, codes, n_groups).finish()


def _log_bin(a: np.ndarray) -> tuple[np.ndarray, int]:
    """Bins of the floats `a >= 0` (any shape): `(bin [same shape], B)` with bins `1 .. B` for
    `a > 0` (increasing with `a`, B <= `_BINS`) and bin 0 for `a == 0`; no logarithm taken.

    The bits of a positive float64 read as an int64 grow with its value: dropping all but the
    top `_MANTISSA_BITS` mantissa bits splits every octave into `2**_MANTISSA_BITS` equal
    bins (relative width <= 2**-_MANTISSA_BITS). The grid spans the observed `a`, at most
    `_OCTAVES` octaves below the largest; anything smaller shares the lowest bin (such `a` are
    below 1e-19 of the largest, negligible next to any k Brent tries).
    """
    key, n_bins, _ = _log_bin_low(a)
    return key, n_bins


def _log_bin_low(a: np.ndarray) -> tuple[np.ndarray, int, int]:
    """`_log_bin(a)` and the raw key (`_raw_key`) of bin 1 (0 when no `a > 0`)."""
    key = _raw_key(a)
    positive = a > 0
    if not positive.any():
        return np.zeros(a.shape, dtype=np.int64), 0, 0
    top = int(key.max())
    low = max(int(key[positive].min()), top - _BINS + 1)
    key -= low - 1
    np.maximum(key, 1, out=key)
    key[~positive] = 0
    return key, top - low + 1, low


def _raw_key(a: np.ndarray) -> np.ndarray:
    """The float64 bits of `a` without the low mantissa bits: increasing with `a > 0`."""
    return a.view(np.int64) >> (52 - _MANTISSA_BITS)


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
