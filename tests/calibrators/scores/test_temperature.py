"""TemperatureScaler: recovery of a known T, float32 input, arg-max, validation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.special import expit, log_expit, logsumexp, softmax

# `_NEWTON_MARGIN`, patched below, is a global of this private module read at call time: the
# module is imported for that alone (allowed in tests/test_imports.py).
import calibrators.scores._temperature as temperature
from calibrators.core.errors import NotFittedError
from calibrators.scores import (
    SIGMOID_BINS,
    SUBSAMPLE_MIN,
    SigmoidBins,
    TemperatureScaler,
    class_probabilities,
    row_max,
    sigmoid_nll,
    softmax_nll,
)

N = 100_000


def sigmoid_sample(t_true: float, n: int = N, n_classes: int = 10, seed: int = 1):
    """Logits [n, C] and 0/1 labels drawn as Bernoulli(sigmoid(max logit / t_true)).

    At n = 100k the Cramér-Rao standard error of T here is about 0.57 %, so a 1 % tolerance
    is a ~1.7 sigma check: it holds for this seed; others may miss it by sampling noise alone.
    """
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 3.0, size=(n, n_classes)) - 2.0
    s = z.max(axis=1)
    labels = (rng.random(n) < expit(s / t_true)).astype(np.int64)
    return z, labels


def softmax_sample(t_true: float, n: int = N, n_classes: int = 10, seed: int = 0):
    """Logits [n, C + 1] and target columns drawn from Categorical(softmax(z / t_true))."""
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 3.0, size=(n, n_classes + 1))
    cdf = np.cumsum(softmax(z / t_true, axis=1), axis=1)
    labels = np.minimum((rng.random(n)[:, None] > cdf).sum(axis=1), n_classes)
    return z, labels


@pytest.mark.parametrize("t_true", [0.6, 1.7])
def test_sigmoid_recovers_temperature(t_true):
    z, y = sigmoid_sample(t_true)
    scaler = TemperatureScaler(mode="sigmoid").fit(z, y)
    assert scaler.temperature_ == pytest.approx(t_true, rel=0.01)
    assert scaler.n_samples_ == N
    assert scaler.nll_ <= sigmoid_nll(row_max(z), y)(0.0)   # no worse than T = 1


@pytest.mark.parametrize("t_true", [0.6, 1.7])
def test_softmax_recovers_temperature(t_true):
    z, y = softmax_sample(t_true)
    scaler = TemperatureScaler(mode="softmax").fit(z, y)
    assert scaler.temperature_ == pytest.approx(t_true, rel=0.01)


@pytest.mark.parametrize("mode", ["sigmoid", "softmax"])
def test_float32_input_gives_the_same_temperature(mode):
    z, y = sigmoid_sample(1.7) if mode == "sigmoid" else softmax_sample(1.7)
    z32 = z.astype(np.float32)
    t32 = TemperatureScaler(mode=mode).fit(z32, y).temperature_
    t64 = TemperatureScaler(mode=mode).fit(z32.astype(np.float64), y).temperature_
    assert t32 == t64
    assert t32 == pytest.approx(1.7, rel=0.01)


def test_fit_is_the_exact_minimiser_of_the_nll():
    z, y = sigmoid_sample(1.3, n=5000)
    t_fit = TemperatureScaler().fit(z, y).temperature_
    s = z.max(axis=1)
    grid = t_fit * (1.0 + np.linspace(-1e-3, 1e-3, 201))
    nll = [np.mean(np.logaddexp(0.0, s / t) - y * s / t) for t in grid]
    assert grid[int(np.argmin(nll))] == pytest.approx(t_fit, rel=2e-5)


def test_objectives_match_direct_formulas():
    rng = np.random.default_rng(3)
    z = rng.normal(0, 30, size=(200, 5))  # large logits: the stable forms must not overflow
    y01 = rng.integers(0, 2, size=200)
    ycol = rng.integers(0, 5, size=200)
    for t in (0.05, 1.0, 7.0):
        s = z.max(axis=1) / t
        ref = -np.mean(np.where(y01 == 1, log_expit(s), log_expit(-s)))
        assert sigmoid_nll(row_max(z), y01)(np.log(t)) == pytest.approx(ref, rel=1e-9)
        ref = np.mean(logsumexp(z / t, axis=1) - z[np.arange(200), ycol] / t)
        assert softmax_nll(z, ycol)(np.log(t)) == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("mode", ["sigmoid", "softmax"])
def test_transform_never_changes_the_argmax(mode):
    z, y = (sigmoid_sample(0.5, n=3000) if mode == "sigmoid" else softmax_sample(0.5, n=3000))
    scaler = TemperatureScaler(mode=mode).fit(z, y)
    probs = scaler.transform(z)
    n_obj = z.shape[1] if mode == "sigmoid" else z.shape[1] - 1
    assert probs.shape == (len(z), n_obj)
    np.testing.assert_array_equal(probs.argmax(axis=1), z[:, :n_obj].argmax(axis=1))
    assert scaler.temperature_ == pytest.approx(0.5, rel=0.05)  # labels drawn at T = 0.5
    assert not np.allclose(probs, class_probabilities(z, mode))  # the scores did change


def test_fit_transform_and_n_columns_check():
    z, y = softmax_sample(1.2, n=2000)
    scaler = TemperatureScaler(mode="softmax")
    probs = scaler.fit_transform(z, y)
    assert probs.shape == (2000, 10)
    with pytest.raises(ValueError, match="logits has 10 columns but the scaler was fit on 11"):
        scaler.transform(z[:, :10])


def test_transform_before_fit_raises_not_fitted():
    with pytest.raises(NotFittedError, match="not fitted"):
        TemperatureScaler().transform(np.zeros((2, 3)))
    assert issubclass(NotFittedError, ValueError)


@pytest.mark.parametrize("logits, labels, match", [
    (np.zeros((0, 3)), np.zeros(0, int), "logits is empty"),
    (np.zeros(5), np.zeros(5, int), "logits must have 2 dimensions"),
    (np.array([[0.0, np.nan]] * 3), np.zeros(3, int), r"logits has NaN at index \[0, 1\]"),
    (np.array([[0.0, np.inf]] * 3), np.zeros(3, int), r"logits has Inf"),
    (np.zeros((3, 2)), np.zeros(4, int), "labels has 4 rows but logits has 3"),
    (np.zeros((3, 2)), np.array([0, 2, 1]), r"labels\[1\] = 2 is out of range"),
    (np.zeros((3, 2)), np.array([0, -1, 1]), r"labels\[1\] = -1 is out of range"),
    (np.zeros((3, 2)), np.array([0.5, 1, 1]), "labels must hold integers"),
])
def test_sigmoid_bad_input_names_the_argument(logits, labels, match):
    with pytest.raises(ValueError, match=match):
        TemperatureScaler().fit(logits, labels)


def test_softmax_label_range_and_width():
    with pytest.raises(ValueError, match=r"labels\[0\] = 3 is out of range for 3 logit columns"):
        TemperatureScaler(mode="softmax").fit(np.zeros((2, 3)), np.array([3, 0]))
    with pytest.raises(ValueError, match="at least 2 column"):
        TemperatureScaler(mode="softmax").fit(np.zeros((2, 1)), np.array([0, 0]))


@pytest.mark.parametrize("kwargs, match", [
    ({"mode": "tanh"}, "mode must be one of"),
    ({"bounds": (0.0, 10.0)}, "bounds must satisfy 0 < low < high"),
    ({"bounds": (5.0, 1.0)}, "bounds must satisfy"),
    ({"bounds": "ab"}, "bounds must be a pair of numbers"),
])
def test_bad_hyper_parameters(kwargs, match):
    z, y = sigmoid_sample(1.0, n=10)
    with pytest.raises(ValueError, match=match):
        TemperatureScaler(**kwargs).fit(z, y)


def test_optimum_at_the_bound_warns():
    z = np.array([[3.0], [2.0], [-1.0], [-4.0]])
    y = np.array([1, 1, 0, 0])  # separable: NLL keeps falling as T -> 0
    with pytest.warns(RuntimeWarning, match="edge of bounds"):
        scaler = TemperatureScaler(bounds=(0.1, 10.0)).fit(z, y)
    assert scaler.temperature_ == pytest.approx(0.1, rel=1e-5)


# -- the fast searches equal the exact minimiser -------------------------------------------------
def exact_temperature(objective, bounds=(0.01, 100.0)) -> float:
    """T minimising an exact NLL of log T, by bounded Brent to 1e-11."""
    result = minimize_scalar(objective, bounds=np.log(bounds), method="bounded",
                             options={"xatol": 1e-11})
    return float(np.exp(result.x))


@pytest.mark.parametrize("seed, scale, shift", [(0, 3.0, -2.0), (1, 0.3, 0.0), (2, 12.0, 4.0)])
def test_binned_sigmoid_fit_equals_the_exact_minimiser(seed, scale, shift):
    n = 3 * SIGMOID_BINS  # above the threshold: the binned search is used
    rng = np.random.default_rng(seed)
    z = rng.standard_t(3, size=(n, 4)) * scale + shift  # heavy tails stretch the bins
    y = (rng.random(n) < expit(z.max(axis=1) / 1.3)).astype(np.int64)
    scaler = TemperatureScaler().fit(z, y)
    exact = sigmoid_nll(row_max(z), y)
    assert scaler.temperature_ == pytest.approx(exact_temperature(exact), rel=1e-6)
    assert scaler.nll_ == pytest.approx(exact(np.log(scaler.temperature_)), rel=1e-9)


def test_binned_sigmoid_nll_error_is_within_its_bound():
    rng = np.random.default_rng(4)
    s = rng.normal(0.0, 4.0, 50_000)
    y = rng.integers(0, 2, 50_000)
    n_bins = 1024  # coarse, so the error is measurable
    binned, exact = SigmoidBins.from_logits(s, y, n_bins).objective(), sigmoid_nll(s, y)
    h = np.ptp(s) / n_bins
    for t in (0.3, 1.0, 4.0):
        error = abs(binned(np.log(t)) - exact(np.log(t)))
        assert 0 < error <= (h / t) ** 3 / 48
    same = np.full(10, 2.5)  # zero span: one bin, exact
    assert SigmoidBins.from_logits(same, y[:10]).objective()(0.3) == pytest.approx(
        sigmoid_nll(same, y[:10])(0.3), rel=1e-14)


@pytest.mark.parametrize("t_true", [0.4, 1.5, 6.0])
def test_softmax_subsample_bracket_fit_equals_the_exact_minimiser(t_true):
    z, y = softmax_sample(t_true, n=SUBSAMPLE_MIN, n_classes=6, seed=5)
    scaler = TemperatureScaler(mode="softmax").fit(z, y)
    exact = exact_temperature(softmax_nll(z, y))
    assert scaler.temperature_ == pytest.approx(exact, rel=1e-6)
    assert scaler.temperature_ == pytest.approx(t_true, rel=0.02)


def test_softmax_bracket_that_misses_is_searched_again(monkeypatch):
    z, y = softmax_sample(1.7, n=SUBSAMPLE_MIN, n_classes=4, seed=6)
    full = TemperatureScaler(mode="softmax").fit(z, y)
    # a first bracket far shorter than the Newton step: the root lies beyond its edge
    monkeypatch.setattr(temperature, "_NEWTON_MARGIN", 1e-4)
    again = TemperatureScaler(mode="softmax").fit(z, y)
    exact = exact_temperature(softmax_nll(z, y))
    assert again.temperature_ == pytest.approx(exact, rel=1e-6)
    assert full.temperature_ == pytest.approx(exact, rel=1e-6)
    assert again.n_evaluations_ > full.n_evaluations_
