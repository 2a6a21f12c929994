"""What separates the IoU bins (detectors.report.iou_bins) and the box errors behind them
(detectors.report.attention.box_errors)."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators import Dump
from detectors.report.attention import (
    AttentionStats,
    attention_stats,
    box_errors,
    closest_gt_index,
    closest_gt_iou,
)
from detectors.report.iou_bins import error_bins_table, error_rho_table, error_rhos, why_sentence

CAR = [2.0, 4.5, 1.6]   # w l h


def _dump(det: np.ndarray, gt: np.ndarray, det_frame: np.ndarray, gt_frame: np.ndarray,
          n_frames: int) -> Dump:
    boxes = det[:, None] if det.ndim == 2 else det              # [N, L, 9]
    logits = np.full((*boxes.shape[:2], 2), -6.0)
    logits[:, :, 0] = 4.0                                    # confident cars
    return Dump(classes=("car", "pedestrian"), score_mode="sigmoid",
                frame_ids=np.array([f"f{i}" for i in range(n_frames)]), det_frame=det_frame,
                det_logits=logits, det_boxes=boxes, gt_frame=gt_frame,
                gt_labels=np.zeros(len(gt), dtype=np.int64), gt_boxes=gt)


def _box(x: float, y: float, yaw: float = 0.0, w: float = 2.0, length: float = 4.5
         ) -> list[float]:
    return [x, y, 0.0, w, length, 1.6, yaw, 0.0, 0.0]


def test_box_errors_against_the_closest_ground_truth() -> None:
    gt = np.array([_box(10, 0, yaw=-3.1), _box(30, 0), _box(5, 5)])
    det = np.array([_box(10.3, 0.4, yaw=3.1, length=5.0),   # frame 0, nearest gt 0
                    _box(29.0, 0, w=2.5),                    # frame 0, nearest gt 1
                    _box(0, 0)])                             # frame 2: no ground truth
    dump = _dump(det, gt, np.array([0, 0, 2]), np.array([0, 0, 1]), n_frames=3)
    index = closest_gt_index(dump)
    assert index.tolist() == [0, 1, -1]
    e = box_errors(dump, index)
    np.testing.assert_allclose(e.centre[:2], [0.5, 1.0])
    np.testing.assert_allclose(e.yaw[:2], [2 * np.pi - 6.2, 0.0], atol=1e-12)  # wrapped
    np.testing.assert_allclose(e.length[:2], [0.5, 0.0])
    np.testing.assert_allclose(e.width[:2], [0.0, 0.5])
    assert all(np.isnan(v[2]) for v in (e.centre, e.yaw, e.length, e.width))
    iou = closest_gt_iou(dump)
    assert iou[2] == 0 and 0 < iou[1] < iou[0] < 1
    np.testing.assert_array_equal(closest_gt_iou(dump, index), iou)
    np.testing.assert_array_equal(e.layer_centre[:, -1], e.centre)
    picked = e.select(np.array([False, True, False]))
    assert picked.centre.tolist() == [1.0] and picked.width.tolist() == [0.5]
    # every layer's centre against the final box's closest ground truth
    layered = np.stack([det + np.r_[3.0, 4.0, np.zeros(7)], det], axis=1)   # layer 1: +5 m
    e2 = box_errors(_dump(layered, gt, np.array([0, 0, 2]), np.array([0, 0, 1]), 3))
    assert e2.layer_centre.shape == (3, 2)
    np.testing.assert_allclose(e2.layer_centre[:2, 1], [0.5, 1.0])
    np.testing.assert_allclose(e2.layer_centre[0, 0], np.hypot(3.3, 4.4))
    assert np.isnan(e2.layer_centre[2]).all()


def _stats(as_of_shift: bool, n: int = 400) -> AttentionStats:
    """Confident cars whose box slides off its truth by `shift`; AS grows with the shift
    or is noise."""
    rng = np.random.default_rng(0)
    shift = rng.uniform(0.0, 2.0, size=n)
    dist = rng.uniform(5.0, 45.0, size=n)
    gt = np.array([_box(d, 0.0) for d in dist])
    det = gt.copy()
    det[:, 1] = shift
    dump = _dump(det, gt, np.arange(n), np.arange(n), n_frames=n)
    spread = (1.0 + shift) if as_of_shift else rng.lognormal(size=n)
    cov = spread[:, None, None, None] * np.eye(2)              # [N, 1 layer, 2, 2]
    return attention_stats(dump, cov, cell=0.8, min_score=0.8)


def test_error_rhos_find_an_attention_that_follows_the_centre_error() -> None:
    follows = error_rhos(_stats(as_of_shift=True))
    assert follows["centre"][0] == pytest.approx(1.0)          # AS is a function of it
    assert follows["iou"][0] == pytest.approx(-1.0)            # IoU falls as it grows
    assert follows["centre"][1] == pytest.approx(-1.0)
    noise = error_rhos(_stats(as_of_shift=False))
    assert abs(noise["centre"][0]) < 0.15 and noise["centre"][1] == pytest.approx(-1.0)
    table = error_rho_table(follows)
    assert "| centre error (m) | 1 | -1 |" in table and "| IoU | -1 | - |" in table


def test_error_bins_table_holds_the_medians_of_each_iou_bin() -> None:
    stats = _stats(as_of_shift=True)
    rows = error_bins_table(stats, 0.8).splitlines()[2:]
    keep = stats.iou > 0
    bins = np.minimum((stats.iou[keep] * 10).astype(int), 9)
    populated = np.unique(bins)
    assert len(rows) == len(populated)
    for row, b in zip(rows, populated, strict=True):
        centre = np.median(stats.errors.centre[keep][bins == b])
        cells = row.split(" | ")
        assert int(cells[1]) == int(np.sum(bins == b))
        assert float(cells[2]) == pytest.approx(centre, abs=5e-4)
        assert float(cells[3]) == pytest.approx(centre / 0.8, abs=5e-3)


def test_why_sentence_states_what_the_numbers_say() -> None:
    follows = why_sentence(_stats(as_of_shift=True), 0.8)
    assert ("AS follows the IoU with per-detection ρ = -1.00 and, of the box errors, the "
            "centre error most (ρ = 1.00)") in follows
    noise = why_sentence(_stats(as_of_shift=False), 0.8)
    assert "AS carries next to nothing of the errors that set IoU" in noise
    assert "of a 0.8 m token cell" in noise
    assert "Median centre error after each decoder layer: " in noise


def test_stats_without_box_errors_are_refused() -> None:
    stats = _stats(as_of_shift=True)
    bare = AttentionStats(stats.vs_iou, stats.vs_distance, stats.per_layer,
                          stats.n_detections, stats.min_score)
    with pytest.raises(ValueError, match="box errors"):
        error_rhos(bare)
