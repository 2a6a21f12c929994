import json
import math

import numpy as np
import pytest
from scipy import stats

from calibrators import metrics


def _random_gaussians(rng, n, d):
    """Random PD covariances [n, d, d] and residuals r ~ N(0, Σ_i)."""
    a = rng.normal(size=(n, d, d))
    cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(d)
    chol = np.linalg.cholesky(cov)
    r = np.einsum("nij,nj->ni", chol, rng.normal(size=(n, d)))
    return r, cov


def test_mahalanobis_hand_value():
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[2.0, 1.0], [1.0, 2.0]]])
    r = np.array([[2.0, 1.0], [1.0, 1.0]])
    # second: Σ⁻¹ = [[2, -1], [-1, 2]] / 3, rᵀΣ⁻¹r = (2 - 1 - 1 + 2) / 3 = 2/3
    np.testing.assert_allclose(metrics.mahalanobis(r, cov), [math.sqrt(2.0), math.sqrt(2 / 3)])


def test_regression_nll_equals_scipy_logpdf_mean():
    rng = np.random.default_rng(0)
    r, cov = _random_gaussians(rng, 6, 3)
    r = r * 1.7  # not exactly the model's distribution: the value is what it is
    expected = -np.mean([stats.multivariate_normal(np.zeros(3), c).logpdf(x)
                         for x, c in zip(r, cov, strict=True)])
    assert metrics.regression_nll(r, cov) == pytest.approx(expected, rel=1e-12)


def test_regression_nll_hand_value_1d():
    # N(0, 4) at r = 2: 0.5 (log 2π + log 4 + 1)
    value = metrics.regression_nll([[2.0]], [[[4.0]]])
    assert value == pytest.approx(0.5 * (math.log(2 * math.pi) + math.log(4.0) + 1.0))


def test_mahalanobis_of_gaussian_residuals_is_chi_square_and_coverage_is_nominal():
    rng = np.random.default_rng(1)
    n, d = 60_000, 3
    r, cov = _random_gaussians(rng, n, d)
    md = metrics.mahalanobis(r, cov)
    # MD² ~ χ²_3: mean 3, variance 6
    assert np.mean(md**2) == pytest.approx(d, abs=5 * math.sqrt(2 * d / n))
    cov_result = metrics.coverage(r, cov)
    np.testing.assert_allclose(cov_result.radii, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(cov_result.nominal, stats.chi2(d).cdf([1.0, 4.0, 9.0]))
    tol = 5 * np.sqrt(cov_result.nominal * (1 - cov_result.nominal) / n)
    assert np.all(np.abs(cov_result.observed - cov_result.nominal) <= tol)
    # overconfident covariances (a quarter of the truth) cover much less than nominal
    under = metrics.coverage(r, cov / 4.0, radii=[2.0])
    assert under.observed[0] == pytest.approx(stats.chi2(d).cdf(1.0), abs=0.01)


def test_coverage_counts_the_boundary_and_serialises():
    cov = np.tile(np.eye(2), (4, 1, 1))
    r = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 0.0], [0.0, 0.5]])
    result = metrics.coverage(r, cov, radii=(1, 2, 3))
    np.testing.assert_allclose(result.observed, [0.5, 0.75, 1.0])
    d = result.to_dict()
    assert d["observed"] == [0.5, 0.75, 1.0]
    json.dumps(d, allow_nan=False)


def test_residual_uncertainty_hand_case():
    r = np.array([[3.0, 4.0], [0.5, 0.0], [0.0, 0.0]])
    cov = np.array([np.diag([9.0, 16.0]), np.diag([4.0, 0.0]), np.zeros((2, 2))])
    plot = metrics.residual_uncertainty(r, cov)
    np.testing.assert_allclose(plot.residual_norm, [5.0, 0.5, 0.0])
    np.testing.assert_allclose(plot.sigma, [5.0, 2.0, 0.0])
    assert plot.within_1sigma == pytest.approx(1.0)  # on the band counts as inside
    assert plot.within_3sigma == pytest.approx(1.0)
    r2 = np.array([[4.0, 0.0], [0.0, 1.0]])  # 4 > sqrt(2), 4 <= 3 sqrt(2)
    cov2 = np.tile(np.eye(2), (2, 1, 1))  # sigma = sqrt(2)
    plot2 = metrics.residual_uncertainty(r2, cov2)
    assert (plot2.within_1sigma, plot2.within_3sigma) == (0.5, 1.0)
    assert set(plot2.to_dict()) == {"residual_norm", "sigma", "within_1sigma", "within_3sigma"}


