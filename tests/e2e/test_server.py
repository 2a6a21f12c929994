"""End to end: a real `detcal serve` process driven over HTTP with httpx.

Fit from an uploaded dump, watch the job, calibrate, fit a second version, activate and roll
back, restart the process and find everything still there, and a table of bad inputs.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators.scores import predict
from tests.e2e.conftest import ADMIN

pytestmark = pytest.mark.e2e


def _body(dump, idx, **kw) -> dict:
    dets = [{"id": int(i), "logits": dump.det_logits[i, -1].tolist(),
             "box": dump.det_boxes[i, -1].tolist(), "covariance": dump.det_cov[i].tolist()}
            for i in idx]
    return {"frames": [{"frame_id": "f", "detections": dets}], **kw}


def test_fit_job_succeeds_and_first_version_is_active(http, fitted):
    assert fitted["state"] == "succeeded", fitted
    assert fitted["profile"]["id"] == "lidar@1" and fitted["progress"] == 1.0
    assert fitted["report"]["fit"]["counts"]["tp"] > 0
    assert http.get("/v1/profiles/lidar").json()["active_version"] == 1
    assert http.get("/readyz").json()["checks"]["profile"] == "lidar@1"


def test_calibrate_changes_scores_not_labels_and_ellipses_grow(http, fitted, dump):
    idx = np.arange(60)
    r = http.post("/v1/calibrate", json=_body(dump, idx))
    assert r.status_code == 200, r.text
    rows = r.json()["frames"][0]["detections"]
    labels, raw = predict(dump.det_logits[idx, -1], "sigmoid")
    assert [d["label_index"] for d in rows] == labels.tolist()
    np.testing.assert_allclose([d["score_raw"] for d in rows], raw)
    assert all(abs(d["score"] - d["score_raw"]) > 1e-9 for d in rows)
    k = http.get("/v1/profiles/lidar/1").json()["profile"]["depth_k"]["car"]
    assert k > 0
    cov = [[0.05, 0.0], [0.0, 0.05]]
    dets = [{"score": 0.7, "label": "car", "box": [d, 0, 1, 1.9, 4.6, 1.7, 0, 0, 0],
             "covariance": cov} for d in (5, 15, 30, 45, 60)]
    rows = http.post("/v1/calibrate", json={"frames": [{"detections": dets}]}).json()[
        "frames"][0]["detections"]
    # within one conformal cell (30+ m: one radius) the ellipse grows with Σ' = Σ + k·d·I;
    # across cells each cell's own radius serves (a near cell's tail floor may be wider)
    major = [d["ellipse"]["semi_major"] for d in rows[2:]]
    assert all(b > a for a, b in zip(major, major[1:], strict=False)), major
    np.testing.assert_allclose([d["covariance"][0][0] for d in rows],
                               [0.05 + k * d for d in (5, 15, 30, 45, 60)])


def test_second_version_activate_and_roll_back(http, fitted, dump_npz, admin, wait, dump):
    # the session's server is shared (the schemathesis run fits and activates too): compare
    # with what it holds now, not with fixed version numbers
    before = http.get("/v1/profiles/lidar").json()
    old = before["active_version"]
    r = http.post("/v1/fit", headers=admin, files={"dump": ("val.npz", dump_npz)},
                  data={"name": "lidar", "cov_source": "given", "threshold": "1.5"})
    assert r.status_code == 202
    job = wait(http, r.json()["job_id"])
    new = max(v["version"] for v in before["versions"]) + 1
    assert job["state"] == "succeeded" and job["profile"]["id"] == f"lidar@{new}"
    assert http.get("/v1/profiles/lidar").json()["active_version"] == old  # not activated
    assert http.post(f"/v1/profiles/lidar/{new}/activate", headers=admin).status_code == 200
    body = _body(dump, [0, 1, 2])
    assert http.post("/v1/calibrate", json=body).json()["profile"]["id"] == f"lidar@{new}"
    assert http.post(f"/v1/profiles/lidar/{old}/activate", headers=admin).status_code == 200
    assert http.post("/v1/calibrate", json=body).json()["profile"]["id"] == f"lidar@{old}"
    pinned = http.post("/v1/calibrate", json={**body, "profile": f"lidar@{new}"}).json()
    assert pinned["profile"]["id"] == f"lidar@{new}"


def test_failed_fit_leaves_active_profile_serving(http, fitted, dump_npz, admin, wait):
    old = http.get("/v1/profiles/lidar").json()["active_version"]
    r = http.post("/v1/fit", headers=admin, files={"dump": ("val.npz", dump_npz)},
                  data={"name": "lidar", "min_score": "1.0", "activate": "true"})
    job = wait(http, r.json()["job_id"])
    assert job["state"] == "failed" and job["error"]
    assert http.get("/v1/profiles/lidar").json()["active_version"] == old


def test_nuscenes_document(http, fitted, dump, tmp_path):
    from calibrators.io import save_nuscenes

    res, gt = tmp_path / "r.json", tmp_path / "g.json"
    save_nuscenes(dump.select_frames(np.arange(dump.n_frames) < 2), res, gt)
    doc = json.loads(res.read_text())
    r = http.post("/v1/calibrate/nuscenes", json=doc)
    assert r.status_code == 200, r.text
    out = r.json()
    token = next(iter(out["results"]))
    box = out["results"][token][0]
    assert {"detection_score", "detection_score_raw", "covariance"} <= set(box)
    assert out["calibration"]["profile"]["name"] == "lidar"


BAD = [
    ("nan", b'{"frames":[{"detections":[{"score":NaN,"label":"car","box":[1,0,0,1,1,1,0]}]}]}',
     "application/json", 422),
    ("inf", b'{"frames":[{"detections":[{"score":0.5,"label":"car","box":[Infinity,0,0,1,1,1,0'
            b']}]}]}', "application/json", 422),
    ("shape", b'{"frames":[{"detections":[{"logits":[1,2],"box":[1,0,0,1,1,1,0],'
              b'"covariance":[[1,0],[0,1]]}]}]}', "application/json", 422),
    ("non-psd", b'{"frames":[{"detections":[{"score":0.5,"label":"car","box":[1,0,0,1,1,1,0],'
                b'"covariance":[[1,3],[3,1]]}]}]}', "application/json", 422),
    ("class", b'{"frames":[{"detections":[{"score":0.5,"label":"zeppelin","box":[1,0,0,1,1,1,0],'
              b'"covariance":[[1,0],[0,1]]}]}]}', "application/json", 422),
    ("profile", b'{"profile":"nope","frames":[{"detections":[]}]}', "application/json", 404),
    ("empty", b"", "application/json", 422),
    ("content-type", b"frames", "text/plain", 415),
    ("oversized", b"[" + b"0," * 5_000_000 + b"0]", "application/json", 413),
]


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_bad_inputs_are_4xx(http, fitted, case):
    _, content, ctype, status = case
    r = http.post("/v1/calibrate", content=content, headers={"content-type": ctype})
    assert r.status_code == status, r.text


def test_admin_token_rules(http, fitted):
    assert http.post("/v1/profiles/lidar/1/activate").status_code == 401
    wrong = {"Authorization": "Bearer not-the-token"}
    assert http.post("/v1/profiles/lidar/1/activate", headers=wrong).status_code == 403
    assert http.post("/v1/fit", headers=wrong, files={"dump": ("x", b"x")}).status_code == 403


def test_metrics_after_traffic(http, fitted):
    text = http.get("/metrics").text
    assert "detcal_http_request_duration_seconds_bucket" in text
    assert 'detcal_fit_jobs{state="succeeded"}' in text
    assert "detcal_detections_calibrated_total" in text


def test_restart_keeps_profiles_and_jobs(http, server, fitted):
    before = http.get("/v1/profiles/lidar").json()
    server.restart()
    after = http.get("/v1/profiles/lidar").json()
    assert after == before
    assert http.get(f"/v1/jobs/{fitted['id']}", headers=ADMIN).json()["state"] == "succeeded"
    assert http.get("/readyz").status_code == 200
    assert server.starts == 2
