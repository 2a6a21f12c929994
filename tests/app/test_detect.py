"""POST /v1/detect: a bundled detector on a simulated frame, calibrated in the same response.

Uses the shipped lidar weights when present; otherwise a freshly initialised lidar detector
(the real model, untrained) so the whole path still runs.
"""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from app.main import create_app

detectors = pytest.importorskip("detectors")


@pytest.fixture
def detect_client(seeded):
    import torch

    from detectors import build_detector
    from detectors.registry import weights_path

    torch.set_num_threads(1)
    app = create_app(seeded)
    if not weights_path("lidar").exists():
        app.state.detectors._models["lidar"] = build_detector("lidar", pretrained=False).eval()
    with TestClient(app) as c:
        yield c


def test_detect_on_a_simulated_frame(detect_client):
    r = detect_client.post("/v1/detect", json={"sensor": "lidar", "seed": 7, "min_score": 0.0,
                                               "profile": "layers"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["sensor"] == "lidar" and body["seed"] == 7
    assert body["profile"]["id"] == "layers@1" and body["ground_truth"]
    dets = body["frames"][0]["detections"]
    assert 0 < len(dets) <= 100
    assert all(d["ellipse"]["semi_major"] >= d["ellipse"]["semi_minor"] >= 0 for d in dets)
    raw = [d["score_raw"] for d in dets]
    assert raw == sorted(raw, reverse=True)


def test_detect_with_a_given_profile_uses_layer_spread(detect_client):
    r = detect_client.post("/v1/detect", json={"seed": 7, "min_score": 0.0})
    assert r.status_code == 200, r.text
    assert r.json()["profile"]["id"] == "lidar@1"


def test_detect_points_of_the_wrong_width(detect_client):
    r = detect_client.post("/v1/detect", json={"points": [[0.0, 1.0]], "profile": "layers"})
    assert r.status_code == 422 and "columns" in r.text
