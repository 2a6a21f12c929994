"""POST /v1/fit and GET /v1/jobs/{id}: uploads, background fits, failures that change nothing."""

from __future__ import annotations

import hashlib
from pathlib import Path

from calibrators.io import save_nuscenes

ADMIN = {"Authorization": "Bearer test-admin-token-0123456789"}


def test_first_fit_of_a_new_name_lands_active(empty_client, npz_bytes, wait, settings):
    r = empty_client.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz_bytes)},
                          data={"name": "cam", "holdout": "0.2"})
    assert r.status_code == 202, r.text
    accepted = r.json()
    assert r.headers["location"] == accepted["status_url"]
    assert accepted["dump_sha256"] == hashlib.sha256(npz_bytes).hexdigest()
    assert (settings.dumps_dir / accepted["dump_sha256"]).read_bytes() == npz_bytes
    job = wait(empty_client, accepted["job_id"])
    assert job["state"] == "succeeded", job
    assert job["progress"] == 1.0 and job["profile"]["id"] == "cam@1"
    assert job["options"]["holdout"] == 0.2 and job["options"]["dims"] == ["x", "y"]
    assert job["report"]["fit"]["counts"]["tp"] > 0 and job["report"]["holdout"] is not None
    versions = empty_client.get("/v1/profiles/cam").json()
    assert versions["active_version"] == 1
    detail = empty_client.get("/v1/profiles/cam/1").json()
    assert detail["profile"]["provenance"]["dump_sha256"] == accepted["dump_sha256"]
    assert detail["job_id"] == accepted["job_id"]


def test_later_fit_is_not_active_unless_asked(client, npz_bytes, wait):
    first = client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", npz_bytes)},
                        data={"cov_source": "none"})
    assert wait(client, first.json()["job_id"])["profile"]["id"] == "lidar@2"
    assert client.get("/v1/profiles/lidar").json()["active_version"] == 1
    second = client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", npz_bytes)},
                         data={"activate": "true", "cov_source": "layers"})
    assert wait(client, second.json()["job_id"])["profile"]["id"] == "lidar@3"
    assert client.get("/v1/profiles/lidar").json()["active_version"] == 3
    detail = client.get("/v1/profiles/lidar/3").json()
    assert detail["profile"]["cov_source"] == "layers" and detail["active"]


def test_failed_fit_keeps_the_active_profile(client, npz_bytes, wait):
    r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", npz_bytes)},
                    data={"min_score": "1.0", "activate": "true"})
    assert r.status_code == 202, r.text
    job = wait(client, r.json()["job_id"])
    assert job["state"] == "failed" and "min_score" in job["error"]
    assert job["profile"] is None
    assert client.get("/v1/profiles/lidar").json()["active_version"] == 1
    assert len(client.get("/v1/profiles/lidar").json()["versions"]) == 1
    assert 'detcal_fit_jobs{state="failed"} 1.0' in client.get("/metrics").text


def test_nuscenes_pair_upload(empty_client, dump_given, tmp_path: Path, wait):
    res, gt = tmp_path / "results.json", tmp_path / "gt.json"
    save_nuscenes(dump_given, res, gt)
    r = empty_client.post("/v1/fit", headers=ADMIN, data={"name": "nus"},
                          files={"results": ("r.json", res.read_bytes()),
                                 "gt": ("g.json", gt.read_bytes())})
    assert r.status_code == 202, r.text
    job = wait(empty_client, r.json()["job_id"])
    assert job["state"] == "succeeded", job
    assert job["gt_sha256"] == hashlib.sha256(gt.read_bytes()).hexdigest()


def test_jobs_listing(client, npz_bytes, wait):
    r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", npz_bytes)})
    wait(client, r.json()["job_id"])
    jobs = client.get("/v1/jobs", headers=ADMIN).json()
    assert jobs[0]["id"] == r.json()["job_id"]


def test_fit_with_logits_modulation(empty_client, npz_bytes, dump_given, wait):
    r = empty_client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", npz_bytes)},
                          data={"name": "mod", "modulation": "true"})
    assert r.status_code == 202, r.text
    job = wait(empty_client, r.json()["job_id"])
    assert job["state"] == "succeeded", job
    assert job["options"]["modulation"] is True
    detail = empty_client.get("/v1/profiles/mod/1").json()
    assert detail["profile"]["modulation"] is True
    # the fitted profile is served from every layer's logits, and refuses final logits only
    det = {"id": 0, "layer_logits": dump_given.det_logits[0].tolist(),
           "box": dump_given.det_boxes[0, -1].tolist(),
           "covariance": dump_given.det_cov[0].tolist()}
    body = {"profile": "mod", "frames": [{"frame_id": "f", "detections": [det]}]}
    assert empty_client.post("/v1/calibrate", json=body).status_code == 200
    det.pop("layer_logits")
    det["logits"] = dump_given.det_logits[0, -1].tolist()
    assert empty_client.post("/v1/calibrate", json=body).status_code == 422


def test_modulation_needs_layer_logits_at_upload(empty_client, dump_given, tmp_path: Path):
    res, gt = tmp_path / "results.json", tmp_path / "gt.json"
    save_nuscenes(dump_given, res, gt)      # nuScenes results carry final scores only
    r = empty_client.post("/v1/fit", headers=ADMIN, data={"modulation": "true"},
                          files={"results": ("r.json", res.read_bytes()),
                                 "gt": ("g.json", gt.read_bytes())})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "modulation"]
    assert empty_client.get("/v1/jobs", headers=ADMIN).json() == []


def test_the_openapi_example_of_fit_is_accepted(client, wait):
    """The multipart example the schema publishes (text parts) gets a 202; its one-box fit
    then fails with the reason, and the active profile stays."""
    content = client.get("/openapi.json").json()["paths"]["/v1/fit"]["post"]["requestBody"][
        "content"]["multipart/form-data"]
    (example,) = [e["value"] for e in content["examples"].values()]
    files = {k: (f"{k}.json", v) for k, v in example.items() if k in ("results", "gt")}
    data = {k: v for k, v in example.items() if k not in files}
    r = client.post("/v1/fit", headers=ADMIN, files=files, data=data)
    assert r.status_code == 202, r.text
    job = wait(client, r.json()["job_id"])
    assert job["state"] in ("succeeded", "failed") and (job["state"] == "succeeded"
                                                        or job["error"])
    assert client.get("/v1/profiles/lidar").json()["active_version"] == 1
