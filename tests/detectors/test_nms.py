"""Class-wise circle NMS (detectors.nms) and the "topk_nms" decoding built on it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detectors.infer import postprocess
from detectors.nms import NMS_RADIUS_SQ, circle_nms, class_radii_sq

CLASSES = ("car", "pedestrian")


def test_a_close_detection_of_the_same_class_is_dropped_another_class_is_not() -> None:
    centres = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [3.0, 0.0], [0.3, 0.0]])
    labels = torch.tensor([0, 0, 1, 0, 1])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.95])
    keep = circle_nms(centres, labels, scores, class_radii_sq(CLASSES))
    # car radius 2 m: the car at 1 m goes, the car at 3 m stays; pedestrian radius 0.42 m:
    # the pedestrians 0.7 m apart both stay, and a car never suppresses a pedestrian.
    assert keep.tolist() == [4, 0, 2, 3]


def test_suppression_is_greedy_a_dropped_detection_suppresses_nothing() -> None:
    centres = torch.tensor([[0.0, 0.0], [1.5, 0.0], [3.0, 0.0]])
    keep = circle_nms(centres, torch.zeros(3, dtype=torch.long), torch.tensor([0.9, 0.8, 0.7]),
                      class_radii_sq(CLASSES))
    assert keep.tolist() == [0, 2]   # 1 falls to 0; 2 is 3 m from 0 and 1 is gone


def test_kept_detections_of_a_class_are_farther_apart_than_its_radius() -> None:
    rng = np.random.default_rng(0)
    centres = torch.from_numpy(rng.uniform(-10, 10, (300, 2))).float()
    labels = torch.from_numpy(rng.integers(0, 2, 300))
    scores = torch.from_numpy(rng.random(300)).float()
    radii = class_radii_sq(CLASSES)
    keep = circle_nms(centres, labels, scores, radii)
    assert torch.all(scores[keep][:-1] >= scores[keep][1:])
    for c in (0, 1):
        own = centres[keep][labels[keep] == c]
        d2 = torch.cdist(own, own).square() + torch.eye(len(own)) * 1e9
        assert float(d2.min()) >= float(radii[c])
    # every dropped detection has a kept one of its class, scored higher, within its radius
    dropped = sorted(set(range(300)) - set(keep.tolist()))
    for i in dropped:
        same = keep[(labels[keep] == labels[i]) & (scores[keep] >= scores[i])]
        assert float((centres[same] - centres[i]).square().sum(1).min()) < float(
            radii[labels[i]])


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="centres"):
        circle_nms(torch.zeros(3, 3), torch.zeros(3, dtype=torch.long), torch.zeros(3),
                   class_radii_sq(CLASSES))
    with pytest.raises(ValueError, match="forklift"):
        class_radii_sq(("car", "forklift"))
    assert set(NMS_RADIUS_SQ) >= {"car", "truck", "bus", "trailer", "construction_vehicle",
                                  "pedestrian", "motorcycle", "bicycle", "traffic_cone",
                                  "barrier"}


def test_topk_nms_drops_a_duplicate_query_but_keeps_the_look_alike_class() -> None:
    # queries 0 and 1 sit 0.5 m apart; query 0's second class (pedestrian) stays
    p = torch.tensor([[0.9, 0.5], [0.8, 0.01], [0.01, 0.7]])
    boxes = torch.zeros(3, 9)
    boxes[:, 0] = torch.tensor([0.0, 0.5, 20.0])
    out = {"pred_logits": torch.logit(p)[None, None].expand(2, 1, 3, 2),
           "pred_boxes": boxes[None, None].expand(2, 1, 3, 9),
           "attention": torch.full((2, 1, 3, 4), 0.25)}
    (plain,) = postprocess(out, max_detections=4, decode="topk")
    (nms,) = postprocess(out, max_detections=4, decode="topk_nms", classes=CLASSES)
    assert plain.query_index.tolist() == [0, 1, 2, 0]
    assert nms.query_index.tolist() == [0, 2, 0] and nms.labels.tolist() == [0, 1, 1]
    with pytest.raises(ValueError, match="classes"):
        postprocess(out, decode="topk_nms")