@pytest.mark.parametrize("d", [1, 2])
def test_residual_uncertainty_bands_of_calibrated_gaussians(d):
    rng = np.random.default_rng(2 + d)
    n = 50_000
    s = rng.uniform(0.5, 3.0, n)
    cov = s[:, None, None] ** 2 * np.eye(d)
    r = rng.normal(size=(n, d)) * s[:, None]
    plot = metrics.residual_uncertainty(r, cov)
    # isotropic: ‖r‖² / s² ~ χ²_d and trace Σ = d s²  → P = chi2(d).cdf(k² d)
    for k, got in ((1, plot.within_1sigma), (3, plot.within_3sigma)):
        p = stats.chi2(d).cdf(k * k * d)
        assert got == pytest.approx(p, abs=5 * math.sqrt(p * (1 - p) / n) + 1e-4)
    if d == 1:
        assert plot.within_1sigma == pytest.approx(0.683, abs=0.01)
        assert plot.within_3sigma == pytest.approx(0.997, abs=0.002)


# ---------------------------------------------------------------- bad input

_R = np.array([[0.5, -0.2], [1.0, 0.3]])
_S = np.tile(np.eye(2), (2, 1, 1))
_SINGULAR = np.array([np.eye(2), [[1.0, 1.0], [1.0, 1.0]]])
_ASYM = np.array([[[1.0, 0.5], [0.0, 1.0]], np.eye(2)])
_NOT_PSD = np.array([np.eye(2), [[1.0, 2.0], [2.0, 1.0]]])

BAD = [
    ("r NaN", metrics.regression_nll, (np.array([[0.0, np.nan], [0, 0]]), _S), {},
     r"residuals has NaN at index \[0, 1\]"),
    ("r 1-D", metrics.mahalanobis, ([0.5, 0.2], _S), {}, "residuals must have 2 dimensions"),
    ("r empty", metrics.regression_nll, (np.zeros((0, 2)), np.zeros((0, 2, 2))), {},
     "residuals is empty"),
    ("r no dims", metrics.mahalanobis, (np.zeros((2, 0)), np.zeros((2, 0, 0))), {},
     "residuals has 0 dimensions"),
    ("cov Inf", metrics.regression_nll, (_R, np.array([np.eye(2), [[np.inf, 0], [0, 1]]])), {},
     r"covariances has Inf at index \[1, 0, 0\]"),
    ("cov shape", metrics.regression_nll, (_R, np.eye(2)), {},
     r"covariances must have shape \[N, D, D\]"),
    ("cov count", metrics.mahalanobis, (_R, np.tile(np.eye(2), (3, 1, 1))), {},
     "covariances has 3 matrices but 2 were expected"),
    ("cov dim", metrics.coverage, (_R, np.tile(np.eye(3), (2, 1, 1))), {},
     "covariances must be 2x2, got 3x3"),
    ("cov asym", metrics.regression_nll, (_R, _ASYM), {},
     r"covariances\[0\] is not symmetric"),
    ("cov not PSD", metrics.mahalanobis, (_R, _NOT_PSD), {},
     r"covariances\[1\] is not positive semi-definite"),
    ("cov singular nll", metrics.regression_nll, (_R, _SINGULAR), {},
     r"covariances\[1\] is not positive definite"),
    ("cov singular md", metrics.mahalanobis, (_R, _SINGULAR), {},
     r"covariances\[1\] is not positive definite"),
    ("cov singular coverage", metrics.coverage, (_R, _SINGULAR), {},
     r"covariances\[1\] is not positive definite"),
    ("radii zero", metrics.coverage, (_R, _S), {"radii": (1.0, 0.0)},
     "radii must be > 0; entry 1 is 0.0"),
    ("radii NaN", metrics.coverage, (_R, _S), {"radii": (np.nan,)}, "radii has NaN at index 0"),
    ("radii empty", metrics.coverage, (_R, _S), {"radii": ()}, "radii is empty"),
    ("radii 2-D", metrics.coverage, (_R, _S), {"radii": [[1.0]]},
     "radii must have 1 dimensions"),
    ("residual plot asym", metrics.residual_uncertainty, (_R, _ASYM), {},
     r"covariances\[0\] is not symmetric"),
    ("residual plot count", metrics.residual_uncertainty, (_R[:1], _S), {},
     "covariances has 2 matrices but 1 were expected"),
]


@pytest.mark.parametrize("fn, args, kwargs, message", [b[1:] for b in BAD],
                         ids=[b[0] for b in BAD])
def test_bad_input_raises_named_value_error(fn, args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        fn(*args, **kwargs)
