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


def test_detect_sends_the_group_heads_hypotheses_and_labels(seeded):
    """A group-head detector's box hypotheses reach a profile that serves only them (without
    them it would be a 422), and every detection keeps the class the top-K decoder gave it."""
    from dataclasses import replace

    import torch

    from app.store import Store
    from calibrators import fit_profile
    from calibrators.data import synthetic_dump
    from detectors.model import Detector
    from detectors.registry import detector_config

    dump = synthetic_dump(n_frames=20, seed=0, n_hypotheses=6, with_cov=False)
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("hyp", fit_profile(dump, cov_source="hypotheses",
                                         other_sources=False).to_json())
    store.close()
    app = create_app(seeded)
    torch.manual_seed(0)
    model = Detector(replace(detector_config("lidar"), head="group", token_stride=4)).eval()
    app.state.detectors._models["lidar"] = model
    with TestClient(app) as c:
        r = c.post("/v1/detect", json={"sensor": "lidar", "seed": 7, "min_score": 0.0,
                                       "profile": "hyp"})
    assert r.status_code == 200, r.text
    dets = r.json()["frames"][0]["detections"]
    assert 50 < len(dets) <= 100   # the 100 best pairs, less what circle NMS drops
    raw = [d["score_raw"] for d in dets]
    assert raw == sorted(raw, reverse=True)
    # the same pairs straight from the model: (label, raw score) per detection, in order
    from detectors.infer import detect
    from detectors.sim import make_frame

    points = torch.from_numpy(make_frame(7, "lidar").sensor_frame.points.astype("float32"))
    (det,) = list(detect(model, [points], max_detections=100))
    assert [d["label_index"] for d in dets] == det.labels.tolist()
    assert raw == pytest.approx(det.scores.double().tolist(), rel=1e-6)
