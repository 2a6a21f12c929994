"""The Gaussian NLL of depth scaling as a function of `k`, exact (`DepthTerms`) and binned
(`DepthBins`), on the grid of `_depth_grid`, searched by `_depth_search`
(`fit_k`); used by `DepthScaler` and `ShrinkageDepthScaler`. The math is in the docstring
of `_depth`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.covariance._depth_grid import (  # noqa: F401
    GRID_BINS,
    MANTISSA_BITS,
    OCTAVES,
    bin_key,
    log_bin,
    log_bin_low,
    raw_key,
)
from calibrators.covariance._spectral import spectral, spectral_2x2

_LOG_2PI = float(np.log(2.0 * np.pi))
_CHUNK = 1 << 15  # samples per block of the NLL and binning loops: buffers stay in the cache
_U64_MAX = int(np.iinfo(np.uint64).max)


@dataclass(frozen=True)
class DepthTerms:
    """Per-sample NLL terms, dims first: `eig [D, N]` of Σ, `sq [D, N] = (Uᵀ r)²`, `dist [N]`."""

    eig: np.ndarray
    sq: np.ndarray
    dist: np.ndarray
    grid: tuple[int, int, bool] | None = None  # `_key_grid(self, [])` when taken in build

    @classmethod
    def build(cls, r: np.ndarray, cov: np.ndarray | None, d: np.ndarray) -> DepthTerms:
        """Terms of residuals `r [N, D]` under `cov [N, D, D]` (None = 0) at distances `d`;
        checks that Σ is symmetric PSD and that Σ + k·d·I can be regular."""
        near = np.flatnonzero(d == 0)
        scan = None
        if cov is None:
            eig, sq = np.zeros((r.shape[1], r.shape[0])), np.ascontiguousarray((r * r).T)
        elif r.shape[1] == 2:  # the grid of a = λ/d from each block while it is in the cache
            scan = None if len(near) else _GridScan(d)
            eig, sq = spectral_2x2(cov, r, None if scan is None else scan.add_block)
        else:
            eig, sq = spectral(cov, r)
        # eig >= 0, ascending (`_zero_tiny`): row 0 is the min
        singular = near[eig[0, near] == 0]
        if len(singular):
            i = int(singular[0])
            what = "covariances is None" if cov is None else f"covariances[{i}] is singular"
            raise ValueError(f"distances[{i}] is 0 and {what}: Σ + k·d·I is singular for every k")
        return cls(eig, sq, d, None if scan is None else scan.grid())

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

    def fitted_nll(self, k: np.ndarray, codes: np.ndarray, pooled_k: float,
                   counts: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """`(group_nll(k, codes), nll(pooled_k))` in one pass over the data, each summed in
        the same order as there; `counts [G]`, the samples per group, if known."""
        n_dims, n = self.eig.shape
        totals, pooled = np.zeros(len(k)), 0.0
        size = min(n, _CHUNK)
        buf, var, tmp, kd, kd_pooled = (np.empty(size) for _ in range(5))
        with np.errstate(divide="ignore", invalid="ignore"):
            for start in range(0, n, _CHUNK):
                sl = slice(start, min(start + _CHUNK, n))
                m = sl.stop - start
                b, v, t, kg, kp = buf[:m], var[:m], tmp[:m], kd[:m], kd_pooled[:m]
                group, dist = codes[sl], self.dist[sl]
                np.take(k, group, out=kg)
                kg *= dist
                np.multiply(dist, pooled_k, out=kp)
                for j in range(n_dims):
                    eig, sq = self.eig[j, sl], self.sq[j, sl]
                    np.add(eig, kg, out=v)
                    if j:
                        b += np.log(v, out=t)
                    else:  # the same as 0 + log v
                        np.log(v, out=b)
                    b += np.divide(sq, v, out=t)
                    np.add(kp, eig, out=v)
                    pooled += float(np.log(v, out=t).sum())
                    pooled += float(np.divide(sq, v, out=t).sum())
                totals += np.bincount(group, weights=b, minlength=len(k))
            if counts is None:
                counts = np.bincount(codes, minlength=len(k))
            value = 0.5 * totals / counts + 0.5 * n_dims * _LOG_2PI
            pooled_value = 0.5 * pooled / n + 0.5 * n_dims * _LOG_2PI
        return (np.where(np.isfinite(value), value, np.inf),
                pooled_value if np.isfinite(pooled_value) else np.inf)


@dataclass(frozen=True)
class DepthBins:
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
                  sum_b: np.ndarray, sum_ab: np.ndarray) -> DepthBins:
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
    """Additive per-group sums behind `DepthBins` (module docstring of `_depth`).

    `n [G]` samples and `const [G]` (sum of the k-free terms) per group, and `sums [4, G,
    1 + B]`: the sums of 1, a, b and a·b per group and bin; column 0 holds the pairs with
    `a = 0`, column `i >= 1` the raw log-bin key `low - 1 + i` (`raw_key`). Sums over disjoint
    parts of the data add up (`+`, which also re-applies the grid's floor of `OCTAVES`
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
    def build(cls, terms: DepthTerms, codes: np.ndarray, n_groups: int) -> BinSums:
        """Sums of the terms of samples in groups `codes [N]` (0 .. n_groups - 1), in
        cache-sized blocks of samples: no full-size temporary array. Pairs are added dim by
        dim, samples in order (`np.add.at` adds in index order), so every sum is rounded
        exactly as one `np.bincount` over the `[D, N]` pairs rounds it."""
        n_dims, size = terms.eig.shape
        near = np.flatnonzero(terms.dist == 0)
        low, n_bins, plain = terms.grid if terms.grid is not None else _key_grid(terms, near)
        width = n_bins + 1
        group_offset = np.arange(n_groups) * width + (1 - low if plain else 0)
        sums = np.zeros((4, n_groups, width))
        flat = sums.reshape(4, -1)  # the groups' columns side by side: key = g·(1 + B) + bin
        const = np.zeros(n_groups)
        buf = _PairBuffers(min(size, _CHUNK))
        for j in range(n_dims):
            for start in range(0, size, _CHUNK):
                stop = min(start + _CHUNK, size)
                if j == 0:
                    np.add.at(const, codes[start:stop], _row_const(terms, start, stop, near))
                rows = _far_rows(start, stop, near)
                group = codes[rows]
                a, b, key = buf.pairs(terms, j, rows)
                bin_key(a, low, n_bins, plain, out=key)
                key += np.take(group_offset, group, out=buf.offset[:len(group)])
                np.add.at(flat[0], key, 1.0)
                np.add.at(flat[1], key, a)
                np.add.at(flat[2], key, b)
                b *= a
                np.add.at(flat[3], key, b)
        # every sample with d > 0 put D pairs in its group's bins (exact counts in float)
        n = sums[0].sum(axis=1).astype(np.int64) // n_dims
        n += np.bincount(codes[near], minlength=n_groups)[:n_groups]
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
        low = max(min(p.low for p in parts), top - GRID_BINS + 1)
        sums = np.zeros((4, len(self.n), top - low + 2))
        for p in (self, other):
            sums[:, :, 0] += p.sums[:, :, 0]
            if p.sums.shape[2] > 1:  # key -> column, keys under the floor into its bin
                cols = np.maximum(np.arange(p.low, p.top + 1), low) - low + 1
                np.add.at(sums, (slice(None), slice(None), cols), p.sums[:, :, 1:])
        return BinSums(self.n_dims, self.n + other.n, self.const + other.const, low, sums)

    def finish(self) -> tuple[list[DepthBins], DepthBins]:
        """`DepthBins` statistics of every group and of all groups pooled."""
        groups = [DepthBins.from_sums(int(self.n[g]), self.n_dims, float(self.const[g]),
                                    *self.sums[:, g]) for g in range(len(self.n))]
        pooled = DepthBins.from_sums(int(self.n.sum()), self.n_dims, float(self.const.sum()),
                                   *self.sums.sum(axis=1))
        return groups, pooled


class _PairBuffers:
    """Reused buffers of one block of `BinSums.build`: `a = λ/d`, `b = q/d` and the bin keys
    `[m]` of one dim, and the group offsets `[m]`."""

    def __init__(self, size: int) -> None:
        self.a, self.b = np.empty(size), np.empty(size)
        self.key, self.offset = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)

    def pairs(self, terms: DepthTerms, j: int, rows: slice | np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`(a [m], b [m], key buffer [m])` of dim `j` of the samples `rows` (all d > 0)."""
        dist = terms.dist[rows]
        a, b = self.a[:len(dist)], self.b[:len(dist)]
        np.divide(terms.eig[j, rows], dist, out=a)
        np.divide(terms.sq[j, rows], dist, out=b)
        return a, b, self.key[:len(dist)]


def _row_const(terms: DepthTerms, start: int, stop: int, near: np.ndarray) -> np.ndarray:
    """The k-free terms `[m]` of samples `start .. stop - 1`: `D·log d`, and for d = 0 (the
    sorted indices `near`; Σ is regular there, checked in `DepthTerms.build`) the whole NLL sum
    `Σ_j log λ_j + q_j/λ_j`."""
    with np.errstate(divide="ignore"):
        row = terms.eig.shape[0] * np.log(terms.dist[start:stop])
    lo, hi = np.searchsorted(near, (start, stop))
    if lo < hi:
        idx = near[lo:hi]
        eig, sq = terms.eig[:, idx], terms.sq[:, idx]
        row[idx - start] = (np.log(eig) + sq / eig).sum(axis=0)
    return row


def _far_rows(start: int, stop: int, near: np.ndarray) -> slice | np.ndarray:
    """The samples `start .. stop - 1` that are not in `near` (sorted indices, d = 0): a
    slice, or an index array where the block holds some of `near`."""
    lo, hi = np.searchsorted(near, (start, stop))
    if lo == hi:
        return slice(start, stop)
    keep = np.ones(stop - start, dtype=bool)
    keep[near[lo:hi] - start] = False
    return np.flatnonzero(keep) + start


def _key_grid(terms: DepthTerms, near: np.ndarray) -> tuple[int, int, bool]:
    """`_GridScan.grid()` of the `a = λ/d` of all samples not in `near` (d > 0), in blocks."""
    n_dims, size = terms.eig.shape
    scan = _GridScan(terms.dist)
    buf = np.empty(n_dims * min(size, _CHUNK))
    for start in range(0, size, _CHUNK):
        rows = _far_rows(start, min(start + _CHUNK, size), near)
        dist = terms.dist[rows]
        a = buf[:n_dims * len(dist)].reshape(n_dims, len(dist))
        scan.add(np.divide(terms.eig[:, rows], dist, out=a))
    return scan.grid()


class _GridScan:
    """The largest and the smallest positive of blocks of `a = λ/d >= 0` (`_zero_tiny`), and
    whether any is 0: what `grid()` (`log_bin_low`'s grid) needs."""

    def __init__(self, dist: np.ndarray) -> None:
        self.dist, self.buf, self.bits = dist, np.empty(0), np.empty(0, dtype=np.uint64)
        self.largest, self.smallest, self.wrapped = 0, _U64_MAX, 0

    def add_block(self, start: int, eig: np.ndarray) -> None:
        """Adds `eig [D, m]` of samples `start ..` (all d > 0); `start = 0` starts afresh."""
        if start == 0:
            self.largest, self.smallest, self.wrapped = 0, _U64_MAX, 0
        m = eig.shape[1]
        if self.buf.size < eig.size:
            self.buf = np.empty(eig.size)
        a = self.buf[:eig.size].reshape(eig.shape)
        self.add(np.divide(eig, self.dist[start:start + m], out=a))

    def add(self, a: np.ndarray) -> None:
        """Adds the contiguous `a` (any shape)."""
        if not a.size:
            return
        # the bits of a >= 0 grow with it; a = 0 (bits 0) - 1 wraps to the largest uint64
        bits = a.reshape(-1).view(np.uint64)
        if self.bits.size < a.size:
            self.bits = np.empty(a.size, dtype=np.uint64)
        below = np.subtract(bits, 1, out=self.bits[:a.size])
        self.smallest, high = min(self.smallest, int(below.min())), int(below.max())
        self.wrapped = max(self.wrapped, high)
        self.largest = max(self.largest, int(bits.max()) if high == _U64_MAX else high + 1)

    def grid(self) -> tuple[int, int, bool]:
        """`(low, B, plain)`: the grid `log_bin_low` puts on the `a`, from the largest `a`
        and the smallest positive one (`(0, 0, False)` when no `a > 0`); `plain` when no `a`
        is 0 and the grid reaches the smallest, so that every bin is `1 + raw key - low`."""
        if self.largest == 0:
            return 0, 0, False
        top = self.largest >> (52 - MANTISSA_BITS)
        low = (self.smallest + 1) >> (52 - MANTISSA_BITS)
        plain = self.wrapped < _U64_MAX and low >= top - GRID_BINS + 1
        low = max(low, top - GRID_BINS + 1)
        return low, top - low + 1, plain


def depth_bins(terms: DepthTerms, codes: np.ndarray, n_groups: int
               ) -> tuple[list[DepthBins], DepthBins]:
    """`DepthBins` statistics of every group `g` (`codes [N] == g`) and of all samples pooled,
    on one logarithmic grid of `a = λ/d` (`log_bin`)."""
    return BinSums.build(terms, codes, n_groups).finish()


