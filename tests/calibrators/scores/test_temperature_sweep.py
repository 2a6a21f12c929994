"""Accuracy over the whole range the speed claims cover: T in [0.3, 5] at any scale of the
logits (both modes, on the fast paths: sigmoid bins, softmax subsample bracket); k over four
decades: covariance/test_depth_sweep.py. The fast searches must find the exact minimiser; no
timing here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.special import expit, softmax

from calibrators.scores import (
    SIGMOID_BINS,
    SUBSAMPLE_MIN,
    TemperatureScaler,
    row_max,
    sigmoid_nll,
    softmax_nll,
)

CASES = [(t, 3.0) for t in (0.3, 0.7, 1.5, 2.7, 5.0)] + [
    (t, s) for t in (0.3, 1.5, 5.0) for s in (0.3, 30.0)]


def exact_minimiser(objective, bounds) -> float:
    result = minimize_scalar(objective, bounds=np.log(bounds), method="bounded",
                             options={"xatol": 1e-11})
    return float(np.exp(result.x))


@pytest.mark.parametrize("t_true, scale", CASES)
def test_sigmoid_fit_is_exact_for_any_temperature_and_scale(t_true, scale):
    n = SIGMOID_BINS + 5_000   # the binned search, bracketed on coarsened bins
    rng = np.random.default_rng(int(100 * t_true + scale))
    z = rng.normal(0.0, scale, (n, 1)) - 0.5 * scale
    y = (rng.random(n) < expit(z[:, 0] / t_true)).astype(np.int64)
    fitted = TemperatureScaler().fit(z.astype(np.float32), y).temperature_
    exact = exact_minimiser(sigmoid_nll(row_max(z.astype(np.float32).astype(np.float64)), y),
                            (0.01, 100.0))
    assert fitted == pytest.approx(exact, rel=1e-6)
    if scale == 3.0:
        assert fitted == pytest.approx(t_true, rel=0.03)


@pytest.mark.parametrize("t_true, scale", CASES)
def test_softmax_fit_is_exact_for_any_temperature_and_scale(t_true, scale):
    n, width = SUBSAMPLE_MIN, 7   # the subsample-bracketed search
    rng = np.random.default_rng(int(100 * t_true + scale) + 1)
    z = rng.normal(0.0, scale, (n, width))
    cdf = np.cumsum(softmax(z / t_true, axis=1), axis=1)
    y = np.minimum((rng.random(n)[:, None] > cdf).sum(axis=1), width - 1)
    scaler = TemperatureScaler(mode="softmax").fit(z.astype(np.float32), y)
    exact = exact_minimiser(softmax_nll(z.astype(np.float32).astype(np.float64), y),
                            (0.01, 100.0))
    assert scaler.temperature_ == pytest.approx(exact, rel=1e-6)
    assert scaler.n_evaluations_ < 30   # a bracket that fits the data, not the full bounds
    if scale == 3.0:
        assert scaler.temperature_ == pytest.approx(t_true, rel=0.02)
