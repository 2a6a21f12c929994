"""Spectral decomposition of batched covariances for depth scaling, checked once.

`Σ_i = U_i Λ_i U_iᵀ` turns `Σ_i + k·d_i·I` into `U_i (Λ_i + k·d_i) U_iᵀ`, so the NLL of a
residual needs only the eigenvalues `Λ_i` `[N, D]` and the squared projections `(U_iᵀ r_i)²`
`[N, D]`; the symmetry and PSD checks reuse the same eigenvalues.
"""

from __future__ import annotations

import numpy as np

from calibrators.checks import covariance_tolerance


def _spectral(cov: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues `[D, N]` of Σ = U Λ Uᵀ and `(Uᵀ r)² [D, N]`, by `np.linalg.eigh`."""
    tol = covariance_tolerance(np.abs(cov).reshape(len(cov), -1).max(axis=1), cov.shape[1])
    _check_symmetric(np.abs(cov - np.swapaxes(cov, 1, 2)).reshape(len(cov), -1).max(axis=1),
                     tol)
    eig, vecs = np.linalg.eigh(cov)
    _check_psd(eig[:, 0], tol)
    sq = np.einsum("nij,ni->jn", vecs, r) ** 2
    return _zero_tiny(np.ascontiguousarray(eig.T)), np.ascontiguousarray(sq)


def _spectral_2x2(cov: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_spectral` in closed form for D = 2, with no eigenvectors and no trigonometry.

    For Σ = [[a, b], [b, c]]: λ = (a + c)/2 ∓ h with h = hypot((a - c)/2, b). The major axis
    is at angle θ with cos 2θ = (a - c)/(2h), sin 2θ = b/h, so the squared projection of
    r = (x, y) onto it is p_hi = |r|²/2 + ((a - c)(x² - y²)/4 + b·x·y)/h and p_lo = |r|² - p_hi;
    for h = 0 any split gives the same NLL. Works on contiguous `[N]` components, in place.
    """
    n = len(cov)
    a, b, b_t, c = np.ascontiguousarray(cov.reshape(n, 4).T)
    x, y = np.ascontiguousarray(r.T)
    scale = np.abs(a)
    for other in (c, b):
        np.maximum(scale, np.abs(other), out=scale)
    tol = covariance_tolerance(scale, 2)
    b_t -= b
    _check_symmetric(np.abs(b_t, out=b_t), tol)

    diff = a - c
    diff *= 0.5
    if float(scale.max()) < 1e150:  # h² cannot overflow: sqrt is 4x faster than hypot
        half_gap = diff * diff
        half_gap += b * b
        np.sqrt(half_gap, out=half_gap)
    else:
        half_gap = np.hypot(diff, b)
    eig = np.empty((2, n))
    np.add(a, c, out=eig[1])
    eig[1] *= 0.5
    np.subtract(eig[1], half_gap, out=eig[0])
    eig[1] += half_gap
    _check_psd(eig[0], tol)

    sq = np.empty((2, n))
    rr, p_hi = sq[0], sq[1]
    np.multiply(x, x, out=rr)
    y_sq = y * y
    along = rr - y_sq  # x² - y²
    rr += y_sq
    along *= diff
    along *= 0.5  # (a - c)(x² - y²)/4
    np.multiply(x, y, out=y_sq)
    y_sq *= b
    along += y_sq
    distinct = half_gap > 1e-12 * np.maximum(np.abs(eig[1]), np.finfo(np.float64).tiny)
    np.divide(along, half_gap, out=p_hi, where=distinct)
    p_hi[~distinct] = 0.0
    p_hi += 0.5 * rr
    np.clip(p_hi, 0.0, rr, out=p_hi)
    rr -= p_hi  # row 0 becomes p_lo
    return _zero_tiny(eig), sq


def _zero_tiny(eig: np.ndarray) -> np.ndarray:
    """Eigenvalues `[D, N]` (ascending) below 1e-12 of each matrix's largest set to 0, in
    place."""
    threshold = np.maximum(eig[-1], np.finfo(np.float64).tiny)
    threshold *= 1e-12
    np.copyto(eig, 0.0, where=eig <= threshold)
    return eig


def _check_symmetric(gap: np.ndarray, tol: np.ndarray) -> None:
    """The symmetry test of `checks.check_covariances` on `max |Σ - Σᵀ|` per matrix, with
    its allowance `tol` (`checks.covariance_tolerance`)."""
    asym = gap > tol
    if asym.any():
        raise ValueError(f"covariances[{int(np.argmax(asym))}] is not symmetric")


def _check_psd(eig_min: np.ndarray, tol: np.ndarray) -> None:
    """The PSD test of `checks.check_covariances` on the smallest eigenvalues `[N]`, with its
    allowance `tol` (`checks.covariance_tolerance`)."""
    bad = eig_min < -tol
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"covariances[{i}] is not positive semi-definite (smallest eigenvalue "
                         f"{eig_min[i]:.3g})")
