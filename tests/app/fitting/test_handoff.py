"""An uploaded fit dump is parsed once: the request's checked parse is what the job fits
(app.fitting.handoff), and a job that finds none parses the stored file."""

from __future__ import annotations

import io
from pathlib import Path

from app.fitting.handoff import ParsedUploads
from app.fitting.runner import JobRunner
from app.store import Store
from calibrators.io import load_dump
from tests.app.conftest import ADMIN


def test_the_newest_parse_is_kept_and_taken_once():
    parsed = ParsedUploads(capacity=1)
    parsed.put(("a", None), "dump a")
    parsed.put(("b", "g"), "dump b")   # pushes out a
    assert parsed.take(("a", None)) is None
    assert parsed.take(("b", "g")) == "dump b"
    assert parsed.take(("b", "g")) is None and len(parsed) == 0


def test_a_job_fits_the_handed_parse_without_reading_the_file(tmp_path: Path, npz_bytes):
    store = Store(f"sqlite:///{tmp_path / 'detcal.db'}", tmp_path / "dumps")
    try:
        sha = store.put_dump(io.BytesIO(npz_bytes), "npz").sha256
        (tmp_path / "val.npz").write_bytes(npz_bytes)
        runner = JobRunner(store, workers=0)
        runner.parsed.put((sha, None), load_dump(tmp_path / "val.npz"))
        store.dump_path(sha).unlink()   # only the handed parse can be fit now
        job = store.create_job("lidar", {}, sha)
        claimed = store.claim_job(runner.instance)
        assert claimed.id == job.id
        runner.run(claimed)
        assert store.get_job(job.id).state == "succeeded", store.get_job(job.id).error
        assert len(runner.parsed) == 0
        job = store.create_job("lidar", {}, sha)   # nothing handed, no file: it fails
        runner.run(store.claim_job(runner.instance))
        assert store.get_job(job.id).state == "failed"
    finally:
        store.close()


def test_the_request_hands_its_parse_to_its_job(client, npz_bytes):
    runner = client.app.state.runner
    runner.stop()   # the job waits until this test runs it
    r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz_bytes)},
                    data={"name": "handed"})
    assert r.status_code == 202, r.text
    assert len(runner.parsed) == 1
    store = client.app.state.store
    store.dump_path(r.json()["dump_sha256"]).unlink()   # only the request's parse remains
    runner.run(store.claim_job(runner.instance))
    job = store.get_job(r.json()["job_id"])
    assert job.state == "succeeded", job.error
    assert len(runner.parsed) == 0
