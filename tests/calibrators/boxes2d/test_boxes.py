"""Detections2D / GroundTruth2D: what they hold, and every bad field named with its reason."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.boxes2d import Detections2D, GroundTruth2D
from calibrators.core.errors import FieldError

BOX = [[10.0, 20.0, 30.0, 40.0], [0.0, 0.0, 5.0, 5.0]]


def _dt(**kw):
    args = dict(image_id=[1, 2], category_id=[3, 3], bbox=BOX, score=[0.9, 0.1])
    return Detections2D(**{**args, **kw})


def _gt(**kw):
    args = dict(image_id=[1, 2], category_id=[3, 3], bbox=BOX)
    return GroundTruth2D(**{**args, **kw})


def test_detections_hold_typed_arrays():
    dt = _dt()
    assert len(dt) == 2
    assert dt.image_id.dtype == np.int64 and dt.category_id.dtype == np.int64
    assert dt.bbox.dtype == np.float64 and dt.bbox.shape == (2, 4)
    assert dt.score.tolist() == [0.9, 0.1]


def test_ground_truth_defaults_area_to_the_box_and_flags_to_false():
    gt = _gt()
    assert gt.area.tolist() == [1200.0, 25.0]
    assert gt.iscrowd.tolist() == [False, False] and gt.ignore.tolist() == [False, False]
    gt = _gt(area=[7.0, 8.0], iscrowd=[1, 0], ignore=[False, True])
    assert gt.area.tolist() == [7.0, 8.0]
    assert gt.iscrowd.tolist() == [True, False] and gt.ignore.tolist() == [False, True]


def test_empty_containers():
    assert len(Detections2D([], [], [], [])) == 0
    gt = GroundTruth2D(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4)))
    assert gt.bbox.shape == (0, 4) and gt.area.shape == (0,)


@pytest.mark.parametrize(("kwargs", "field", "row", "message"), [
    (dict(bbox=[[0, 0, -1.0, 5], [0, 0, 1, 1]]), "bbox", 0, r"bbox\[0\] has a negative width"),
    (dict(bbox=[[0, 0, 1, 1], [0, 0, 1, -2]]), "bbox", 1, r"bbox\[1\] has a negative height"),
    (dict(bbox=[[0, 0, 1, 1], [0, np.nan, 1, 1]]), "bbox", 1, r"bbox has NaN at index \[1, 1\]"),
    (dict(bbox=[[0, 0, 1, 1], [1e308, 0, 1e308, 1]]), "bbox", 1, r"x \+ w or y \+ h"),
    (dict(bbox=[[0, 0, 1e200, 1e200], [0, 0, 1, 1]]), "bbox", 0, r"over- or underflows"),
    (dict(bbox=[[0, 0, 1e-200, 1e-200], [0, 0, 1, 1]]), "bbox", 0, r"over- or underflows"),
    (dict(bbox=[[0, 0, 1, 1]]), "bbox", None, r"bbox has 1 rows but image_id has 2"),
    (dict(bbox=[[0, 0, 1], [0, 0, 1]]), "bbox", None, r"shape \[N, 4\]"),
    (dict(score=[0.5, np.inf]), "score", 1, r"score has Inf at index 1"),
    (dict(score=[0.5]), "score", None, r"score has 1 rows"),
    (dict(category_id=[1.5, 2]), "category_id", None, r"category_id must hold integers"),
    (dict(image_id=[[1, 2]]), "image_id", None, r"image_id must have 1 dimensions"),
])
def test_detections_name_the_bad_field(kwargs, field, row, message):
    with pytest.raises(FieldError, match=message) as info:
        _dt(**kwargs)
    assert info.value.field == field and info.value.row == row


@pytest.mark.parametrize(("kwargs", "field", "row", "message"), [
    (dict(area=[1.0, -1.0]), "area", 1, r"area\[1\] has a negative value"),
    (dict(area=[1.0]), "area", None, r"area has 1 rows"),
    (dict(iscrowd=[0, 2]), "iscrowd", 1, r"iscrowd\[1\] has a value other than 0, 1"),
    (dict(ignore=[True]), "ignore", None, r"ignore has 1 rows"),
    (dict(category_id=[1]), "category_id", None, r"category_id has 1 rows"),
])
def test_ground_truth_names_the_bad_field(kwargs, field, row, message):
    with pytest.raises(FieldError, match=message) as info:
        _gt(**kwargs)
    assert info.value.field == field and info.value.row == row


def test_from_coco_reads_the_fields_pycocotools_reads():
    results = [{"image_id": 1, "category_id": 2, "bbox": [1, 2, 3, 4], "score": 0.5,
                "extra": "kept out"}]
    dt = Detections2D.from_coco(results)
    assert dt.bbox.tolist() == [[1.0, 2.0, 3.0, 4.0]] and dt.score.tolist() == [0.5]
    annotations = [{"id": 7, "image_id": 1, "category_id": 2, "bbox": [1, 2, 3, 4],
                    "area": 5.0, "ignore": 1},
                   {"id": 8, "image_id": 1, "category_id": 2, "bbox": [1, 2, 3, 4],
                    "area": 6.0, "iscrowd": 1}]
    gt = GroundTruth2D.from_coco(annotations)
    assert gt.area.tolist() == [5.0, 6.0] and gt.iscrowd.tolist() == [False, True]
    # pycocotools overwrites `ignore` with `iscrowd`: from_coco does not read it
    assert gt.ignore.tolist() == [False, False]
    assert len(Detections2D.from_coco([])) == 0 and len(GroundTruth2D.from_coco([])) == 0


def test_from_coco_names_a_missing_key():
    with pytest.raises(FieldError, match=r"results\[1\] has no 'score'") as info:
        Detections2D.from_coco([{"image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1],
                                 "score": 1.0},
                                {"image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1]}])
    assert info.value.field == "score" and info.value.row == 1
    with pytest.raises(FieldError, match=r"annotations\[0\] has no 'area'"):
        GroundTruth2D.from_coco([{"image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1]}])
