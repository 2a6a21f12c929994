"""The classification NLL of temperature scaling as a function of `log T`: exact (sigmoid and
softmax), and the sigmoid NLL from binned sufficient statistics (`SigmoidBins`); used by
`calibrators.temperature` (in memory) and `calibrators.stream` (per chunk, then merged).

An objective is a function `log T -> mean NLL`. Float64 arithmetic throughout.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

Objective = Callable[[float], float]

SIGMOID_BINS = 1 << 16  # bins of the predicted logit (sigmoid, more detections than this)
_COARSEN = 64  # the bracketing search runs on bins this many times as wide
_COARSE_XTOL = 1e-3  # Brent tolerance on log T of the bracketing search
_SIGMOID_BRACKET = 0.05  # width in log T of the fine search's first bracket
_GOLDEN = (3.0 - 5.0**0.5) / 2.0  # where bounded Brent places its first point in a bracket
_CHUNK_FLOATS = 1 << 16  # 512 KiB of float64 per work buffer: stays in the CPU cache


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """`a [M] · b [M]` by numpy's own loop: a BLAS dot may start threads, which on a busy
    machine costs milliseconds per call."""
    return float(np.einsum("i,i->", a, b))


def _chunks(n: int, width: int) -> list[slice]:
    """Row slices covering `range(n)` whose `[rows, width]` blocks fit the cache budget."""
    rows = max(256, _CHUNK_FLOATS // max(width, 1))
    return [slice(i, min(i + rows, n)) for i in range(0, n, rows)]


def row_max(z: np.ndarray) -> np.ndarray:
    """`z.max(axis=1)` for `[N, C']` as float64, as column-wise maxima over cache-sized row
    blocks (several times faster than numpy's reduction over short rows)."""
    if z.shape[1] == 1:
        return np.ascontiguousarray(z[:, 0], dtype=np.float64)
    out = np.empty(z.shape[0])
    for sl in _chunks(z.shape[0], z.shape[1]):
        block, m = z[sl], out[sl]
        np.copyto(m, block[:, 0])
        for j in range(1, z.shape[1]):
            np.maximum(m, block[:, j], out=m)
    return out


def sigmoid_nll(s: np.ndarray, y: np.ndarray) -> Objective:
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


@dataclass(frozen=True)
class SigmoidBins:
    """Sufficient statistics of the sigmoid NLL of predicted logits `s [N]`, labels `y [N]`.

    `n`, `sum_ys = Σ y·s`, the grid (`low`, bin `width`) and per bin `[B]`: `count`, and
    `offset` / `offset_sq` / `offset_cu`, the sums of each logit's offset from its bin's left
    edge (in bin widths), of its square and of its cube. Sums over disjoint parts of the data
    on the same grid add up (`+`), so a dataset can be binned chunk by chunk.

    `objective()`: the linear term `mean(y·s)/T` is exact; a bin of `m` logits with mean
    `s̄` and central moments `M2`, `M3` stands for its third-order Taylor sum about `s̄`,
    `m·f(x) + M2/(2T²)·f2(x) + M3/(6T³)·f3(x)`, `x = s̄/T`, `f` = softplus and `f2`, `f3` its
    second and third derivatives (the first-order terms cancel about the mean). The fourth
    derivative of softplus is at most 1/8 in magnitude, so the mean NLL is off by at most
    `(h/T)^4 / 192` for bins of width `h` (`error_bound`), about 1e-17 for logits spanning
    30 at T = 1 on `SIGMOID_BINS` bins.
    """

    n: int
    sum_ys: float
    low: float
    width: float
    count: np.ndarray
    offset: np.ndarray
    offset_sq: np.ndarray
    offset_cu: np.ndarray

    @staticmethod
    def grid(low: float, high: float, n_bins: int = SIGMOID_BINS) -> tuple[float, float]:
        """(low, bin width) of `n_bins` equal bins over `[low, high]` (width 1 if empty)."""
        span = float(high) - float(low)
        return float(low), (span / n_bins if span > 0 else 1.0)

    @classmethod
    def from_logits(cls, s: np.ndarray, y: np.ndarray, n_bins: int = SIGMOID_BINS,
                    span: tuple[float, float] | None = None) -> SigmoidBins:
        """Bin `s [N]` (float64) with 0/1 labels `y [N]` on `n_bins` bins over `span`
        (`(low, high)`, containing every `s`; default `(min s, max s)`)."""
        low, high = (float(s.min()), float(s.max())) if span is None else span
        low, width = cls.grid(low, high, n_bins)
        pos = np.subtract(s, low)
        pos *= 1.0 / width   # in [0, n_bins]: integer part = bin, the rest = the offset
        idx = pos.astype(np.intp)
        np.clip(idx, 0, n_bins - 1, out=idx)
        pos -= idx
        count = np.bincount(idx, minlength=n_bins).astype(np.float64)
        offset = np.bincount(idx, weights=pos, minlength=n_bins)
        power = pos * pos
        offset_sq = np.bincount(idx, weights=power, minlength=n_bins)
        power *= pos
        return cls(n=len(s), sum_ys=_dot(y.astype(np.float64), s), low=low, width=width,
                   count=count, offset=offset, offset_sq=offset_sq,
                   offset_cu=np.bincount(idx, weights=power, minlength=n_bins))

    def error_bound(self, log_t: float) -> float:
        """Bound on the absolute error of `objective()(log_t)`: `(h/T)^4 / 192`."""
        return float((self.width * np.exp(-log_t)) ** 4 / 192.0)

    def __add__(self, other: SigmoidBins) -> SigmoidBins:
        if (self.low, self.width, len(self.count)) != (other.low, other.width, len(other.count)):
            raise ValueError("SigmoidBins on different grids cannot be added")
        return SigmoidBins(self.n + other.n, self.sum_ys + other.sum_ys, self.low, self.width,
                           self.count + other.count, self.offset + other.offset,
                           self.offset_sq + other.offset_sq, self.offset_cu + other.offset_cu)

    def coarsen(self, factor: int) -> SigmoidBins:
        """The same statistics on bins `factor` times as wide (`B` divisible by `factor`):
        an offset `o` in fine bin `j` of a coarse bin is `(j + o) / factor` there."""
        j = np.tile(np.arange(factor, dtype=np.float64), len(self.count) // factor)
        m, s1, s2, s3 = self.count, self.offset, self.offset_sq, self.offset_cu

        def merged(x: np.ndarray) -> np.ndarray:
            return x.reshape(-1, factor).sum(axis=1)

        return SigmoidBins(
            self.n, self.sum_ys, self.low, self.width * factor, merged(m),
            merged((m * j + s1) / factor), merged((m * j * j + 2.0 * j * s1 + s2) / factor**2),
            merged((m * j**3 + 3.0 * j * j * s1 + 3.0 * j * s2 + s3) / factor**3))

    def objective(self) -> Objective:
        """The mean NLL vs `log T` from the bins (class docstring), O(used bins) per call.

        With `e = exp(-|x|)`: `softplus(x) = max(x, 0) + log1p(e)`, `f2 = σ(1 - σ) =
        e / (1 + e)²` and `f3 = σ(1 - σ)(1 - 2σ) = -sign(x)·f2·(1 - e) / (1 + e)`; the
        `max(x, 0)` part is linear in 1/T and summed once."""
        used = self.count > 0
        m = self.count[used]
        mean_offset = self.offset[used] / m
        centre = self.low + (np.flatnonzero(used) + mean_offset) * self.width
        s2 = self.offset_sq[used]
        half_m2 = 0.5 * np.maximum(s2 - m * mean_offset**2, 0.0) * self.width**2 / self.n
        m3 = self.offset_cu[used] - 3.0 * mean_offset * s2 + 2.0 * m * mean_offset**3
        sixth_m3 = -np.sign(centre) * m3 * self.width**3 / (6.0 * self.n)
        weight = m / self.n
        positive = _dot(weight, np.maximum(centre, 0.0))
        neg_abs = -np.abs(centre)
        mean_ys = self.sum_ys / self.n

        def nll(log_t: float) -> float:
            inv_t = float(np.exp(-log_t))
            e = np.exp(neg_abs * inv_t)
            tail = _dot(weight, np.log1p(e))
            e1 = 1.0 + e
            f2 = e / (e1 * e1)
            curvature = _dot(half_m2, f2) * inv_t**2
            skew = _dot(sixth_m3, f2 * (1.0 - e) / e1) * inv_t**3
            return (positive - mean_ys) * inv_t + tail + curvature + skew

        return nll

    def bracket(self, bounds: tuple[float, float]) -> tuple[float, float]:
        """A `_SIGMOID_BRACKET` bracket on log T (within `bounds`) around the optimum of the
        coarsened bins (a few microseconds per evaluation), placed where bounded Brent takes
        its first point. A miss only costs evaluations: the search widens it."""
        factor = _COARSEN if len(self.count) % _COARSEN == 0 else 1
        coarse = self.coarsen(factor).objective()
        result = minimize_scalar(coarse, bounds=bounds, method="bounded",
                                 options={"xatol": _COARSE_XTOL})
        centre = float(result.x)
        return (max(bounds[0], centre - _GOLDEN * _SIGMOID_BRACKET),
                min(bounds[1], centre + (1.0 - _GOLDEN) * _SIGMOID_BRACKET))


def softmax_terms(z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """`(z - row max [N, C'], Σ of the shifted target logits)` of `z [N, C']`, `y [N]`."""
    shifted = z - row_max(z)[:, None]
    return shifted, float(shifted[np.arange(len(z)), y].sum())


def softmax_log_sum(shifted: np.ndarray, inv_t: float, buf: np.ndarray | None = None,
                    row_sums: np.ndarray | None = None) -> float:
    """`Σ_rows log Σ_cols exp(shifted / T)` of `shifted [N, C']` (rows shifted to max 0),
    exponentiating cache-sized blocks in one buffer and summing rows by a matrix-vector
    product."""
    n, width = shifted.shape
    chunks = _chunks(n, width)
    buf = np.empty((chunks[0].stop, width)) if buf is None else buf
    row_sums = np.empty(n) if row_sums is None else row_sums
    ones = np.ones(width)
    for sl in chunks:
        block = buf[:sl.stop - sl.start]
        np.multiply(shifted[sl], inv_t, out=block)
        np.exp(block, out=block)
        np.matmul(block, ones, out=row_sums[sl])
    return float(np.log(row_sums).sum())


def softmax_nll(z: np.ndarray, y: np.ndarray) -> Objective:
    """Mean categorical NLL `mean(logsumexp(z/T) - z_y/T)` as a function of `log T`.

    Rows are shifted by their maximum `m` once (`z - m <= 0`); since `T > 0`,
    `logsumexp(z/T) = m/T + log(sum(exp((z - m)/T)))`, which never overflows.
    """
    n, width = z.shape
    shifted, sum_shift_target = softmax_terms(z, y)
    buf = np.empty((_chunks(n, width)[0].stop, width))
    row_sums = np.empty(n)

    def nll(log_t: float) -> float:
        inv_t = float(np.exp(-log_t))
        return (softmax_log_sum(shifted, inv_t, buf, row_sums) - sum_shift_target * inv_t) / n

    return nll
