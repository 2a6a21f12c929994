import json
import math

import numpy as np
import pytest

from calibrators import metrics

# ---------------------------------------------------------------- ECE / MCE / reliability


def test_ece_and_mce_of_a_hand_made_case():
    # 2 bins: [0, 0.5) holds 0.2, 0.4 (mean 0.3, acc 0) and [0.5, 1] holds 0.7, 0.9 (0.8, acc 1)
    conf = [0.2, 0.4, 0.7, 0.9]
    correct = [0, 0, 1, 1]
    assert metrics.expected_calibration_error(conf, correct, n_bins=2) == pytest.approx(
        0.5 * 0.3 + 0.5 * 0.2)
    assert metrics.max_calibration_error(conf, correct, n_bins=2) == pytest.approx(0.3)


def test_last_bin_is_closed_and_edges_are_left_closed():
    diagram = metrics.reliability_diagram([1.0, 0.5, 0.0], [True, False, True], n_bins=2)
    np.testing.assert_allclose(diagram.bin_edges, [0.0, 0.5, 1.0])
    assert diagram.count.tolist() == [1, 2]  # 0.5 opens the upper bin, 1.0 is inside it
    np.testing.assert_allclose(diagram.confidence, [0.0, 0.75])
    np.testing.assert_allclose(diagram.accuracy, [1.0, 0.5])
    assert metrics.expected_calibration_error([1.0], [1]) == 0.0


def test_perfectly_calibrated_sample_has_ece_near_zero():
    rng = np.random.default_rng(0)
    conf = rng.uniform(0.0, 1.0, 200_000)
    correct = rng.uniform(size=conf.size) < conf
    ece = metrics.expected_calibration_error(conf, correct)
    # each of 10 bins has ~20k samples: |acc - conf| ~ sqrt(0.25 / 20k) ≈ 0.0035 at most
    assert ece < 0.01
    assert metrics.max_calibration_error(conf, correct) >= ece


def test_overconfident_sample_has_the_closed_form_ece():
    # P(correct | c) = c², so every bin's gap is E[c - c²] over the bin and ECE = ∫ c - c² = 1/6
    rng = np.random.default_rng(1)
    conf = rng.uniform(0.0, 1.0, 200_000)
    correct = rng.uniform(size=conf.size) < conf**2
    assert metrics.expected_calibration_error(conf, correct) == pytest.approx(1 / 6, abs=0.01)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mce_is_at_least_ece_and_matches_a_loop(seed):
    rng = np.random.default_rng(seed)
    conf = rng.beta(2, 1, 300)
    correct = rng.uniform(size=300) < 0.7
    gaps, weights = [], []
    for m in range(7):
        lo, hi = m / 7, (m + 1) / 7
        sel = (conf >= lo) & ((conf < hi) if m < 6 else (conf <= hi))
        if sel.any():
            gaps.append(abs(correct[sel].mean() - conf[sel].mean()))
            weights.append(sel.mean())
    ece = metrics.expected_calibration_error(conf, correct, n_bins=7)
    mce = metrics.max_calibration_error(conf, correct, n_bins=7)
    assert ece == pytest.approx(float(np.dot(gaps, weights)), abs=1e-12)
    assert mce == pytest.approx(max(gaps), abs=1e-12)
    assert mce >= ece


def test_reliability_diagram_empty_bins_and_json():
    diagram = metrics.reliability_diagram([0.05, 0.95, 0.95], [0, 1, 0], n_bins=4)
    assert diagram.count.tolist() == [1, 0, 0, 2]
    assert np.isnan(diagram.accuracy[1]) and np.isnan(diagram.confidence[2])
    d = diagram.to_dict()
    assert d["accuracy"] == [0.0, None, None, 0.5]
    assert d["count"] == [1, 0, 0, 2]
    json.dumps(d, allow_nan=False)
    with pytest.raises(AttributeError):
        diagram.count = None  # frozen


# ---------------------------------------------------------------- D-ECE


def test_detection_ece_with_one_feature_bin_equals_ece():
    rng = np.random.default_rng(3)
    conf = rng.uniform(size=5000)
    tp = rng.uniform(size=5000) < conf**1.5
    xy = rng.uniform(-50, 50, size=(5000, 2))
    ece = metrics.expected_calibration_error(conf, tp, n_bins=10)
    assert metrics.detection_ece(conf, tp, xy, n_bins=(10, 1, 1)) == pytest.approx(ece, abs=1e-12)


