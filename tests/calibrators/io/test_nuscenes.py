"""calibrators.io: the nuScenes results JSON + ground-truth JSON pair, written and read back,
and every malformed box or document refused with its key path named (results documents
without ground truth and calibrated documents: test_nuscenes_documents.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators.evaluation import evaluate
from calibrators.io import load_nuscenes, save_nuscenes
from tests.calibrators.io.dump_cases import devkit_box, nusc_dump, write_pair


@pytest.mark.parametrize("ego", [True, False])
def test_nuscenes_round_trip(tmp_path, ego):
    dump = nusc_dump(ego=ego)
    res, gt = tmp_path / "results.json", tmp_path / "gt.json"
    save_nuscenes(dump, res, gt)
    back = load_nuscenes(res, gt)
    assert back.classes == dump.classes and back.score_mode == dump.score_mode
    order = np.argsort(dump.det_frame, kind="stable")  # written frame by frame
    gorder = np.argsort(dump.gt_frame, kind="stable")
    np.testing.assert_array_equal(back.frame_ids, dump.frame_ids)
    np.testing.assert_array_equal(back.det_frame, dump.det_frame[order])
    np.testing.assert_array_equal(back.det_logits, dump.det_logits[order])
    np.testing.assert_allclose(back.det_boxes, dump.det_boxes[order], atol=1e-9)
    np.testing.assert_allclose(back.det_cov, dump.det_cov[order])
    np.testing.assert_array_equal(back.gt_labels, dump.gt_labels[gorder])
    np.testing.assert_allclose(back.gt_boxes, dump.gt_boxes[gorder], atol=1e-9)
    if ego:
        np.testing.assert_allclose(back.ego_translation, dump.ego_translation, atol=1e-9)
    else:
        assert back.ego_translation is None
    a = evaluate(dump, class_range=None, max_boxes_per_frame=None)
    b = evaluate(back, class_range=None, max_boxes_per_frame=None)
    assert a.mean_ap > 0.1
    for name in a.ap:
        assert a.ap[name] == pytest.approx(b.ap[name], abs=1e-12)


def test_nuscenes_scores_and_covariances_as_extra_keys(tmp_path):
    dump = nusc_dump(cov=False)
    res, gt = tmp_path / "r.json", tmp_path / "g.json"
    scores = np.linspace(0.01, 0.99, dump.n_detections)
    cov = np.tile(np.eye(2) * 4.0, (dump.n_detections, 1, 1))
    save_nuscenes(dump, res, gt, scores=scores, covariances=cov)
    boxes = [b for v in json.loads(res.read_text())["results"].values() for b in v]
    first = np.flatnonzero(dump.det_frame == 0)[0]
    assert boxes[0]["detection_score"] == scores[first]
    assert boxes[0]["detection_score_raw"] == pytest.approx(dump.det_scores[first])
    assert boxes[0]["covariance"] == [[4.0, 0.0], [0.0, 4.0]]
    gt_boxes = [b for v in json.loads(gt.read_text())["results"].values() for b in v]
    assert all(b["detection_score"] == -1.0 for b in gt_boxes)
    with pytest.raises(ValueError, match="covariances must have shape"):
        save_nuscenes(dump, res, gt, covariances=cov[:, :1, :1])


def test_plain_results_get_sigmoid_logits_from_the_score(tmp_path):
    res, gt = write_pair(
        tmp_path,
        {"a": [devkit_box("a", "pedestrian", (1, 2, 0), 0.7),
               devkit_box("a", "car", (5, 0, 0), 1e-9)], "b": []},
        {"a": [devkit_box("a", "car", (5, 0, 0), -1.0, num_pts=4),
               devkit_box("a", "bus", (9, 9, 0), -1.0, num_pts=0)],  # no points: dropped
         "b": [devkit_box("b", "car", (1, 0, 0), -1.0)]})
    dump = load_nuscenes(res, gt)
    assert dump.classes[:2] == ("car", "truck") and dump.score_mode == "sigmoid"
    assert dump.det_labels.tolist() == [5, 0]
    np.testing.assert_allclose(dump.det_scores, [0.7, 1e-9])
    np.testing.assert_allclose(dump.det_logits[0, 0, 0], np.log(1e-6 / (1 - 1e-6)))
    assert dump.gt_labels.tolist() == [0, 0] and dump.gt_frame.tolist() == [0, 1]
    assert dump.ego_translation is None


def test_yaw_from_a_non_unit_quaternion(tmp_path):
    q = 2.0 * np.array([np.cos(0.15), 0.0, 0.0, np.sin(0.15)])
    b = devkit_box("a", "car", (0, 0, 0))
    b["rotation"] = q.tolist()
    res, gt = write_pair(tmp_path, {"a": [b]}, {"a": []})
    assert load_nuscenes(res, gt).det_boxes[0, 0, 6] == pytest.approx(0.3)


def test_ego_position_from_ego_translation(tmp_path):
    ego = np.array([100.0, 200.0, 0.0])
    det = devkit_box("a", "car", (110, 200, 1), ego_translation=[10.0, 0.0, 1.0])
    gt = devkit_box("a", "car", (90, 205, 1), -1.0, ego_translation=[-10.0, 5.0, 1.0])
    res, g = write_pair(tmp_path, {"a": [det]}, {"a": [gt]})
    np.testing.assert_allclose(load_nuscenes(res, g).ego_translation, [ego])
    gt["ego_translation"] = [-10.0, 6.0, 1.0]  # 1 m off
    res, g = write_pair(tmp_path, {"a": [det]}, {"a": [gt]})
    with pytest.raises(ValueError, match="disagree on the ego position"):
        load_nuscenes(res, g)


def test_a_label_that_is_not_the_arg_max_is_kept(tmp_path):
    # Top-K (query, class) decoding: the same query's logits give a car and a truck box.
    logits = [2.0, 0.5] + [-3.0] * 8
    car = devkit_box("a", "car", (1, 1, 0))
    truck = devkit_box("a", "truck", (1, 1, 0))
    for b in (car, truck):
        b["detection_logits"] = logits
    res, gt = write_pair(tmp_path, {"a": [car, truck]}, {"a": []})
    dump = load_nuscenes(res, gt)
    assert dump.det_labels.tolist() == [0, 1]
    np.testing.assert_allclose(dump.det_scores, 1 / (1 + np.exp(-np.array([2.0, 0.5]))))
    # Labels that are the arg-max everywhere stay implicit.
    truck["detection_name"] = "car"
    res, gt = write_pair(tmp_path, {"a": [car, truck]}, {"a": []})
    assert load_nuscenes(res, gt).det_label is None


@pytest.mark.parametrize("mutate, message", [
    (lambda b: b.pop("translation"), "missing 'translation'"),
    (lambda b: b.update(velocity=[float("nan"), 0.0]), r"velocity has NaN"),
    (lambda b: b.update(size=[1.0, 2.0]), "size must be 3 numbers"),
    (lambda b: b.update(detection_name="cat"), "detection_name must be one of .* got 'cat'"),
    (lambda b: b.update(detection_score=1.5), "detection_score must .*probabilities"),
    (lambda b: b.update(rotation=[0, 0, 0, 0]), "zero quaternion"),
    (lambda b: b.update(sample_token="zzz"), "sample_token is 'zzz'"),
])
def test_bad_nuscenes_boxes_are_named(tmp_path, mutate, message):
    b = devkit_box("a", "truck", (1, 1, 0))
    mutate(b)
    res, gt = write_pair(tmp_path, {"a": [b]}, {"a": []})
    with pytest.raises(ValueError, match=message):
        load_nuscenes(res, gt)


def test_sample_tokens_must_agree(tmp_path):
    res, gt = write_pair(tmp_path, {"a": []}, {"a": [], "b": []})
    with pytest.raises(ValueError, match="ground truth has 1 sample token"):
        load_nuscenes(res, gt)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_nuscenes(tmp_path / "bad.json", gt)


@pytest.mark.parametrize("meta, box, message", [
    ({"classes": 5}, {}, r"meta.classes must be a non-empty list of strings, got 5"),
    ({"classes": None}, {}, "meta.classes must be a non-empty list of strings, got null"),
    ({"classes": "car"}, {}, "meta.classes must be a non-empty list of strings"),
    ({"cov_dims": 7}, {}, "meta.cov_dims must be a non-empty list of strings, got 7"),
    ({"score_mode": ["softmax"]}, {}, "meta.score_mode must be one of"),
    ({}, {"detection_name": ["car"]},
     r"results\['a'\]\[0\].detection_name must be one of .*got an array"),
    ({}, {"num_pts": None}, r"results\['a'\]\[0\].num_pts must be a whole number.*null"),
    ({}, {"num_pts": [3]}, r"results\['a'\]\[0\].num_pts must be a whole number"),
    ({}, {"num_pts": 2.5}, r"num_pts must be a whole number.*got 2.5"),
    ({}, {"num_pts": "1e400"}, r"results\['a'\]\[0\].num_pts must be a whole number.*got inf"),
    ({}, {"translation": ["1", 2, 3]}, r"results\['a'\]\[0\].translation must be 3 numbers"),
    ({}, {"size": [True, 2.0, 1.0]}, r"results\['a'\]\[0\].size must be 3 numbers"),
    ({}, {"detection_score": "0.5"}, r"detection_score must be a number, got '0.5'"),
    ({}, {"velocity": {"x": 1}}, r"velocity must be 2 numbers, got an object"),
])
def test_malformed_nuscenes_values_name_the_key_path(tmp_path, meta, box, message):
    b = {**devkit_box("a", "car", (1, 1, 0)), **box}
    res, gt = write_pair(tmp_path, {"a": [b]}, {"a": []}, meta={**meta, "x": 0})
    if b.get("num_pts") == "1e400":  # a number JSON can hold but a float cannot
        res.write_text(res.read_text().replace('"num_pts": "1e400"', '"num_pts": 1e400'))
    with pytest.raises(ValueError, match=message):
        load_nuscenes(res, gt)


def test_nuscenes_depth_and_size_are_refused_before_parsing(tmp_path):
    res, gt = write_pair(tmp_path, {"a": [devkit_box("a", "car", (1, 1, 0))]}, {"a": []})
    deep = '{"meta": {"classes": ' + "[" * 3000 + "]" * 3000 + '}, "results": {}}'
    (tmp_path / "deep.json").write_text(deep)
    with pytest.raises(ValueError, match="results file nests arrays/objects 33 deep"):
        load_nuscenes(tmp_path / "deep.json", gt)
    with pytest.raises(ValueError, match="ground truth file nests"):
        load_nuscenes(res, tmp_path / "deep.json")
    with pytest.raises(ValueError, match="larger than the limit of 100 bytes") as err:
        load_nuscenes(res, gt, max_bytes=100)
    assert str(tmp_path) not in str(err.value)
    # brackets and escaped quotes inside strings do not count
    tricky = devkit_box("a", "car", (1, 1, 0), attribute_name='\\"' + "[{" * 50)
    res, gt = write_pair(tmp_path, {"a": [tricky]}, {"a": []})
    assert load_nuscenes(res, gt).n_detections == 1
