"""calibrators.io: the nuScenes results JSON + ground-truth JSON pair, and calibrated results
documents."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from calibrators.data import Dump
from calibrators.evaluation import evaluate
from calibrators.io import (
    calibrate_results_document,
    ellipses_json,
    load_dump,
    load_nuscenes,
    save_dump,
    save_nuscenes,
)
from tests.calibrators.test_io import CLASSES, arrays, assert_same, write


# -- nuScenes JSON -----------------------------------------------------------------------------
def nusc_dump(seed=0, ego=True, cov=True):
    content = arrays(seed=seed, n=30, g=10, f=4, layers=1, optional=True)
    if not ego:
        del content["ego_translation"]
    if not cov:
        del content["det_cov"]
    g = len(content["gt_boxes"])  # the first g detections find their ground truth
    content["det_frame"][:g] = content["gt_frame"]
    content["det_boxes"][:g, 0] = content["gt_boxes"] + 0.3
    content["det_logits"][np.arange(g), 0, content["gt_labels"]] += 10.0
    fields = {k: (str(v) if k == "score_mode" else v) for k, v in content.items()}
    return Dump(**fields)


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


def devkit_box(token, name, xyz, score=0.5, yaw=0.0, **extra):
    return {"sample_token": token, "translation": list(xyz), "size": [2.0, 4.0, 1.5],
            "rotation": [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))],
            "velocity": [1.0, 0.0], "detection_name": name, "detection_score": score,
            "attribute_name": "", **extra}


def write_pair(tmp_path, results, gt, meta=None):
    res, g = tmp_path / "r.json", tmp_path / "g.json"
    res.write_text(json.dumps({"meta": meta or {}, "results": results}))
    g.write_text(json.dumps({"meta": {}, "results": gt}))
    return res, g


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


def test_npz_through_a_file_object(tmp_path):

    dump = load_dump(write(tmp_path / "a.npz", arrays()))
    buf = io.BytesIO()
    save_dump(buf, dump)
    assert_same(load_dump(io.BytesIO(buf.getvalue())), dump)
    with pytest.raises(ValueError, match="not an NPZ archive: not a zip file"):
        load_dump(io.BytesIO(b"garbage"))


# -- optional ground truth, cov_dims, calibrating a results document ---------------------------
def test_save_without_gt_path_writes_only_the_results(tmp_path):
    dump = nusc_dump()
    res = tmp_path / "results.json"
    save_nuscenes(dump, res)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]
    back = load_nuscenes(res)
    np.testing.assert_array_equal(back.det_logits,
                                  dump.det_logits[np.argsort(dump.det_frame, kind="stable")])


def test_load_without_gt_gives_a_dump_with_no_ground_truth(tmp_path):
    res, _ = write_pair(tmp_path, {"a": [devkit_box("a", "car", (1, 2, 0), 0.8)], "b": [],
                                   "c": [devkit_box("c", "bus", (3, 0, 0), 0.4)]}, {})
    dump = load_nuscenes(res)
    assert dump.frame_ids.tolist() == ["a", "b", "c"]
    assert dump.det_frame.tolist() == [0, 2]
    assert dump.gt_boxes.shape == (0, 9) and len(dump.gt_labels) == 0 and len(dump.gt_frame) == 0
    np.testing.assert_allclose(dump.det_scores, [0.8, 0.4])


def test_load_without_gt_takes_the_ego_from_the_results(tmp_path):
    det = devkit_box("a", "car", (110, 200, 1), ego_translation=[10.0, 0.0, 1.0])
    res, _ = write_pair(tmp_path, {"a": [det]}, {})
    np.testing.assert_allclose(load_nuscenes(res).ego_translation, [[100.0, 200.0, 0.0]])


def test_save_covariances_over_other_dims(tmp_path):
    dump = nusc_dump()  # det_cov over x, y
    res = tmp_path / "r.json"
    cov = np.tile(np.diag([1.0, 2.0, 3.0]), (dump.n_detections, 1, 1))
    save_nuscenes(dump, res, covariances=cov, cov_dims=("x", "y", "yaw"))
    content = json.loads(res.read_text())
    assert content["meta"]["cov_dims"] == ["x", "y", "yaw"]
    back = load_nuscenes(res)
    assert back.cov_dims == ("x", "y", "yaw")
    np.testing.assert_array_equal(back.det_cov, cov)


@pytest.mark.parametrize("kwargs, message", [
    ({"cov_dims": ("x", "y", "yaw")}, "cov_dims is given without covariances"),
    ({"covariances": np.ones((30, 2, 2)), "cov_dims": ("x", "q")}, "cov_dims must be one of"),
    ({"covariances": np.ones((30, 2, 2)), "cov_dims": ("x", "x")}, "cov_dims must name distinct"),
    ({"covariances": np.ones((30, 2, 2)), "cov_dims": ("x", "y", "z")},
     r"covariances must have shape \[30, 3, 3\]"),
    ({"covariances": np.ones((30, 3, 3))}, r"covariances must have shape \[30, 2, 2\]"),
    ({"scores": np.full(30, 1.5)}, "scores must hold probabilities"),
    ({"scores": np.full(29, 0.5)}, "scores has 29 rows"),
])
def test_save_refuses_bad_scores_covariances_and_dims(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message):
        save_nuscenes(nusc_dump(), tmp_path / "r.json", **kwargs)
    assert not (tmp_path / "r.json").exists()


def results_document():
    """A devkit-style results document with fields a Dump does not hold."""
    return {
        "meta": {"use_lidar": True, "classes": list(CLASSES), "note": "from a detector"},
        "results": {
            "s1": [devkit_box("s1", "car", (1, 2, 0), 0.9, num_pts=17,
                              attribute_name="vehicle.moving", extra_field=[1, 2])],
            "s0": [devkit_box("s0", "pedestrian", (4, 0, 0), 0.3, num_pts=3,
                              attribute_name="pedestrian.standing"),
                   devkit_box("s0", "car", (9, 1, 0), 0.6, detection_score_raw=0.55)],
            "s2": [],
        },
        "extra_top_level": {"kept": True},
    }


def test_calibrate_results_document_keeps_every_other_field(tmp_path):
    doc = results_document()
    original = json.loads(json.dumps(doc))
    res = tmp_path / "r.json"
    res.write_text(json.dumps(doc))
    dump = load_nuscenes(res)  # boxes in the order calibrate_results_document writes them
    assert dump.det_labels.tolist() == [0, 1, 0]
    scores = np.array([0.8, 0.2, 0.5])
    cov = np.stack([np.eye(2) * (i + 1) for i in range(3)])
    out = calibrate_results_document(doc, scores, cov, cov_dims=("x", "y"))
    assert doc == original  # the input is not modified
    assert out["extra_top_level"] == {"kept": True}
    assert out["meta"] == {**original["meta"], "cov_dims": ["x", "y"]}
    boxes = [b for t in ("s1", "s0") for b in out["results"][t]]
    before = [b for t in ("s1", "s0") for b in original["results"][t]]
    for i, (new, old) in enumerate(zip(boxes, before, strict=True)):
        assert new["detection_score"] == scores[i]
        assert new["covariance"] == cov[i].tolist()
        for key in set(old) - {"detection_score"}:
            assert new[key] == old[key], key
    assert [b["detection_score_raw"] for b in boxes] == [0.9, 0.3, 0.55]  # existing raw kept
    assert out["results"]["s2"] == []
    back_path = tmp_path / "calibrated.json"
    back_path.write_text(json.dumps(out))
    back = load_nuscenes(back_path)
    np.testing.assert_allclose(back.det_scores, scores)
    np.testing.assert_array_equal(back.det_cov, cov)


def test_calibrate_results_document_scores_only_and_other_dims():
    doc = results_document()
    out = calibrate_results_document(doc, np.array([0.1, 0.2, 0.3]))
    assert "cov_dims" not in out["meta"]
    assert all("covariance" not in b for v in out["results"].values() for b in v)
    cov = np.tile(np.eye(3), (3, 1, 1))
    out = calibrate_results_document(doc, np.array([0.1, 0.2, 0.3]), cov,
                                     cov_dims=("x", "y", "yaw"))
    assert out["meta"]["cov_dims"] == ["x", "y", "yaw"]


@pytest.mark.parametrize("doc, scores, kwargs, message", [
    ({"results": []}, np.zeros(0), {}, "document must be a results document"),
    ([], np.zeros(0), {}, "document must be a results document"),
    ({"results": {"a": {}}}, np.zeros(0), {}, r"results\['a'\] must be a list of box objects"),
    (None, np.full(2, 0.5), {}, "scores has 2 rows but document"),
    (None, np.full(3, 2.0), {}, "scores must hold probabilities"),
    (None, np.full(3, 0.5), {"covariances": np.ones((3, 2, 2)), "cov_dims": ("x", "y", "z")},
     r"covariances must have shape \[3, 3, 3\]"),
    (None, np.full(3, 0.5), {"covariances": np.full((3, 2, 2), np.nan)}, "covariances has NaN"),
])
def test_calibrate_results_document_refuses_bad_input(doc, scores, kwargs, message):
    with pytest.raises(ValueError, match=message):
        calibrate_results_document(results_document() if doc is None else doc, scores, **kwargs)


def _served(method="conformal", groups=("car 0-15 m", "car 15-30 m", "pooled classes 30+ m")):
    """A stand-in for `CalibratedDetections` of 3 detections at levels 0.5 and 0.9."""
    from calibrators.profile import CalibratedDetections
    from calibrators.regions import Ellipse

    regions = {} if method is None else {
        q: Ellipse(np.array([1.0, 2.0, 3.0]) * r, np.array([0.5, 1.0, 1.5]) * r,
                   np.array([0.0, 0.3, -1.2])) for q, r in ((0.5, 1.0), (0.9, 2.0))}
    return CalibratedDetections(
        labels=np.zeros(3, dtype=np.int64), scores=np.full(3, 0.5), scores_raw=np.full(3, 0.6),
        class_scores=None, covariances=np.tile(np.eye(2), (3, 1, 1)), ellipses=None,
        distances=np.array([5.0, 20.0, 40.0]), regions=regions, region_method=method,
        region_groups=None if groups is None else list(groups))


def test_ellipses_json_keys_levels_as_str_of_float():
    rows = ellipses_json(_served())
    assert list(rows[1]) == ["0.5", "0.9"]
    assert rows[1]["0.9"] == {"semi_major": 4.0, "semi_minor": 2.0, "angle": 0.3,
                              "method": "conformal", "group": "car 15-30 m"}
    gauss = ellipses_json(_served("gaussian", None))
    assert all(r["0.5"]["method"] == "gaussian" and r["0.5"]["group"] is None for r in gauss)
    assert ellipses_json(_served(None, None)) == [None, None, None]   # cov_dims lack x, y


def test_ellipses_json_refuses_non_finite_semi_axes():
    served = _served()
    served.regions[0.9].semi_major[2] = np.inf
    with pytest.raises(ValueError, match=r"ellipses\['0.9'\].semi_major has Inf at index 2"):
        ellipses_json(served)


def test_ellipses_json_writes_unbounded_regions_as_null_axes():
    served = _served()
    served.region_radii = {q: np.ones(3) for q in served.regions}
    served.region_radii[0.9][1] = np.inf
    served.regions[0.9].semi_major[1] = served.regions[0.9].semi_minor[1] = np.inf
    rows = ellipses_json(served)
    assert rows[1]["0.9"]["semi_major"] is None and rows[1]["0.9"]["semi_minor"] is None
    assert rows[1]["0.9"]["angle"] == 0.3 and rows[0]["0.9"]["semi_major"] == 2.0
    json.dumps(rows, allow_nan=False)


def test_calibrate_results_document_writes_ellipses():
    doc = results_document()
    doc["results"]["s1"][0]["ellipses"] = {"0.3": {"semi_major": 9.0}}   # replaced, not merged
    rows = ellipses_json(_served())
    out = calibrate_results_document(doc, np.array([0.1, 0.2, 0.3]), ellipses=rows)
    boxes = [b for t in ("s1", "s0") for b in out["results"][t]]
    assert [b["ellipses"] for b in boxes] == rows
    json.dumps(out, allow_nan=False)
    assert "ellipses" not in calibrate_results_document(
        results_document(), np.array([0.1, 0.2, 0.3]))["results"]["s1"][0]
    with pytest.raises(ValueError, match="ellipses has 2 rows but document"):
        calibrate_results_document(doc, np.array([0.1, 0.2, 0.3]), ellipses=rows[:2])
