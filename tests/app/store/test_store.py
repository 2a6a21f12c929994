"""The store contract on both backends: versions, activation, jobs, dumps, atomicity.

Every test taking `store` (or `url`) runs on a SQLite file and on a throwaway Postgres
cluster (tests/app/pg.py; skipped locally without the server binaries, a failure under CI).
"""

from __future__ import annotations

import io
import json
import threading
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import text
from sqlalchemy.exc import DBAPIError

from app.store import JobLostError, NotFoundError, Store


def refuse_updates(store: Store, table: str, when: str | None = None) -> None:
    """Install a trigger that makes the database refuse UPDATEs of `table` (if `when`)."""
    with store.engine.begin() as conn:
        if store.backend == "sqlite":
            cond = f"WHEN {when} " if when else ""
            conn.execute(text(f"CREATE TRIGGER refuse_{table} BEFORE UPDATE ON {table} {cond}"
                              "BEGIN SELECT RAISE(ABORT, 'refused'); END"))
        else:
            cond = f"WHEN ({when}) " if when else ""
            conn.execute(text("CREATE OR REPLACE FUNCTION refuse() RETURNS trigger "
                              "LANGUAGE plpgsql AS $$ BEGIN RAISE EXCEPTION 'refused'; END $$"))
            conn.execute(text(f"CREATE TRIGGER refuse_{table} BEFORE UPDATE ON {table} "
                              f"FOR EACH ROW {cond}EXECUTE FUNCTION refuse()"))


def test_sqlite_runs_in_wal_mode_with_foreign_keys(tmp_path: Path) -> None:
    store = Store(f"sqlite:///{tmp_path / 'detcal.db'}", tmp_path / "dumps")
    with store.engine.connect() as conn:
        assert conn.execute(text("PRAGMA journal_mode")).scalar() == "wal"
        assert conn.execute(text("PRAGMA foreign_keys")).scalar() == 1
    store.close()


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
    assert [v.active for v in store.versions("lidar")] == [False, True]


def test_versions_are_immutable(store: Store) -> None:
    """Adding and activating other versions never changes a stored version's content."""
    v1 = store.add_profile("lidar", '{"t": 1.5}', dump_sha256="a" * 64)
    store.add_profile("lidar", '{"t": 2.5}', activate=True)
    store.activate("lidar", 1)
    again = store.get("lidar", 1)
    assert (again.id, again.json, again.sha256, again.dump_sha256, again.created_at) == (
        v1.id, v1.json, v1.sha256, v1.dump_sha256, v1.created_at)
    with pytest.raises(DBAPIError):           # (name, version) is unique in the database
        with store.engine.begin() as conn:
            conn.execute(text("INSERT INTO profiles (name, version, created_at, json, sha256) "
                              "VALUES ('lidar', 1, CURRENT_TIMESTAMP, '{}', 'x')"))
    assert store.get("lidar", 1).json == '{"t": 1.5}'


def test_failed_activation_keeps_the_pointer(store: Store) -> None:
    """A refused pointer move lands nothing: neither the new version nor the activation."""
    store.add_profile("lidar", "{}")
    refuse_updates(store, "active_profiles")
    with pytest.raises(DBAPIError):
        store.add_profile("lidar", '{"new": 1}', activate=True)
    with pytest.raises(DBAPIError):
        store.activate("lidar", 1)
    assert [v.version for v in store.versions("lidar")] == [1]
    assert store.active("lidar").version == 1


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
    refuse_updates(store, "jobs", "NEW.state = 'succeeded'")
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


def run_threads(target, n: int) -> list[Exception]:
    """Run `target(i)` for i < n in n threads at once; the exceptions they raised."""
    errors: list[Exception] = []
    start = threading.Barrier(n)

    def run(i: int) -> None:
        start.wait()
        try:
            target(i)
        except Exception as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return errors


def test_concurrent_fits_get_distinct_versions(store: Store) -> None:
    errors = run_threads(lambda i: store.add_profile("lidar", json.dumps({"i": i}),
                                                     activate=i % 2 == 1), 6)
    assert not errors
    versions = store.versions("lidar")
    assert [v.version for v in versions] == [1, 2, 3, 4, 5, 6]
    assert sorted(json.loads(v.json)["i"] for v in versions) == list(range(6))
    assert sum(v.active for v in versions) == 1                 # one active version per name


def test_concurrent_claims_take_each_job_once(store: Store) -> None:
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    jobs = {store.create_job("lidar", {"i": i}, sha).id for i in range(6)}
    claimed: list[str] = []

    def claim_all(_: int) -> None:
        while (job := store.claim_job()) is not None:
            claimed.append(job.id)

    assert not run_threads(claim_all, 3)
    claim_all(0)                                                # whatever a loser left
    assert sorted(claimed) == sorted(jobs)                     # each exactly once
    assert all(store.get_job(j).attempts == 1 for j in jobs)


def test_data_survives_reopening(url: str, tmp_path: Path) -> None:
    s = Store(url, tmp_path / "dumps")
    s.add_profile("lidar", "{}")
    s.add_profile("lidar", "{}")
    s.activate("lidar", 2)
    s.close()
    again = Store(url, tmp_path / "dumps")
    assert again.active_version("lidar") == 2 and again.count_profiles() == 2
    again.close()


