"""Logits modulation (Eq. 4-1): the formula, its validation, and the optional profile stage."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators import summarize
from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile
from calibrators.profile import CalibrationProfile
from calibrators.scores import class_probabilities, modulate_logits

CLASSES = ("car", "pedestrian")


def test_formula_matches_a_hand_computation():
    # one detection, L = 3 layers, 2 columns
    layers = np.array([[[1.0, -2.0], [2.0, -2.0], [3.0, -2.0]]])
    # column 0: mean 2, population variance ((1)^2 + 0 + 1^2) / 3 = 2/3; column 1: variance 0
    expected = np.array([[3.0 * (1.0 - np.tanh(2.0 / 3.0)), -2.0]])
    np.testing.assert_allclose(modulate_logits(layers), expected, rtol=0, atol=1e-15)


def test_formula_on_random_input_and_dtype():
    rng = np.random.default_rng(0)
    layers = rng.normal(size=(50, 4, 6)).astype(np.float32)
    z = layers.astype(np.float64)
    var = ((z - z.mean(axis=1, keepdims=True)) ** 2).sum(axis=1) / 4   # ddof = 0
    out = modulate_logits(layers)
    assert out.dtype == np.float64 and out.shape == (50, 6)
    np.testing.assert_allclose(out, z[:, -1] * (1 - np.tanh(var)), rtol=1e-12)
    assert modulate_logits(np.zeros((0, 2, 6))).shape == (0, 6)


def test_single_layer_and_bad_input_are_refused():
    with pytest.raises(ValueError, match=r"layer_logits has 1 decoder layer.*L >= 2"):
        modulate_logits(np.zeros((3, 1, 4)))
    with pytest.raises(ValueError, match="layer_logits must have 3 dimensions"):
        modulate_logits(np.zeros((3, 4)))
    bad = np.zeros((2, 3, 4))
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"layer_logits has NaN at index \[1, 2, 3\]"):
        modulate_logits(bad)


def test_shrinks_confident_but_unstable_logits_and_keeps_stable_ones():
    stable = [[6.0, -4.0]] * 3                         # layers agree: unchanged
    unstable = [[1.0, -4.0], [4.0, -4.0], [6.0, -4.0]]  # confident final layer, layers disagree
    out = modulate_logits(np.array([stable, unstable]))
    np.testing.assert_array_equal(out[0], [6.0, -4.0])
    assert 0 < out[1, 0] < 0.1 * 6.0                   # var = 38/9 -> factor 1 - tanh(4.2) ≈ 4e-4
    assert out[1, 1] == -4.0
    # every logit moves towards 0, never across it
    rng = np.random.default_rng(1)
    layers = rng.normal(scale=3.0, size=(200, 3, 5))
    mod = modulate_logits(layers)
    assert np.all(np.abs(mod) <= np.abs(layers[:, -1]))
    assert np.all(np.sign(mod) * np.sign(layers[:, -1]) >= 0)


def test_argmax_may_change():
    # class 0 wins the final layer but is unstable; class 1 is stable: modulation flips them
    layers = np.array([[[0.0, 2.0], [1.0, 2.0], [3.0, 2.0]]])
    assert np.argmax(layers[0, -1]) == 0
    assert np.argmax(modulate_logits(layers)[0]) == 1


# -- the optional profile stage ---------------------------------------------------------------
def _profile(**overrides) -> CalibrationProfile:
    fields = dict(classes=CLASSES, score_mode="sigmoid", temperature=2.0, modulation=True,
                  cov_source="none")
    fields.update(overrides)
    return CalibrationProfile(**fields)


def test_profile_round_trip_with_modulation():
    profile = _profile()
    text = profile.to_json()
    assert json.loads(text)["modulation"] is True
    back = CalibrationProfile.from_json(text)
    assert back == profile and back.modulation is True
    assert back.to_json() == text
    assert back.summary()["modulation"] is True


def test_older_json_without_modulation_reads_as_false():
    data = json.loads(_profile(modulation=False).to_json())
    del data["modulation"]
    assert CalibrationProfile.from_json(json.dumps(data)).modulation is False


@pytest.mark.parametrize("value", [1, "true", None])
def test_modulation_must_be_a_json_bool(value):
    data = json.loads(_profile().to_json())
    data["modulation"] = value
    with pytest.raises(ValueError, match="modulation"):
        CalibrationProfile.from_json(json.dumps(data))


def test_calibrate_needs_layer_logits_and_keeps_the_raw_label():
    profile = _profile()
    boxes = np.ones((1, 9))
    with pytest.raises(ValueError, match=r"applies logits modulation, which needs layer_logits"):
        profile.calibrate(logits=np.zeros((1, 2)), boxes=boxes)
    with pytest.raises(ValueError, match="needs layer_logits with at least 2 layers, got 1"):
        profile.calibrate(layer_logits=np.zeros((1, 1, 2)), boxes=boxes)
    with pytest.raises(ValueError, match="layer_logits has 3 columns"):
        profile.calibrate(layer_logits=np.zeros((1, 2, 3)), boxes=boxes)
    layers = np.array([[[0.0, 2.0], [1.0, 2.0], [3.0, 2.0]]])   # modulation flips the arg-max
    out = profile.calibrate(layer_logits=layers, boxes=boxes)
    z = modulate_logits(layers)
    assert out.labels.tolist() == [0]                           # the detector's label
    np.testing.assert_allclose(out.class_scores, class_probabilities(z, "sigmoid", 2.0))
    assert out.scores[0] == pytest.approx(1 / (1 + np.exp(-z[0, 0] / 2.0)))
    assert out.scores_raw[0] == pytest.approx(1 / (1 + np.exp(-3.0)))


def test_profile_without_modulation_accepts_layer_logits_as_the_final_layer():
    profile = _profile(modulation=False)
    layers = np.random.default_rng(2).normal(size=(4, 3, 2))
    a = profile.calibrate(layer_logits=layers, boxes=np.ones((4, 9)))
    b = profile.calibrate(logits=layers[:, -1], boxes=np.ones((4, 9)))
    np.testing.assert_array_equal(a.scores, b.scores)
    with pytest.raises(ValueError, match="either logits or scores"):
        profile.calibrate(logits=layers[:, -1], layer_logits=layers, boxes=np.ones((4, 9)))


@pytest.fixture(scope="module")
def dump():
    return synthetic_dump(n_frames=20, n_layers=3, seed=6)


@pytest.mark.parametrize("score_mode", ["sigmoid", "softmax"])
def test_fit_profile_with_modulation(score_mode):
    dump = synthetic_dump(n_frames=20, n_layers=3, score_mode=score_mode, seed=6)
    plain = fit_profile(dump, cov_source="given")
    mod = fit_profile(dump, cov_source="given", modulation=True)
    assert plain.modulation is False and mod.modulation is True
    assert mod.temperature != plain.temperature
    assert mod.depth_k == plain.depth_k                  # modulation leaves regression alone
    assert CalibrationProfile.from_json(mod.to_json()) == mod
    report = mod.report["fit"]
    assert report["classification"]["nll"]["after"] is not None
    # the report's "after" side is calibrate() on the dump's layer logits
    out = mod.calibrate(layer_logits=dump.det_logits, boxes=dump.final_boxes,
                        covariances=dump.det_cov)
    again = summarize(dump, mod)
    assert again.classification["ece"].after == pytest.approx(
        _ece(out.scores, dump, mod))


def _ece(scores, dump, profile):
    from calibrators import match_dump, metrics

    tp = match_dump(dump, profile.matching["threshold"]).tp
    return metrics.expected_calibration_error(scores, tp)


def test_fit_profile_modulation_needs_layers(dump):
    one_layer = synthetic_dump(n_frames=5, n_layers=1, seed=7)
    with pytest.raises(ValueError, match="modulation=True needs .* at least 2 decoder layers"):
        fit_profile(one_layer, modulation=True)
    with pytest.raises(ValueError, match="modulation must be True or False"):
        fit_profile(dump, modulation="yes")
