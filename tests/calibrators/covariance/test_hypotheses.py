"""The `hypotheses` covariance source: group-score-weighted covariance of H box centres."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibrators.covariance import hypotheses_covariance


def _boxes(centres: list[list[float]]) -> np.ndarray:
    """`[1, H, 9]` boxes at the given (x, y) centres."""
    out = np.tile(np.array([0, 0, 0.5, 2, 4, 1.5, 0.3, 0, 0], dtype=float), (1, len(centres), 1))
    out[0, :, 0:2] = centres
    return out


def test_two_hypotheses_give_the_weighted_bernoulli_covariance() -> None:
    boxes = _boxes([[0.0, 0.0], [4.0, 0.0], [10.0, 10.0]])
    scores = np.array([[0.3, 0.1, 0.0]])  # the third group has no score: no weight
    cov = hypotheses_covariance(boxes, scores)
    # weights 0.75 / 0.25 on x = 0 and 4: variance p (1 - p) d^2 = 0.1875 * 16 = 3
    np.testing.assert_allclose(cov[0], [[3.0, 0.0], [0.0, 0.0]], atol=1e-12)


def test_matches_a_weighted_sample_covariance_and_is_psd() -> None:
    rng = np.random.default_rng(0)
    boxes = rng.normal(size=(50, 6, 9)) * 3
    scores = rng.uniform(0, 1, size=(50, 6))
    cov = hypotheses_covariance(boxes, scores, dims=("x", "y", "z"))
    assert cov.shape == (50, 3, 3)
    for i in (0, 17, 49):
        want = np.cov(boxes[i, :, 0:3].T, aweights=scores[i], ddof=0)
        np.testing.assert_allclose(cov[i], want, atol=1e-10)
    assert np.linalg.eigvalsh(cov).min() > -1e-10


def test_agreeing_hypotheses_or_one_dominant_group_give_no_spread() -> None:
    same = _boxes([[5.0, -2.0]] * 6)
    assert np.abs(hypotheses_covariance(same, np.ones((1, 6)))).max() < 1e-12
    apart = _boxes([[0.0, 0.0], [30.0, 0.0]])
    assert np.abs(hypotheses_covariance(apart, np.array([[0.9, 0.0]]))).max() < 1e-12


def test_zero_scores_weigh_equally_and_yaw_wraps() -> None:
    boxes = _boxes([[0.0, 0.0], [2.0, 0.0]])
    np.testing.assert_allclose(hypotheses_covariance(boxes, np.zeros((1, 2)))[0, 0, 0], 1.0)
    boxes[0, :, 6] = [math.pi - 0.1, -math.pi + 0.1]  # 0.2 rad apart across the seam
    cov = hypotheses_covariance(boxes, np.array([[0.5, 0.5]]), dims=("yaw",))
    np.testing.assert_allclose(cov[0, 0, 0], 0.01, atol=1e-12)


@pytest.mark.parametrize(
    ("boxes", "scores", "message"),
    [
        (np.zeros((2, 3, 7)), np.zeros((2, 3)), "hyp_boxes must have shape"),
        (np.zeros((2, 3, 9)), np.zeros((2, 2)), "hyp_scores must have shape"),
        (np.zeros((2, 3, 9)), -np.ones((2, 3)), "negative score at row 0"),
        (np.full((2, 3, 9), np.nan), np.zeros((2, 3)), "hyp_boxes has NaN"),
    ],
)
def test_bad_input_names_the_argument(boxes, scores, message) -> None:
    with pytest.raises(ValueError, match=message):
        hypotheses_covariance(boxes, scores)
