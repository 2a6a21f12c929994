"""The dump writer's files load with calibrators.io (NPZ v1 and nuScenes JSON)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from calibrators.io import load_dump, load_nuscenes
from detectors.dumpwriter import build_dump, frame_id, visible_gt, write_dump
from detectors.model import Detector, DetectorConfig
from detectors.sim import CLASSES, FEATURES, make_frame

SEEDS = (100000, 100001)


@pytest.fixture(scope="module")
def model() -> Detector:
    torch.manual_seed(0)
    cfg = DetectorConfig(sensor="radar5", features=tuple(FEATURES["radar5"]), classes=CLASSES,
                         grid_size=64, grid_cell=1.6, pillar_channels=8, c1=16, c2=16,
                         d_model=16, n_heads=2, d_ffn=32, n_layers=3, n_queries=20,
                         dropout=0.1)
    return Detector(cfg).eval()


@pytest.mark.parametrize("cov_source", ["layers", "attention", "none"])
def test_npz_dump_round_trips(model: Detector, tmp_path: Path, cov_source: str) -> None:
    dump = build_dump(model, SEEDS, cov_source=cov_source, max_detections=15, gt_filter="none",
                      decode="topk")   # exactly 15 per frame (NMS could drop some)
    (path,) = write_dump(dump, tmp_path / "val.npz")
    loaded = load_dump(path)
    assert loaded.classes == CLASSES and loaded.score_mode == "sigmoid"
    assert loaded.frame_ids.tolist() == [frame_id(s) for s in SEEDS]
    assert loaded.det_logits.shape == (2 * 15, 3, len(CLASSES))
    assert loaded.det_boxes.shape == (2 * 15, 3, 9)
    np.testing.assert_allclose(loaded.det_boxes, dump.det_boxes)
    if cov_source == "none":
        assert loaded.det_cov is None
    else:
        assert loaded.det_cov.shape == (2 * 15, 2, 2)
        assert (np.linalg.eigvalsh(loaded.det_cov)[:, 0] >= -1e-9).all()
    # the ground truth is the scenes' ground truth, frame by frame
    for i, seed in enumerate(SEEDS):
        scene = make_frame(seed, "radar5").scene
        np.testing.assert_allclose(loaded.gt_boxes[loaded.gt_frame == i], scene.boxes,
                                   rtol=1e-6, atol=1e-6)
        assert loaded.gt_labels[loaded.gt_frame == i].tolist() == list(scene.labels)


def test_layer_covariance_in_the_dump_is_the_spread_of_its_layer_boxes(model: Detector) -> None:
    dump = build_dump(model, SEEDS[:1], cov_source="layers", max_detections=5)
    for i in range(dump.n_detections):
        want = np.cov(dump.det_boxes[i, :, :2].T, ddof=1)
        np.testing.assert_allclose(dump.det_cov[i], want, rtol=1e-5, atol=1e-8)


def test_nuscenes_dump_loads(model: Detector, tmp_path: Path) -> None:
    dump = build_dump(model, SEEDS, cov_source="layers", max_detections=10)
    results, gt = write_dump(dump, tmp_path / "results.json", fmt="nuscenes")
    assert gt.name == "results_gt.json"
    loaded = load_nuscenes(results, gt)
    assert loaded.n_detections == dump.n_detections
    assert len(loaded.gt_labels) == len(dump.gt_labels)
    np.testing.assert_allclose(np.sort(loaded.det_scores), np.sort(dump.det_scores), atol=1e-5)


def test_ground_truth_filters_follow_the_points(model: Detector) -> None:
    frame = make_frame(SEEDS[0], "radar5")
    own = np.asarray(frame.sensor_frame.gt_num_points) > 0
    lidar = np.asarray(make_frame(SEEDS[0], "lidar").sensor_frame.gt_num_points) > 0
    assert visible_gt(frame, "radar5", "sensor").tolist() == own.tolist()
    assert visible_gt(frame, "radar5", "lidar_radar").tolist() == (own | lidar).tolist()
    assert visible_gt(frame, "radar5", "none").all()
    dump = build_dump(model, SEEDS[:1], cov_source="none", gt_filter="sensor")
    np.testing.assert_allclose(dump.gt_boxes, np.asarray(frame.scene.boxes)[own], atol=1e-6)


def test_bad_cov_source_is_refused(model: Detector) -> None:
    with pytest.raises(ValueError, match="cov_source"):
        build_dump(model, SEEDS[:1], cov_source="dropout")


def test_shipped_bootstrap_dump_is_a_valid_lidar_dump():
    """`make run` fits its default profile from this file (app/fitting/bootstrap.py)."""
    from pathlib import Path

    import detectors
    from calibrators.io import load_dump
    from detectors.sim import CLASSES

    path = Path(detectors.__file__).parent / "data" / "lidar_val.npz"
    dump = load_dump(path)
    assert dump.classes == tuple(CLASSES) and dump.score_mode == "sigmoid"
    assert dump.n_frames == 60 and dump.n_layers >= 2 and len(dump.gt_labels) > 0
