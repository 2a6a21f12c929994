"""POST /v1/fit with `dataset`: a Parquet dataset under DETCAL_DATASETS_DIR is fit in place,
part by part, to the profile the in-memory fit gives; nothing outside that folder can be
named, and options a streamed fit cannot reproduce are refused before a job is queued."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile
from calibrators.io import save_parquet
from tests.app.conftest import ADMIN, TOKEN, wait_job
from tests.calibrators.fit.test_fit_stream import assert_close_tree


@pytest.fixture(scope="module")
def datasets(tmp_path_factory, dump_given):
    root = tmp_path_factory.mktemp("datasets")
    save_parquet(root / "val", dump_given, rows_per_part=200)
    save_parquet(root / "soft", synthetic_dump(n_frames=12, seed=4, score_mode="softmax"))
    outside = tmp_path_factory.mktemp("outside")
    save_parquet(outside / "secret", dump_given)
    os.symlink(outside / "secret", root / "escape")
    return root


@pytest.fixture
def client(tmp_path, datasets) -> Iterator[TestClient]:
    settings = Settings(data_dir=tmp_path / "data", admin_token=TOKEN, datasets_dir=datasets)
    with TestClient(create_app(settings)) as c:
        yield c


def _fit(client: TestClient, **form: str):
    return client.post("/v1/fit", headers=ADMIN, data={"name": "streamed", **form})


def test_a_dataset_is_fit_in_place_to_the_in_memory_profile(client, dump_given):
    r = _fit(client, dataset="val", calibration="0")
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["job_id"])
    assert job["state"] == "succeeded", job
    served = client.get("/v1/profiles/streamed/1").json()["profile"]
    memory = fit_profile(dump_given, calibration=0.0)
    assert served["temperature"] == pytest.approx(memory.temperature, rel=1e-6)


def test_a_dataset_fit_with_one_temperature_serves_conformal_regions(client, dump_given):
    """Covariance scaling chosen on the calibration part and conformal radii, streamed,
    serve what the in-memory fit serves."""
    r = _fit(client, dataset="val", score_method="temperature", min_group="30")
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["job_id"])
    assert job["state"] == "succeeded", job
    served = client.get("/v1/profiles/streamed/1").json()["profile"]
    memory = fit_profile(dump_given, score_method="temperature", min_group=30)
    assert served["regions"]["method"] == memory.region_method == "conformal"
    assert served["regions"]["conformal"]["counts"] == memory.regions["conformal"]["counts"]
    assert (served["covariance_scaling"] or {}).get("method") == \
        (memory.covariance_scaling or {}).get("method")
    body = {"profile": "streamed", "levels": [0.9], "frames": [{"frame_id": "f", "detections": [
        {"logits": dump_given.det_logits[0, -1].tolist(),
         "box": dump_given.det_boxes[0, -1].tolist(),
         "covariance": dump_given.det_cov[0].tolist()}]}]}
    ellipse = client.post("/v1/calibrate", json=body).json()["frames"][0]["detections"][0][
        "ellipses"]["0.9"]
    assert ellipse["method"] == "conformal" and ellipse["calibration_n"] > 0


@pytest.mark.parametrize(("name", "words"), [
    ("../outside", "without '..'"), ("/etc", "without '..'"), ("nope", "is not a folder"),
    ("escape", "leads outside"), ("", "is empty"),
])
def test_names_outside_the_datasets_folder_are_refused(client, name, words):
    r = _fit(client, dataset=name, calibration="0")
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["body", "dataset"] and words in detail["msg"], detail


def test_a_dataset_fit_with_default_options_serves_the_in_memory_scores(client, dump_given):
    """The default fit, streamed: score candidates and κ chosen on the calibration part."""
    r = _fit(client, dataset="val")
    assert r.status_code == 202, r.text
    job = wait_job(client, r.json()["job_id"])
    assert job["state"] == "succeeded", job
    served = client.get("/v1/profiles/streamed/1").json()["profile"]
    memory = fit_profile(dump_given)
    assert served["score_calibration"]["method"] == memory.score_method
    assert_close_tree(served["score_calibration"], json.loads(memory.to_json())[
        "score_calibration"], "score_calibration")


def test_options_a_streamed_fit_cannot_reproduce_are_refused_before_queueing(client):
    r = _fit(client, dataset="soft")                 # auto on softmax scores, with calibration
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "score_method"]
    assert client.get("/v1/jobs", headers=ADMIN).json() == []


def test_one_source_per_fit_and_none_without_the_setting(tmp_path, npz_bytes):
    settings = Settings(data_dir=tmp_path / "data", admin_token=TOKEN)
    with TestClient(create_app(settings)) as c:
        r = c.post("/v1/fit", headers=ADMIN, data={"dataset": "val"})
        assert r.status_code == 422 and "DETCAL_DATASETS_DIR" in r.text
        r = c.post("/v1/fit", headers=ADMIN, data={"dataset": "val"},
                   files={"dump": ("v.npz", npz_bytes)})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body"]
