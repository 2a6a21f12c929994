"""The store's files on both backends: clean-up of partial and unreferenced uploads, private
file modes, and stores written by an older detcal (columns added when opened)."""

from __future__ import annotations

import io
import os
import stat
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import text, update

from app.store import NotFoundError, Store
from app.store.files import LOCK_FILE, flocked
from app.store.models import DumpRow


# -- clean-up of the dumps directory ----------------------------------------------------------
def _age(path: Path, seconds: float) -> None:
    old = time.time() - seconds
    os.utime(path, (old, old))


def _backdate_dumps(store: Store, seconds: float) -> None:
    then = datetime.now(UTC) - timedelta(seconds=seconds)
    with store.engine.begin() as conn:
        conn.execute(update(DumpRow).values(created_at=then, used_at=then))


def test_clean_up_removes_partial_and_unreferenced_uploads_only(store: Store) -> None:
    store.add_profile("lidar", "{}", dump_sha256="b" * 64)         # referenced, never stored
    for_job = store.put_dump(io.BytesIO(b"job"), "npz").sha256
    for_gt = store.put_dump(io.BytesIO(b"gt"), "nuscenes-gt").sha256
    for_profile = store.put_dump(io.BytesIO(b"profile"), "npz").sha256
    rejected = store.put_dump(io.BytesIO(b"rejected"), "npz").sha256
    recent = store.put_dump(io.BytesIO(b"recent"), "npz").sha256
    job = store.create_job("lidar", {}, for_job, for_gt)
    store.claim_job("w")
    store.fail_job(job.id, "boom", "w")                 # a failed job's dumps stay too
    store.add_profile("radar", "{}", dump_sha256=for_profile)
    _backdate_dumps(store, 7200)
    store.put_dump(io.BytesIO(b"recent"), "npz")       # uploaded again: its grace restarts
    partial = store.dumps_dir / ".upload-abc123"
    partial.write_bytes(b"half an upload")
    stray = store.dumps_dir / ("c" * 64)                # a file whose row never got written
    stray.write_bytes(b"stray")
    _age(stray, 7200)
    young_stray = store.dumps_dir / ("d" * 64)
    young_stray.write_bytes(b"young")
    unrelated = store.dumps_dir / "README"
    unrelated.write_text("not ours")

    report = store.clean_dumps(timedelta(hours=1))
    assert (report.partial, report.dumps, report.skipped) == (1, 2, False)
    assert report.bytes == len(b"half an upload") + len(b"rejected") + len(b"stray")
    kept = {p.name for p in store.dumps_dir.iterdir()}
    assert {for_job, for_gt, for_profile, recent, "d" * 64, "README"} <= kept
    assert not ({rejected, "c" * 64, partial.name} & kept)
    with pytest.raises(NotFoundError):
        store.dump_path(rejected)
    assert store.put_dump(io.BytesIO(b"rejected"), "npz").created     # can come back


def test_clean_up_waits_for_uploads_in_progress(store: Store) -> None:
    partial = store.dumps_dir / ".upload-inprogress"
    partial.write_bytes(b"being written")
    with flocked(store.dumps_dir / LOCK_FILE, exclusive=False):    # an upload under way
        assert store.clean_dumps(timedelta(0), wait_s=0.1).skipped
    assert partial.exists()
    assert store.clean_dumps(timedelta(0)).partial == 1 and not partial.exists()


# -- file modes and older stores --------------------------------------------------------------
def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_store_files_are_private(tmp_path: Path) -> None:
    data = tmp_path / "data"
    store = Store(f"sqlite:///{data / 'detcal.db'}", data / "dumps")
    sha = store.put_dump(io.BytesIO(b"dump"), "npz").sha256
    store.add_profile("lidar", "{}")
    assert _mode(data) == _mode(data / "dumps") == 0o700
    for name in ("detcal.db", "detcal.db-wal", "detcal.db-shm", f"dumps/{sha}", "dumps/.lock"):
        assert _mode(data / name) == 0o600, name
    store.close()


def test_an_older_world_readable_store_is_tightened(tmp_path: Path) -> None:
    store = Store(f"sqlite:///{tmp_path / 'detcal.db'}", tmp_path / "dumps")
    sha = store.put_dump(io.BytesIO(b"dump"), "npz").sha256
    store.add_profile("lidar", "{}", dump_sha256=sha)
    store.close()
    for path in (tmp_path / "detcal.db", tmp_path / "dumps" / sha):
        path.chmod(0o644)
    (tmp_path / "dumps").chmod(0o755)
    store = Store(f"sqlite:///{tmp_path / 'detcal.db'}", tmp_path / "dumps")
    store.clean_dumps()
    assert _mode(tmp_path / "detcal.db") == _mode(tmp_path / "dumps" / sha) == 0o600
    assert _mode(tmp_path / "dumps") == 0o700
    store.close()


def test_a_store_of_an_older_detcal_gets_the_new_columns(url: str, tmp_path: Path) -> None:
    """A database written before jobs had owners and pointers generations opens, keeps its
    data and works (the columns are added with ALTER TABLE)."""
    store = Store(url, tmp_path / "dumps")
    sha = store.put_dump(io.BytesIO(b"d"), "npz").sha256
    store.add_profile("lidar", "{}")
    old_job = store.create_job("lidar", {}, sha, activate=True)
    with store.engine.begin() as conn:
        for table, column in (("jobs", "worker"), ("jobs", "seen_version"),
                              ("jobs", "seen_generation"), ("jobs", "activation"),
                              ("dumps", "used_at"), ("active_profiles", "generation")):
            conn.execute(text(f"ALTER TABLE {table} DROP COLUMN {column}"))
    store.close()
    store = Store(url, tmp_path / "dumps")
    try:
        assert store.claim_job("w").id == old_job.id
        assert store.complete_job(old_job.id, "{}", "w").active      # no record: activates
        new = store.create_job("lidar", {}, sha, activate=True)
        store.activate("lidar", 1)
        store.claim_job("w")
        assert not store.complete_job(new.id, "{}", "w").active
        assert store.clean_dumps(timedelta(0)).dumps == 0            # referenced by jobs
    finally:
        store.close()
