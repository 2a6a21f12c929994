"""The profile store: immutable profile versions, atomic activation, fit jobs, uploaded dumps.

Works on SQLite (WAL, foreign keys on, busy timeout) and Postgres (psycopg 3); the URL
decides. Every write that must be all-or-nothing (a fit landing its version, an activation)
is one transaction. Writes that pick a version number or move an active pointer serialize per
profile name (`Store._serialize`): SQLite takes its one write lock up front, Postgres a
transaction-scoped advisory lock on the name, so concurrent fits of one name get distinct
versions without relying on retries.

A fit job is owned by the worker that claimed it: only that worker's progress, failure or
result counts (a re-queued job's late result is refused with JobLostError). A job submitted
with `activate` remembers the active pointer it saw and, when it lands, moves the pointer
only if nobody moved it since (compare-and-set in the landing transaction). Uploaded dumps
and their clean-up: app/store/dumps.py; fit jobs: app/store/jobs.py; private file modes:
app/store/files.py; aliases: app/store/aliases.py; the audit log of writes:
app/store/audit.py; feedback health: app/store/feedback_health.py.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy import (
    Connection,
    create_engine,
    event,
    func,
    select,
    text,
)
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.store.aliases import AliasStore
from app.store.audit import AuditEntry, AuditLog
from app.store.base import version_row
from app.store.changes import CommitMarker
from app.store.dumps import DumpFiles
from app.store.feedback_health import HealthStore
from app.store.files import private_dir, private_sqlite
from app.store.jobs import JobQueue
from app.store.models import (
    ActiveRow,
    Base,
    ProfileRow,
    add_missing_columns,
    utcnow,
)
from app.store.records import (
    NameSummary,
    NotFoundError,
    ProfileRecord,
    aware,
)
from app.store.urls import engine_url

log = logging.getLogger("detcal.store")


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=10000")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()


def _lock_key(scope: str, name: str) -> int:
    """A signed 64-bit advisory-lock key for `name` within `scope` (Postgres)."""
    digest = hashlib.sha256(f"detcal:{scope}:{name}".encode()).digest()
    return int.from_bytes(digest[:8], "big", signed=True)


class Store(AuditLog, AliasStore, DumpFiles, JobQueue, HealthStore):
    """Repository over the database at `url`, with uploaded files under `dumps_dir`."""

    def __init__(self, url: str, dumps_dir: Path) -> None:
        parsed = engine_url(url)
        self.url = parsed.render_as_string(hide_password=True)
        self.dumps_dir = private_dir(Path(dumps_dir))
        self.backend = parsed.get_backend_name()
        is_sqlite = self.backend == "sqlite"
        if is_sqlite and parsed.database and parsed.database != ":memory:":
            database = Path(parsed.database)
            if not database.parent.exists():
                private_dir(database.parent)
            private_sqlite(database)
        kwargs: dict[str, Any] = {"connect_args": {"check_same_thread": False}} if is_sqlite else {
            "pool_pre_ping": True}
        self.engine = create_engine(parsed, **kwargs)
        if is_sqlite:
            event.listen(self.engine, "connect", _sqlite_pragmas)
        for attempt in range(3):
            try:
                with self.engine.begin() as conn:
                    # Several server processes may start at once on one Postgres database.
                    self._serialize(conn, "schema", "create")
                    Base.metadata.create_all(conn)
                    add_missing_columns(conn)
                break
            except DBAPIError:  # SQLite: another process added the same column first
                if attempt == 2:
                    raise
        self._session = sessionmaker(self.engine, expire_on_commit=False)
        self._marker = (CommitMarker(Path(parsed.database)) if is_sqlite and parsed.database
                        and parsed.database != ":memory:" else None)

    def change_marker(self) -> CommitMarker | None:
        """The SQLite database's commit marker (`CommitMarker.value()` changes whenever anything
        is committed), or None where the backend offers none (Postgres)."""
        return self._marker

    def commit_marker(self) -> int | None:
        """A number that changes whenever anything is committed to the database (SQLite,
        `app.store.changes`), or None where the backend offers none (Postgres): callers
        caching what the database says then read it again every time."""
        return None if self._marker is None else self._marker.value()

    def _serialize(self, conn: Connection | Session, scope: str, name: str) -> None:
        """Hold a lock on (`scope`, `name`) until the transaction ends; call it first.

        Postgres: a transaction-scoped advisory lock on the pair. SQLite (profile scope):
        take the database's write lock before reading, so the version read next is the
        latest one (pysqlite would otherwise read outside the transaction and leave the
        race to the unique constraint and retries).
        """
        if self.backend == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"),
                         {"key": _lock_key(scope, name)})
        elif self.backend == "sqlite" and scope == "profile":
            conn.execute(text("UPDATE active_profiles SET version = version WHERE 0"))

    def close(self) -> None:
        """Release every pooled connection."""
        if self._marker is not None:
            self._marker.close()
        self.engine.dispose()

    @contextmanager
    def _tx(self) -> Iterator[Session]:
        with self._session() as session, session.begin():
            yield session

    def ping(self) -> bool:
        """True when the database answers a trivial query."""
        try:
            with self.engine.connect() as conn:
                conn.execute(text("SELECT 1"))
            return True
        except Exception:  # noqa: BLE001 - readiness reports any failure as not ready
            return False

    # -- profiles -----------------------------------------------------------------------
    def add_profile(self, name: str, profile_json: str, *, dump_sha256: str | None = None,
                    activate: bool = False) -> ProfileRecord:
        """Store a new version of `name` (version = last + 1); first of a name becomes active."""
        for attempt in range(5):
            try:
                with self._tx() as s:
                    return self._insert_version(s, name, profile_json, dump_sha256, None,
                                                activate)[0]
            except IntegrityError:
                if attempt == 4:
                    raise
        raise AssertionError("unreachable")

    def _insert_version(self, s: Session, name: str, profile_json: str,
                        dump_sha256: str | None, job_id: str | None, activate: bool,
                        seen_generation: int | None = None) -> tuple[ProfileRecord, str | None]:
        """Insert the next version of `name`; move the pointer to it when `activate` (and, if
        `seen_generation` is given, only if the pointer is still that generation, 0 = none).
        Returns the version and, when a requested activation was refused, why."""
        self._serialize(s, "profile", name)
        last = s.scalar(select(func.max(ProfileRow.version)).where(ProfileRow.name == name))
        row = ProfileRow(name=name, version=(last or 0) + 1, json=profile_json,
                         sha256=hashlib.sha256(profile_json.encode()).hexdigest(),
                         dump_sha256=dump_sha256, job_id=job_id, created_at=utcnow())
        s.add(row)
        s.flush()
        active = s.get(ActiveRow, name)
        refused = None
        if active is None:  # the first version of a name is active whatever was asked
            s.add(ActiveRow(name=name, profile_id=row.id, version=row.version))
        elif activate and seen_generation is not None and active.generation != seen_generation:
            refused = f"{name}@{active.version} was activated after this job was submitted"
        elif activate:
            _move(active, row)
        s.flush()
        landed_active = active is None or (activate and refused is None)
        return _profile(row, row.version if landed_active else active.version), refused

    def names(self) -> list[NameSummary]:
        """Every profile name with its active version and version count."""
        with self._session() as s:
            rows = s.execute(
                select(ProfileRow.name, func.count(ProfileRow.id), func.max(ProfileRow.version),
                       ActiveRow.version)
                .join(ActiveRow, ActiveRow.name == ProfileRow.name, isouter=True)
                .group_by(ProfileRow.name, ActiveRow.version)
                .order_by(ProfileRow.name)).all()
        return [NameSummary(name=n, active_version=a, n_versions=c, latest_version=m)
                for n, c, m, a in rows]

    def versions(self, name: str) -> list[ProfileRecord]:
        """Every version of `name`, oldest first; NotFoundError if it has none."""
        with self._session() as s:
            rows = s.scalars(select(ProfileRow).where(ProfileRow.name == name)
                             .order_by(ProfileRow.version)).all()
            active = s.get(ActiveRow, name)
        if not rows:
            raise NotFoundError(f"profile {name!r} does not exist")
        return [_profile(r, active.version if active else None) for r in rows]

    def get(self, name: str, version: int) -> ProfileRecord:
        """One version of `name`; NotFoundError if absent."""
        with self._session() as s:
            row = s.scalar(select(ProfileRow).where(ProfileRow.name == name,
                                                    ProfileRow.version == version))
            active = s.get(ActiveRow, name)
        if row is None:
            raise NotFoundError(f"profile {name!r} has no version {version}")
        return _profile(row, active.version if active else None)

    def active(self, name: str) -> ProfileRecord:
        """The active version of `name`; NotFoundError if the name has no versions."""
        with self._session() as s:
            active = s.get(ActiveRow, name)
            row = s.get(ProfileRow, active.profile_id) if active else None
        if row is None:
            raise NotFoundError(f"profile {name!r} does not exist")
        return _profile(row, row.version)

    def active_version(self, name: str) -> int | None:
        """Just the active version number of `name` (one indexed read), None if unknown."""
        with self._session() as s:
            return s.scalar(select(ActiveRow.version).where(ActiveRow.name == name))

    def active_versions(self) -> dict[str, int]:
        """Active version of every name."""
        with self._session() as s:
            return dict(s.execute(select(ActiveRow.name, ActiveRow.version)).all())

    def activate(self, name: str, version: int, audit: AuditEntry | None = None
                 ) -> ProfileRecord:
        """Make `version` the active one of `name`, atomically (rolling back = older version),
        recording `audit` in the same transaction with `detail.previous` (the version that
        was active, read under the name's lock)."""
        with self._tx() as s:
            self._serialize(s, "profile", name)
            row = version_row(s, name, version)
            active = s.get(ActiveRow, name)
            previous = None if active is None else active.version
            if active is None:
                s.add(ActiveRow(name=name, profile_id=row.id, version=version))
            else:
                _move(active, row)
            self._audit_previous(s, audit, previous)
        log.info("activated %s@%d (was %s)%s", name, version,
                 "none" if previous is None else f"{name}@{previous}",
                 f" by {audit.token_id}" if audit else "")
        return _profile(row, version)

    def count_profiles(self) -> int:
        """How many profile versions are stored in all."""
        with self._session() as s:
            return int(s.scalar(select(func.count(ProfileRow.id))) or 0)


def _move(active: ActiveRow, row: ProfileRow) -> None:
    """Point `active` at `row` (a new generation, even if it is the version already active)."""
    active.profile_id, active.version, active.activated_at = row.id, row.version, utcnow()
    active.generation = (active.generation or 0) + 1


def _profile(row: ProfileRow, active_version: int | None) -> ProfileRecord:
    return ProfileRecord(id=row.id, name=row.name, version=row.version,
                         created_at=aware(row.created_at) or datetime.min,
                         sha256=row.sha256, dump_sha256=row.dump_sha256, job_id=row.job_id,
                         active=row.version == active_version, json=row.json)
