"""Store contract of aliases, the audit log and feedback health rows (SQLite and Postgres),
and an old store file gaining the new tables."""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import pytest

from app.store import CHAMPION, AuditEntry, HealthChunk, NotFoundError, Store


def _chunk(frames: int, status: str = "ok") -> HealthChunk:
    return HealthChunk(frames_total=frames, counts="{}", drift='{"x": 1}', status=status,
                       alarms_total=0)


def test_aliases_point_at_versions_and_champion_is_the_active_pointer(store: Store) -> None:
    store.add_profile("lidar", "{}")
    store.add_profile("lidar", '{"v": 2}')
    assert [(a.alias, a.version) for a in store.aliases("lidar")] == [(CHAMPION, 1)]
    store.set_alias("lidar", "challenger", 2)
    assert store.alias_version("lidar", "challenger") == 2
    store.set_alias("lidar", "challenger", 1)            # moved
    assert store.alias_version("lidar", "challenger") == 1
    store.set_alias("lidar", CHAMPION, 2)                # = activate
    assert store.active_version("lidar") == 2 and store.alias_version("lidar", CHAMPION) == 2
    assert [(a.alias, a.version) for a in store.aliases("lidar")] == [
        (CHAMPION, 2), ("challenger", 1)]
    store.delete_alias("lidar", "challenger")
    with pytest.raises(NotFoundError, match="no alias 'challenger'"):
        store.alias_version("lidar", "challenger")
    with pytest.raises(NotFoundError, match="no version 9"):
        store.set_alias("lidar", "x", 9)


def test_each_write_is_audited_once_in_its_own_transaction(store: Store) -> None:
    store.add_profile("lidar", "{}")
    store.set_alias("lidar", "challenger", 1, AuditEntry("alias", "lidar@challenger", "tok-a"))
    store.activate("lidar", 1, AuditEntry("activate", "lidar@champion", "tok-b", {"v": 1}))
    with pytest.raises(NotFoundError):   # a failed write leaves no entry
        store.activate("lidar", 5, AuditEntry("activate", "lidar@champion", "tok-b"))
    log = store.audit_log()
    assert [(e.action, e.target, e.token_id) for e in log] == [
        ("activate", "lidar@champion", "tok-b"), ("alias", "lidar@challenger", "tok-a")]
    # the store adds `previous`, read in the write's own transaction (issue 25)
    assert log[0].detail == {"v": 1, "previous": 1} and log[0].id > log[1].id
    assert log[1].detail == {"previous": None}
    assert [e.action for e in store.audit_log(before=log[0].id)] == ["alias"]
    assert [e.action for e in store.audit_log(action="alias")] == ["alias"]
    assert len(store.audit_log(target="lidar")) == 2 and store.audit_log(target="li") == []


def test_health_rows_append_in_sequence_and_answer_window_queries(store: Store) -> None:
    rec = store.add_profile("lidar", "{}")
    seen = []

    def advance(latest):
        seen.append(None if latest is None else latest.frames_total)
        base = 0 if latest is None else latest.frames_total
        return [_chunk(base + 10), _chunk(base + 20)]

    store.append_health("lidar", rec.id, advance)
    rows = store.append_health("lidar", rec.id, advance,
                               AuditEntry("feedback", "lidar@1", "tok-a"))
    assert seen == [None, 20] and [r.seq for r in rows] == [3, 4]
    assert store.latest_health(rec.id).frames_total == 40
    assert store.health_at_most(rec.id, 25).frames_total == 20
    assert store.health_at_most(rec.id, 5) is None
    assert [r.frames_total for r in store.health_series(rec.id)] == [10, 20, 30, 40]
    (over,) = store.health_overview()
    assert (over.name, over.version, over.active, over.latest.seq) == ("lidar", 1, True, 4)
    assert store.activated_at("lidar", 1) is not None
    assert [e.action for e in store.audit_log()] == ["feedback"]


def test_concurrent_feedback_of_one_version_never_interleaves(store: Store) -> None:
    rec = store.add_profile("lidar", "{}")

    def advance(latest):
        base = 0 if latest is None else latest.frames_total
        return [_chunk(base + 1)]

    threads = [threading.Thread(target=store.append_health, args=("lidar", rec.id, advance))
               for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [r.frames_total for r in store.health_series(rec.id)] == list(range(1, 9))


def test_a_store_file_of_an_older_detcal_gains_the_new_tables(tmp_path: Path) -> None:
    db = tmp_path / "old.db"
    first = Store(f"sqlite:///{db}", tmp_path / "dumps")
    first.add_profile("lidar", "{}")
    first.close()
    with sqlite3.connect(db) as conn:   # as an older detcal left it
        for table in ("profile_aliases", "audit_log", "feedback_health"):
            conn.execute(f"DROP TABLE {table}")
    store = Store(f"sqlite:///{db}", tmp_path / "dumps")
    store.set_alias("lidar", "challenger", 1, AuditEntry("alias", "lidar@challenger", "t"))
    assert store.active_version("lidar") == 1 and len(store.audit_log()) == 1
    store.close()
