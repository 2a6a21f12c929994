"""Kill -9 a real `detcal serve` during fits, restart it, and check nothing accepted is lost.

Three kills, each of a fresh fit job submitted with `activate=true`: right after its upload is
accepted (202), while it runs (its fit under way), and while it lands (inside the landing
transaction, made to last by a slow SQLite trigger this test installs). After each kill, with
the server dead, the store must be consistent (integrity check, foreign keys, no half-written
version, the previous version still active); after the restart the job must be re-queued (or
failed) within a second, then land exactly once. Also: a rollback made while a fit runs is
kept (the fit's version lands inactive and the job says why), partial uploads left by a kill
are removed at start-up, and the data directory is private.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from tests.e2e.conftest import ADMIN, Server, wait_job

pytestmark = pytest.mark.e2e

SLOW_ROWS = 400          # the landing trigger walks SLOW_ROWS**3 rows: a few seconds


@contextmanager
def _db(server: Server) -> Iterator[sqlite3.Connection]:
    """A connection of the test's own to the server's SQLite store (autocommit)."""
    conn = sqlite3.connect(server.data_dir / "detcal.db", timeout=10, isolation_level=None)
    try:
        yield conn
    finally:
        conn.close()


def _fit(http: httpx.Client, npz: bytes) -> str:
    r = http.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz)},
                  data={"name": "lidar", "activate": "true"})
    assert r.status_code == 202, r.text
    return r.json()["job_id"]


def _kill(server: Server) -> None:
    assert server.proc is not None
    os.kill(server.proc.pid, signal.SIGKILL)
    server.proc.wait(10)
    server.proc = None


def _dead_store(server: Server, job_id: str, active: int) -> tuple[str, int]:
    """With the server dead: the store is consistent, `active` is still the active version
    and the killed job landed nothing; (state, attempts) of the killed job."""
    with _db(server) as db:
        assert db.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        assert db.execute("PRAGMA foreign_key_check").fetchall() == []
        versions = [v for (v,) in db.execute(
            "SELECT version FROM profiles WHERE name = 'lidar' ORDER BY version")]
        assert versions == list(range(1, len(versions) + 1))
        assert db.execute("SELECT name, version FROM active_profiles").fetchall() == [
            ("lidar", active)]
        assert db.execute("SELECT count(*) FROM profiles WHERE job_id = ?",
                          (job_id,)).fetchone() == (0,)
        landed = db.execute("SELECT j.id, p.job_id FROM jobs j LEFT JOIN profiles p "
                            "ON p.id = j.profile_id WHERE j.state = 'succeeded'").fetchall()
        assert all(job == owner for job, owner in landed)      # every success has its version
        state, attempts = db.execute("SELECT state, attempts FROM jobs WHERE id = ?",
                                     (job_id,)).fetchone()
    assert state in ("queued", "running")
    return state, attempts


def _restart(server: Server, http: httpx.Client, job_id: str, attempts: int) -> dict:
    """Start the server again; within a second its killed job is queued again (or run again,
    or failed), not left `running` for a dead process."""
    server.start()
    deadline = time.monotonic() + 1.0
    while True:
        job = http.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()
        if job["state"] != "running" or job["attempts"] > attempts:
            return job
        assert time.monotonic() < deadline, f"job still held by the killed process: {job}"
        time.sleep(0.05)


def _landed_once(http: httpx.Client, server: Server, job_id: str) -> dict:
    job = wait_job(http, job_id, timeout_s=60)
    assert job["state"] == "succeeded", job
    with _db(server) as db:
        assert db.execute("SELECT count(*) FROM profiles WHERE job_id = ?",
                          (job_id,)).fetchone() == (1,)
    return job


def _active(http: httpx.Client) -> int:
    return http.get("/v1/profiles/lidar").json()["active_version"]


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _write_locked_for(db: sqlite3.Connection, seconds: float, timeout_s: float) -> None:
    """Return once another connection has held the database's write lock for `seconds`
    without a break (the landing transaction; progress writes take milliseconds)."""
    db.execute("PRAGMA busy_timeout = 0")
    deadline = time.monotonic() + timeout_s
    since = None
    while time.monotonic() < deadline:
        try:
            db.execute("BEGIN IMMEDIATE")
            db.execute("ROLLBACK")
            since = None
        except sqlite3.OperationalError:
            since = since or time.monotonic()
            if time.monotonic() - since >= seconds:
                return
        time.sleep(0.02)
    raise AssertionError("the fit never reached its landing transaction")


def test_kills_during_fits_lose_nothing(own_server, dump_npz, large_dump_npz):
    server = own_server
    dumps = server.data_dir / "dumps"
    with httpx.Client(base_url=server.url, timeout=30.0) as http:
        first = wait_job(http, _fit(http, dump_npz))
        assert first["state"] == "succeeded" and _active(http) == 1

        # 1. Killed right after the upload was accepted.
        job = _fit(http, large_dump_npz)
        _kill(server)
        active = 1
        state, attempts = _dead_store(server, job, active)
        partial = dumps / ".upload-killed-mid-upload"
        partial.write_bytes(b"\0" * 2**20)             # what a kill during an upload leaves
        _restart(server, http, job, attempts)
        assert not partial.exists()
        active = _landed_once(http, server, job)["profile"]["version"]
        assert _active(http) == active

        # 2. Killed while the fit runs.
        job = _fit(http, large_dump_npz)
        deadline = time.monotonic() + 30
        while (body := http.get(f"/v1/jobs/{job}", headers=ADMIN).json())["stage"] in (
                None, "starting", "loading dump"):
            assert body["state"] == "queued" or body["state"] == "running", body
            assert time.monotonic() < deadline, body
            time.sleep(0.01)
        _kill(server)
        state, attempts = _dead_store(server, job, active)
        assert state == "running"
        _restart(server, http, job, attempts)
        active = _landed_once(http, server, job)["profile"]["version"]

        # 3. Killed inside the landing transaction (a trigger makes it last seconds).
        with _db(server) as db:
            db.execute("CREATE TABLE e2e_slow (x INTEGER)")
            db.executemany("INSERT INTO e2e_slow VALUES (?)", [(i,) for i in range(SLOW_ROWS)])
            db.execute("CREATE TRIGGER e2e_slow_landing AFTER INSERT ON profiles "
                       "WHEN NEW.job_id IS NOT NULL BEGIN "
                       "SELECT max(a.x + b.x * c.x) FROM e2e_slow a, e2e_slow b, e2e_slow c; "
                       "END")
            job = _fit(http, large_dump_npz)
            _write_locked_for(db, 0.3, timeout_s=30)
            _kill(server)
            state, attempts = _dead_store(server, job, active)
            assert state == "running"
            db.execute("DROP TRIGGER e2e_slow_landing")
            db.execute("DROP TABLE e2e_slow")
        _restart(server, http, job, attempts)
        active = _landed_once(http, server, job)["profile"]["version"]
        assert _active(http) == active == 4

    data = server.data_dir
    assert _mode(data) == _mode(dumps) == _mode(dumps / ".runners") == 0o700
    private = [data / "detcal.db", data / "detcal.db-wal", data / "detcal.db-shm",
               *dumps.iterdir(), *(dumps / ".runners").iterdir()]
    assert {p.name: _mode(p) for p in private if p.is_file()} == {
        p.name: 0o600 for p in private if p.is_file()}
    assert len(list((dumps / ".runners").glob("*.lock"))) == 1      # the live server's only


def test_rollback_while_a_fit_runs_is_kept(own_server, dump_npz, large_dump_npz):
    """Issue 11 item 8: activate version 1 while an `activate=true` fit runs; the fit's version
    lands inactive and its job says why."""
    with httpx.Client(base_url=own_server.url, timeout=30.0) as http:
        assert wait_job(http, _fit(http, dump_npz))["state"] == "succeeded"
        job = _fit(http, large_dump_npz)
        while http.get(f"/v1/jobs/{job}", headers=ADMIN).json()["state"] == "queued":
            time.sleep(0.01)
        assert http.post("/v1/profiles/lidar/1/activate", headers=ADMIN).status_code == 200
        assert http.get(f"/v1/jobs/{job}", headers=ADMIN).json()["state"] == "running", (
            "the fit ended before the rollback: the test's dump is too small for this machine")
        done = wait_job(http, job)
        assert done["state"] == "succeeded" and done["profile"]["id"] == "lidar@2"
        assert done["activation"].startswith("not activated: lidar@1 was activated after"), done
        assert _active(http) == 1
        again = wait_job(http, _fit(http, dump_npz))          # nothing moved since: activates
        assert again["activation"] == "activated" and _active(http) == 3