def test_detection_ece_hand_case_position_reveals_miscalibration():
    # one confidence bin: precision 0.5 vs conf 0.8 → ECE 0.3; split by x the two halves
    # have precision 1 and 0 → 0.5 · 0.2 + 0.5 · 0.8 = 0.5
    conf = [0.8, 0.8, 0.8, 0.8]
    tp = [1, 1, 0, 0]
    x = [[0.0], [0.1], [0.9], [1.0]]
    assert metrics.expected_calibration_error(conf, tp, n_bins=1) == pytest.approx(0.3)
    assert metrics.detection_ece(conf, tp, x, n_bins=(1, 2)) == pytest.approx(0.5)
    assert metrics.detection_ece(conf, tp, [0.0, 0.1, 0.9, 1.0], n_bins=(1, 2)) == pytest.approx(
        0.5)  # a 1-D feature is one column


def test_detection_ece_matches_a_loop_over_joint_bins():
    rng = np.random.default_rng(4)
    n = 400
    conf = rng.uniform(size=n)
    tp = rng.uniform(size=n) < 0.6
    feats = np.c_[rng.uniform(-10, 30, n), rng.normal(0, 5, n)]
    ranges = [(-10.0, 30.0), (-8.0, 8.0)]  # second column has values outside → edge bins
    dims = (4, 3, 2)

    def idx(v, lo, hi, m):
        return min(max(int(math.floor((v - lo) / (hi - lo) * m)), 0), m - 1)

    cells: dict[tuple[int, int, int], list[int]] = {}
    for i in range(n):
        key = (idx(conf[i], 0, 1, 4), idx(feats[i, 0], *ranges[0], 3),
               idx(feats[i, 1], *ranges[1], 2))
        cells.setdefault(key, []).append(i)
    expected = sum(len(ix) / n * abs(tp[ix].mean() - conf[ix].mean()) for ix in cells.values())
    got = metrics.detection_ece(conf, tp, feats, n_bins=dims, ranges=ranges)
    assert got == pytest.approx(expected, abs=1e-12)
    # an int n_bins is used for every dimension; a constant feature column is one bin
    const = np.c_[feats[:, 0], np.full(n, 2.0)]
    assert metrics.detection_ece(conf, tp, const, n_bins=5) == pytest.approx(
        metrics.detection_ece(conf, tp, const[:, :1], n_bins=5), abs=1e-12)


# ---------------------------------------------------------------- NLL / Brier


def test_binary_nll_and_brier_hand_values():
    p, y = [0.9, 0.2], [1, 0]
    assert metrics.classification_nll(p, y) == pytest.approx(-(math.log(0.9) + math.log(0.8)) / 2)
    assert metrics.brier_score(p, y) == pytest.approx((0.01 + 0.04) / 2)
    assert metrics.classification_nll(p, [True, False]) == metrics.classification_nll(p, y)


def test_multiclass_nll_and_brier_hand_values():
    p = [[0.7, 0.2, 0.1], [0.1, 0.8, 0.1]]
    y = [0, 2]
    assert metrics.classification_nll(p, y) == pytest.approx(-(math.log(0.7) + math.log(0.1)) / 2)
    # row 0: 0.3² + 0.2² + 0.1² = 0.14; row 1: 0.1² + 0.8² + 0.9² = 1.46
    assert metrics.brier_score(p, y) == pytest.approx((0.14 + 1.46) / 2)


def test_nll_clips_certain_mistakes():
    assert metrics.classification_nll([1.0], [0]) == pytest.approx(-math.log(1e-12))
    assert metrics.classification_nll([[0.0, 1.0]], [0]) == pytest.approx(-math.log(1e-12))
    assert metrics.classification_nll([1.0, 0.0], [1, 0]) == pytest.approx(0.0, abs=1e-11)


# ---------------------------------------------------------------- bad input

_C = [0.2, 0.8]
_Y = [0, 1]

