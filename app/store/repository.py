"""The profile store: immutable profile versions, atomic activation, fit jobs, uploaded dumps.

Works on SQLite (WAL, foreign keys on, busy timeout) and Postgres (psycopg 3); the URL
decides. Every write that must be all-or-nothing (a fit landing its version, an activation)
is one transaction. Writes that pick a version number or move an active pointer serialize per
profile name (`Store._serialize`): SQLite takes its one write lock up front, Postgres a
transaction-scoped advisory lock on the name, so concurrent fits of one name get distinct
versions without relying on retries.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, BinaryIO

from sqlalchemy import Connection, create_engine, event, func, select, text, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.store.models import ActiveRow, Base, DumpRow, JobRow, ProfileRow, utcnow
from app.store.records import (
    DumpRecord,
    JobRecord,
    NameSummary,
    NotFoundError,
    ProfileRecord,
    aware,
)
from app.store.urls import engine_url

_CHUNK = 1 << 20


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


class Store:
    """Repository over the database at `url`, with uploaded files under `dumps_dir`."""

    def __init__(self, url: str, dumps_dir: Path) -> None:
        parsed = engine_url(url)
        self.url = parsed.render_as_string(hide_password=True)
        self.dumps_dir = Path(dumps_dir)
        self.dumps_dir.mkdir(parents=True, exist_ok=True)
        self.backend = parsed.get_backend_name()
        is_sqlite = self.backend == "sqlite"
        if is_sqlite and parsed.database and parsed.database != ":memory:":
            Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
        kwargs: dict[str, Any] = {"connect_args": {"check_same_thread": False}} if is_sqlite else {
            "pool_pre_ping": True}
        self.engine = create_engine(parsed, **kwargs)
        if is_sqlite:
            event.listen(self.engine, "connect", _sqlite_pragmas)
        with self.engine.begin() as conn:
            # Several server processes may start at once on one Postgres database.
            self._serialize(conn, "schema", "create")
            Base.metadata.create_all(conn)
        self._session = sessionmaker(self.engine, expire_on_commit=False)

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

    # -- dumps --------------------------------------------------------------------------
    def put_dump(self, source: BinaryIO, kind: str) -> DumpRecord:
        """Copy `source` to `dumps/<sha256>` (atomically, once) and record it."""
        digest = hashlib.sha256()
        size = 0
        fd, tmp = tempfile.mkstemp(dir=self.dumps_dir, prefix=".upload-")
        try:
            with os.fdopen(fd, "wb") as out:
                while chunk := source.read(_CHUNK):
                    digest.update(chunk)
                    size += len(chunk)
                    out.write(chunk)
            sha = digest.hexdigest()
            final = self.dumps_dir / sha
            if final.exists():
                os.unlink(tmp)
            else:
                os.replace(tmp, final)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        try:
            with self._tx() as s:
                created = s.get(DumpRow, sha) is None
                if created:
                    s.add(DumpRow(sha256=sha, kind=kind, size=size))
        except IntegrityError:
            created = False  # the same bytes were recorded concurrently
        return DumpRecord(sha256=sha, kind=kind, size=size, created=created)

    def dump_path(self, sha256: str) -> Path:
        """Path of the stored upload with this digest."""
        path = self.dumps_dir / sha256
        if len(sha256) != 64 or not path.is_file():
            raise NotFoundError(f"dump {sha256} is not stored")
        return path

    # -- profiles -----------------------------------------------------------------------
    def add_profile(self, name: str, profile_json: str, *, dump_sha256: str | None = None,
                    activate: bool = False) -> ProfileRecord:
        """Store a new version of `name` (version = last + 1); first of a name becomes active."""
        for attempt in range(5):
            try:
                with self._tx() as s:
                    return self._insert_version(s, name, profile_json, dump_sha256, None,
                                                activate)
            except IntegrityError:
                if attempt == 4:
                    raise
        raise AssertionError("unreachable")

    def _insert_version(self, s: Session, name: str, profile_json: str,
                        dump_sha256: str | None, job_id: str | None,
                        activate: bool) -> ProfileRecord:
        self._serialize(s, "profile", name)
        last = s.scalar(select(func.max(ProfileRow.version)).where(ProfileRow.name == name))
        row = ProfileRow(name=name, version=(last or 0) + 1, json=profile_json,
                         sha256=hashlib.sha256(profile_json.encode()).hexdigest(),
                         dump_sha256=dump_sha256, job_id=job_id, created_at=utcnow())
        s.add(row)
        s.flush()
        active = s.get(ActiveRow, name)
        if active is None:
            s.add(ActiveRow(name=name, profile_id=row.id, version=row.version))
        elif activate:
            active.profile_id, active.version, active.activated_at = row.id, row.version, utcnow()
        s.flush()
        return _profile(row, active_version=row.version if active is None or activate
                        else active.version)

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

    def activate(self, name: str, version: int) -> ProfileRecord:
        """Make `version` the active one of `name`, atomically (rolling back = older version)."""
        with self._tx() as s:
            self._serialize(s, "profile", name)
            row = s.scalar(select(ProfileRow).where(ProfileRow.name == name,
                                                    ProfileRow.version == version))
            if row is None:
                raise NotFoundError(f"profile {name!r} has no version {version}")
            active = s.get(ActiveRow, name)
            if active is None:
                s.add(ActiveRow(name=name, profile_id=row.id, version=version))
            else:
                active.profile_id, active.version, active.activated_at = row.id, version, utcnow()
        return _profile(row, version)

    def count_profiles(self) -> int:
        """How many profile versions are stored in all."""
        with self._session() as s:
            return int(s.scalar(select(func.count(ProfileRow.id))) or 0)

    # -- jobs ---------------------------------------------------------------------------
    def create_job(self, name: str, options: dict[str, Any], dump_sha256: str,
                   gt_sha256: str | None = None, activate: bool = False) -> JobRecord:
        """Queue a fit job of `name` on a stored dump."""
        row = JobRow(id=uuid.uuid4().hex, name=name, state="queued", progress=0.0,
                     options=json.dumps(options, sort_keys=True), dump_sha256=dump_sha256,
                     gt_sha256=gt_sha256, activate=activate, attempts=0, created_at=utcnow())
        with self._tx() as s:
            s.add(row)
        return JobRecord.from_row(row, None)

    def get_job(self, job_id: str) -> JobRecord:
        """One job with the version it produced; NotFoundError if unknown."""
        with self._session() as s:
            row = s.get(JobRow, job_id)
            if row is None:
                raise NotFoundError(f"job {job_id!r} does not exist")
            version = s.scalar(select(ProfileRow.version).where(
                ProfileRow.id == row.profile_id)) if row.profile_id else None
        return JobRecord.from_row(row, version)

    def claim_job(self) -> JobRecord | None:
        """Atomically move the oldest queued job to running and return it (None if none)."""
        for _ in range(5):
            with self._tx() as s:
                # Postgres: skip rows another worker is claiming; SQLite renders no FOR UPDATE.
                job_id = s.scalar(select(JobRow.id).where(JobRow.state == "queued")
                                  .order_by(JobRow.created_at).limit(1)
                                  .with_for_update(skip_locked=True))
                if job_id is None:
                    return None
                now = utcnow()
                claimed = s.execute(
                    update(JobRow).where(JobRow.id == job_id, JobRow.state == "queued")
                    .values(state="running", started_at=now, heartbeat_at=now,
                            attempts=JobRow.attempts + 1, stage="starting")).rowcount
            if claimed == 1:
                return self.get_job(job_id)
        return None

    def update_job(self, job_id: str, progress: float, stage: str | None) -> None:
        """Record progress of a running job (also its heartbeat)."""
        with self._tx() as s:
            s.execute(update(JobRow).where(JobRow.id == job_id, JobRow.state == "running")
                      .values(progress=max(0.0, min(1.0, progress)), stage=_text(stage, 200),
                              heartbeat_at=utcnow()))

    def fail_job(self, job_id: str, error: str) -> None:
        """Mark a job failed with its error message; nothing else changes."""
        with self._tx() as s:
            s.execute(update(JobRow).where(JobRow.id == job_id)
                      .values(state="failed", error=_text(error, 4000), finished_at=utcnow(),
                              stage="failed"))

    def complete_job(self, job_id: str, profile_json: str) -> ProfileRecord:
        """In one transaction: write the job's profile version and mark the job succeeded."""
        for attempt in range(5):
            try:
                with self._tx() as s:
                    job = s.get(JobRow, job_id)
                    if job is None:
                        raise NotFoundError(f"job {job_id!r} does not exist")
                    record = self._insert_version(s, job.name, profile_json, job.dump_sha256,
                                                  job.id, job.activate)
                    job.state, job.progress, job.stage = "succeeded", 1.0, "done"
                    job.finished_at, job.profile_id = utcnow(), record.id
                    return record
            except IntegrityError:
                if attempt == 4:
                    raise
        raise AssertionError("unreachable")

    def requeue_stale(self, older_than: timedelta, max_attempts: int = 3) -> int:
        """Re-queue running jobs whose heartbeat is older than `older_than` (worker died)."""
        cutoff = utcnow() - older_than
        with self._tx() as s:
            rows = s.scalars(select(JobRow).where(JobRow.state == "running")).all()
            n = 0
            for row in rows:
                beat = aware(row.heartbeat_at)
                if beat is not None and beat >= cutoff:
                    continue
                if row.attempts >= max_attempts:
                    row.state, row.finished_at = "failed", utcnow()
                    row.error = f"interrupted {row.attempts} times (worker stopped)"
                else:
                    row.state, row.stage = "queued", "re-queued after an interrupted run"
                n += 1
        return n

    def job_counts(self) -> dict[str, int]:
        """Number of jobs in each state."""
        with self._session() as s:
            return dict(s.execute(select(JobRow.state, func.count(JobRow.id))
                                  .group_by(JobRow.state)).all())

    def recent_jobs(self, limit: int = 10) -> list[JobRecord]:
        """The newest jobs, newest first."""
        with self._session() as s:
            rows = s.scalars(select(JobRow).order_by(JobRow.created_at.desc()).limit(limit)).all()
            ids = [r.profile_id for r in rows if r.profile_id]
            versions = dict(s.execute(select(ProfileRow.id, ProfileRow.version)
                                      .where(ProfileRow.id.in_(ids))).all()) if ids else {}
        return [JobRecord.from_row(r, versions.get(r.profile_id)) for r in rows]


def _text(value: str | None, limit: int) -> str | None:
    """`value` cut to `limit` characters, without NUL (Postgres text cannot hold it)."""
    return None if value is None else value.replace("\x00", "")[:limit]


def _profile(row: ProfileRow, active_version: int | None) -> ProfileRecord:
    return ProfileRecord(id=row.id, name=row.name, version=row.version,
                         created_at=aware(row.created_at) or datetime.min,
                         sha256=row.sha256, dump_sha256=row.dump_sha256, job_id=row.job_id,
                         active=row.version == active_version, json=row.json)
