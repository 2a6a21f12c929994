"""Unified-vs-group analyses (detectors.report.groups): class switches, inter-group spread,
per-layer quartiles, Spearman trends of the attention spread."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from calibrators import Dump
from detectors.model import Detector
from detectors.report.attention import binned
from detectors.report.groups import (
    attention_trends,
    class_switches,
    collect_outputs,
    inter_group_std,
    per_layer,
    sample_rho,
    trend,
)


def test_class_switches_count_no_object_as_a_class() -> None:
    logits = np.full((3, 3, 2), -5.0)
    logits[0, :, 0] = 3.0                      # car at every layer: no switch
    logits[1, 0, 0], logits[1, 1:, 1] = 3.0, 3.0  # car -> pedestrian after layer 1
    logits[2, 1, 1] = 3.0                      # no object -> pedestrian -> no object
    out = class_switches(logits, np.array([0, 1, 1]), n_frames=3)
    assert out.tolist() == [[0, 0], [2, 1], [0, 0]]
    with pytest.raises(ValueError, match="det_frame"):
        class_switches(logits, np.array([0, 1]), n_frames=3)


def test_inter_group_std_of_the_centres() -> None:
    boxes = np.zeros((1, 2, 6, 9))
    boxes[0, 1, :, 0] = np.arange(6.0)         # layer 2: x spread over 0..5
    std = inter_group_std(boxes)
    assert std.shape == (1, 2, 3)
    np.testing.assert_allclose(std[0, 1], [np.std(np.arange(6.0), ddof=1), 0, 0])
    assert std[0, 0].max() == 0
    stat = per_layer(std[..., 0])
    assert stat.labels == ("layer 1", "layer 2") and stat.median[1] > 0


def test_trend_is_spearmans_rho_of_the_bin_medians() -> None:
    values = np.repeat(np.arange(5.0), 10)
    groups = np.repeat(np.arange(5), 10)
    up = binned(values, groups, 5, tuple("abcde"))
    down = binned(-values, groups, 5, tuple("abcde"))
    assert trend(up) == pytest.approx(1.0) and trend(down) == pytest.approx(-1.0)
    assert np.isnan(trend(binned(values[:20], groups[:20], 5, tuple("abcde"))))
    flat = binned(26.3 + 1e-12 * values, groups, 5, tuple("abcde"))  # float noise only
    assert np.isnan(trend(flat))


def test_attention_trends_reads_distance_and_iou_per_layer() -> None:
    rng = np.random.default_rng(0)
    n = 400
    dist = rng.uniform(2, 75, size=n)
    final = np.zeros((n, 9))
    final[:, 0], final[:, 3:6] = dist, [2.0, 4.5, 1.6]
    gt = final.copy()
    shift = rng.uniform(0.0, 3.0, size=n)      # IoU falls as the box moves off its truth
    final[:, 1] = shift
    boxes = np.repeat(final[:, None], 2, axis=1)
    logits = np.full((n, 2, 2), -6.0)
    logits[:, :, 0] = 4.0                      # all confident cars
    dump = Dump(classes=("car", "pedestrian"), score_mode="sigmoid",
                frame_ids=np.array([f"f{i}" for i in range(n)]), det_frame=np.arange(n),
                det_logits=logits, det_boxes=boxes, gt_frame=np.arange(n),
                gt_labels=np.zeros(n, dtype=np.int64), gt_boxes=gt)
    var = (dist / 10 * (1 + shift))[:, None, None] * np.eye(2)   # grows with both
    cov = np.stack([var, var], axis=1)                      # [N, 2 layers, 2, 2]
    trends = attention_trends(dump, cov, cell=1.6)
    assert [t.layer for t in trends] == [1, 2]
    assert trends[-1].rho_distance >= 0.6 and trends[-1].rho_iou <= -0.6
    assert trends[-1].rank_deficient == 0.0
    assert trends[-1].stats.n_detections == n
    # per detection: AS grows with distance and falls with IoU
    assert trends[-1].sample_rho_distance > 0.5 and trends[-1].sample_rho_iou < -0.3
    # an AS that ignores both gives per-detection rhos near 0
    noise = rng.lognormal(size=n)[:, None, None, None] * np.eye(2)
    flat = attention_trends(dump, np.concatenate([noise, noise], axis=1), cell=1.6)[-1]
    assert abs(flat.sample_rho_distance) < 0.15 and abs(flat.sample_rho_iou) < 0.15


def test_sample_rho_is_spearmans_rho_over_the_rows() -> None:
    x = np.arange(10.0)
    assert sample_rho(x, x ** 3) == pytest.approx(1.0)
    assert sample_rho(x, -np.exp(x)) == pytest.approx(-1.0)
    assert np.isnan(sample_rho(x[:2], x[:2])) and np.isnan(sample_rho(x, np.ones(10)))
    with pytest.raises(ValueError, match="one shape"):
        sample_rho(x, x[:5])


def test_collect_outputs_of_a_group_model(tiny_config) -> None:
    torch.manual_seed(0)
    model = Detector(tiny_config(head="group", n_queries=10)).eval()
    out = collect_outputs(model, [3, 4], max_detections=5)
    assert out.layer_logits.shape == (10, 2, 10) and out.group_boxes.shape == (10, 2, 6, 9)
    assert out.det_frame.tolist() == [0] * 5 + [1] * 5
    assert class_switches(out.layer_logits, out.det_frame, out.n_frames).shape == (2, 1)
    unified = collect_outputs(Detector(tiny_config(n_queries=10)).eval(), [3])
    assert unified.group_boxes is None and unified.layer_logits.shape == (10, 2, 10)
