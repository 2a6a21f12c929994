"""Shrinkage of per-class score calibrators toward their pooled fit (`shrink` κ): a class with
`n` true positives serves `n / (n + κ)` of its own fit.

The world: every class follows one calibration law, `P(TP | z) = sigmoid(0.6·z - 0.4)`; class 0
holds thousands of detections, class 1 only 60. Its own fit is noisy; the pooled one is not."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit

from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile
from calibrators.scores import SCORE_CALIBRATION_METHODS, make_score_calibrator


def _draw(rng: np.random.Generator, n_small: int = 60):
    labels = np.r_[np.zeros(4000, int), np.ones(n_small, int)]
    z = rng.normal(0.0, 2.0, labels.size)
    tp = rng.random(labels.size) < expit(0.6 * z - 0.4)
    return z, labels, tp


@pytest.mark.parametrize("method", ["platt", "isotonic"])
def test_a_small_class_is_served_closer_to_the_truth_with_shrinkage(method):
    rng = np.random.default_rng(0)
    grid = np.linspace(-4, 4, 41)
    truth = expit(0.6 * grid - 0.4)
    errors = {0.0: [], 100.0: []}
    for _ in range(40):
        z, labels, tp = _draw(rng)
        for kappa, out in errors.items():
            cal = make_score_calibrator(method, shrink=kappa).fit(z, labels, tp, 2)
            p = cal.transform(grid, np.ones(grid.size, int))
            out.append(float(np.mean((p - truth) ** 2)))
    assert np.mean(errors[100.0]) < 0.7 * np.mean(errors[0.0])


@pytest.mark.parametrize("method", SCORE_CALIBRATION_METHODS)
def test_shrunk_scores_still_increase_with_the_logit_and_round_trip(method):
    z, labels, tp = _draw(np.random.default_rng(1))
    d = np.random.default_rng(2).uniform(0, 60, z.size)
    cal = make_score_calibrator(method, shrink=30.0).fit(z, labels, tp, 2, distances=d)
    grid = np.linspace(-6, 6, 200)
    for k in (0, 1):
        p = cal.transform(grid, np.full(grid.size, k), distances=np.full(grid.size, 20.0))
        assert (np.diff(p) > 0).all()
    back = type(cal).from_dict(cal.to_dict())
    assert np.array_equal(back.transform(z, labels, distances=d),
                          cal.transform(z, labels, distances=d))
    w = cal.class_weights()
    assert w[0] > w[1] and np.allclose(w, cal.n_positives_ / (cal.n_positives_ + 30.0))


def test_without_shrinkage_the_json_and_the_scores_are_as_before():
    z, labels, tp = _draw(np.random.default_rng(3))
    plain = make_score_calibrator("platt").fit(z, labels, tp, 2)
    assert "shrink" not in plain.to_dict()["hyper"]   # calibrators fit before load the same
    assert (plain.class_weights() == 1.0).all()


@pytest.mark.parametrize("shrink", [-1.0, float("inf"), "10", True])
def test_a_bad_shrink_is_refused_naming_it(shrink):
    z, labels, tp = _draw(np.random.default_rng(4))
    with pytest.raises(ValueError, match="shrink"):
        make_score_calibrator("platt", shrink=shrink).fit(z, labels, tp, 2)


def test_a_fit_chooses_the_shrinkage_by_held_out_nll_unless_fixed():
    dump = synthetic_dump(n_frames=60, seed=5)
    chosen = fit_profile(dump, score_method="platt", other_sources=False)
    score = chosen.report["selection"]["score"]
    nll = score["shrink_candidates"]
    assert set(map(float, nll)) == {0.0, 10.0, 30.0, 100.0, 300.0, 1000.0}
    assert nll[str(score["shrink"])] == min(nll.values())
    fixed = fit_profile(dump, score_method="platt", other_sources=False, score_shrink=0.0)
    assert fixed.report["selection"]["score"]["shrink"] == 0.0
    assert fixed.report["selection"]["score"]["shrink_candidates"] == {}
