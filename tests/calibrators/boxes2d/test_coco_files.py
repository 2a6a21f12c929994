"""COCO results and instances files: read -> write -> read round trips, and every bad field
named (hand-made cases, and Hypothesis mutations of a valid file)."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.boxes2d import (
    ConformalBoxes,
    Detections2D,
    GroundTruth2D,
    coco_results,
    parse_instances,
    read_coco_instances,
    read_coco_results,
    write_coco_results,
)
from calibrators.core.errors import FieldError

INSTANCES = {
    "info": {"description": "test"},
    "images": [{"id": 1, "width": 640, "height": 480, "file_name": "a.jpg"},
               {"id": 2, "width": 320, "height": 240, "file_name": "b.jpg"}],
    "annotations": [
        {"id": 10, "image_id": 1, "category_id": 3, "bbox": [10, 20, 30, 40], "area": 1200.0,
         "iscrowd": 0, "segmentation": [[10, 20, 40, 20, 40, 60]]},
        {"id": 11, "image_id": 1, "category_id": 7, "bbox": [100.5, 50, 20, 20], "area": 400},
        {"id": 12, "image_id": 2, "category_id": 3, "bbox": [0, 0, 300, 200], "area": 6e4,
         "iscrowd": 1},
        {"id": 13, "image_id": 2, "category_id": 7, "bbox": [5, 5, 0, 0], "area": 0},
    ],
    "categories": [{"id": 3, "name": "car", "supercategory": "vehicle"},
                   {"id": 7, "name": "person"}],
}
RESULTS = [
    {"image_id": 1, "category_id": 3, "bbox": [11, 19, 30, 41], "score": 0.91,
     "logits": [2.3, -1.0], "layer_boxes": [[9, 18, 33, 44], [11, 19, 30, 41]]},
    {"image_id": 1, "category_id": 7, "bbox": [99, 52, 21.5, 19], "score": 0.4,
     "logits": [-3.0, -0.4], "layer_boxes": [[98, 50, 20, 20], [99, 52, 21.5, 19]]},
    {"image_id": 2, "category_id": 3, "bbox": [10, 10, 50, 50], "score": 0.05,
     "logits": [-2.9, -5.5], "layer_boxes": [[12, 10, 50, 52], [10, 10, 50, 50]]},
]


def write(path: Path, value) -> Path:
    path.write_text(json.dumps(value))
    return path


def test_instances_are_read_field_by_field(tmp_path):
    inst = read_coco_instances(write(tmp_path / "gt.json", INSTANCES))
    assert inst.image_id.tolist() == [1, 2] and inst.width.tolist() == [640, 320]
    assert inst.category_id.tolist() == [3, 7] and inst.category_name == ("car", "person")
    assert inst.annotation_id.tolist() == [10, 11, 12, 13]
    gt = inst.ground_truth
    assert isinstance(gt, GroundTruth2D) and len(gt) == 4
    assert gt.iscrowd.tolist() == [False, False, True, False]
    assert gt.area.tolist() == [1200.0, 400.0, 6e4, 0.0]
    assert inst.image_size([2, 1, 2]).tolist() == [[320, 240], [640, 480], [320, 240]]
    with pytest.raises(FieldError, match=r"image_id\[1\] 5 is not the id of any of the images"):
        inst.image_size([1, 5])


def test_results_read_write_read_round_trip(tmp_path):
    first = read_coco_results(write(tmp_path / "r.json", RESULTS))
    assert first.logits.shape == (3, 2) and first.layer_boxes.shape == (3, 2, 4)
    write_coco_results(tmp_path / "again.json", first)
    again = read_coco_results(tmp_path / "again.json")
    for name in ("image_id", "category_id", "bbox", "score", "logits", "layer_boxes"):
        assert getattr(again, name).tobytes() == getattr(first, name).tobytes(), name
    assert json.loads((tmp_path / "again.json").read_text()) == RESULTS  # same values, order


def test_calibrated_results_carry_the_raw_score_and_regions(tmp_path):
    found = read_coco_results(write(tmp_path / "r.json", RESULTS))
    rng = np.random.default_rng(0)
    boxes = np.tile(found.bbox, (100, 1))
    est = ConformalBoxes(min_group=50).fit(boxes, boxes + rng.normal(0, 2, boxes.shape),
                                           np.tile(found.category_id, 100))
    served = est.serve(found.bbox, found.category_id, None, [0.9, 0.999])
    calibrated = np.array([0.8, 0.3, 0.01])
    write_coco_results(tmp_path / "cal.json", found, calibrated, served)
    records = json.loads((tmp_path / "cal.json").read_text())
    assert [r["score"] for r in records] == calibrated.tolist()
    assert [r["score_raw"] for r in records] == found.score.tolist()
    region = records[0]["region_0.9"]
    assert region["inner"] == served.inner[0, 0].tolist()
    assert region["outer"] == served.outer[0, 0].tolist()
    assert region["guarantee"] in ("cell", "pooled", "marginal")
    assert region["calibration_n"] == int(served.calibration_n[0, 0])
    assert records[0]["region_0.999"]["inner"] is None   # 150 scores cannot certify 0.999
    back = read_coco_results(tmp_path / "cal.json")
    assert back.score.tolist() == calibrated.tolist()
    assert back.bbox.tobytes() == found.bbox.tobytes()
    assert coco_results(found)[0] == RESULTS[0]


def test_python_callers_may_pass_numpy_numbers_and_tuples():
    dt = Detections2D.from_coco([{"image_id": np.int64(1), "category_id": 2,
                                  "bbox": (1, np.float32(2.5), 3, 4), "score": np.float32(0.5)}])
    assert dt.bbox.tolist() == [[1.0, 2.5, 3.0, 4.0]] and dt.score.tolist() == [0.5]
    truth = GroundTruth2D.from_coco([{"image_id": 1, "category_id": 2,
                                      "bbox": np.array([1.0, 2, 3, 4]), "area": 12,
                                      "iscrowd": True}])
    assert truth.iscrowd.tolist() == [True]


def mutated(doc, path, value):
    out = copy.deepcopy(doc)
    target = out
    for key in path[:-1]:
        target = target[key]
    if value is DELETE:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return out


DELETE = object()


@pytest.mark.parametrize(("path", "value", "field", "row", "message"), [
    (("annotations", 3, "bbox"), [1, 2, -3, 4], "bbox", 3,
     r"annotations\[3\]\.bbox must be 4 finite numbers with w, h >= 0, got \[1, 2, -3, 4\]"),
    (("annotations", 1, "bbox"), [1, 2, 3], "bbox", 1, r"annotations\[1\]\.bbox must be 4"),
    (("annotations", 0, "bbox"), "10 20 30 40", "bbox", 0, r"annotations\[0\]\.bbox must be 4"),
    (("annotations", 2, "bbox"), [0, 0, 1e308, 1e308], "bbox", 2,
     r"annotations\[2\]\.bbox has an area w·h that over- or underflows"),
    (("annotations", 2, "area"), -1, "area", 2, r"annotations\[2\]\.area must be a number >= 0"),
    (("annotations", 1, "iscrowd"), 2, "iscrowd", 1, r"annotations\[1\]\.iscrowd must be 0 or 1"),
    (("annotations", 1, "image_id"), 1.0, "image_id", 1,
     r"annotations\[1\]\.image_id must be an integer, got 1\.0"),
    (("annotations", 1, "image_id"), 9, "image_id", 1,
     r"annotations\[1\]\.image_id 9 is not the id of any of the images"),
    (("annotations", 3, "category_id"), 4, "category_id", 3,
     r"annotations\[3\]\.category_id 4 is not the id of any of the categories"),
    (("annotations", 2, "id"), 10, "id", 2, r"annotations\[2\]\.id 10 repeats annotations\[0\]"),
    (("annotations", 0, "area"), DELETE, "area", 0, r"annotations\[0\] has no 'area'"),
    (("annotations", 1), [1, 2], "annotations", 1, r"annotations\[1\] must be an object"),
    (("images", 1, "width"), 0, "width", 1, r"images\[1\]\.width must be an integer > 0"),
    (("images", 0, "height"), "480", "height", 0, r"images\[0\]\.height must be an integer"),
    (("images", 1, "id"), 1, "id", 1, r"images\[1\]\.id 1 repeats images\[0\]\.id"),
    (("categories", 1, "name"), None, "name", 1, r"categories\[1\]\.name must be a string"),
    (("categories",), {"id": 3}, "categories", None, r"categories must be a list of objects"),
    (("images",), DELETE, "images", None, r"the instances document has no 'images'"),
])
def test_a_bad_instances_field_is_named(tmp_path, path, value, field, row, message):
    doc = mutated(INSTANCES, path, value)
    with pytest.raises(FieldError, match=message) as info:
        read_coco_instances(write(tmp_path / "gt.json", doc))
    assert (info.value.field, info.value.row) == (field, row)


@pytest.mark.parametrize(("path", "value", "field", "row", "message"), [
    ((1, "score"), 1.5, "score", 1, r"results\[1\]\.score must be a number in \[0, 1\]"),
    ((1, "score"), "0.4", "score", 1, r"results\[1\]\.score must be a finite number, got '0.4'"),
    ((0, "score"), True, "score", 0, r"results\[0\]\.score must be a finite number, got True"),
    ((2, "bbox"), [1, 2, 3, -4], "bbox", 2, r"results\[2\]\.bbox must be 4 finite numbers"),
    ((2, "category_id"), None, "category_id", 2, r"results\[2\]\.category_id must be an integer"),
    ((0, "image_id"), 2 ** 70, "image_id", 0, r"results\[0\]\.image_id is outside the 64-bit"),
    ((1, "logits"), [1.0], "logits", 1, r"results\[1\]\.logits has 1 entries but results\[0\]"),
    ((1, "logits"), DELETE, "logits", 1, r"results\[1\] has no 'logits' but results\[0\] has"),
    ((2, "logits"), [1.0, "x"], "logits", 2, r"results\[2\]\.logits must be a non-empty list"),
    ((2, "layer_boxes"), [[0, 0, 1, 1], [0, 0, -1, 1]], "layer_boxes", 2,
     r"results\[2\]\.layer_boxes\[1\] must be 4 finite numbers with w, h >= 0"),
    ((0, "layer_boxes"), [[0, 0, 1, 1]], "layer_boxes", 1,
     r"results\[1\]\.layer_boxes has 2 entries but results\[0\]\.layer_boxes has 1"),
    ((1,), "detection", "results", 1, r"results\[1\] must be an object, got str"),
])
def test_a_bad_results_field_is_named(tmp_path, path, value, field, row, message):
    doc = mutated(RESULTS, path, value)
    with pytest.raises(FieldError, match=message) as info:
        read_coco_results(write(tmp_path / "r.json", doc))
    assert (info.value.field, info.value.row) == (field, row)


def test_results_on_images_the_instances_lack(tmp_path):
    inst = parse_instances(INSTANCES)
    doc = mutated(RESULTS, (2, "image_id"), 5)
    with pytest.raises(FieldError, match=r"results\[2\]\.image_id 5 is not the id of any image"):
        read_coco_results(write(tmp_path / "r.json", doc), instances=inst)
    assert len(read_coco_results(write(tmp_path / "ok.json", RESULTS), instances=inst)) == 3


def test_files_are_bounded_and_strict_json(tmp_path):
    path = write(tmp_path / "r.json", RESULTS)
    with pytest.raises(FieldError, match="limit of 100 bytes") as info:
        read_coco_results(path, max_bytes=100)
    assert info.value.field == "results"
    (tmp_path / "nan.json").write_text('[{"image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1],'
                                       ' "score": NaN}]')
    with pytest.raises(FieldError, match="not valid JSON: NaN is not a JSON number"):
        read_coco_results(tmp_path / "nan.json")
    (tmp_path / "bad.json").write_text('{"images": [')
    with pytest.raises(FieldError, match="instances: not valid JSON"):
        read_coco_instances(tmp_path / "bad.json")
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(FieldError, match="results: not valid JSON"):
        read_coco_results(tmp_path / "deep.json")
    with pytest.raises(FieldError, match="no such file"):
        read_coco_results(tmp_path / "missing.json")
    with pytest.raises(FieldError, match="results must be a list of objects, got an object"):
        read_coco_results(write(tmp_path / "obj.json", {"results": RESULTS}))


# -- Hypothesis: mutations of a valid file -----------------------------------------------------
#: Values that break each kind of field, as JSON can write them (NaN and infinities are not
#: JSON: a Python caller's NaN is tried through parse_instances / from_coco instead).
BAD = {
    "int": ["1", 1.5, 1.0, True, None, [1], {"v": 1}, 2 ** 64],
    "box": [[1, 2, 3], [1, 2, 3, 4, 5], [0, 0, -1, 1], [0, 0, 1, -0.5], ["0", 0, 1, 1],
            [0, 0, 1, None], [True, 0, 1, 1], "box", None, 7, [], [[0, 0, 1, 1]],
            [0, 0, 1, math.nan], [math.inf, 0, 1, 1]],
    "area": [-1, -0.001, "12", None, True, [1], math.nan, math.inf],
    "flag": [2, -1, 0.5, "0", None, [0]],
    "score": [-0.1, 1.0001, "0.5", True, None, [0.5], math.nan, -math.inf],
}
FIELDS = {"annotations": {"image_id": "int", "category_id": "int", "id": "int", "bbox": "box",
                          "area": "area", "iscrowd": "flag"},
          "results": {"image_id": "int", "category_id": "int", "bbox": "box",
                      "score": "score"}}


@st.composite
def bad_documents(draw):
    """(which list, record index, key, mutated document or results list)."""
    which = draw(st.sampled_from(sorted(FIELDS)))
    records = INSTANCES["annotations"] if which == "annotations" else RESULTS
    i = draw(st.integers(0, len(records) - 1))
    key = draw(st.sampled_from(sorted(FIELDS[which])))
    value = draw(st.sampled_from([DELETE, *BAD[FIELDS[which][key]]]))
    if key == "iscrowd" and value is DELETE:
        value = 3   # iscrowd is optional: a missing one is valid
    if which == "annotations":
        return which, i, key, mutated(INSTANCES, ("annotations", i, key), value)
    return which, i, key, mutated(RESULTS, (i, key), value)


@settings(max_examples=300, deadline=None)
@given(bad_documents())
def test_any_bad_field_is_named_with_its_record(data):
    which, i, key, doc = data
    with pytest.raises(FieldError) as info:
        if which == "annotations":
            parse_instances(doc)
        else:
            found = Detections2D.from_coco(doc)
            bad = (found.score < 0) | (found.score > 1)   # what read_coco_results adds
            if bad.any():
                raise FieldError("score", f"results[{int(np.argmax(bad))}].score must be a "
                                          "number in [0, 1]", row=int(np.argmax(bad)))
    assert info.value.field == key
    assert info.value.row == i
    assert f"{which}[{i}]" in str(info.value)


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_a_valid_file_in_any_record_order_reads_the_same_rows(data):
    order = data.draw(st.permutations(range(len(RESULTS))))
    found = Detections2D.from_coco([RESULTS[k] for k in order])
    base = Detections2D.from_coco(RESULTS)
    assert found.bbox.tolist() == base.bbox[list(order)].tolist()
    assert found.layer_boxes.tolist() == base.layer_boxes[list(order)].tolist()
