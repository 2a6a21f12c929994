"""Issue 25, item 3: a dataset whose inner folders or part files are links leading outside
DETCAL_DATASETS_DIR is refused (at submit, and again when the job runs); no response carries
an absolute server path; a part larger than DETCAL_MAX_FIT_DETECTIONS is a 413."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from calibrators.io import save_parquet
from tests.app.conftest import ADMIN, TOKEN, wait_job


@pytest.fixture(scope="module")
def roots(tmp_path_factory, dump_given) -> tuple[Path, Path]:
    """`datasets/` with `val` (plain), `inner` (detections/ and ground_truth/ link to a copy
    outside), `onefile` (one part file links outside), `inside` (links within the folder),
    `nometa` (no detcal.json); and the folder outside."""
    root, outside = tmp_path_factory.mktemp("datasets"), tmp_path_factory.mktemp("outside")
    save_parquet(root / "val", dump_given, rows_per_part=200)
    save_parquet(outside / "secret", dump_given, rows_per_part=200)
    shutil.copytree(root / "val", root / "inner", ignore=shutil.ignore_patterns("detections",
                                                                                "ground_truth"))
    for sub in ("detections", "ground_truth"):
        os.symlink(outside / "secret" / sub, root / "inner" / sub)
    shutil.copytree(root / "val", root / "onefile")
    part = sorted((root / "onefile" / "detections").iterdir())[0]
    part.unlink()
    os.symlink(outside / "secret" / "detections" / part.name, part)
    shutil.copytree(root / "val", root / "inside")
    shutil.rmtree(root / "inside" / "ground_truth")
    os.symlink(root / "val" / "ground_truth", root / "inside" / "ground_truth")
    (root / "nometa").mkdir()
    return root, outside


def _client(tmp_path: Path, root: Path, **extra: object) -> TestClient:
    settings = Settings(data_dir=tmp_path / "data", admin_token=TOKEN, datasets_dir=root,
                        **extra)
    return TestClient(create_app(settings))


def _fit(client: TestClient, name: str):
    return client.post("/v1/fit", headers=ADMIN, data={"name": "ds", "dataset": name,
                                                      "calibration": "0"})


@pytest.mark.parametrize(("name", "what"), [("inner", "detections"),
                                            ("onefile", "detections/part-")])
def test_inner_links_leading_out_are_refused(tmp_path, roots, name, what):
    root, outside = roots
    with _client(tmp_path, root) as client:
        r = _fit(client, name)
        assert r.status_code == 422, r.text
        msg = r.json()["detail"][0]["msg"]
        assert "leading outside DETCAL_DATASETS_DIR" in msg and what in msg, msg
        assert str(outside) not in r.text and str(root) not in r.text
        assert client.get("/v1/jobs", headers=ADMIN).json() == []


def test_links_that_stay_inside_are_fit(tmp_path, roots):
    with _client(tmp_path, roots[0]) as client:
        r = _fit(client, "inside")
        assert r.status_code == 202, r.text
        assert wait_job(client, r.json()["job_id"])["state"] == "succeeded"


def test_a_link_made_after_submit_fails_the_job_without_a_path(tmp_path, roots, dump_given):
    root, outside = roots
    work = tmp_path / "datasets"
    shutil.copytree(root / "val", work / "late")
    with _client(tmp_path, work, fit_workers=1) as client:
        client.app.state.runner.stop()          # hold the job in the queue
        r = _fit(client, "late")
        assert r.status_code == 202, r.text
        shutil.rmtree(work / "late" / "ground_truth")
        os.symlink(outside / "secret" / "ground_truth", work / "late" / "ground_truth")
    with _client(tmp_path, work) as client:     # a new runner takes the queued job
        job = wait_job(client, r.json()["job_id"])
        assert job["state"] == "failed" and "leading outside" in job["error"], job
        assert str(work) not in str(job) and str(outside) not in str(job)


def test_no_server_path_in_a_bad_dataset_message(tmp_path, roots):
    root = roots[0]
    with _client(tmp_path, root) as client:
        r = _fit(client, "nometa")
        assert r.status_code == 422, r.text
        assert "detcal.json" in r.text
        assert str(root) not in r.text and str(root.resolve()) not in r.text, r.text


def test_a_part_larger_than_the_fit_limit_is_413(tmp_path, roots):
    with _client(tmp_path, roots[0], max_fit_detections=50) as client:
        r = _fit(client, "val")
        assert r.status_code == 413, r.text
        assert "DETCAL_MAX_FIT_DETECTIONS" in r.json()["detail"][0]["msg"]
