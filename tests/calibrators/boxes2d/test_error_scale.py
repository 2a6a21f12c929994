"""`EdgeErrorScale`: the fitted scale of each box edge's error that adaptive box regions
divide by."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.boxes2d import EdgeErrorScale, box_edges
from calibrators.core.errors import FieldError


def _data(n: int = 4000, seed: int = 0, unit: float = 1.0):
    """Boxes well inside a 640 x 480 image whose edge errors are Laplace with a scale that
    grows with the box's extent along the edge and falls with the score, plus a layer σ that
    tracks it; everything in pixels times `unit`."""
    rng = np.random.default_rng(seed)
    w, h = rng.uniform(10, 200, n), rng.uniform(10, 150, n)
    xy = np.c_[rng.uniform(5, 630 - w), rng.uniform(5, 470 - h)]
    det = np.c_[xy, w, h]
    score = rng.uniform(0.05, 0.95, n)
    along = np.c_[w, h, w, h]
    scale = 0.05 * along * np.exp(-0.8 * (score - 0.5))[:, None]
    err = rng.laplace(0, 1, (n, 4)) * scale
    e = box_edges(det) + err
    true = np.c_[e[:, :2], np.maximum(e[:, 2:] - e[:, :2], 1.0)]
    sigma = scale * np.exp(rng.normal(0, 0.3, (n, 4)))
    return det * unit, true * unit, score, sigma * unit, scale * unit


def test_the_scale_follows_the_error_it_was_fit_on():
    det, true, score, sigma, scale = _data()
    model = EdgeErrorScale().fit(det, true, score, sigma)
    assert model.features_ == ["edge", "log_along", "log_across", "score_logit",
                               "log_layer_sigma"]
    got = model.predict(det, score, sigma)
    assert got.shape == (len(det), 4) and (got > 0).all()
    # the fitted scale ranks detections as the true one does
    r = np.corrcoef(np.log(got).ravel(), np.log(scale).ravel())[0, 1]
    assert r > 0.9
    # and errors divided by it are spread much more alike for narrow and wide boxes
    err = np.abs(box_edges(true) - box_edges(det))
    narrow = det[:, 2] < np.median(det[:, 2])

    def log_ratio(x: np.ndarray) -> float:
        return abs(np.log(np.median(x[narrow, 0]) / np.median(x[~narrow, 0])))

    assert log_ratio(err / got) < 0.4 * log_ratio(err)


@pytest.mark.parametrize("unit", [0.01, 3.0, 1000.0])
def test_the_scale_reads_the_same_in_any_pixel_unit(unit):
    det, true, score, sigma, _ = _data(800, seed=1)
    base = EdgeErrorScale().fit(det, true, score, sigma).predict(det, score, sigma)
    d2, t2, _, s2, _ = _data(800, seed=1, unit=unit)
    scaled = EdgeErrorScale().fit(d2, t2, score, s2).predict(d2, score, s2)
    np.testing.assert_allclose(scaled, base * unit, rtol=1e-7)


@settings(max_examples=25, deadline=None)
@given(st.randoms(use_true_random=False))
def test_the_fit_does_not_depend_on_the_row_order(rnd):
    det, true, score, sigma, _ = _data(300, seed=2)
    order = np.arange(len(det))
    rnd.shuffle(order)
    a = EdgeErrorScale().fit(det, true, score, sigma)
    b = EdgeErrorScale().fit(det[order], true[order], score[order], sigma[order])
    np.testing.assert_allclose(a.coef_, b.coef_, rtol=1e-9, atol=1e-12)


def test_the_border_term_reads_the_image_size():
    det, true, score, _, _ = _data(600, seed=3)
    size = np.tile([640.0, 480.0], (len(det), 1))
    # boxes clipped at the left border: their x1 is exact
    clipped = det.copy()
    clipped[:200, 2] += clipped[:200, 0]
    clipped[:200, 0] = 0.0
    t = true.copy()
    t[:200, 2] = t[:200, 0] + t[:200, 2]
    t[:200, 0] = 0.0
    model = EdgeErrorScale().fit(clipped, t, score, None, size)
    assert model.features_[-1] == "at_border" and model.uses_image_size
    assert not model.uses_layer_sigma
    got = model.predict(clipped, score, None, size)
    assert np.median(got[:200, 0]) < 0.5 * np.median(got[200:, 0])
    with pytest.raises(FieldError) as err:
        model.predict(clipped, score)
    assert err.value.field == "image_size"


def test_what_the_model_reads_must_be_sent():
    det, true, score, sigma, _ = _data(300)
    model = EdgeErrorScale().fit(det, true, score, sigma)
    with pytest.raises(FieldError) as err:
        model.predict(det, score)
    assert err.value.field == "layer_boxes"
    with pytest.raises(FieldError) as err:
        model.predict(det, score[:-1], sigma)
    assert err.value.field == "score"
    with pytest.raises(FieldError) as err:
        model.predict(det, np.full(len(det), 1.5), sigma)
    assert err.value.field == "score" and err.value.row == 0
    assert model.predict(det[:0], score[:0], sigma[:0]).shape == (0, 4)


def test_the_dict_round_trip_predicts_identically():
    det, true, score, sigma, _ = _data(500)
    model = EdgeErrorScale().fit(det, true, score, sigma)
    back = EdgeErrorScale.from_dict(json.loads(json.dumps(model.to_dict())))
    np.testing.assert_array_equal(back.predict(det, score, sigma),
                                  model.predict(det, score, sigma))


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: d.pop("coef"), "an object with"),
    (lambda d: d.update(features=["edge", "magic"]), "scale.features"),
    (lambda d: d.update(features=["edge", "log_across"]), "not a term list"),
    (lambda d: d.update(coef=[1.0]), "scale.coef"),
    (lambda d: d["coef"].__setitem__(0, float("nan")), "scale.coef"),
    (lambda d: d.update(error_floor=0), "scale.error_floor"),
    (lambda d: d.update(sigma_floor=None), "scale.sigma_floor"),
    (lambda d: d.update(n=1), "scale.n"),
])
def test_a_bad_dict_is_named(change, message):
    det, true, score, sigma, _ = _data(300)
    data = EdgeErrorScale().fit(det, true, score, sigma).to_dict()
    change(data)
    with pytest.raises(ValueError, match=message):
        EdgeErrorScale.from_dict(data)
