"""A request that does not match its profile: a detect of another sensor is served with a
warning (or with the profile named after the sensor), a calibrate whose class list differs
from the profile's is a 422 saying what differs."""

from __future__ import annotations

import json

import pytest

from calibrators import CalibrationProfile

pytest.importorskip("torch")


def test_detect_of_a_sensor_without_its_profile_is_warned(client):
    r = client.post("/v1/detect", json={"sensor": "camera", "seed": 1})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["profile"]["name"] == "lidar"                  # the default profile
    assert len(body["warnings"]) == 1
    assert "no profile is named 'camera'" in body["warnings"][0]
    assert "lidar@1" in body["warnings"][0]
    named = client.post("/v1/detect", json={"sensor": "camera", "seed": 1, "profile": "lidar"})
    assert "named after another sensor" in named.json()["warnings"][0]
    same = client.post("/v1/detect", json={"sensor": "lidar", "seed": 1})
    assert same.status_code == 200 and same.json()["warnings"] == []


def test_detect_uses_the_profile_named_after_its_sensor(client, profile_json_given):
    client.app.state.store.add_profile("camera", profile_json_given)
    r = client.post("/v1/detect", json={"sensor": "camera", "seed": 1})
    assert r.status_code == 200, r.text
    assert r.json()["profile"]["name"] == "camera" and r.json()["warnings"] == []


def _request(classes: list[str] | None, profile_json: str) -> dict:
    profile = CalibrationProfile.from_json(profile_json)
    det = {"logits": [0.0] * len(profile.classes), "box": [5.0, 1.0, 0, 2, 4, 1.5, 0, 0, 0],
           "covariance": [[0.1, 0.0], [0.0, 0.1]]}
    body = {"frames": [{"frame_id": "f0", "detections": [det]}]}
    return body if classes is None else {**body, "classes": classes}


def test_calibrate_with_the_profiles_classes_is_served(client, profile_json_given):
    classes = list(CalibrationProfile.from_json(profile_json_given).classes)
    for sent in (None, classes):
        r = client.post("/v1/calibrate", json=_request(sent, profile_json_given))
        assert r.status_code == 200, r.text


def test_calibrate_with_other_classes_is_a_422_saying_what_differs(client, profile_json_given):
    classes = list(CalibrationProfile.from_json(profile_json_given).classes)
    cases = {"missing " + classes[-1]: classes[:-1] + ["boat"],
             "same classes in another order": [classes[1], classes[0], *classes[2:]]}
    for says, sent in cases.items():
        r = client.post("/v1/calibrate", content=json.dumps(_request(sent, profile_json_given)),
                        headers={"Content-Type": "application/json"})
        assert r.status_code == 422, r.text
        item = r.json()["detail"][0]
        assert item["loc"] == ["body", "classes"] and says in item["msg"], item
    assert "not in the profile: boat" in client.post(
        "/v1/calibrate", json=_request(classes[:-1] + ["boat"], profile_json_given)).text
