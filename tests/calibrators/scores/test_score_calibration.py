"""Per-class score calibrators: parameter recovery, ECE, strict monotonicity, fallback,
round trip, factory and validation."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.special import expit

from calibrators.core.errors import NotFittedError
from calibrators.metrics import expected_calibration_error
from calibrators.scores import (
    SCORE_CALIBRATION_METHODS,
    ClassTemperatureScaler,
    HistogramBinning,
    IsotonicCalibrator,
    PlattScaler,
    make_score_calibrator,
    score_calibrator_from_dict,
)


def draw(prob, n_per_class: int, n_classes: int, seed: int, spread: float = 3.0):
    """Logits z ~ N(0, spread²), labels interleaved, distances U(0, 60), tp ~ prob(z, c, d)."""
    rng = np.random.default_rng(seed)
    labels = rng.permutation(np.repeat(np.arange(n_classes), n_per_class))
    z = rng.normal(0.0, spread, labels.size)
    d = rng.uniform(0.0, 60.0, labels.size)
    tp = rng.random(labels.size) < prob(z, labels, d)
    return z, labels, tp, d


def test_class_temperature_recovers_each_t():
    temps = np.array([0.5, 1.0, 2.5])
    z, labels, tp, _ = draw(lambda z, c, d: expit(z / temps[c]), 20000, 3, seed=1)
    cal = ClassTemperatureScaler().fit(z, labels, tp, 3)
    np.testing.assert_allclose(cal.temperature_, temps, rtol=0.04)
    assert cal.fallback_classes_ == []
    assert cal.n_samples_.tolist() == [20000] * 3


def test_platt_recovers_slope_and_intercept():
    a, b = np.array([2.0, 0.7]), np.array([-1.0, 0.5])
    z, labels, tp, _ = draw(lambda z, c, d: expit(a[c] * z + b[c]), 15000, 2, seed=2,
                            spread=1.5)
    cal = PlattScaler().fit(z, labels, tp, 2)
    np.testing.assert_allclose(cal.coef_[:, 0], a, rtol=0.05)
    np.testing.assert_allclose(cal.coef_[:, 1], b, atol=0.06)
    assert (cal.coef_[:, 2] == 0).all()


def test_platt_range_recovers_distance_term():
    g = np.array([-0.05, 0.02])
    z, labels, tp, d = draw(lambda z, c, d: expit(z + 1.0 + g[c] * d), 15000, 2, seed=3,
                            spread=1.5)
    cal = make_score_calibrator("platt_range").fit(z, labels, tp, 2, distances=d)
    np.testing.assert_allclose(cal.coef_[:, 2], g, atol=0.005)
    np.testing.assert_allclose(cal.coef_[:, 0], 1.0, rtol=0.06)


def test_platt_stays_finite_on_separable_data():
    z = np.linspace(-5, 5, 200)
    cal = PlattScaler().fit(z, np.zeros(200, dtype=int), z > 0, 1)
    assert np.isfinite(cal.coef_).all() and cal.coef_[0, 0] > 1.0


def miscalibrated(z, c, d):
    """Truth far from sigmoid(z) and different per class: ECE of sigmoid(z) is large."""
    return np.where(c == 0, expit(z) ** 3, 0.15 + 0.7 * expit(0.4 * z + 1.0))


@pytest.mark.parametrize("method", ["isotonic", "histogram"])
def test_nonparametric_reduce_held_out_ece_to_the_oracle_level(method):
    """Held out, the class-wise ECE falls from > 0.08 to within 0.015 of the ECE of the true
    probabilities on the same detections (the binned ECE's own sampling noise)."""
    z, labels, tp, _ = draw(miscalibrated, 12000, 2, seed=4)
    fit, test = slice(0, 12000), slice(12000, None)
    cal = make_score_calibrator(method).fit(z[fit], labels[fit], tp[fit], 2)
    p = cal.transform(z[test], labels[test])
    truth = miscalibrated(z[test], labels[test], None)
    for c in range(2):
        rows = labels[test] == c
        before = expected_calibration_error(expit(z[test][rows]), tp[test][rows])
        after = expected_calibration_error(p[rows], tp[test][rows])
        oracle = expected_calibration_error(truth[rows], tp[test][rows])
        assert before > 0.08 and after < oracle + 0.015, (c, before, after, oracle)


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_strictly_increasing_in_z_per_class_and_in_unit_interval(method):
    z, labels, tp, d = draw(miscalibrated, 3000, 2, seed=5)
    labels[:30] = 2  # a small class: served by the pooled fit
    cal = make_score_calibrator(method, max_knots=20) if method == "isotonic" else \
        make_score_calibrator(method)
    cal.fit(z, labels, tp, 3, distances=d)
    grid = np.linspace(-15.0, 15.0, 4001)
    for c in range(3):
        for dist in (0.0, 40.0):
            p = cal.transform(grid, np.full(grid.size, c), np.full(grid.size, dist))
            assert (np.diff(p) > 0).all(), (method, c, dist)
            assert (p > 0).all() and (p < 1).all()


def test_isotonic_compacts_knots_and_keeps_ties_tied():
    z, labels, tp, _ = draw(miscalibrated, 20000, 1, seed=6)
    z = np.round(z, 2)  # many exact ties
    cal = IsotonicCalibrator(max_knots=50).fit(z, labels, tp, 1)
    knots = cal.knots_[0]
    assert knots.shape[0] == 2 and 2 <= knots.shape[1] <= 50
    assert (np.diff(knots[0]) > 0).all() and (np.diff(knots[1]) >= 0).all()
    p = cal.transform(z, labels)
    order = np.argsort(z, kind="stable")
    zs, ps = z[order], p[order]
    assert (ps[1:][zs[1:] == zs[:-1]] == ps[:-1][zs[1:] == zs[:-1]]).all()
    assert (np.diff(ps)[np.diff(zs) > 0] > 0).all()


def test_histogram_uses_the_prior_and_equal_mass_bins():
    z = np.arange(100.0)
    tp = np.zeros(100, dtype=bool)
    tp[50:] = True  # bins of 50: 0/50 and 50/50 true positives
    cal = HistogramBinning(n_bins=2, min_samples=1, prior=(1.0, 1.0)).fit(
        np.r_[z, z], np.r_[np.zeros(100, int), np.ones(100, int)], np.r_[tp, tp], 2)
    np.testing.assert_allclose(cal.knots_[0], [[24.5, 74.5], [1 / 52, 51 / 52]])


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_round_trip_serves_identically(method):
    z, labels, tp, d = draw(miscalibrated, 800, 3, seed=7)
    labels[labels == 2] = 1  # class 2 empty: a fallback class
    cal = make_score_calibrator(method).fit(z, labels, tp, 3, distances=d)
    text = json.dumps(cal.to_dict(), allow_nan=False)
    back = score_calibrator_from_dict(json.loads(text))
    assert type(back) is type(cal) and back.method_name == method
    assert back.fallback_classes_ == cal.fallback_classes_ == [2]
    np.testing.assert_array_equal(back.transform(z, labels, d), cal.transform(z, labels, d))
    assert back.to_dict() == cal.to_dict()


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_fallback_classes_take_the_pooled_fit(method):
    z, labels, tp, d = draw(miscalibrated, 1000, 2, seed=8)
    labels[:20] = 2  # too few detections
    labels[(labels == 1) & ~tp] = 3  # class 3: only false positives; class 1 only true
    cal = make_score_calibrator(method).fit(z, labels, tp, 4, distances=d)
    assert cal.fallback_classes_ == [1, 2, 3]
    assert cal.to_dict()["classes"][0] is not None
    assert all(cal.to_dict()["classes"][c] is None for c in (1, 2, 3))
    grid = np.linspace(-4, 4, 9)
    dist = np.full(9, 10.0)
    pooled = [cal.transform(grid, np.full(9, c), dist) for c in (1, 2, 3)]
    np.testing.assert_array_equal(pooled[0], pooled[1])
    np.testing.assert_array_equal(pooled[0], pooled[2])
    assert not np.array_equal(cal.transform(grid, np.zeros(9, int), dist), pooled[0])


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_rows_are_served_independently(method):
    """The output of a row depends on its own logit, label (never changed) and distance."""
    z, labels, tp, d = draw(miscalibrated, 500, 2, seed=9)
    cal = make_score_calibrator(method).fit(z, labels, tp, 2, distances=d)
    batch = cal.transform(z, labels, d)
    perm = np.random.default_rng(0).permutation(z.size)
    np.testing.assert_array_equal(cal.transform(z[perm], labels[perm], d[perm]), batch[perm])
    one = [cal.transform(z[i:i + 1], labels[i:i + 1], d[i:i + 1])[0] for i in range(5)]
    np.testing.assert_array_equal(one, batch[:5])


def test_factory_and_dispatcher_name_the_method():
    with pytest.raises(ValueError, match=r"method must be one of \['class_temperature'"):
        make_score_calibrator("beta")
    with pytest.raises(ValueError, match="method"):
        score_calibrator_from_dict({"method": "beta"})
    with pytest.raises(ValueError, match="range_term"):
        make_score_calibrator("platt", range_term=True)
    assert make_score_calibrator("platt_range").range_term is True
    assert isinstance(make_score_calibrator("histogram", n_bins=5), HistogramBinning)


def test_validation_names_the_argument():
    z, labels, tp, d = draw(miscalibrated, 100, 2, seed=10)
    cal = IsotonicCalibrator()
    with pytest.raises(NotFittedError):
        cal.transform(z, labels)
    with pytest.raises(ValueError, match="labels"):
        cal.fit(z, labels + 5, tp, 2)
    with pytest.raises(ValueError, match="tp"):
        cal.fit(z, labels, np.ones_like(tp), 2)
    with pytest.raises(ValueError, match="z has NaN"):
        cal.fit(np.r_[np.nan, z[1:]], labels, tp, 2)
    with pytest.raises(ValueError, match="distances"):
        PlattScaler(range_term=True).fit(z, labels, tp, 2)
    with pytest.raises(ValueError, match="min_each"):
        IsotonicCalibrator(min_each=0).fit(z, labels, tp, 2)
    with pytest.raises(ValueError, match="eps"):
        IsotonicCalibrator(eps=0.0).fit(z, labels, tp, 2)
    with pytest.raises(ValueError, match="prior"):
        HistogramBinning(prior=(0.0, 1.0)).fit(z, labels, tp, 2)
    fitted = cal.fit(z, labels, tp, 2)
    with pytest.raises(ValueError, match="labels"):
        fitted.transform(z, labels + 2)
