"""LaECE and D-ECE of 2-D detections on hand-computed cases, and the layer-spread covariance
of box edges."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.boxes2d import (
    EDGE_NAMES,
    Detections2D,
    GroundTruth2D,
    box_edges,
    detection_ece_2d,
    edge_covariance,
    edge_sigma,
    edges_box,
    localisation_ece_2d,
    match_labels,
)
from calibrators.core.errors import FieldError
from calibrators.metrics import localisation_ece

# image 1: category 1 has one box A, category 2 one box B; image 2: a category-1 crowd.
TRUTH = GroundTruth2D([1, 1, 2], [1, 2, 1],
                      [[0, 0, 10, 10], [0, 0, 20, 20], [0, 0, 100, 100]], iscrowd=[0, 0, 1])
FOUND = Detections2D(
    [1, 1, 1, 2, 1],
    [1, 1, 2, 1, 3],
    [[0, 0, 10, 5],        # d0 on A: IoU 0.5, TP
     [50, 50, 10, 10],     # d1: A is taken, FP (IoU 0)
     [0, 0, 20, 20],       # d2 on B: IoU 1, TP
     [10, 10, 10, 10],     # d3 inside the crowd: ignored
     [0, 0, 5, 5]],        # d4: category 3 has no ground truth: left out
    [0.9, 0.6, 0.3, 0.8, 0.7])


def test_laece_by_hand():
    # category 1: bins of 0.9 and 0.6 -> (|0.5 - 0.9| + |0 - 0.6|) / 2 = 0.5
    # category 2: |1.0 - 0.3| = 0.7;  LaECE = (0.5 + 0.7) / 2 = 0.6
    for threshold in (0.0, 0.5):
        result = localisation_ece_2d(FOUND, TRUTH, iou_threshold=threshold)
        assert result.classes.tolist() == [1, 2]
        assert result.per_class == pytest.approx([0.5, 0.7])
        assert result.count.tolist() == [2, 1]
        assert result.value == pytest.approx(0.6)
    # at 0.6, d0 no longer matches: category 1 is all false positives, (0.9 + 0.6) / 2
    assert localisation_ece_2d(FOUND, TRUTH, iou_threshold=0.6).per_class[0] == \
        pytest.approx(0.75)
    # calibrated scores replace the detector's: a perfect category 1 (0.5 and 0)
    perfect = localisation_ece_2d(FOUND, TRUTH, scores=[0.5, 0.0, 1.0, 0.8, 0.7])
    assert perfect.per_class == pytest.approx([0.0, 0.0]) and perfect.value == 0.0


def test_laece_bins_are_closed_on_the_right():
    # 0.04 shares the first bin [0, 0.04] with 0.02; 0.05 is in (0.04, 0.08]
    same = localisation_ece([0.02, 0.04], [0.04, 0.02], [0, 0])
    apart = localisation_ece([0.02, 0.05], [0.05, 0.02], [0, 0])
    assert same.value == pytest.approx(0.0)
    assert apart.value == pytest.approx((0.03 + 0.03) / 2)
    with pytest.raises(FieldError, match="iou"):
        localisation_ece([0.5], [1.5], [0])


def test_dece_by_hand():
    found = Detections2D([1] * 4, [1] * 4,
                         [[0, 0, 10, 10], [60, 0, 10, 10], [80, 0, 10, 10], [10, 0, 10, 10]],
                         [0.9, 0.8, 0.2, 0.3])
    truth = GroundTruth2D([1, 1], [1, 1], [[0, 0, 10, 10], [60, 0, 10, 10]])
    labels = match_labels(found, truth, 0.5)
    assert labels.true_positive.tolist() == [True, True, False, False]
    size = np.tile([[100.0, 100.0]], (4, 1))
    # cx = 0.05, 0.65, 0.85, 0.15; 2 confidence bins x 2 cx bins:
    #   [hi, left] {0.9 TP} -> 0.1; [hi, right] {0.8 TP} -> 0.2;
    #   [lo, right] {0.2 FP} -> 0.2; [lo, left] {0.3 FP} -> 0.3;  D-ECE = 0.8 / 4
    assert detection_ece_2d(found, labels, size, features=("cx",), n_bins=2) == \
        pytest.approx(0.2)
    # confidence only, 2 bins: |2 - 1.7| + |0 - 0.5| over 4
    assert detection_ece_2d(found, labels, size, features=(), n_bins=2) == pytest.approx(0.2)
    # ignored detections are left out; calibrated scores replace the detector's
    crowd = GroundTruth2D([1, 1, 1], [1, 1, 1],
                          [[0, 0, 10, 10], [60, 0, 10, 10], [75, 0, 25, 25]], iscrowd=[0, 0, 1])
    ignored = match_labels(found, crowd, 0.5)
    assert ignored.ignored.tolist() == [False, False, True, False]
    assert detection_ece_2d(found, ignored, size, features=(), n_bins=2,
                            scores=[1.0, 1.0, 0.5, 0.0]) == 0.0
    with pytest.raises(FieldError, match="features"):
        detection_ece_2d(found, labels, size, features=("x",))


def test_edge_covariance_is_the_layer_spread_of_the_edges():
    layers = np.array([[[10, 20, 30, 40], [12, 18, 30, 44], [11, 20, 33, 40]]], dtype=float)
    edges = box_edges(layers[0])                         # [L, 4] x1, y1, x2, y2
    assert EDGE_NAMES == ("x1", "y1", "x2", "y2")
    np.testing.assert_allclose(edges_box(edges), layers[0])
    cov = edge_covariance(layers, min_sigma=0.0)
    np.testing.assert_allclose(cov[0], np.cov(edges.T))
    floored = edge_covariance(layers, min_sigma=2.0)
    var = np.diag(np.cov(edges.T))
    np.testing.assert_allclose(np.diag(floored[0]), np.maximum(var, 4.0))
    off = ~np.eye(4, dtype=bool)
    np.testing.assert_allclose(floored[0][off], np.cov(edges.T)[off])
    assert np.linalg.eigvalsh(floored[0]).min() >= -1e-9
    np.testing.assert_allclose(edge_sigma(floored), np.sqrt(np.maximum(var, 4.0))[None])
    same = edge_covariance(np.repeat(layers[:, :1], 3, axis=1))     # layers agree exactly
    np.testing.assert_allclose(same[0], np.eye(4))
    with pytest.raises(FieldError, match="L >= 2"):
        edge_covariance(layers[:, :1])
    with pytest.raises(FieldError, match=r"layer_boxes\[0\]\[1\] has a negative width"):
        edge_covariance(np.array([[[0, 0, 1, 1], [0, 0, -1, 1]]], dtype=float))
