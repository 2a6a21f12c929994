"""calibrators.io: results documents without ground truth, covariances over other dims, and
the ellipses of calibrated results documents (`ellipses_json`)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from calibrators.io import ellipses_json, load_nuscenes, save_nuscenes
from tests.calibrators.io.dump_cases import CLASSES, devkit_box, nusc_dump, write_pair


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
        region_groups=None if groups is None else list(groups),
        region_guarantees={} if method is None else {
            q: np.array(["cell", "pooled", "marginal"] if groups else ["none"] * 3, dtype=object)
            for q in regions},
        region_counts={} if method is None else {
            q: np.array([120, 300, 900] if groups else [-1] * 3) for q in regions})


def test_ellipses_json_keys_levels_as_str_of_float():
    rows = ellipses_json(_served())
    assert list(rows[1]) == ["0.5", "0.9"]
    assert rows[1]["0.9"] == {"semi_major": 4.0, "semi_minor": 2.0, "angle": 0.3,
                              "method": "conformal", "group": "car 15-30 m",
                              "guarantee": "pooled", "calibration_n": 300}
    gauss = ellipses_json(_served("gaussian", None))
    assert all(r["0.5"]["method"] == "gaussian" and r["0.5"]["group"] is None
               and r["0.5"]["guarantee"] == "none" and r["0.5"]["calibration_n"] is None
               for r in gauss)
    assert ellipses_json(_served(None, None)) == [None, None, None]   # cov_dims lack x, y


def test_ellipses_json_refuses_non_finite_semi_axes():
    served = _served()
    served.regions[0.9].semi_major[2] = np.inf
    with pytest.raises(ValueError, match=r"ellipses\['0.9'\].semi_major has Inf at index 2"):
        ellipses_json(served)


def test_ellipses_json_writes_unbounded_regions_as_null_axes():
    served = _served()
    served = dataclasses.replace(served, region_radii={q: np.ones(3) for q in served.regions})
    served.region_radii[0.9][1] = np.inf
    served.regions[0.9].semi_major[1] = served.regions[0.9].semi_minor[1] = np.inf
    rows = ellipses_json(served)
    assert rows[1]["0.9"]["semi_major"] is None and rows[1]["0.9"]["semi_minor"] is None
    assert rows[1]["0.9"]["angle"] == 0.3 and rows[0]["0.9"]["semi_major"] == 2.0
    json.dumps(rows, allow_nan=False)


