"""PositionCalibrator (netcal-style logistic calibration with box terms) and score_inputs (the
2-D way into the per-class score calibrators)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.special import expit, logit

from calibrators.boxes2d import (
    BOX_FEATURES,
    Detections2D,
    PositionCalibrator,
    box_features,
    category_index,
    score_inputs,
)
from calibrators.core.errors import FieldError, NotFittedError
from calibrators.metrics import detection_ece
from calibrators.scores import make_score_calibrator

#: The known effect: P(TP) = sigmoid(0.8·z − 0.5 + 1.5·cx − 1.0·h); cy and w play no part.
TRUE_COEF = np.array([0.8, -0.5, 1.5, 0.0, 0.0, -1.0])


def position_data(seed: int, n: int = 30000, n_classes: int = 2):
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 2.0, n)
    feats = rng.uniform(0.0, 1.0, (n, 4))
    labels = rng.integers(0, n_classes, n)
    p_true = expit(TRUE_COEF[0] * z + TRUE_COEF[1] + feats @ TRUE_COEF[2:])
    return z, labels, rng.random(n) < p_true, feats, p_true


def test_recovers_a_known_position_effect():
    z, labels, tp, feats, p_true = position_data(0)
    est = PositionCalibrator().fit(z, labels, tp, 2, feats)
    assert est.fallback_classes_ == []
    for row in (*est.coef_, est.pooled_coef_):
        np.testing.assert_allclose(row, TRUE_COEF, atol=0.15)
    np.testing.assert_allclose(est.pooled_coef_, TRUE_COEF, atol=0.08)
    # held out: the calibrated probability is the true one, and position-aware D-ECE drops
    z2, labels2, tp2, feats2, p2 = position_data(1, n=20000)
    p = est.transform(z2, labels2, feats2)
    assert np.abs(p - p2).mean() < 0.015
    platt = make_score_calibrator("platt").fit(z, labels, tp, 2)
    plain = platt.transform(z2, labels2)
    assert np.abs(plain - p2).mean() > 3 * np.abs(p - p2).mean()
    dece = [detection_ece(q, tp2, feats2[:, [0, 3]], (10, 4, 4), [(0, 1), (0, 1)])
            for q in (p, plain)]
    assert dece[0] < 0.6 * dece[1], dece


def test_strictly_increasing_in_the_logit_for_a_fixed_box():
    z, labels, tp, feats, _ = position_data(2, n=5000)
    tp = tp & (z < 0) | (z > 1)     # a slope towards 0: the bound keeps it positive
    est = PositionCalibrator(min_slope=1e-3, l2=0.0).fit(-z, labels, tp, 2, feats)
    assert (est.coef_[:, 0] >= 1e-3 - 1e-12).all()
    grid = np.linspace(-8, 8, 200)
    for k in (0, 1):
        box = np.tile(feats[k], (200, 1))
        assert (np.diff(est.transform(grid, np.full(200, k), box)) > 0).all()


def test_a_small_class_falls_back_to_the_pooled_fit():
    z, labels, tp, feats, _ = position_data(3, n=4000, n_classes=2)
    labels[:10] = 2
    labels[10:][labels[10:] == 2] = 0
    est = PositionCalibrator(features=("cx", "h")).fit(z, labels, tp, 3, feats[:, [0, 3]])
    assert est.fallback_classes_ == [2] and est.coef_.shape == (3, 4)
    np.testing.assert_array_equal(est.coef_[2], est.pooled_coef_)
    assert est.n_samples_.tolist()[2] == 10


def test_estimator_convention_and_round_trip():
    z, labels, tp, feats, _ = position_data(4, n=3000)
    est = PositionCalibrator()
    before = set(vars(est))
    with pytest.raises(NotFittedError):
        est.transform(z, labels, feats)
    with pytest.raises(NotFittedError):
        est.to_dict()
    assert est.fit(z, labels, tp, 2, feats) is est
    added = set(vars(est)) - before
    assert added and all(a.endswith("_") for a in added)
    text = json.dumps(est.to_dict(), allow_nan=False)
    back = PositionCalibrator.from_dict(json.loads(text))
    assert {a for a in vars(back) if a.endswith("_")} == added
    assert back.transform(z, labels, feats).tobytes() == est.transform(z, labels, feats).tobytes()
    assert json.dumps(back.to_dict(), allow_nan=False) == text
    with pytest.raises(ValueError, match="must be a dict"):
        PositionCalibrator.from_dict([1])
    with pytest.raises(ValueError, match="lacks"):
        PositionCalibrator.from_dict({})


@pytest.mark.parametrize(("kwargs", "args", "field"), [
    (dict(features=("cx", "area")), {}, "features"),
    (dict(l2=-1.0), {}, "l2"),
    (dict(min_slope=0.0), {}, "min_slope"),
    ({}, dict(feats=np.zeros((50, 3))), "box_features"),
    ({}, dict(tp=np.ones(50, bool)), "tp"),
    ({}, dict(labels=np.full(50, 5)), "labels"),
])
def test_bad_input_names_the_field(kwargs, args, field):
    z, labels, tp, feats, _ = position_data(5, n=50)
    data = {**dict(z=z, labels=labels, tp=tp, feats=feats), **args}
    with pytest.raises(FieldError) as info:
        PositionCalibrator(**kwargs).fit(data["z"], data["labels"], data["tp"], 2, data["feats"])
    assert info.value.field == field


def test_box_features_are_relative_to_the_image():
    feats = box_features([[10, 20, 40, 60]], [[200, 100]])
    np.testing.assert_allclose(feats, [[0.15, 0.5, 0.2, 0.6]])
    assert box_features([[10, 20, 40, 60]], [[200, 100]], ("h", "cx")).tolist() == [[0.6, 0.15]]
    assert BOX_FEATURES == ("cx", "cy", "w", "h")
    with pytest.raises(FieldError, match=r"image_size\[0\] must be > 0"):
        box_features([[0, 0, 1, 1]], [[0, 10]])


def test_score_inputs_give_the_label_logit_and_index():
    dets = Detections2D([1, 1, 2], [18, 3, 18], [[0, 0, 1, 1]] * 3, [0.9, 0.2, 0.5])
    z, labels = score_inputs(dets, [18, 3])          # the stated order: 18 is class 0
    assert labels.tolist() == [0, 1, 0]
    np.testing.assert_allclose(z, logit([0.9, 0.2, 0.5]))
    with_logits = Detections2D(dets.image_id, dets.category_id, dets.bbox, dets.score,
                               logits=[[2.0, -1.0], [0.5, 3.0], [1.0, 1.0]])
    assert score_inputs(with_logits, [18, 3], "sigmoid").z.tolist() == [2.0, 3.0, 1.0]
    softmax = Detections2D(dets.image_id, dets.category_id, dets.bbox, dets.score,
                           logits=[[1.0, 0.0, 0.0]] * 3)
    p = np.exp(1.0) / (np.exp(1.0) + 2.0)
    np.testing.assert_allclose(score_inputs(softmax, [18, 3], "softmax").z[0], logit(p))
    with pytest.raises(FieldError, match="state the score mode") as info:
        score_inputs(with_logits, [18, 3])
    assert info.value.field == "mode"
    with pytest.raises(FieldError, match="3 columns"):
        score_inputs(softmax, [18, 3], "sigmoid")
    with pytest.raises(FieldError, match=r"category_id\[1\] = 3 is not in category_ids"):
        score_inputs(dets, [18])
    with pytest.raises(FieldError, match="distinct"):
        category_index(dets.category_id, [18, 18])


def test_the_per_class_calibrators_serve_2d_detections():
    z, labels, tp, feats, _ = position_data(6, n=4000)
    dets = Detections2D(np.arange(4000), np.where(labels == 0, 5, 9),
                        np.c_[feats[:, :2] * 100, np.ones((4000, 2))], expit(z))
    z2, labels2 = score_inputs(dets, [5, 9])
    np.testing.assert_allclose(z2, z, rtol=1e-9, atol=1e-9)
    calibrator = make_score_calibrator("isotonic").fit(z2, labels2, tp, 2)
    p = calibrator.transform(z2, labels2)
    assert p.shape == (4000,) and ((p > 0) & (p < 1)).all()
