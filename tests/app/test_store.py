"""The profile store on a real SQLite file: versions, activation, jobs, dumps, atomicity."""

from __future__ import annotations

import io
import json
import threading
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import text
from sqlalchemy.exc import DBAPIError

from app.store import NotFoundError, Store


@pytest.fixture
def store(tmp_path: Path) -> Store:
    s = Store(f"sqlite:///{tmp_path / 'detcal.db'}", tmp_path / "dumps")
    yield s
    s.close()


def test_sqlite_runs_in_wal_mode_with_foreign_keys(store: Store) -> None:
    with store.engine.connect() as conn:
        assert conn.execute(text("PRAGMA journal_mode")).scalar() == "wal"
        assert conn.execute(text("PRAGMA foreign_keys")).scalar() == 1


def test_versions_count_up_and_first_becomes_active(store: Store) -> None:
    v1 = store.add_profile("lidar", '{"a": 1}')
    v2 = store.add_profile("lidar", '{"a": 2}')
    other = store.add_profile("radar", '{"b": 1}')
    assert (v1.version, v2.version, other.version) == (1, 2, 1)
    assert v1.active and not v2.active and other.active
    assert store.active("lidar").version == 1
    assert [v.version for v in store.versions("lidar")] == [1, 2]
    names = {n.name: n for n in store.names()}
    assert names["lidar"].active_version == 1 and names["lidar"].n_versions == 2
    assert store.get("lidar", 2).json == '{"a": 2}'


def test_activate_and_roll_back(store: Store) -> None:
    store.add_profile("lidar", "{}")
    store.add_profile("lidar", '{"x": 1}')
    assert store.activate("lidar", 2).active
    assert store.active_version("lidar") == 2
    store.activate("lidar", 1)
    assert store.active("lidar").version == 1
    with pytest.raises(NotFoundError, match="no version 3"):
        store.activate("lidar", 3)
    assert store.active_version("lidar") == 1


def test_add_with_activate_moves_the_pointer(store: Store) -> None:
    store.add_profile("lidar", "{}")
    assert store.add_profile("lidar", "{}", activate=True).active
    assert store.active_version("lidar") == 2


def test_unknown_names_are_not_found(store: Store) -> None:
    with pytest.raises(NotFoundError):
        store.versions("nope")
    with pytest.raises(NotFoundError):
        store.active("nope")
    with pytest.raises(NotFoundError):
        store.get_job("0" * 32)
    assert store.active_version("nope") is None


def test_dumps_are_content_addressed_and_deduplicated(store: Store) -> None:
    a = store.put_dump(io.BytesIO(b"hello dump"), "npz")
    b = store.put_dump(io.BytesIO(b"hello dump"), "npz")
    assert a.sha256 == b.sha256 and a.created and not b.created
    path = store.dump_path(a.sha256)
    assert path.name == a.sha256 and path.read_bytes() == b"hello dump"
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".upload-")]


def test_job_lifecycle_lands_version_and_success_together(store: Store) -> None:
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {"threshold": 2.0}, sha)
    assert job.state == "queued"
    claimed = store.claim_job()
    assert claimed is not None and claimed.id == job.id and claimed.state == "running"
    assert store.claim_job() is None                      # nothing else queued
    store.update_job(job.id, 0.5, "depth")
    assert store.get_job(job.id).progress == 0.5
    record = store.complete_job(job.id, '{"t": 1}')
    done = store.get_job(job.id)
    assert done.state == "succeeded" and done.profile_version == record.version == 1
    assert record.job_id == job.id and record.dump_sha256 == sha and record.active


def test_failed_job_changes_no_profile(store: Store) -> None:
    store.add_profile("lidar", "{}")
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha, activate=True)
    store.claim_job()
    store.fail_job(job.id, "ValueError: boom")
    assert store.get_job(job.id).error == "ValueError: boom"
    assert [v.version for v in store.versions("lidar")] == [1]
    assert store.active_version("lidar") == 1


def test_complete_is_one_transaction(store: Store) -> None:
    """The database refusing the job update (after the version insert) lands nothing."""
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha)
    store.claim_job()
    with store.engine.begin() as conn:
        conn.execute(text("CREATE TRIGGER refuse BEFORE UPDATE OF state ON jobs "
                          "WHEN NEW.state = 'succeeded' BEGIN SELECT RAISE(ABORT, 'no'); END"))
    with pytest.raises(DBAPIError):
        store.complete_job(job.id, '{"t": 1}')
    assert store.count_profiles() == 0
    assert store.active_version("lidar") is None
    assert store.get_job(job.id).state == "running"


def test_stale_running_jobs_are_requeued_then_failed(store: Store) -> None:
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha)
    for _ in range(3):
        assert store.claim_job() is not None
        store.requeue_stale(timedelta(seconds=-1))
    final = store.get_job(job.id)
    assert final.state == "failed" and "interrupted 3 times" in (final.error or "")


def test_concurrent_fits_get_distinct_versions(store: Store) -> None:
    errors: list[Exception] = []

    def add(i: int) -> None:
        try:
            store.add_profile("lidar", json.dumps({"i": i}))
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=add, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert [v.version for v in store.versions("lidar")] == [1, 2, 3, 4, 5, 6]


def test_data_survives_reopening(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'detcal.db'}"
    s = Store(url, tmp_path / "dumps")
    s.add_profile("lidar", "{}")
    s.add_profile("lidar", "{}")
    s.activate("lidar", 2)
    s.close()
    again = Store(url, tmp_path / "dumps")
    assert again.active_version("lidar") == 2 and again.count_profiles() == 2
    again.close()
