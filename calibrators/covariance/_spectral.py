"""Spectral decomposition of batched covariances for depth scaling, checked once.

`Σ_i = U_i Λ_i U_iᵀ` turns `Σ_i + k·d_i·I` into `U_i (Λ_i + k·d_i) U_iᵀ`, so the NLL of a
residual needs only the eigenvalues `Λ_i` `[N, D]` and the squared projections `(U_iᵀ r_i)²`
`[N, D]`; the symmetry and PSD checks reuse the same eigenvalues.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calibrators.core.checks import covariance_tolerance

_BLOCK = 1 << 15  # rows per block of `spectral_2x2`: its temporaries stay in the CPU cache
_TINY = float(np.finfo(np.float64).tiny)


def spectral(cov: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues `[D, N]` of Σ = U Λ Uᵀ and `(Uᵀ r)² [D, N]`, by `np.linalg.eigh`."""
    tol = covariance_tolerance(np.abs(cov).reshape(len(cov), -1).max(axis=1), cov.shape[1])
    _check_symmetric(np.abs(cov - np.swapaxes(cov, 1, 2)).reshape(len(cov), -1).max(axis=1),
                     tol)
    eig, vecs = np.linalg.eigh(cov)
    _check_psd(eig[:, 0], tol)
    sq = np.einsum("nij,ni->jn", vecs, r) ** 2
    return _zero_tiny(np.ascontiguousarray(eig.T)), np.ascontiguousarray(sq)


