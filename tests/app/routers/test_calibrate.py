"""POST /v1/calibrate and /v1/calibrate/nuscenes against real fitted profiles."""

from __future__ import annotations

import json
import math

import numpy as np

from calibrators.profile import CalibrationProfile
from calibrators.scores import predict


def test_logits_are_calibrated_as_the_library_does(client, detection, dump_given,
                                                   profile_json_given):
    idx = list(range(40))
    dets = [detection(dump_given, i) for i in idx]
    body = {"frames": [{"frame_id": "f0", "detections": dets}]}
    r = client.post("/v1/calibrate", json=body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["profile"]["id"] == "lidar@1" and out["cov_dims"] == ["x", "y"]
    dets = out["frames"][0]["detections"]
    assert [d["id"] for d in dets] == idx
    prof = CalibrationProfile.from_json(profile_json_given)
    ref = prof.calibrate(logits=dump_given.det_logits[idx, -1],
                         boxes=dump_given.det_boxes[idx, -1], covariances=dump_given.det_cov[idx])
    np.testing.assert_allclose([d["score"] for d in dets], ref.scores)
    np.testing.assert_allclose([d["covariance"] for d in dets], ref.covariances)
    np.testing.assert_allclose([d["ellipse"]["semi_major"] for d in dets], ref.ellipses.semi_major)
    labels, raw = predict(dump_given.det_logits[idx, -1], "sigmoid")
    assert [d["label_index"] for d in dets] == labels.tolist()       # arg-max kept
    np.testing.assert_allclose([d["score_raw"] for d in dets], raw)
    if ref.class_scores is None:   # a per-class score stage (docs/api.md: when it is null)
        assert prof.score_calibration is not None
        assert all(d["class_scores"] is None for d in dets)
    else:
        np.testing.assert_allclose([d["class_scores"] for d in dets], ref.class_scores)
    assert prof.temperature > 1.0
    assert all(d["score"] != d["score_raw"] for d in dets)


def test_ellipses_grow_with_distance(client):
    dets = [{"score": 0.8, "label": "car", "box": [d, 0, 1, 2, 4.5, 1.6, 0, 0, 0],
             "covariance": [[0.05, 0.0], [0.0, 0.05]]} for d in (5.0, 20.0, 40.0, 60.0)]
    r = client.post("/v1/calibrate", json={"frames": [{"detections": dets}],
                                           "ellipse_confidence": 0.9})
    assert r.status_code == 200, r.text
    rows = r.json()["frames"][0]["detections"]
    major = [d["ellipse"]["semi_major"] for d in rows]
    assert major == sorted(major) and major[0] < major[-1]
    assert rows[0]["ellipse"]["confidence"] == 0.9
    assert [d["distance"] for d in rows] == [5.0, 20.0, 40.0, 60.0]
    assert rows[0]["class_scores"] is None


def test_ego_translation_sets_the_distance(client):
    det = {"score": 0.5, "label": 0, "box": [110, 0, 1, 2, 4, 1.5, 0],
           "covariance": [[0.1, 0], [0, 0.1]]}
    r = client.post("/v1/calibrate", json={"frames": [
        {"frame_id": "a", "ego_translation": [100, 0, 0], "detections": [det]}]})
    assert r.status_code == 200, r.text
    assert math.isclose(r.json()["frames"][0]["detections"][0]["distance"], 10.0)


def test_mixed_evidence_forms_keep_request_order(client, detection, dump_given):
    a = detection(dump_given, 0)
    b = {"score": 0.7, "label": "pedestrian", "box": [3, 4, 0, 1, 1, 2, 0, 0, 0],
         "covariance": [[0.1, 0], [0, 0.1]], "id": "b"}
    p = 1 / (1 + np.exp(-dump_given.det_logits[1, -1]))
    c = {"scores": p.tolist(), "box": dump_given.det_boxes[1, -1].tolist(),
         "covariance": dump_given.det_cov[1].tolist(), "id": "c"}
    d = {"layer_logits": dump_given.det_logits[2].tolist(),
         "layer_boxes": dump_given.det_boxes[2].tolist(),
         "covariance": dump_given.det_cov[2].tolist(), "id": "d"}
    r = client.post("/v1/calibrate", json={"frames": [{"detections": [a, b]},
                                                      {"detections": [c, d]}]})
    assert r.status_code == 200, r.text
    frames = r.json()["frames"]
    assert [x["id"] for x in frames[0]["detections"]] == [0, "b"]
    assert [x["id"] for x in frames[1]["detections"]] == ["c", "d"]
    assert frames[0]["detections"][1]["label"] == "pedestrian"
    assert math.isclose(frames[0]["detections"][1]["distance"], 5.0)


def test_named_version_and_layers_profile(client, detection, dump_given):
    det = detection(dump_given, 3, cov=False, layers=True)
    r = client.post("/v1/calibrate", json={"profile": "layers@1", "frames": [{"detections":
                                                                           [det]}]})
    assert r.status_code == 200, r.text
    assert r.json()["profile"]["id"] == "layers@1"


def test_detections_counter_and_route_metrics(client, detection, dump_given):
    body = {"frames": [{"detections": [detection(dump_given, i) for i in range(7)]}]}
    assert client.post("/v1/calibrate", json=body).status_code == 200
    text = client.get("/metrics").text
    assert 'detcal_detections_calibrated_total{profile="lidar"} 7.0' in text
    assert 'route="/v1/calibrate"' in text
    assert 'detcal_active_profile_version{profile="lidar"} 1.0' in text
    assert 'detcal_fit_jobs{state="queued"} 0.0' in text


def test_nuscenes_document_round_trip(client):
    doc = {"meta": {"use_lidar": True}, "results": {"tok-a": [{
        "sample_token": "tok-a", "translation": [120.0, 50.0, 1.0], "size": [1.9, 4.6, 1.7],
        "rotation": [1.0, 0.0, 0.0, 0.0], "velocity": [1.0, 0.0], "detection_name": "car",
        "detection_score": 0.8, "attribute_name": "vehicle.moving", "num_pts": 12,
        "ego_translation": [20.0, 0.0, 1.0], "covariance": [[0.1, 0.0], [0.0, 0.1]]}]}}
    r = client.post("/v1/calibrate/nuscenes?ellipse_confidence=0.5", json=doc)
    assert r.status_code == 200, r.text
    out = r.json()
    box = out["results"]["tok-a"][0]
    assert box["detection_score_raw"] == 0.8 and box["detection_score"] != 0.8
    assert box["num_pts"] == 12 and box["translation"] == [120.0, 50.0, 1.0]
    assert len(box["covariance"]) == 2 and box["covariance"][0][0] > 0.1   # k·d added, d = 20
    assert out["meta"] == {"use_lidar": True}
    assert out["calibration"]["cov_dims"] == ["x", "y"]                 # the dims of Σ' written
    assert out["calibration"]["profile"]["id"] == "lidar@1"
    json.dumps(out, allow_nan=False)
