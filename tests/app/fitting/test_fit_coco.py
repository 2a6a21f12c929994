"""POST /v1/fit with a COCO pair (`coco_results` + `coco_gt`): a fit job that lands a 2-D
profile, served by POST /v1/calibrate; the pair bounded and checked before a job is queued,
each refusal naming its field."""

from __future__ import annotations

import hashlib
import json

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from calibrators.boxes2d import synthetic_coco
from tests.app.conftest import ADMIN, TOKEN


@pytest.fixture(scope="module")
def coco_files() -> tuple[bytes, bytes]:
    results, instances = synthetic_coco(300, seed=4)
    return json.dumps(results).encode(), json.dumps(instances).encode()


def _fit(client: TestClient, results: bytes, gt: bytes, **data: str):
    return client.post("/v1/fit", headers=ADMIN, data=data,
                       files={"coco_results": ("r.json", results), "coco_gt": ("g.json", gt)})


def test_a_coco_pair_fits_a_stored_2d_profile_that_serves(empty_client, coco_files, wait,
                                                          settings):
    results, gt = coco_files
    r = _fit(empty_client, results, gt, name="cam2d", holdout="0.25", iou_threshold="0.5")
    assert r.status_code == 202, r.text
    accepted = r.json()
    assert accepted["dump_sha256"] == hashlib.sha256(results).hexdigest()
    assert (settings.dumps_dir / accepted["dump_sha256"]).read_bytes() == results
    job = wait(empty_client, accepted["job_id"])
    assert job["state"] == "succeeded", job
    assert job["profile"]["id"] == "cam2d@1"
    assert job["gt_sha256"] == hashlib.sha256(gt).hexdigest()
    assert job["options"]["holdout"] == 0.25 and "cov_source" not in job["options"]
    held = job["report"]["holdout"]
    assert held["ece"]["calibrated"] < held["ece"]["raw"]
    profile = empty_client.get("/v1/profiles/cam2d/1").json()["profile"]
    assert profile["kind"] == "boxes2d"
    assert profile["provenance"]["results_sha256"] == accepted["dump_sha256"]
    assert profile["provenance"]["instances_sha256"] == job["gt_sha256"]
    assert [c["name"] for c in profile["categories"]] == ["car", "person"]
    record = json.loads(results)[0]
    body = {"profile": "cam2d", "levels": [0.9], "images": [{
        "image_id": record["image_id"], "detections": [
            {k: record[k] for k in ("category_id", "bbox", "score", "layer_boxes")}]}]}
    served = empty_client.post("/v1/calibrate", json=body)
    assert served.status_code == 200, served.text
    det = served.json()["images"][0]["detections"][0]
    assert det["score_raw"] == record["score"] and 0 < det["score"] < 1
    assert det["region_0.9"]["outer"] is not None


def test_the_job_fits_the_stored_files_when_the_handoff_is_gone(empty_client, coco_files):
    results, gt = coco_files
    runner = empty_client.app.state.runner
    runner.stop()   # the job waits until this test runs it
    r = _fit(empty_client, results, gt, name="again", score_method="isotonic")
    assert r.status_code == 202, r.text
    assert len(runner.parsed) == 1
    runner.parsed.take((r.json()["dump_sha256"], hashlib.sha256(gt).hexdigest()))
    store = empty_client.app.state.store
    runner.run(store.claim_job(runner.instance))   # reads the stored pair again
    job = store.get_job(r.json()["job_id"])
    assert job.state == "succeeded", job.error
    detail = empty_client.get(f"/v1/jobs/{job.id}", headers=ADMIN).json()
    assert detail["report"]["selection"]["score"]["chosen"] == "isotonic"


def _loc(r) -> list:
    assert r.status_code == 422, r.text
    return r.json()["detail"][0]["loc"]


def test_options_of_the_other_kind_of_fit_are_refused_by_name(empty_client, coco_files,
                                                              npz_bytes):
    results, gt = coco_files
    assert _loc(_fit(empty_client, results, gt, cov_source="none")) == ["body", "cov_source"]
    assert _loc(_fit(empty_client, results, gt, score_method="platt_range")) == [
        "body", "score_method"]
    assert _loc(_fit(empty_client, results, gt, score_mode="sigmoid")) == ["body",
                                                                           "score_mode"]
    assert _loc(_fit(empty_client, results, gt, iou_threshold="1.5")) == ["body",
                                                                          "iou_threshold"]
    r = empty_client.post("/v1/fit", headers=ADMIN, data={"iou_threshold": "0.7"},
                          files={"dump": ("v.npz", npz_bytes)})
    assert _loc(r) == ["body", "iou_threshold"] and "COCO (2-D) fit" in r.text
    r = empty_client.post("/v1/fit", headers=ADMIN, data={"score_method": "position"},
                          files={"dump": ("v.npz", npz_bytes)})
    assert _loc(r) == ["body", "score_method"]


def test_half_a_pair_or_two_forms_are_refused(empty_client, coco_files, npz_bytes):
    results, gt = coco_files
    r = empty_client.post("/v1/fit", headers=ADMIN,
                          files={"coco_results": ("r.json", results)})
    assert _loc(r) == ["body"] and "coco_gt" in r.text
    r = empty_client.post("/v1/fit", headers=ADMIN,
                          files={"coco_results": ("r.json", results), "coco_gt": ("g", gt),
                                 "dump": ("v.npz", npz_bytes)})
    assert _loc(r) == ["body"]


def test_bad_files_are_refused_naming_the_record(empty_client, coco_files):
    results, gt = coco_files
    records = json.loads(results)
    records[4]["bbox"] = [1, 2, -3, 4]
    r = _fit(empty_client, json.dumps(records).encode(), gt)
    assert _loc(r) == ["body", "coco_results"] and "results[4].bbox" in r.text
    records = json.loads(results)
    records[2]["category_id"] = 9
    r = _fit(empty_client, json.dumps(records).encode(), gt)
    assert _loc(r) == ["body", "coco_results"] and "category_id" in r.text
    instances = json.loads(gt)
    del instances["images"]
    r = _fit(empty_client, results, json.dumps(instances).encode())
    assert _loc(r) == ["body", "coco_gt"] and "'images'" in r.text
    r = _fit(empty_client, b'[{"image_id": 1, "score": NaN}]', gt)
    assert _loc(r) == ["body", "coco_results"] and "not valid JSON" in r.text
    r = _fit(empty_client, results, b"{" * 100_000)
    assert _loc(r) == ["body", "coco_gt"]
    assert empty_client.get("/v1/jobs", headers=ADMIN).json() == []   # nothing was queued


def _client(tmp_path, **limits) -> TestClient:
    return TestClient(create_app(Settings(data_dir=tmp_path / "data", admin_token=TOKEN,
                                          **limits)))


def test_the_pair_is_bounded_before_it_is_parsed(tmp_path, coco_files):
    results, gt = coco_files
    with _client(tmp_path / "bytes", max_json_dump_bytes=len(results) + len(gt) - 1) as c:
        r = _fit(c, results, gt)
        assert r.status_code == 413, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "coco_results"]
        assert "DETCAL_MAX_JSON_DUMP_BYTES" in r.text
    n = len(json.loads(results))
    with _client(tmp_path / "rows", max_fit_detections=n - 1) as c:
        r = _fit(c, results, gt)
        assert r.status_code == 413, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "coco_results"]
        assert f"{n} detections" in r.text and "DETCAL_MAX_FIT_DETECTIONS" in r.text