def spectral_2x2(cov: np.ndarray, r: np.ndarray,
                  on_block: Callable[[int, np.ndarray], None] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """`spectral` in closed form for D = 2, with no eigenvectors and no trigonometry.

    For Σ = [[a, b], [b, c]]: λ = (a + c)/2 ∓ h with h = hypot((a - c)/2, b). The major axis
    is at angle θ with cos 2θ = (a - c)/(2h), sin 2θ = b/h, so the squared projection of
    r = (x, y) onto it is p_hi = |r|²/2 + ((a - c)(x² - y²)/4 + b·x·y)/h and p_lo = |r|² - p_hi;
    for h = 0 any split gives the same NLL. Runs in cache-sized blocks of rows (`_Block`),
    writing straight into the `[2, N]` outputs: no full-size temporary array. `on_block(start,
    eig [2, m])` sees the final eigenvalues of each block of rows `start ..`, in order (it
    starts at 0 again if the blocks are run again).
    """
    try:
        return _blocks(cov, r, False, on_block)
    except _Overflow:  # rare: start again with h by hypot everywhere, as one pass would
        return _blocks(cov, r, True, on_block)


class _Overflow(Exception):
    """Raised by a block holding a matrix with max(|a|, |b|, |c|) >= 1e150."""


def _blocks(cov: np.ndarray, r: np.ndarray, hypot: bool,
            on_block: Callable[[int, np.ndarray], None] | None
            ) -> tuple[np.ndarray, np.ndarray]:
    """`spectral_2x2` block by block; h by `np.hypot` if `hypot`, else by a square root
    (4x faster), which raises `_Overflow` on the first block where h² could overflow."""
    n = len(cov)
    eig, sq = np.empty((2, n)), np.empty((2, n))
    flat = cov.reshape(n, 4)
    block = _Block(min(n, _BLOCK))
    psd_error: tuple[int, np.ndarray, np.ndarray] | None = None
    for start in range(0, n, _BLOCK):
        stop = min(start + _BLOCK, n)
        bad = block.run(flat[start:stop], r[start:stop], eig[:, start:stop],
                        sq[:, start:stop], start, hypot)
        if bad is not None and psd_error is None:  # a later row may still be asymmetric
            psd_error = bad
        if on_block is not None:
            on_block(start, eig[:, start:stop])
    if psd_error is not None:
        _check_psd(psd_error[1], psd_error[2], psd_error[0])
    return eig, sq


class _Block:
    """Buffers `[m]` of one block of `spectral_2x2` and its computation on them.

    `buf` rows: 0 `(a - c)/2`, 1 `h`, 2 and 3 scratch of the projections, 4 scratch."""

    def __init__(self, size: int) -> None:
        self.buf, self.zero = np.empty((5, size)), np.zeros(size)
        self.mask = np.empty(size, dtype=bool)

    def run(self, flat: np.ndarray, r: np.ndarray, eig: np.ndarray, sq: np.ndarray,
            offset: int, hypot: bool) -> tuple[int, np.ndarray, np.ndarray] | None:
        """Eigenvalues into `eig [2, m]` and squared projections into `sq [2, m]` of the
        matrices `flat [m, 4]` (row-major 2x2) and residuals `r [m, 2]`; raises if a matrix
        is not symmetric; returns `(offset, smallest eigenvalues, tolerances)` copies if one
        is not PSD (the caller raises once no later row is asymmetric), else None. Raises
        `_Overflow` unless `hypot` where some max(|a|, |b|, |c|) >= 1e150 (one pass takes h by
        hypot for all matrices then).

        The tolerances (`covariance_tolerance` of `max(|a|, |b|, |c|)`) are only computed
        where a test can fail: `b_t != b` somewhere, or a negative smallest eigenvalue."""
        a, b, b_t, c = flat.T
        tol = self._symmetry_tolerance(a, b, b_t, c, offset)
        self._eigenvalues(a, b, c, eig, hypot)
        lo, hi = eig
        psd = None
        lo_min = float(lo.min())
        if lo_min < 0.0:
            tol = _tolerance(a, b, c) if tol is None else tol
            if np.less(lo, -tol).any():
                psd = (offset, lo.copy(), tol.copy())
        # 1e-12·max(|λ_hi|, tiny) is both the `_zero_tiny` threshold and the one of h = 0 to
        # rounding; where every λ_lo (<= λ_hi) and h is above its largest, no row is tested
        bound = 1e-12 * max(abs(float(hi.max())), abs(float(hi.min())), _TINY)
        self._projections(r, b, hi, sq, bound)
        if not lo_min > bound:
            _zero_tiny(eig)
        return psd

    def _symmetry_tolerance(self, a: np.ndarray, b: np.ndarray, b_t: np.ndarray, c: np.ndarray,
                            offset: int) -> np.ndarray | None:
        """Raise if a matrix is not symmetric; the tolerances `[m]` if they were needed for
        that (some `b_t != b`), else None."""
        m = len(a)
        if not np.not_equal(b_t, b, out=self.mask[:m]).any():
            return None
        tol = _tolerance(a, b, c)
        tmp = self.buf[4, :m]
        np.subtract(b_t, b, out=tmp)
        _check_symmetric(np.abs(tmp, out=tmp), tol, offset)
        return tol

    def _eigenvalues(self, a: np.ndarray, b: np.ndarray, c: np.ndarray, eig: np.ndarray,
                     hypot: bool) -> None:
        """λ = (a + c)/2 ∓ h into `eig [2, m]`, with `(a - c)/2` and h left in `buf` rows 0
        and 1; `_Overflow` as `run` says."""
        m = len(a)
        diff, half_gap, tmp = self.buf[0, :m], self.buf[1, :m], self.buf[4, :m]
        np.subtract(a, c, out=diff)
        diff *= 0.5
        lo, hi = eig
        np.add(a, c, out=hi)
        hi *= 0.5
        if hypot:
            np.hypot(diff, b, out=half_gap)
        else:
            with np.errstate(over="ignore"):  # inf where h² overflows: _Overflow below
                np.multiply(diff, diff, out=half_gap)
                np.multiply(b, b, out=tmp)
                half_gap += tmp
            np.sqrt(half_gap, out=half_gap)
            # (a + c)/2 + h >= max(a, c, |b|): only a block past 1e149 can hold a 1e150
            if (not float(hi.max()) + float(half_gap.max()) < 1e149
                    and float(_scale(a, b, c).max()) >= 1e150):
                raise _Overflow
        np.subtract(hi, half_gap, out=lo)
        hi += half_gap

    def _projections(self, r: np.ndarray, b: np.ndarray, hi: np.ndarray, sq: np.ndarray,
                     bound: float) -> None:
        """`(Uᵀ r)²` into `sq [2, m]` (row 0 along the minor axis, row 1 the major) from the
        `buf` rows `_eigenvalues` left; p_hi is 0 where h <= 1e-12·max(|λ_hi|, tiny), tested
        only unless every h is above `bound`."""
        m = len(r)
        diff, half_gap, y_sq, along, tmp = self.buf[:, :m]
        x, y = r.T
        rr, p_hi = sq
        np.multiply(x, x, out=rr)
        np.multiply(y, y, out=y_sq)
        np.subtract(rr, y_sq, out=along)  # x² - y²
        rr += y_sq
        along *= diff
        along *= 0.5  # (a - c)(x² - y²)/4
        np.multiply(x, y, out=y_sq)
        y_sq *= b
        along += y_sq
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(along, half_gap, out=p_hi)
        if not float(half_gap.min()) > bound:
            np.abs(hi, out=tmp)
            np.maximum(tmp, _TINY, out=tmp)
            tmp *= 1e-12
            np.copyto(p_hi, 0.0, where=np.less_equal(half_gap, tmp, out=self.mask[:m]))
        np.multiply(rr, 0.5, out=tmp)
        p_hi += tmp
        # np.clip(p_hi, 0, rr) at a fifth of the cost (np.maximum is slow on a scalar)
        np.maximum(p_hi, self.zero[:m], out=p_hi)
        np.minimum(p_hi, rr, out=p_hi)
        rr -= p_hi  # row 0 becomes p_lo


def _scale(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """`max(|a|, |c|, |b|)` `[m]` of the 2x2 matrices [[a, b], [., c]] (`[m]` each)."""
    scale = np.abs(a)
    for other in (c, b):
        np.maximum(scale, np.abs(other), out=scale)
    return scale


def _tolerance(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """`covariance_tolerance` `[m]` of the 2x2 matrices [[a, b], [., c]] (`[m]` each)."""
    return covariance_tolerance(_scale(a, b, c), 2)


def _zero_tiny(eig: np.ndarray) -> np.ndarray:
    """Eigenvalues `[D, N]` (ascending) below 1e-12 of each matrix's largest set to 0, in
    place."""
    threshold = np.maximum(eig[-1], np.finfo(np.float64).tiny)
    threshold *= 1e-12
    np.copyto(eig, 0.0, where=eig <= threshold)
    return eig


def _check_symmetric(gap: np.ndarray, tol: np.ndarray, offset: int = 0) -> None:
    """The symmetry test of `checks.check_covariances` on `max |Σ - Σᵀ|` per matrix, with
    its allowance `tol` (`checks.covariance_tolerance`); `offset` is the row of `gap[0]`."""
    asym = gap > tol
    if asym.any():
        raise ValueError(f"covariances[{offset + int(np.argmax(asym))}] is not symmetric")


def _check_psd(eig_min: np.ndarray, tol: np.ndarray, offset: int = 0) -> None:
    """The PSD test of `checks.check_covariances` on the smallest eigenvalues `[N]`, with its
    allowance `tol` (`checks.covariance_tolerance`); `offset` is the row of `eig_min[0]`."""
    bad = eig_min < -tol
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"covariances[{offset + i}] is not positive semi-definite (smallest "
                         f"eigenvalue {eig_min[i]:.3g})")