# -- compare-and-set activation of fit jobs ---------------------------------------------------
def _land(store: Store, job_id: str, text: str = '{"fit": 1}'):
    assert store.claim_job("w") is not None
    return store.complete_job(job_id, text, "w")


def test_a_rollback_while_a_fit_runs_is_kept(store: Store) -> None:
    """Issue 11: activate an older version while an `activate` fit runs; the fit lands its
    version inactive and says why."""
    store.add_profile("lidar", "{}")
    store.add_profile("lidar", "{}", activate=True)
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha, activate=True)        # sees lidar@2
    store.activate("lidar", 1)                                      # the rollback
    record = _land(store, job.id)
    assert record.version == 3 and not record.active
    assert store.active_version("lidar") == 1
    done = store.get_job(job.id)
    assert done.state == "succeeded" and done.profile_version == 3
    assert done.activation == ("not activated: lidar@1 was activated after this job was "
                               "submitted (it saw lidar@2); lidar@3 landed inactive, "
                               "activate it to serve it")


def test_activating_the_same_version_again_also_counts_as_a_move(store: Store) -> None:
    store.add_profile("lidar", "{}")
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha, activate=True)
    store.activate("lidar", 1)              # re-affirms lidar@1 after the fit was submitted
    assert not _land(store, job.id).active
    assert store.active_version("lidar") == 1


def test_an_unmoved_pointer_is_moved_by_the_fit(store: Store) -> None:
    store.add_profile("lidar", "{}")
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha, activate=True)
    store.add_profile("lidar", "{}")        # a new inactive version does not move the pointer
    assert _land(store, job.id).active and store.active_version("lidar") == 3
    assert store.get_job(job.id).activation == "activated"
    plain = store.create_job("lidar", {}, sha)
    assert not _land(store, plain.id).active and store.get_job(plain.id).activation is None


def test_a_first_version_landed_meanwhile_wins(store: Store) -> None:
    """Two fits of a new name, both submitted with `activate`: the first to land is active
    (first version of a name), the second saw no active version and lands inactive."""
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    a = store.create_job("lidar", {}, sha, activate=True)
    b = store.create_job("lidar", {}, sha, activate=True)
    assert _land(store, a.id).active
    assert not _land(store, b.id).active
    assert store.active_version("lidar") == 1
    assert store.get_job(b.id).activation.startswith(
        "not activated: lidar@1 was activated after this job was submitted (it saw no active")


def test_concurrent_landings_and_rollbacks_keep_one_pointer(store: Store) -> None:
    """Fits landing while versions are activated: each fit activates only if nothing moved the
    pointer between its submission and its landing; one active version at the end."""
    store.add_profile("lidar", "{}")
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    jobs = [store.create_job("lidar", {"i": i}, sha, activate=True).id for i in range(4)]
    for _ in jobs:
        assert store.claim_job("w") is not None

    def work(i: int) -> None:
        if i < 4:
            store.complete_job(jobs[i], json.dumps({"i": i}), "w")
        else:
            store.activate("lidar", 1)

    assert not run_threads(work, 6)
    outcomes = [store.get_job(j).activation for j in jobs]
    assert sum(o == "activated" for o in outcomes) <= 1      # all saw generation 1
    assert sum(v.active for v in store.versions("lidar")) == 1


# -- job ownership and re-queueing ------------------------------------------------------------
def test_a_requeued_jobs_late_result_does_not_land(store: Store) -> None:
    store.add_profile("lidar", "{}")
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha, activate=True)
    assert store.claim_job("dead").worker == "dead"
    assert store.requeue_stale(None, dead_workers={"dead"}) == 1
    requeued = store.get_job(job.id)
    assert requeued.state == "queued" and requeued.worker is None
    assert "its worker process died" in (requeued.stage or "")
    assert not store.update_job(job.id, 0.5, "late", "dead")
    assert not store.fail_job(job.id, "late", "dead")
    with pytest.raises(JobLostError):
        store.complete_job(job.id, '{"late": 1}', "dead")
    assert store.claim_job("alive").attempts == 2
    with pytest.raises(JobLostError):
        store.complete_job(job.id, '{"late": 1}', "dead")
    assert [v.version for v in store.versions("lidar")] == [1]
    assert store.complete_job(job.id, '{"t": 1}', "alive").version == 2


def test_requeue_leaves_live_workers_and_landed_jobs_alone(store: Store) -> None:
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    live = store.create_job("lidar", {}, sha)
    done = store.create_job("lidar", {}, sha)
    store.claim_job("live")
    store.claim_job("dead")
    store.complete_job(done.id, "{}", "dead")
    assert store.running_workers() == {"live"}
    assert store.requeue_stale(timedelta(minutes=5), dead_workers={"dead", "other"}) == 0
    assert store.get_job(live.id).state == "running"
    assert store.get_job(done.id).state == "succeeded"


def test_a_job_killed_three_times_fails(store: Store) -> None:
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    job = store.create_job("lidar", {}, sha)
    for _ in range(3):
        store.claim_job("w")
        store.requeue_stale(None, dead_workers={"w"})
    final = store.get_job(job.id)
    assert final.state == "failed" and final.error == (
        "interrupted 3 times (worker stopped: its worker process died)")
