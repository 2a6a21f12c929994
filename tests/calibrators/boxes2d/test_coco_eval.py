"""evaluate_coco on hand-made cases: each number worked out by hand and checked against
pycocotools' COCOeval on the same dicts."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

# `PAIR_CHUNK`, patched below, is a global of this private module read at call time: the
# module is imported for that alone (allowed in tests/test_imports.py).
import calibrators.boxes2d._match as matching
from calibrators.boxes2d import (
    STAT_NAMES,
    CocoEvaluation,
    Detections2D,
    GroundTruth2D,
    evaluate_coco,
)
from calibrators.core.errors import FieldError
from tests.calibrators.boxes2d.reference import (
    assert_same,
    coco_dataset,
    run_ours,
    run_pycocotools,
)

#: A perfect AP: pycocotools' precision `tp / (fp + tp + np.spacing(1))` is one ulp below 1
#: after a single true positive (1 / (1 + 2⁻⁵²)) and means round, so "1" is 1 to 1e-15.
ONE = pytest.approx(1.0, abs=1e-15)


def coco(gts, dets, images=None, categories=None, **flags):
    """gts: (image, category, x, y, w, h[, area]); dets: (image, category, x, y, w, h, score);
    `iscrowd` / `keep_ignore`: a set of gt positions with that flag."""
    annotations = []
    for i, (image, cat, *box) in enumerate(gts):
        area = box[4] if len(box) > 4 else box[2] * box[3]
        ann = {"image_id": image, "category_id": cat, "bbox": [float(v) for v in box[:4]],
               "area": float(area), "iscrowd": int(i in flags.get("iscrowd", ()))}
        if "keep_ignore" in flags:
            ann["keep_ignore"] = int(i in flags["keep_ignore"])
        annotations.append(ann)
    results = [{"image_id": image, "category_id": cat, "bbox": [float(v) for v in box],
                "score": score} for image, cat, *box, score in dets]
    images = images or sorted({a["image_id"] for a in annotations} | {r["image_id"]
                                                                       for r in results})
    categories = categories or sorted({a["category_id"] for a in annotations}
                                      | {r["category_id"] for r in results})
    return coco_dataset(annotations, images, categories), results


def both(dataset, results, keep_ignore=False):
    """Ours, after checking it equals pycocotools."""
    ours = run_ours(dataset, results)
    assert_same(ours, run_pycocotools(dataset, results, keep_ignore=keep_ignore))
    return ours


def stats(ours: CocoEvaluation) -> dict[str, float]:
    return {k: round(v, 12) for k, v in ours.summary().items()}


def test_perfect_detections():
    ds, res = coco([(1, 1, 0, 0, 50, 50), (1, 1, 100, 0, 40, 40)],
                   [(1, 1, 0, 0, 50, 50, 0.9), (1, 1, 100, 0, 40, 40, 0.8)])
    ours = both(ds, res)
    assert stats(ours) == {"AP": 1, "AP50": 1, "AP75": 1, "AP_small": -1, "AP_medium": 1,
                           "AP_large": -1, "AR1": 0.5, "AR10": 1, "AR100": 1, "AR_small": -1,
                           "AR_medium": 1, "AR_large": -1}
    assert ours.ap.tolist() == [ONE] and ours.category_ids.tolist() == [1]
    assert (ours.n_images, ours.n_detections, ours.n_gt) == (1, 2, 2)


def test_precision_after_one_true_positive_is_one_ulp_below_one():
    ours = both(*coco([(1, 1, 0, 0, 50, 50)], [(1, 1, 0, 0, 50, 50, 0.9)]))
    assert (ours.precision[:, :, 0, 0, :] == 1 / (1 + np.spacing(1))).all()
    assert (ours.recall[:, 0, 0, :] == 1.0).all()


def test_a_crowd_absorbs_the_detections_inside_it():
    gts = [(1, 1, 0, 0, 50, 50), (1, 1, 100, 100, 200, 200)]
    dets = [(1, 1, 0, 0, 50, 50, 0.9), (1, 1, 120, 120, 20, 20, 0.95),
            (1, 1, 150, 150, 20, 20, 0.8)]
    # Crowd: both detections inside it match it (IoU = the fraction inside = 1) and are ignored.
    ours = both(*coco(gts, dets, iscrowd={1}))
    assert ours.stats[0] == ONE and ours.ap.tolist() == [ONE]
    # Not a crowd: IoU 400 / 40000, two false positives; the 0.95 one ranks first.
    plain = both(*coco(gts, dets))
    # AP50: precision 1/2 at recall 1/2, reached by the recall thresholds 0, .01, ..., .5
    assert plain.stats[1] == pytest.approx(0.5 * 51 / 101, abs=1e-15)
    assert plain.recall[0, 0, 0, 2] == 0.5


def test_the_ignore_flag_ignores_but_matches_once():
    gts = [(1, 1, 0, 0, 50, 50), (1, 1, 100, 100, 40, 40)]
    dets = [(1, 1, 0, 0, 50, 50, 0.9), (1, 1, 100, 100, 40, 40, 0.95),
            (1, 1, 100, 100, 40, 40, 0.8)]
    # The first detection on the ignored box is ignored; the second finds it taken: a false
    # positive after the true positive, so precision stays 1 up to recall 1.
    ours = both(*coco(gts, dets, keep_ignore={1}), keep_ignore=True)
    assert ours.stats[0] == ONE and ours.stats[8] == 1.0
    gt = GroundTruth2D([1, 1], [1, 1], [g[2:] for g in gts], ignore=[False, True])
    assert evaluate_coco(Detections2D.from_coco(coco(gts, dets)[1]), gt).stats[0] == ONE


def test_equal_scores_keep_input_order_within_an_image():
    gt = [(1, 1, 0, 0, 50, 50)]
    fp, tp = (1, 1, 200, 200, 50, 50, 0.5), (1, 1, 0, 0, 50, 50, 0.5)
    assert both(*coco(gt, [fp, tp])).stats[0] == 0.5
    assert both(*coco(gt, [tp, fp])).stats[0] == ONE


def test_equal_scores_across_images_go_to_the_earlier_image():
    on_1, on_2 = (1, 1, 0, 0, 50, 50, 0.5), (2, 1, 0, 0, 50, 50, 0.5)
    # pycocotools concatenates images in id order, then sorts stably: image 1's detection
    # ranks first whatever the input order
    assert both(*coco([(1, 1, 0, 0, 50, 50)], [on_2, on_1])).stats[0] == ONE
    assert both(*coco([(2, 1, 0, 0, 50, 50)], [on_2, on_1])).stats[0] == 0.5


def test_a_detection_between_two_boxes_of_equal_iou_takes_the_later_one():
    # IoU 90 / 110 with both boxes; pycocotools replaces its best match on ">=": box 2 wins,
    # so the 0.8 detection (exactly box 1) is a true positive at every threshold.
    gts = [(1, 1, 0, 0, 10, 10), (1, 1, 2, 0, 10, 10)]
    dets = [(1, 1, 1, 0, 10, 10, 0.9), (1, 1, 0, 0, 10, 10, 0.8)]
    ours = both(*coco(gts, dets))
    # t <= .8: both true positives; t >= .85: the first is a false positive, then recall 1/2
    # at precision 1/2 for the 51 recall thresholds up to .5.
    assert ours.stats[0] == pytest.approx((7 + 3 * 0.5 * 51 / 101) / 10, abs=1e-15)
    assert ours.stats[1] == ONE


def test_area_ranges_are_closed_and_use_the_area_field():
    # area exactly 32² is small and medium; exactly 96² is medium and large
    ds, res = coco([(1, 1, 0, 0, 32, 32), (2, 1, 0, 0, 96, 96)],
                   [(1, 1, 0, 0, 32, 32, 0.9), (2, 1, 0, 0, 96, 96, 0.8)])
    ours = both(ds, res)
    assert ours.stats[3:6].tolist() == [ONE, ONE, ONE]
    # a 100 x 100 box whose segmentation covers 500 px² is small, not large
    ours = both(*coco([(1, 1, 0, 0, 100, 100, 500.0)], [(1, 1, 0, 0, 100, 100, 0.9)]))
    assert ours.stats[3:6].tolist() == [ONE, -1.0, -1.0]


def test_unmatched_detections_outside_the_range_are_ignored():
    gts = [(1, 1, 0, 0, 10, 10)]  # small
    dets = [(1, 1, 300, 300, 200, 200, 0.95), (1, 1, 0, 0, 10, 10, 0.9),
            (1, 1, 500, 0, 10, 10, 0.99)]
    ours = both(*coco(gts, dets))
    # "small": the large false positive is ignored, the small one is not
    assert ours.stats[3] == pytest.approx(0.5)
    assert ours.stats[0] == pytest.approx(1 / 3)


def test_images_without_ground_truth_give_false_positives():
    ds, res = coco([(1, 1, 0, 0, 50, 50)], [(1, 1, 0, 0, 50, 50, 0.5),
                                             (2, 1, 0, 0, 50, 50, 0.9)], images=[1, 2, 3])
    assert both(ds, res).stats[0] == 0.5


def test_categories_without_detections_or_ground_truth():
    gts = [(1, 1, 0, 0, 50, 50), (1, 2, 0, 0, 50, 50)]
    dets = [(1, 1, 0, 0, 50, 50, 0.9), (1, 3, 0, 0, 50, 50, 0.9)]
    ours = both(*coco(gts, dets))
    assert ours.category_ids.tolist() == [1, 2, 3]
    assert ours.ap.tolist() == [ONE, 0.0, -1.0] and ours.ap50.tolist() == [ONE, 0.0, -1.0]
    assert ours.stats[0] == pytest.approx(0.5, abs=1e-15)
    assert (ours.precision[:, :, 2] == -1).all() and (ours.precision[:, :, 1, 0] == 0).all()


def test_a_duplicate_is_a_false_positive():
    ours = both(*coco([(1, 1, 0, 0, 50, 50)], [(1, 1, 0, 0, 50, 50, 0.9),
                                               (1, 1, 1, 1, 50, 50, 0.8)]))
    assert ours.stats[0] == ONE and ours.recall[0, 0, 0, 0] == 1.0


def test_only_the_first_100_detections_of_an_image_and_category_count():
    dets = [(1, 1, 200 + i, 200, 10, 10, 0.9) for i in range(100)] + [(1, 1, 0, 0, 50, 50, 0.1)]
    ours = both(*coco([(1, 1, 0, 0, 50, 50)], dets))
    assert ours.stats[0] == 0.0 and ours.stats[8] == 0.0 and ours.n_detections == 100
    # another category's detections do not count against the cap
    ours = both(*coco([(1, 1, 0, 0, 50, 50)], dets[:50] + [(1, 2, 0, 0, 5, 5, 0.95)] * 60
                      + dets[100:]))
    assert ours.stats[8] == 1.0


def test_max_dets_caps_recall():
    gts = [(1, 1, 0, 0, 50, 50), (1, 1, 100, 0, 50, 50), (2, 1, 0, 0, 50, 50)]
    dets = [(1, 1, 0, 0, 50, 50, 0.9), (1, 1, 100, 0, 50, 50, 0.8), (2, 1, 0, 0, 50, 50, 0.7)]
    ours = both(*coco(gts, dets))
    assert ours.stats[6:9] == pytest.approx([2 / 3, 1.0, 1.0], abs=1e-15)


def test_no_detections_and_no_ground_truth():
    gt = GroundTruth2D.from_coco([{"image_id": 1, "category_id": 1, "bbox": [0, 0, 50, 50],
                                   "area": 2500.0}])
    none = Detections2D.from_coco([])
    out = evaluate_coco(none, gt)  # pycocotools' loadRes fails on an empty list
    assert out.stats.tolist() == [0, 0, 0, -1, 0, -1, 0, 0, 0, -1, 0, -1]
    empty = GroundTruth2D.from_coco([])
    out = evaluate_coco(Detections2D([1], [1], [[0, 0, 1, 1]], [0.5]), empty)
    assert (out.stats == -1).all() and out.ap.tolist() == [-1.0]
    assert evaluate_coco(none, empty).precision.shape == (10, 101, 0, 4, 3)


def test_image_and_category_ids_restrict_the_evaluation():
    gts = [(1, 1, 0, 0, 50, 50), (2, 1, 0, 0, 50, 50), (1, 2, 0, 0, 50, 50)]
    dets = [(1, 1, 0, 0, 50, 50, 0.9), (2, 1, 300, 0, 50, 50, 0.95), (1, 2, 0, 0, 50, 50, 0.5)]
    ds, res = coco(gts, dets)
    ours = run_ours(ds, res, image_ids=[1], category_ids=[1, 5])
    only = run_ours(*coco(gts[:1], dets[:1], categories=[1, 5]))
    np.testing.assert_array_equal(ours.precision, only.precision)
    assert ours.category_ids.tolist() == [1, 5] and ours.ap.tolist() == [ONE, -1.0]


def test_the_summary_prints_as_pycocotools():
    ds, res = coco([(1, 1, 0, 0, 50, 50), (1, 1, 0, 100, 10, 10)],
                   [(1, 1, 0, 0, 50, 50, 0.9), (1, 1, 0, 100, 10, 12, 0.5)])
    printed = io.StringIO()
    evaluator = run_pycocotools(ds, res)
    with contextlib.redirect_stdout(printed):
        evaluator.summarize()
    ours = run_ours(ds, res)
    assert ours.format_summary() == printed.getvalue().rstrip("\n")
    assert list(ours.summary()) == list(STAT_NAMES)
    assert json.loads(json.dumps(ours.to_dict()))["stats"] == ours.stats.tolist()


def test_bad_arguments_are_named():
    gt = GroundTruth2D([1], [1], [[0, 0, 1, 1]])
    with pytest.raises(FieldError, match="detections must be a Detections2D") as info:
        evaluate_coco({"image_id": [1]}, gt)
    assert info.value.field == "detections"
    with pytest.raises(FieldError, match="image_ids must hold integers"):
        evaluate_coco(Detections2D([], [], [], []), gt, image_ids=["a"])


def test_pairs_taken_in_chunks_give_the_same_numbers(monkeypatch):
    rng = np.random.default_rng(7)
    gts = [(int(i), int(c), *rng.integers(0, 40, 2), *rng.integers(8, 30, 2))
           for i, c in zip(rng.integers(1, 6, 30), rng.integers(1, 3, 30), strict=True)]
    dets = [(*g[:2], g[2] + int(rng.integers(-3, 4)), g[3], g[4], g[5], float(rng.random()))
            for g in gts for _ in range(2)] + [(1, 1, 0, 0, 20, 20, 0.3)] * 5
    ds, res = coco(gts, dets)
    whole = both(ds, res)
    monkeypatch.setattr(matching, "PAIR_CHUNK", 7)  # many chunks, some one group too large
    chunked = run_ours(ds, res)
    np.testing.assert_array_equal(chunked.precision, whole.precision)
    np.testing.assert_array_equal(chunked.recall, whole.recall)
