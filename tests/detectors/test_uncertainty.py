"""Covariance sources on hand-made inputs: layer spread and attention spread (seed 000)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detectors.model.bev import BEVGrid
from detectors.uncertainty import attention_spread, layer_covariance


def _layer_boxes(xy_per_layer: list[list[tuple[float, float]]]) -> torch.Tensor:
    """`[N, L, 9]` boxes whose only varying fields are x, y."""
    xy = torch.tensor(xy_per_layer, dtype=torch.float64)  # [N, L, 2]
    boxes = torch.zeros(*xy.shape[:2], 9, dtype=torch.float64)
    boxes[..., :2] = xy
    boxes[..., 3:6] = torch.tensor([1.9, 4.6, 1.7], dtype=torch.float64)
    return boxes


def test_layer_covariance_of_a_known_walk() -> None:
    # x moves 0 -> 1 -> 2 while y stays: var_x = 1 (ddof=1), no y spread, no correlation.
    # second query: x, y move together by 0, 2, 4: var 4 each, covariance 4.
    boxes = _layer_boxes([[(0, 5), (1, 5), (2, 5)], [(0, 0), (2, 2), (4, 4)]])
    cov = layer_covariance(boxes)
    assert torch.allclose(cov[0], torch.tensor([[1.0, 0.0], [0.0, 0.0]], dtype=torch.float64))
    assert torch.allclose(cov[1], torch.full((2, 2), 4.0, dtype=torch.float64))


def test_layer_covariance_matches_numpy_on_random_boxes() -> None:
    rng = np.random.default_rng(0)
    boxes = torch.from_numpy(rng.normal(size=(7, 4, 9)))
    cov = layer_covariance(boxes, dims=("x", "y", "yaw"))
    for i in range(7):
        want = np.cov(boxes[i][:, [0, 1, 6]].numpy().T, ddof=1)
        np.testing.assert_allclose(cov[i].numpy(), want, atol=1e-12)


def test_layer_covariance_rejects_a_single_layer_and_unknown_dims() -> None:
    with pytest.raises(ValueError, match="at least 2 decoder layers"):
        layer_covariance(torch.zeros(3, 1, 9))
    with pytest.raises(ValueError, match="dims"):
        layer_covariance(torch.zeros(3, 2, 9), dims=("x", "q"))


def test_attention_on_four_corners_has_unit_covariance() -> None:
    # Cells at (+-1, +-1) with equal weight: mean 0, C_K = I, AS = det(I) = 1.
    centres = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [9.0, 9.0]],
                           dtype=torch.float64)
    attention = torch.tensor([[0.2, 0.2, 0.2, 0.2, 0.01]], dtype=torch.float64)
    spread = attention_spread(attention, centres, top_k=4)
    assert torch.allclose(spread.mean, torch.zeros(1, 2, dtype=torch.float64))
    assert torch.allclose(spread.covariance[0], torch.eye(2, dtype=torch.float64))
    assert spread.spread[0].item() == pytest.approx(1.0)


def test_attention_weights_are_renormalised_over_the_top_k_only() -> None:
    # Top-2 weights 0.3 at x=0 and 0.1 at x=4 (renormalised 0.75 / 0.25); the rest ignored.
    # mean x = 1, var x = 0.75 * 1 + 0.25 * 9 = 3, y constant -> AS = 0.
    centres = torch.tensor([[0.0, 2.0], [4.0, 2.0], [-50.0, 2.0], [50.0, 2.0]])
    attention = torch.tensor([[0.3, 0.1, 0.05, 0.05]])
    spread = attention_spread(attention, centres, top_k=2)
    assert spread.mean[0].tolist() == pytest.approx([1.0, 2.0])
    assert torch.allclose(spread.covariance[0], torch.tensor([[3.0, 0.0], [0.0, 0.0]]))
    assert spread.spread[0].item() == pytest.approx(0.0)


def test_attention_spread_on_the_bev_grid_in_metres() -> None:
    # A 3x3 block of equal weights on a 0.8 m grid: per-axis variance 2/3 * 0.8^2, no
    # correlation; the mean is the block's centre cell.
    grid = BEVGrid(size=16, cell=0.8)
    centres = grid.centres().double()
    attention = torch.zeros(1, 16 * 16, dtype=torch.float64)
    rows, cols = np.meshgrid([4, 5, 6], [9, 10, 11], indexing="ij")
    attention[0, torch.from_numpy((rows * 16 + cols).ravel())] = 1.0 / 9
    spread = attention_spread(attention, centres, top_k=9)
    var = 2.0 / 3.0 * 0.8 ** 2
    assert torch.allclose(spread.covariance[0], torch.eye(2, dtype=torch.float64) * var)
    assert spread.mean[0].tolist() == pytest.approx(centres[5 * 16 + 10].tolist())
    assert spread.spread[0].item() == pytest.approx(var ** 2)


def test_attention_spread_validates_its_input() -> None:
    centres = torch.zeros(4, 2)
    with pytest.raises(ValueError, match="top_k"):
        attention_spread(torch.ones(1, 4), centres, top_k=5)
    with pytest.raises(ValueError, match="centres"):
        attention_spread(torch.ones(1, 4), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="negative"):
        attention_spread(torch.tensor([[1.0, -1.0, 0.0, 0.0]]), centres, top_k=2)
