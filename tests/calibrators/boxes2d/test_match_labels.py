"""match_labels: each detection's COCO match at one IoU threshold, against pycocotools'
`evalImgs` (`dtMatches`, `dtIgnore`) on random COCO-format data, and on hand-made cases."""

from __future__ import annotations

import contextlib
import copy
import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from calibrators.boxes2d import (
    IOU_THRESHOLDS,
    Detections2D,
    GroundTruth2D,
    MatchLabels,
    evaluate_coco,
    match_labels,
)
from calibrators.core.errors import FieldError
from tests.calibrators.boxes2d.test_coco_properties import coco_data

THRESHOLDS = st.sampled_from([0.0, 0.1, 0.3, 0.5, 0.55, 0.75, 0.9, 1.0])


def pycocotools_matches(dataset, results, threshold, max_dets):
    """{detection id: (gt id or 0, dtIgnore)} of `COCOeval.evaluate` at one threshold, area
    "all", `maxDets = [max_dets]` (detections past the cap are absent)."""
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = copy.deepcopy(dataset)
        gt.createIndex()
        dt = gt.loadRes(copy.deepcopy(list(results)))
        evaluator = COCOeval(gt, dt, "bbox")
        evaluator.params.iouThrs = np.array([threshold])
        evaluator.params.areaRng = [[0.0, 1e5 ** 2]]
        evaluator.params.areaRngLbl = ["all"]
        evaluator.params.maxDets = [max_dets]
        evaluator.evaluate()
    out = {}
    for e in evaluator.evalImgs:
        if e is None:
            continue
        for k, det_id in enumerate(e["dtIds"]):
            out[det_id] = (int(e["dtMatches"][0, k]), bool(e["dtIgnore"][0, k]))
    return out


def assert_matches_pycocotools(dataset, results, threshold, max_dets=None):
    truth = GroundTruth2D.from_coco(dataset["annotations"])
    found = Detections2D.from_coco(results)
    labels = match_labels(found, truth, threshold, max_dets)
    expected = pycocotools_matches(dataset, results, threshold,
                                   len(results) if max_dets is None else max_dets)
    for i in range(len(results)):
        gt_id, ignored = expected.get(i + 1, (0, True))   # loadRes numbers results 1, 2, ...
        assert labels.gt_row[i] + 1 == gt_id, (i, labels.gt_row[i], gt_id)
        assert labels.ignored[i] == ignored, i
        assert labels.true_positive[i] == (gt_id != 0 and not ignored), i
        if gt_id:
            ann = dataset["annotations"][gt_id - 1]     # coco_dataset numbers them 1, 2, ...
            iou = mask_utils.iou([results[i]["bbox"]], [ann["bbox"]], [ann["iscrowd"]])
            assert labels.iou[i] == float(np.asarray(iou).reshape(-1)[0])
        else:
            assert labels.iou[i] == 0.0


@settings(max_examples=150, deadline=None)
@given(coco_data(), THRESHOLDS)
def test_equals_pycocotools_dt_matches(data, threshold):
    dataset, results = data
    assert_matches_pycocotools(dataset, results, threshold)


@settings(max_examples=60, deadline=None)
@given(coco_data(), THRESHOLDS, st.integers(1, 4))
def test_equals_pycocotools_with_a_per_image_cap(data, threshold, max_dets):
    dataset, results = data
    assert_matches_pycocotools(dataset, results, threshold, max_dets)


def test_equals_pycocotools_on_larger_random_data():
    rng = np.random.default_rng(11)
    for _ in range(5):
        annotations, results = [], []
        for image in range(1, 21):
            for _ in range(int(rng.integers(0, 8))):
                box = [float(v) for v in np.r_[rng.uniform(0, 200, 2), rng.uniform(4, 80, 2)]]
                annotations.append({"image_id": image, "category_id": int(rng.integers(1, 4)),
                                    "bbox": box, "area": box[2] * box[3],
                                    "iscrowd": int(rng.random() < 0.1)})
            for _ in range(int(rng.integers(1, 15))):
                box = np.r_[rng.uniform(0, 200, 2), rng.uniform(4, 80, 2)]
                if annotations and rng.random() < 0.6:
                    near = annotations[int(rng.integers(len(annotations)))]["bbox"]
                    box = np.asarray(near) + rng.normal(0, 4, 4)
                    box[2:] = np.abs(box[2:])
                results.append({"image_id": image, "category_id": int(rng.integers(1, 4)),
                                "bbox": [float(v) for v in box],
                                "score": float(np.round(rng.random(), 2))})
        dataset = {"images": [{"id": i} for i in range(1, 21)],
                   "annotations": [{**a, "id": k + 1} for k, a in enumerate(annotations)],
                   "categories": [{"id": c} for c in (1, 2, 3)]}
        for threshold in (0.0, 0.5, 0.7):
            assert_matches_pycocotools(dataset, results, threshold)