BAD = [
    ("ece NaN", metrics.expected_calibration_error, ([0.2, np.nan], _Y), {},
     "confidences has NaN at index 1"),
    ("ece Inf", metrics.expected_calibration_error, ([np.inf, 0.2], _Y), {},
     "confidences has Inf at index 0"),
    ("ece > 1", metrics.expected_calibration_error, ([0.2, 1.5], _Y), {},
     r"confidences must hold probabilities in \[0, 1\]; entry 1"),
    ("ece < 0", metrics.max_calibration_error, ([-0.1, 0.5], _Y), {},
     "confidences must hold probabilities"),
    ("ece 2-D", metrics.expected_calibration_error, ([[0.2, 0.8]], _Y), {},
     "confidences must have 1 dimensions"),
    ("ece empty", metrics.expected_calibration_error, ([], []), {}, "confidences is empty"),
    ("ece length", metrics.expected_calibration_error, (_C, [0, 1, 1]), {},
     "correct has 3 rows but confidences has 2"),
    ("ece correct 2", metrics.expected_calibration_error, (_C, [0, 2]), {},
     "correct must be 0/1 or bool; entry 1 is 2"),
    ("ece correct NaN", metrics.expected_calibration_error, (_C, [np.nan, 1.0]), {},
     "correct has NaN at index 0"),
    ("ece n_bins 0", metrics.expected_calibration_error, (_C, _Y), {"n_bins": 0},
     "n_bins must be at least 1"),
    ("ece n_bins float", metrics.max_calibration_error, (_C, _Y), {"n_bins": 2.5},
     "n_bins must be an integer"),
    ("diagram n_bins", metrics.reliability_diagram, (_C, _Y), {"n_bins": -3},
     "n_bins must be at least 1"),
    ("diagram NaN", metrics.reliability_diagram, ([np.nan, 0.1], _Y), {},
     "confidences has NaN"),
    ("dece features rows", metrics.detection_ece, (_C, _Y, [[0.0, 1.0]]), {},
     "features has 1 rows but confidences has 2"),
    ("dece features NaN", metrics.detection_ece, (_C, _Y, [[0.0, 1.0], [np.nan, 2.0]]), {},
     r"features has NaN at index \[1, 0\]"),
    ("dece features 3-D", metrics.detection_ece, (_C, _Y, np.zeros((2, 1, 1))), {},
     "features must be"),
    ("dece n_bins len", metrics.detection_ece, (_C, _Y, [[0, 1], [1, 0]]), {"n_bins": (10, 5)},
     "n_bins has 2 entries but confidence \\+ 2 feature columns need 3"),
    ("dece n_bins entry", metrics.detection_ece, (_C, _Y, [[0, 1], [1, 0]]),
     {"n_bins": (10, 0, 5)}, r"n_bins\[1\] must be at least 1"),
    ("dece n_bins type", metrics.detection_ece, (_C, _Y, [[0, 1], [1, 0]]), {"n_bins": "ten"},
     "n_bins must be an int or a sequence of ints"),
    ("dece ranges shape", metrics.detection_ece, (_C, _Y, [[0, 1], [1, 0]]),
     {"ranges": [(0, 1)]}, r"ranges must have shape \[2, 2\]"),
    ("dece ranges order", metrics.detection_ece, (_C, _Y, [[0, 1], [1, 0]]),
     {"ranges": [(0, 1), (3, 3)]}, r"ranges\[1\] must have low < high"),
    ("dece conf", metrics.detection_ece, ([0.2, 7.0], _Y, [[0, 1], [1, 0]]), {},
     "confidences must hold probabilities"),
    ("nll p > 1", metrics.classification_nll, ([0.2, 1.2], _Y), {},
     "probabilities must hold probabilities in"),
    ("nll p NaN", metrics.classification_nll, ([[0.2, np.nan]], [0]), {},
     r"probabilities has NaN at index \[0, 1\]"),
    ("nll p 3-D", metrics.classification_nll, (np.full((1, 1, 1), 0.5), [0]), {},
     r"probabilities must be \[N\] or \[N, C\]"),
    ("nll empty", metrics.classification_nll, ([], []), {}, "probabilities is empty"),
    ("nll binary label", metrics.classification_nll, (_C, [0, 2]), {},
     "labels must be 0/1 or bool"),
    ("nll label range", metrics.classification_nll, ([[0.5, 0.5], [0.1, 0.9]], [0, 2]), {},
     r"labels\[1\] = 2 is out of range for 2 classes"),
    ("nll label negative", metrics.brier_score, ([[0.5, 0.5]], [-1]), {},
     r"labels\[0\] = -1 is out of range"),
    ("nll label float", metrics.brier_score, ([[0.5, 0.5]], [0.5]), {},
     "labels must hold integers"),
    ("brier length", metrics.brier_score, ([[0.5, 0.5]], [0, 1]), {},
     "labels has 2 rows but probabilities has 1"),
    ("brier binary length", metrics.brier_score, (_C, [1]), {},
     "labels has 1 rows but probabilities has 2"),
    ("brier p < 0", metrics.brier_score, ([[-0.5, 0.5]], [0]), {},
     "probabilities must hold probabilities"),
]


@pytest.mark.parametrize("fn, args, kwargs, message", [b[1:] for b in BAD],
                         ids=[b[0] for b in BAD])
def test_bad_input_raises_named_value_error(fn, args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        fn(*args, **kwargs)
