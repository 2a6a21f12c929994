"""The fit-job runner with real processes: jobs of a killed process are re-queued at once, a live
sibling's are not, a stopping runner hands its unfinished fit back, and a rollback made while a
fit is pending is kept (the job says why its version landed inactive)."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.fitting.runner import RUNNERS_DIR, JobRunner
from app.main import create_app
from app.settings import Settings
from app.store import Store
from tests.app.conftest import ADMIN, TOKEN

ROOT = Path(__file__).resolve().parents[3]

# A runner instance in another process that has claimed the oldest queued job and keeps it
# (no fit threads: it stands for a process busy fitting), until it is killed.
SIBLING = """
import sys, time
from app.fitting.runner import JobRunner
from app.store import Store
store = Store(sys.argv[1], sys.argv[2])
runner = JobRunner(store, workers=0)
runner.start()
job = store.claim_job(runner.instance)
print(job.id, runner.instance, flush=True)
time.sleep(600)
"""


@pytest.fixture
def store(tmp_path: Path) -> Iterator[Store]:
    s = Store(f"sqlite:///{tmp_path / 'detcal.db'}", tmp_path / "dumps")
    yield s
    s.close()


Sibling = tuple[subprocess.Popen, str, str]


@pytest.fixture
def sibling(store: Store) -> Iterator[Callable[[], Sibling]]:
    """`sibling()`: start a process that claims the next queued job; (process, job id, its
    runner instance). Killed at teardown if still alive."""
    procs: list[subprocess.Popen] = []

    def start() -> Sibling:
        proc = subprocess.Popen([sys.executable, "-c", SIBLING, store.url, str(store.dumps_dir)],
                                cwd=ROOT, stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        job_id, instance = proc.stdout.readline().split()
        return proc, job_id, instance

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stdout.close()


def _kill(proc: subprocess.Popen) -> None:
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()


def _until(condition, timeout_s: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)
    return value


def test_jobs_of_a_killed_process_are_requeued_at_start(store: Store, sibling,
                                                        npz_bytes: bytes) -> None:
    sha = store.put_dump(io.BytesIO(npz_bytes), "npz").sha256
    queued = store.create_job("lidar", {}, sha)
    proc, job_id, instance = sibling()
    assert job_id == queued.id and store.get_job(job_id).worker == instance
    _kill(proc)
    partial = store.dumps_dir / ".upload-left-by-a-kill"
    partial.write_bytes(b"half")
    runner = JobRunner(store, poll_s=0.05)
    runner.start()
    try:
        job = store.get_job(job_id)                        # no waiting: start() re-queued it
        assert job.state == "queued" or (job.state == "running" and job.attempts == 2), job
        assert not partial.exists()
        done = _until(lambda: (j := store.get_job(job_id)).state == "succeeded" and j,
                      what="the re-queued job to land")
        assert done.attempts == 2 and done.profile_version == 1
        lock_files = {p.name for p in (store.dumps_dir / RUNNERS_DIR).glob("*.lock")}
        assert len(lock_files) == 1                        # the dead sibling's lock is swept
    finally:
        runner.stop()
    assert not list((store.dumps_dir / RUNNERS_DIR).glob("*.lock"))


def test_a_live_siblings_job_is_left_alone_until_it_dies(store: Store, sibling,
                                                         npz_bytes: bytes) -> None:
    sha = store.put_dump(io.BytesIO(npz_bytes), "npz").sha256
    store.create_job("lidar", {}, sha)
    proc, job_id, instance = sibling()
    runner = JobRunner(store, poll_s=0.05)
    runner.start()
    try:
        time.sleep(0.3)                                   # several housekeeping rounds
        job = store.get_job(job_id)
        assert (job.state, job.worker, job.attempts) == ("running", instance, 1)
        _kill(proc)
        done = _until(lambda: (j := store.get_job(job_id)).state == "succeeded" and j,
                      what="the dead sibling's job to be re-run")
        assert done.attempts == 2
    finally:
        runner.stop()


def test_stop_hands_an_unfinished_fit_back(store: Store) -> None:
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha)
    runner = JobRunner(store, workers=0)
    runner.start()
    assert store.claim_job(runner.instance).id == job.id   # as its fit thread would
    runner.stop()
    after = store.get_job(job.id)
    assert after.state == "queued" and after.worker is None
    assert not list((store.dumps_dir / RUNNERS_DIR).glob("*.lock"))


def test_a_rollback_before_the_fit_lands_is_kept(tmp_path: Path, npz_bytes: bytes,
                                                 profile_json_given: str, wait) -> None:
    """POST /v1/fit with activate=true, roll back to lidar@1 before the job lands: the job
    lands lidar@3 inactive and GET /v1/jobs/{id} says why."""
    settings = Settings(data_dir=tmp_path / "data", admin_token=TOKEN)
    seed = Store(settings.sqlalchemy_url, settings.dumps_dir)
    seed.add_profile("lidar", profile_json_given)
    seed.add_profile("lidar", profile_json_given, activate=True)
    seed.close()
    with TestClient(create_app(settings)) as client:
        client.app.state.runner.stop()                     # hold the job until we say so
        r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz_bytes)},
                        data={"name": "lidar", "activate": "true"})
        assert r.status_code == 202, r.text
        job_id = r.json()["job_id"]
        assert client.post("/v1/profiles/lidar/1/activate", headers=ADMIN).status_code == 200
        runner = JobRunner(client.app.state.store, poll_s=0.05)
        runner.start()
        try:
            job = wait(client, job_id)
        finally:
            runner.stop()
        assert job["state"] == "succeeded" and job["profile"]["id"] == "lidar@3"
        assert job["activation"] == (
            "not activated: lidar@1 was activated after this job was submitted (it saw "
            "lidar@2); lidar@3 landed inactive, activate it to serve it")
        assert client.get("/v1/profiles/lidar").json()["active_version"] == 1
        listed = client.get("/v1/jobs", headers=ADMIN).json()
        assert listed[0]["activation"] == job["activation"]
