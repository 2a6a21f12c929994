"""The classification NLL of temperature scaling as a function of `log T`: exact (sigmoid and
softmax), and the sigmoid NLL from binned sufficient statistics (`SigmoidBins`); used by
`_temperature` (in memory) and `calibrators.stream` (per chunk, then merged).

An objective is a function `log T -> mean NLL`; a `ValueGrad` gives `(mean NLL, d mean NLL /
d log T)` (softmax: `SoftmaxSums`, sigmoid bins: `SigmoidBins.value_grad`). Float64
arithmetic throughout.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calibrators.core.checks import check_finite

Objective = Callable[[float], float]
ValueGrad = Callable[[float], tuple[float, float]]

SIGMOID_BINS = 1 << 16  # bins of the predicted logit (sigmoid, more detections than this)
_CHUNK_FLOATS = 1 << 16  # 512 KiB of float64 per work buffer: stays in the CPU cache
_EXP_LIMIT = 600.0  # softmax: a block with |z| / T beyond this is shifted by its rows' max


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
        """(low, bin width) of `n_bins` equal bins over `[low, high]`, a hair (1e-6) wider
        than the span so that `high` falls inside the last bin (width 1 if empty)."""
        span = float(high) - float(low)
        return float(low), (span * (1.0 + 1e-6) / n_bins if span > 0 else 1.0)

    @classmethod
    def from_logits(cls, s: np.ndarray, y: np.ndarray, n_bins: int = SIGMOID_BINS,
                    span: tuple[float, float] | None = None, *, clip: bool = True
                    ) -> SigmoidBins:
        """Bin `s [N]` (float64) with 0/1 labels `y [N]` on `n_bins` bins over `span`
        (`(low, high)`, containing every `s`; default `(min s, max s)`). `clip=False` when
        `span` is exactly `s`'s own minimum and maximum (nothing can round outside)."""
        low, high = (float(s.min()), float(s.max())) if span is None else span
        low, width = cls.grid(low, high, n_bins)
        sums = [np.zeros(n_bins) for _ in range(4)]
        chunks = _chunks(len(s), 1)
        rows = chunks[0].stop if chunks else 0
        pos, whole, power, idx = np.empty(rows), np.empty(rows), np.empty(rows), np.empty(
            rows, dtype=np.intp)
        sum_ys = 0.0
        for sl in chunks:   # cache-sized blocks: no large temporary arrays
            k = sl.stop - sl.start
            p, w, q, i = pos[:k], whole[:k], power[:k], idx[:k]
            np.copyto(q, y[sl], casting="unsafe")   # the labels as floats, block by block
            sum_ys += _dot(q, s[sl])
            np.subtract(s[sl], low, out=p)
            p *= 1.0 / width   # in [0, n_bins): integer part = bin, the rest = the offset
            np.floor(p, out=w)
            np.copyto(i, w, casting="unsafe")
            if span is not None and clip:   # a caller's span: keep stray rounding inside
                np.clip(i, 0, n_bins - 1, out=i)
                np.copyto(w, i)
            p -= w
            np.add.at(sums[0], i, 1.0)   # ufunc.at: no range pass, unlike np.bincount
            np.add.at(sums[1], i, p)
            np.multiply(p, p, out=q)
            np.add.at(sums[2], i, q)
            q *= p
            np.add.at(sums[3], i, q)
        return cls(len(s), sum_ys, low, width, *sums)

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
        an offset `o` in fine bin `j` of a coarse bin is `(j + o) / factor` there, so the
        coarse sums are the fine ones' binomial expansions, taken as products with the
        powers of `j` (no temporaries of the fine grid's size)."""
        j = np.arange(factor, dtype=np.float64)
        j2, j3 = j * j, j * j * j
        # [factor, B / factor]: row j holds fine bin j of every coarse bin, so the sums below
        # run along long rows (numpy is slow at reducing many short ones)
        m, s1, s2, s3 = (np.ascontiguousarray(x.reshape(-1, factor).T)
                         for x in (self.count, self.offset, self.offset_sq, self.offset_cu))

        def at(x: np.ndarray, w: np.ndarray) -> np.ndarray:
            return np.einsum("ji,j->i", x, w)   # numpy's loop: a BLAS call may start threads

        def total(x: np.ndarray) -> np.ndarray:
            return np.add.reduce(x, axis=0)

        return SigmoidBins(
            self.n, self.sum_ys, self.low, self.width * factor, total(m),
            (at(m, j) + total(s1)) / factor,
            (at(m, j2) + 2.0 * at(s1, j) + total(s2)) / factor**2,
            (at(m, j3) + 3.0 * at(s1, j2) + 3.0 * at(s2, j) + total(s3)) / factor**3)

    def gradient_bound(self, log_t: float) -> float:
        """Bound on the absolute error of the derivative in log T of `value_grad()`:
        `(h/T)^4 / 48` (the fourth derivative of `s·σ(s/T)` in `s` is `T^-3·(x f5 + 4 f4)`,
        at most `T^-3 / 2` in magnitude)."""
        return float((self.width * np.exp(-log_t)) ** 4 / 48.0)

    def objective(self) -> Objective:
        """The mean NLL vs `log T` from the bins (`value_grad`)."""
        value_grad = self.value_grad()
        return lambda log_t: value_grad(log_t)[0]

    def value_grad(self) -> ValueGrad:
        """`log T -> (mean NLL, d mean NLL / d log T)` from the bins (class docstring),
        O(used bins) per call. In `β = 1/T`, a bin of centre `c` contributes
        `m·f(βc) + β²M2/2·f2 + β³M3/6·f3` and, to the derivative in β, `m·c·σ(βc) + β·M2·f2
        + β²/2·(M2·c + M3)·f3 + β³/6·M3·c·f4`; the derivative in log T is `-β` times that.

        With `e = exp(-β|c|)`: `softplus(x) = max(x, 0) + log1p(e)`, `c·σ(βc) = max(c, 0) -
        |c|·e / (1 + e)`, `f2 = σ(1 - σ) = e / (1 + e)²`, `f3 = -sign(c)·f2·(1 - e) / (1 + e)`,
        `f4 = f2·(1 - 6·f2)`; the `max(c, 0)` parts are summed once."""
        used = self.count > 0
        m = self.count[used]
        mean_offset = self.offset[used] / m
        centre = self.low + (np.flatnonzero(used) + mean_offset) * self.width
        s2 = self.offset_sq[used]
        m2 = np.maximum(s2 - m * mean_offset**2, 0.0) * (self.width**2 / self.n)
        m3 = (self.offset_cu[used] - 3.0 * mean_offset * s2 + 2.0 * m * mean_offset**3) * (
            self.width**3 / self.n)
        weight = m / self.n
        sign, neg_abs = np.sign(centre), -np.abs(centre)
        linear = _dot(weight, np.maximum(centre, 0.0)) - self.sum_ys / self.n
        weight_abs = -weight * neg_abs
        skew3 = -sign * m3                    # · |f3| (signs folded in)
        mixed3 = -sign * (m2 * centre + m3)   # · |f3|
        skew4 = m3 * centre                   # · f4

        def value_grad(log_t: float) -> tuple[float, float]:
            beta = float(np.exp(-log_t))
            e = np.exp(neg_abs * beta)
            r = 1.0 / (1.0 + e)
            q = e * r            # σ(-β|c|)
            f2 = q * r
            f3 = (1.0 - e) * r
            f3 *= f2
            f4 = 1.0 - 6.0 * f2
            f4 *= f2
            half_b2, sixth_b3 = 0.5 * beta**2, beta**3 / 6.0
            curvature = _dot(m2, f2)
            value = (linear * beta + _dot(weight, np.log1p(e)) + half_b2 * curvature
                     + sixth_b3 * _dot(skew3, f3))
            d_beta = (linear - _dot(weight_abs, q) + beta * curvature
                      + half_b2 * _dot(mixed3, f3) + sixth_b3 * _dot(skew4, f4))
            return value, -beta * d_beta

        return value_grad


class SoftmaxSums:
    """The sums of the softmax NLL of logits `z [N, C']` (C-contiguous float64) with target
    columns `y [N]`, at any `1/T` (`at`); sums over disjoint rows add up, so a dataset can
    be summed part by part.

    One pass over `z` in cache-sized blocks per call: `exp(z / T)` unshifted where the
    block's largest `|z| / T` is at most `_EXP_LIMIT` (no overflow, no subnormal), else with
    each row shifted by its maximum (`logsumexp = m/T + log Σ exp((z - m)/T)`, arguments
    clamped at -700: a term below `e^-700` of the row's largest changes nothing). Row sums by
    a matrix-vector product. The first call also takes `Σ z_y` and each block's largest
    `|z|` (non-finite logits make it, and so every sum, non-finite).
    """

    def __init__(self, z: np.ndarray, y: np.ndarray) -> None:
        self.z, self.y = z, y
        self.chunks = _chunks(z.shape[0], z.shape[1])
        self.target = 0.0
        self._scale: list[float] = []   # per block: the largest |z| (after the first call)

    def at(self, inv_t: float) -> tuple[float, float]:
        """`(Σ_i log Σ_j exp(z_ij / T), Σ_i Σ_j p_ij z_ij)` at `inv_t = 1/T`, `p_i =
        softmax(z_i / T)`; `target = Σ_i z_{i, y_i}` is set by the first call."""
        width = self.z.shape[1]
        rows = self.chunks[0].stop if self.chunks else 0
        buf, row_sum, row_dot = np.empty((rows, width)), np.empty(rows), np.empty(rows)
        ones = np.ones(width)
        first = not self._scale and bool(self.chunks)
        flat_rows = np.arange(0, rows * width, width) if first else None
        log_sum = expected = 0.0
        for b, sl in enumerate(self.chunks):
            block, k = self.z[sl], sl.stop - sl.start
            e, s, w = buf[:k], row_sum[:k], row_dot[:k]
            if flat_rows is not None:
                flat = block.reshape(-1)
                self.target += float(np.take(flat, flat_rows[:k] + self.y[sl]).sum())
                self._scale.append(max(-float(flat.min()), float(flat.max())))
            if inv_t * self._scale[b] <= _EXP_LIMIT:   # False for NaN and Inf
                np.multiply(block, inv_t, out=e)
            else:
                m = row_max(block)
                np.subtract(block, m[:, None], out=e)
                e *= inv_t
                np.maximum(e, -700.0, out=e)
                log_sum += inv_t * float(m.sum())
            np.exp(e, out=e)
            np.matmul(e, ones, out=s)
            np.multiply(e, block, out=e)
            np.matmul(e, ones, out=w)
            np.divide(w, s, out=w)
            expected += float(w.sum())
            np.log(s, out=s)
            log_sum += float(s.sum())
        return log_sum, expected


def softmax_value_grad(z: np.ndarray, y: np.ndarray) -> ValueGrad:
    """`log T -> (mean NLL, d mean NLL / d log T)` of `z [N, C']` (C-contiguous float64),
    `y [N]`: `NLL = mean(logsumexp(z/T) - z_y/T)`, `dNLL/dlog T = -(1/T)·mean(Σ_j p_j z_j -
    z_y)` (`SoftmaxSums`). Raises the
    `FieldError` of non-finite logits."""
    sums = SoftmaxSums(z, y)

    def value_grad(log_t: float) -> tuple[float, float]:
        inv_t = float(np.exp(-log_t))
        log_sum, expected = sums.at(inv_t)
        return softmax_mean(len(z), inv_t, log_sum, expected, sums.target, z)

    return value_grad


def softmax_mean(n: int, inv_t: float, log_sum: float, expected: float, target: float,
                 z: np.ndarray | None = None) -> tuple[float, float]:
    """`(mean NLL, d mean NLL / d log T)` from the sums of `SoftmaxSums` over `n` rows;
    non-finite sums raise the `FieldError` of the logits `z` when given (else ValueError)."""
    if not np.isfinite(log_sum + expected + target):
        if z is not None:
            check_finite("logits", z)
        raise ValueError("logits overflow float64 arithmetic; rescale them")
    return (log_sum - inv_t * target) / n, -inv_t * (expected - target) / n


def softmax_nll(z: np.ndarray, y: np.ndarray) -> Objective:
    """Mean categorical NLL `mean(logsumexp(z/T) - z_y/T)` of `z [N, C']`, `y [N]` as a
    function of `log T` (`softmax_value_grad`)."""
    value_grad = softmax_value_grad(np.ascontiguousarray(z, dtype=np.float64), y)
    return lambda log_t: value_grad(log_t)[0]
