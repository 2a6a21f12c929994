"""Shipped weights load on the CPU in eval mode and detect objects in a fixed test scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detectors import build_detector
from detectors.infer import detect
from detectors.registry import MAX_WEIGHTS_BYTES, sensor_names, weights_path
from detectors.sim import SPLITS, make_frame

# Loose lower bounds on the recall of ground truth within 40 m by a detection of the same
# class within 2 m scoring >= 0.2, over fixed test scenes (not exact numbers).
MIN_RECALL = {"lidar": 0.4, "radar1": 0.05, "radar5": 0.1, "camera": 0.15}
SCENES = list(SPLITS["test"])[:3]


def _recall(sensor: str) -> float:
    model = build_detector(sensor)
    hits, total = 0, 0
    for seed in SCENES:
        frame = make_frame(seed, sensor)
        points = torch.from_numpy(np.array(frame.sensor_frame.points, dtype=np.float32))
        (det,) = list(detect(model, [points], max_detections=model.config.n_queries))
        keep = det.scores >= 0.2
        boxes, labels = det.boxes[keep].numpy(), det.labels[keep].numpy()
        gt = np.asarray(frame.scene.boxes)
        near = np.hypot(gt[:, 0], gt[:, 1]) < 40.0
        for box, label in zip(gt[near], np.asarray(frame.scene.labels)[near], strict=True):
            same = labels == label
            total += 1
            if same.any() and np.hypot(*(boxes[same, :2] - box[:2]).T).min() < 2.0:
                hits += 1
    return hits / max(total, 1)


@pytest.mark.parametrize("sensor", sensor_names())
def test_shipped_weights_load_and_detect(sensor: str) -> None:
    path = weights_path(sensor)
    if not path.exists():
        pytest.skip(f"no shipped weights for {sensor} yet ({path}); "
                    f"train them with `detcal train --sensor {sensor}`")
    assert path.stat().st_size <= MAX_WEIGHTS_BYTES
    torch.set_num_threads(1)
    model = build_detector(sensor)
    assert not model.training
    assert all(p.device.type == "cpu" for p in model.parameters())
    assert _recall(sensor) >= MIN_RECALL[sensor]


def test_unknown_sensor_and_missing_weights_fail_clearly(tmp_path) -> None:
    with pytest.raises(ValueError, match="name must be one of"):
        build_detector("sonar")
    with pytest.raises(FileNotFoundError, match="detcal train --sensor lidar"):
        build_detector("lidar", weights=tmp_path / "nope.pt")
