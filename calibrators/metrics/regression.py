"""Box-regression uncertainty: Gaussian NLL, Mahalanobis distance, coverage, residual plot.

Inputs are residuals `r = y_gt − x_pred` `[N, D]` and predicted covariances `Σ` `[N, D, D]`
(symmetric; positive definite where a density or inverse is needed). One Cholesky
factorisation `Σ = L Lᵀ` per sample, then a batched forward substitution `z = L⁻¹ r`
(O(N·D²)) gives `rᵀΣ⁻¹r = ‖z‖²` and `log|Σ| = 2 Σ log L_jj`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.special import gammaln

from calibrators.core.bins import ResultMixin, check_nonempty
from calibrators.core.checks import as_float_array, check_covariances


def _residuals_and_covariances(residuals: object, covariances: object
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Validated `residuals [N, D]` (N, D >= 1) and symmetric PSD `covariances [N, D, D]`."""
    r = as_float_array("residuals", residuals, ndim=2)
    check_nonempty("residuals", r)
    if r.shape[1] == 0:
        raise ValueError("residuals has 0 dimensions (shape [N, 0])")
    cov = as_float_array("covariances", covariances)
    check_covariances("covariances", cov, n=r.shape[0], dim=r.shape[1])
    return r, cov


def _cholesky(cov: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors `[N, D, D]`; ValueError naming the first non-PD matrix."""
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        pass
    scale = np.maximum(np.abs(cov).max(axis=(1, 2)), np.finfo(np.float64).tiny)
    eig_min = np.linalg.eigvalsh(cov)[:, 0] / scale
    bad = eig_min <= 1e-12
    i = int(np.argmax(bad)) if bad.any() else int(np.argmin(eig_min))
    raise ValueError(f"covariances[{i}] is not positive definite (smallest eigenvalue "
                     f"{eig_min[i] * scale[i]:.3g}); a density needs a full-rank covariance")


def _whiten(r: np.ndarray, chol: np.ndarray) -> np.ndarray:
    """`z = L⁻¹ r` `[N, D]` by forward substitution, vectorised over N."""
    z = np.empty_like(r)
    for j in range(r.shape[1]):
        acc = r[:, j] - np.einsum("nk,nk->n", chol[:, j, :j], z[:, :j])
        z[:, j] = acc / chol[:, j, j]
    return z


def _squared_mahalanobis(r: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`rᵀΣ⁻¹r` `[N]` and `log|Σ|` `[N]`."""
    chol = _cholesky(cov)
    z = _whiten(r, chol)
    logdet = 2.0 * np.sum(np.log(np.diagonal(chol, axis1=1, axis2=2)), axis=1)
    return np.sum(z * z, axis=1), logdet


def regression_nll(residuals: np.ndarray, covariances: np.ndarray) -> float:
    """Mean Gaussian negative log-likelihood (nats) of `residuals [N, D]` under `N(0, Σ_i)`.

    mean_i 0.5 · (D log 2π + log|Σ_i| + r_iᵀ Σ_i⁻¹ r_i); `covariances [N, D, D]` must be
    positive definite.
    """
    r, cov = _residuals_and_covariances(residuals, covariances)
    md2, logdet = _squared_mahalanobis(r, cov)
    d = r.shape[1]
    return float(np.mean(0.5 * (d * np.log(2.0 * np.pi) + logdet + md2)))


def expected_mahalanobis(dim: int) -> float:
    """E[MD] of a calibrated D-dim Gaussian: the χ_D mean sqrt(2)·Γ((D+1)/2)/Γ(D/2)
    (sqrt(pi/2) = 1.2533 in 2-D)."""
    return float(np.sqrt(2.0) * np.exp(gammaln((dim + 1) / 2.0) - gammaln(dim / 2.0)))


def mahalanobis(residuals: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Mahalanobis distance `sqrt(r_iᵀ Σ_i⁻¹ r_i)` `[N]`; `covariances [N, D, D]` PD."""
    r, cov = _residuals_and_covariances(residuals, covariances)
    md2, _ = _squared_mahalanobis(r, cov)
    return np.sqrt(md2)


@dataclass(frozen=True)
class Coverage(ResultMixin):
    """Fraction of residuals within Mahalanobis radius r, with its Gaussian expectation.

    radii: [R]; observed: [R] fraction with MD <= r; nominal: [R] = chi2(D).cdf(r²).
    """

    radii: np.ndarray
    observed: np.ndarray
    nominal: np.ndarray


def coverage(residuals: np.ndarray, covariances: np.ndarray,
             radii: Sequence[float] = (1.0, 2.0, 3.0)) -> Coverage:
    """Observed vs nominal coverage of the Mahalanobis balls of `radii` (> 0).

    residuals: [N, D]; covariances: [N, D, D] positive definite.
    """
    rad = as_float_array("radii", radii, ndim=1)
    check_nonempty("radii", rad)
    if (rad <= 0).any():
        i = int(np.argmax(rad <= 0))
        raise ValueError(f"radii must be > 0; entry {i} is {rad[i]}")
    r, cov = _residuals_and_covariances(residuals, covariances)
    md2, _ = _squared_mahalanobis(r, cov)
    md2_sorted = np.sort(md2)
    inside = np.searchsorted(md2_sorted, rad**2, side="right")
    observed = inside / md2.shape[0]
    nominal = stats.chi2(r.shape[1]).cdf(rad**2)
    return Coverage(rad, observed, np.asarray(nominal, dtype=np.float64))


@dataclass(frozen=True)
class ResidualPlot(ResultMixin):
    """Data of the residual-uncertainty plot (thesis Fig. 2-13).

    residual_norm: [N] ‖r_i‖; sigma: [N] sqrt(trace Σ_i);
    within_1sigma / within_3sigma: fraction of samples with ‖r_i‖ <= 1 (3) · sigma_i.
    For D = 1 a calibrated Gaussian gives 0.683 / 0.997; for isotropic Σ = s²I in D
    dimensions chi2(D).cdf(D) / chi2(D).cdf(9 D) (e.g. 0.632 / 1.000 for D = 2).
    """

    residual_norm: np.ndarray
    sigma: np.ndarray
    within_1sigma: float
    within_3sigma: float


def residual_uncertainty(residuals: np.ndarray, covariances: np.ndarray) -> ResidualPlot:
    """Residual norm vs sqrt(trace Σ) per sample, with the 1σ / 3σ band fractions.

    residuals: [N, D]; covariances: [N, D, D] symmetric PSD (singular allowed).
    """
    r, cov = _residuals_and_covariances(residuals, covariances)
    norm = np.sqrt(np.sum(r * r, axis=1))
    sigma = np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2), 0.0))
    return ResidualPlot(norm, sigma, float(np.mean(norm <= sigma)),
                        float(np.mean(norm <= 3.0 * sigma)))
