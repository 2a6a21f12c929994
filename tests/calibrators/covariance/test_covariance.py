"""layer_spread: sample covariance across decoder layers, yaw wrapping, validation."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.core.vocab import BOX_INDEX as DIM_INDEX
from calibrators.covariance import layer_spread


def test_dim_index_is_the_box_layout():
    assert DIM_INDEX == {"x": 0, "y": 1, "z": 2, "w": 3, "l": 4, "h": 5, "yaw": 6, "vx": 7,
                         "vy": 8}


def test_hand_case_matches_np_cov():
    boxes = np.zeros((1, 3, 9))
    boxes[0, :, 0] = [1.0, 2.0, 6.0]  # x
    boxes[0, :, 1] = [0.0, 1.0, -1.0]  # y
    cov = layer_spread(boxes)
    # by hand: mean x = 3, var x = (4 + 1 + 9) / 2 = 7; mean y = 0, var y = 1,
    # cov xy = ((-2)(0) + (-1)(1) + (3)(-1)) / 2 = -2
    np.testing.assert_allclose(cov[0], [[7.0, -2.0], [-2.0, 1.0]])
    np.testing.assert_allclose(cov[0], np.cov(boxes[0, :, :2].T, ddof=1))


def test_batch_matches_np_cov_for_any_dims():
    rng = np.random.default_rng(0)
    boxes = rng.normal(size=(20, 6, 9))
    dims = ("z", "x", "vy")
    cov = layer_spread(boxes, dims)
    assert cov.shape == (20, 3, 3)
    for i in range(20):
        np.testing.assert_allclose(cov[i], np.cov(boxes[i][:, [2, 0, 8]].T, ddof=1))


def test_yaw_is_wrapped():
    boxes = np.zeros((1, 4, 9))
    boxes[0, :, 6] = [np.pi - 0.1, -np.pi + 0.1, np.pi - 0.05, -np.pi + 0.05]
    cov = layer_spread(boxes, ("yaw",))
    expected = np.var([-0.1, 0.1, -0.05, 0.05], ddof=1)  # deviations across the ±pi seam
    np.testing.assert_allclose(cov[0, 0, 0], expected)


@pytest.mark.parametrize("boxes, dims, match", [
    (np.zeros((3, 1, 9)), ("x", "y"), "needs L >= 2"),
    (np.zeros((3, 2, 7)), ("x", "y"), r"layer_boxes must have shape \[N, L, 9\]"),
    (np.zeros((3, 9)), ("x", "y"), "layer_boxes must have 3 dimensions"),
    (np.full((3, 2, 9), np.nan), ("x", "y"), "layer_boxes has NaN"),
    (np.zeros((3, 2, 9)), ("x", "q"), "dims has unknown box field 'q'"),
    (np.zeros((3, 2, 9)), ("x", "x"), "dims has duplicate names"),
    (np.zeros((3, 2, 9)), (), "dims must name at least one"),
    (np.zeros((3, 2, 9)), "xy", "dims has unknown box field 'xy'"),
])
def test_bad_input(boxes, dims, match):
    with pytest.raises(ValueError, match=match):
        layer_spread(boxes, dims)