def test_agrees_with_evaluate_coco_at_its_thresholds():
    """At t = 0.5 the true positives are those AP50 counts: a perfect detector's AP50 is 1."""
    truth = GroundTruth2D([1, 1, 2], [1, 2, 1], [[0, 0, 10, 10], [20, 20, 10, 10],
                                                 [5, 5, 30, 30]])
    found = Detections2D([1, 1, 2, 2], [1, 2, 1, 1], [[1, 0, 10, 10], [20, 21, 10, 10],
                                                      [5, 5, 30, 30], [60, 60, 5, 5]],
                         [0.9, 0.8, 0.7, 0.6])
    labels = match_labels(found, truth, IOU_THRESHOLDS[0])
    assert labels.true_positive.tolist() == [True, True, True, False]
    assert labels.gt_row.tolist() == [0, 1, 2, -1]
    assert labels.false_positive.tolist() == [False, False, False, True]
    assert evaluate_coco(found, truth).ap50 == pytest.approx([1.0, 1.0])


def test_hand_case_crowd_ignore_and_greedy_order():
    # image 1, one category: g0 plain, g1 crowd over the right half
    truth = GroundTruth2D([1, 1], [7, 7], [[0, 0, 10, 10], [100, 0, 100, 100]],
                          iscrowd=[0, 1])
    found = Detections2D(
        [1, 1, 1, 1], [7, 7, 7, 7],
        [[0, 0, 10, 5],      # IoU 0.5 with g0, second by score: g0 is taken -> FP
         [0, 0, 10, 8],      # IoU 0.8 with g0, first: TP
         [120, 10, 10, 10],  # inside the crowd: matched to it, ignored
         [300, 300, 5, 5]],  # nothing: FP
        [0.5, 0.9, 0.7, 0.1])
    labels = match_labels(found, truth, 0.5)
    assert isinstance(labels, MatchLabels) and len(labels) == 4
    assert labels.true_positive.tolist() == [False, True, False, False]
    assert labels.gt_row.tolist() == [-1, 0, 1, -1]
    assert labels.ignored.tolist() == [False, False, True, False]
    assert labels.iou.tolist() == [0.0, 0.8, 1.0, 0.0]
    # at t = 0 a detection takes any free ground truth of its image and class, even at IoU 0
    assert match_labels(found, truth, 0.0).gt_row.tolist() == [1, 0, 1, 1]
    # past a cap of 2 per image x category (the 0.9 and 0.7 ones stay): left out
    capped = match_labels(found, truth, 0.5, max_dets=2)
    assert capped.ignored.tolist() == [True, False, True, True]
    assert capped.true_positive.tolist() == [False, True, False, False]
    assert capped.to_dict()["gt_row"] == [-1, 0, 1, -1]


def test_empty_inputs_and_bad_arguments():
    none = Detections2D([], [], np.zeros((0, 4)), [])
    truth = GroundTruth2D([1], [1], [[0, 0, 1, 1]])
    assert len(match_labels(none, truth)) == 0
    empty_truth = GroundTruth2D([], [], np.zeros((0, 4)))
    one = Detections2D([1], [1], [[0, 0, 1, 1]], [0.5])
    labels = match_labels(one, empty_truth)
    assert labels.false_positive.tolist() == [True] and labels.gt_row.tolist() == [-1]
    for bad in (-0.1, 1.5, float("nan"), "x", True):
        with pytest.raises(FieldError, match="iou_threshold") as info:
            match_labels(one, truth, bad)
        assert info.value.field == "iou_threshold"
    with pytest.raises(FieldError, match="max_dets"):
        match_labels(one, truth, 0.5, 0)
    with pytest.raises(FieldError, match="ground_truth"):
        match_labels(one, one)


@settings(max_examples=60, deadline=None)
@given(coco_data(distinct_scores=True), THRESHOLDS, st.randoms(use_true_random=False))
def test_permuting_detections_permutes_their_labels(data, threshold, random):
    """Identity is kept: without score ties, row i's labels follow row i wherever it goes."""
    dataset, results = data
    truth = GroundTruth2D.from_coco(dataset["annotations"])
    order = list(range(len(results)))
    random.shuffle(order)
    before = match_labels(Detections2D.from_coco(results), truth, threshold)
    after = match_labels(Detections2D.from_coco([results[k] for k in order]), truth, threshold)
    for name in ("true_positive", "gt_row", "iou", "ignored"):
        np.testing.assert_array_equal(getattr(after, name), getattr(before, name)[order])
