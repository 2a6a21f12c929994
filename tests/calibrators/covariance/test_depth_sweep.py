"""Accuracy over the whole range the speed claims cover: the depth scaler's k over four
decades (T: scores/test_temperature_sweep.py). The fast search must find the exact minimiser;
no timing here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from calibrators.covariance import DepthScaler, DepthTerms


@pytest.mark.parametrize("k_true", [1e-4, 1e-3, 1e-2, 1e-1, 1.0])
@pytest.mark.parametrize("d_max", [5.0, 80.0])
def test_depth_k_is_exact_and_recovered_over_four_decades(k_true, d_max):
    rng = np.random.default_rng(int(1e4 * k_true) + int(d_max))
    n = 40_000
    d = rng.uniform(0.5, d_max, n)
    a = rng.normal(0.0, 0.05, (n, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2)
    full = cov + (k_true * d)[:, None, None] * np.eye(2)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(full), rng.normal(size=(n, 2)))
    scaler = DepthScaler(min_samples=10**9).fit(r, cov, d, np.zeros(n, dtype=int))
    terms = DepthTerms.build(r, cov, d)
    exact = minimize_scalar(lambda u: terms.nll(float(np.exp(u))),
                            bounds=(np.log(1e-8), np.log(25.0)), method="bounded",
                            options={"xatol": 1e-11})
    assert scaler.pooled_k_ == pytest.approx(float(np.exp(exact.x)), rel=1e-6)
    assert scaler.pooled_k_ == pytest.approx(k_true, rel=0.05)
