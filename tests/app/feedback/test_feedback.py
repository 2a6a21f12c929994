"""POST /v1/feedback and GET /v1/profiles/{name}/health on a real app (TestClient, SQLite)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from app.http.deps import token_id
from app.main import create_app
from calibrators import CalibrationProfile, summarize
from calibrators.data import DEFAULT_DEPTH_K, synthetic_dump
from tests.app.conftest import ADMIN, TOKEN
from tests.app.feedback_frames import feedback_frames, npz_bytes

FB, HEALTH = "/v1/feedback", "/v1/profiles/lidar/health"


@pytest.fixture(scope="module")
def labelled():
    """Feedback frames from the world the `lidar` profile was fit on (another seed)."""
    return synthetic_dump(n_frames=24, seed=11)


def _locs(r) -> list:
    return [e["loc"] for e in r.json()["detail"]]


def test_json_feedback_gives_the_figures_the_library_gives_offline(client, labelled,
                                                                   profile_json_given):
    r = client.post(FB, headers=ADMIN, json={"profile": "lidar",
                                             "frames": feedback_frames(labelled)})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["profile"]["id"] == "lidar@1" and body["frames"] == 24
    assert body["tp"] > 0 and body["frames_total"] == 24 and body["status"] == "ok"
    doc = client.get(HEALTH).json()
    summary = summarize(labelled, CalibrationProfile.from_json(profile_json_given)).to_dict()
    win = doc["since_activation"]
    assert win == doc["window"] and win["frames"] == 24
    assert win["ece"]["value"] == pytest.approx(summary["classification"]["ece"]["after"])
    assert win["ece"]["lower"] <= win["ece"]["value"] <= win["ece"]["upper"]
    assert win["tp"] == summary["counts"]["tp"]
    ours = [c["coverage"] for c in win["coverage"]["overall"]]
    offline = summary["regions"]["coverage"]["overall"]
    assert summary["regions"]["levels"] == win["coverage"]["levels"]
    assert ours == pytest.approx(offline)
    for cell in win["coverage"]["cells"]:
        for lo, cov, hi in zip(cell["lower"], cell["coverage"], cell["upper"], strict=True):
            assert lo <= cov <= hi
    assert doc["status"] == "ok" and doc["reasons"] == []
    assert doc["series"][-1]["frames_total"] == 24


def test_a_dump_upload_by_alias_counts_for_that_version(client, labelled):
    client.put("/v1/profiles/lidar/aliases/challenger", headers=ADMIN, json={"version": 1})
    r = client.post(FB, headers=ADMIN, files={"dump": ("fb.npz", npz_bytes(labelled))},
                    data={"profile": "lidar@challenger"})
    assert r.status_code == 200, r.text
    assert r.json()["profile"]["id"] == "lidar@1" and r.json()["frames_total"] == 24
    assert client.get(HEALTH, params={"alias": "challenger"}).json()["window"]["frames"] == 24


def test_health_survives_a_restart(seeded, labelled):
    with TestClient(create_app(seeded)) as c:
        assert c.post(FB, headers=ADMIN, json={"frames": feedback_frames(labelled)}
                      ).status_code == 200
        before = c.get(HEALTH).json()
    with TestClient(create_app(seeded)) as c:
        assert c.get(HEALTH).json() == before


def test_feedback_from_a_shifted_world_degrades_the_version(client):
    shifted = synthetic_dump(n_frames=80, seed=12,
                             depth_k={k: 6 * v for k, v in DEFAULT_DEPTH_K.items()})
    r = client.post(FB, headers=ADMIN, json={"frames": feedback_frames(shifted)})
    assert r.status_code == 200 and r.json()["status"] == "degraded"
    assert r.json()["new_alarms"]
    doc = client.get(HEALTH).json()
    assert doc["status"] == "degraded" and doc["reasons"] == [a["reason"] for a in doc["alarms"]]
    assert "ellipses miss more than" in " ".join(doc["reasons"])
    assert any(p["status"] == "degraded" for p in doc["series"])
    text = client.get("/metrics").text
    assert 'detcal_profile_health_status{profile="lidar",status="degraded",version="1"} 1.0' \
        in text
    assert 'detcal_drift_alarms_total{profile="lidar",version="1"}' in text


def test_a_version_without_feedback_is_insufficient(client):
    doc = client.get("/v1/profiles/layers/health").json()
    assert doc["status"] == "insufficient" and doc["window"]["frames"] == 0
    assert doc["window"]["ece"]["value"] is None and "0 feedback frame" in doc["reasons"][0]


def test_feedback_needs_the_admin_token_and_a_refused_one_leaves_no_trace(client, labelled):
    body = {"frames": feedback_frames(labelled)}
    assert client.post(FB, json=body).status_code == 401
    assert client.post(FB, json=body, headers={"Authorization": "Bearer nope"}).status_code == 403
    assert client.get("/v1/audit", headers=ADMIN).json()["entries"] == []
    assert client.get(HEALTH).json()["window"]["frames"] == 0


@pytest.mark.parametrize(("mutate", "loc"), [
    (lambda f: f[0]["detections"][0].update(logits=None, score=0.5, label="car"),
     ["body", "frames", 0, "detections", 0, "score"]),
    (lambda f: f[0]["ground_truth"][0].update(label="zebra"),
     ["body", "frames", 0, "ground_truth", 0, "label"]),
    (lambda f: f[0]["ground_truth"][0].update(box=[1.0, 2.0]),
     ["body", "frames", 0, "ground_truth", 0, "box"]),
    (lambda f: f[0].pop("ground_truth"), ["body", "frames", 0, "ground_truth"]),
    (lambda f: f[0]["detections"][0].pop("covariance"), ["body", "frames", 0, "detections", 1]),
    (lambda f: f[0]["detections"][0].update(logits=[1.0, 2.0]), ["body", "frames"]),
])
def test_bad_json_feedback_is_a_422_naming_the_field(client, labelled, mutate, loc):
    frames = feedback_frames(labelled.select_frames(labelled.frame_ids == labelled.frame_ids[0]))
    for det in frames[0]["detections"]:
        det.pop("score", None)
    mutate(frames)
    frames[0]["detections"][0] = {k: v for k, v in frames[0]["detections"][0].items()
                                  if v is not None}
    r = client.post(FB, headers=ADMIN, json={"frames": frames})
    assert r.status_code == 422, r.text
    assert loc in _locs(r)


@pytest.mark.parametrize(("request_kwargs", "status", "loc"), [
    ({"files": {"dump": ("x.npz", b"not a zip")}}, 422, ["body", "dump"]),
    ({"data": {"profile": "lidar"}}, 422, ["body", "dump"]),
    ({"files": {"dump": ("x.npz", b"")}, "data": {"profile": ""}}, 422, ["body", "profile"]),
    ({"files": {"dump": ("x.npz", b"x")}, "data": {"other": "1"}}, 422, ["body", "other"]),
    ({"files": {"dump": ("x.npz", b"x")}, "data": {"profile": "lidar@x!"}}, 422,
     ["body", "profile"]),
    ({"content": b"x", "headers": {"content-type": "text/plain"}}, 415,
     ["header", "content-type"]),
    ({"json": {"frames": []}}, 422, ["body", "frames"]),
    ({"json": {"profile": "lidar@0", "frames": [{"detections": [], "ground_truth": []}]}}, 422,
     ["body", "profile"]),
])
def test_bad_feedback_requests_name_the_field(client, request_kwargs, status, loc):
    headers = {**ADMIN, **request_kwargs.pop("headers", {})}
    r = client.post(FB, headers=headers, **request_kwargs)
    assert r.status_code == status, r.text
    assert loc in _locs(r)


def test_unknown_profiles_are_404(client, labelled):
    r = client.post(FB, headers=ADMIN, json={"profile": "nope", "frames": [
        {"detections": [], "ground_truth": []}]})
    assert r.status_code == 404
    assert client.get("/v1/profiles/nope/health").status_code == 404
    assert client.get(HEALTH, params={"alias": "ghost"}).status_code == 404
    r = client.get(HEALTH, params={"alias": "x", "version": 1})
    assert r.status_code == 422 and _locs(r) == [["query", "alias"]]


def test_a_dump_of_other_classes_is_a_422_at_dump(client):
    other = synthetic_dump(n_frames=2, seed=1, classes=("car", "truck"))
    r = client.post(FB, headers=ADMIN, files={"dump": ("o.npz", npz_bytes(other))})
    assert r.status_code == 422 and _locs(r) == [["body", "dump"]]
    assert "classes" in r.text


def test_a_feedback_token_may_send_feedback_and_nothing_else(seeded, labelled):
    settings = seeded.model_copy(update={"feedback_token": SecretStr("labeller-token-0123456789")})
    fb = {"Authorization": "Bearer labeller-token-0123456789"}
    with TestClient(create_app(settings)) as c:
        r = c.post(FB, headers=fb, json={"frames": feedback_frames(labelled)})
        assert r.status_code == 200, r.text
        assert c.post(FB, json={"frames": []}).status_code == 401     # before the body
        assert c.post(FB, headers={"Authorization": "Bearer x"},
                      json={"frames": []}).status_code == 403
        assert c.put("/v1/profiles/lidar/aliases/x", headers=fb,
                     json={"version": 1}).status_code == 403
        assert c.post("/v1/profiles/lidar/1/activate", headers=fb).status_code == 403
        (entry,) = c.get("/v1/audit", headers=ADMIN).json()["entries"]
        assert entry["action"] == "feedback" and entry["token_id"] != token_id(TOKEN)
        assert entry["token_id"] == token_id("labeller-token-0123456789")


def test_a_dump_upload_has_the_upload_limit_and_json_the_request_limit(seeded, labelled):
    """A multipart dump over the request limit but within the upload limit is taken; a JSON
    body over the request limit is a 413 before it is read."""
    body = npz_bytes(labelled)
    settings = seeded.model_copy(update={"max_request_bytes": len(body) // 2,
                                         "max_upload_bytes": 4 * len(body)})
    with TestClient(create_app(settings)) as c:
        r = c.post(FB, headers=ADMIN, files={"dump": ("fb.npz", body)})
        assert r.status_code == 200, r.text
        r = c.post(FB, headers={**ADMIN, "content-type": "application/json"},
                   content=b"{" + b" " * len(body) + b"}")
        assert r.status_code == 413


def _gauges(text: str, name: str) -> dict[str, float]:
    """`{labels: value}` of one metric family in a Prometheus exposition."""
    out = {}
    for line in text.splitlines():
        if line.startswith(name + "{"):
            labels, value = line[len(name):].rsplit(" ", 1)
            out[labels] = float(value)
    return out


def test_metrics_carry_the_rolling_window_the_health_document_shows(seeded, labelled):
    """/metrics has the window's ECE, coverage and frames beside the all-feedback ones, and
    they are the health document's `window` figures (the window shorter than the feedback)."""
    with TestClient(create_app(seeded.model_copy(update={"health_window_frames": 10}))) as c:
        frames = feedback_frames(labelled)
        for chunk in (frames[:12], frames[12:]):
            assert c.post(FB, headers=ADMIN, json={"frames": chunk}).status_code == 200
        doc = c.get(HEALTH).json()
        text = c.get("/metrics").text
    win, key = doc["window"], '{profile="lidar",version="1"}'
    assert win["frames"] == 12 and doc["since_activation"]["frames"] == 24
    assert _gauges(text, "detcal_profile_health_window_frames") == {key: 12.0}
    assert _gauges(text, "detcal_profile_health_frames") == {key: 24.0}
    assert _gauges(text, "detcal_profile_health_window_ece")[key] == pytest.approx(
        win["ece"]["value"], rel=1e-9)
    coverage = _gauges(text, "detcal_profile_health_window_coverage")
    for entry in win["coverage"]["overall"]:
        level = f'{{level="{entry["level"]:g}",profile="lidar",version="1"}}'
        assert coverage[level] == pytest.approx(entry["coverage"], rel=1e-9)
    assert coverage != _gauges(text, "detcal_profile_health_coverage")
