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
and their clean-up: app/store/dumps.py; private file modes: app/store/files.py.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import (
    Connection,
    String,
    cast,
    create_engine,
    event,
    func,
    or_,
    select,
    text,
    update,
)
from sqlalchemy.exc import DBAPIError, IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.store.dumps import DumpFiles
from app.store.files import private_dir, private_sqlite
from app.store.models import (
    ActiveRow,
    Base,
    JobRow,
    ProfileRow,
    add_missing_columns,
    utcnow,
)
from app.store.records import (
    JobLostError,
    JobRecord,
    NameSummary,
    NotFoundError,
    ProfileRecord,
    aware,
)
from app.store.urls import engine_url


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


class Store(DumpFiles):
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
                _move(active, row)
        return _profile(row, version)

    def count_profiles(self) -> int:
        """How many profile versions are stored in all."""
        with self._session() as s:
            return int(s.scalar(select(func.count(ProfileRow.id))) or 0)

    # -- jobs ---------------------------------------------------------------------------
    def create_job(self, name: str, options: dict[str, Any], dump_sha256: str,
                   gt_sha256: str | None = None, activate: bool = False) -> JobRecord:
        """Queue a fit job of `name` on a stored dump; with `activate`, note the active pointer
        now (the job activates its version only if the pointer has not moved when it lands)."""
        row = JobRow(id=uuid.uuid4().hex, name=name, state="queued", progress=0.0,
                     options=json.dumps(options, sort_keys=True), dump_sha256=dump_sha256,
                     gt_sha256=gt_sha256, activate=activate, attempts=0, created_at=utcnow())
        with self._tx() as s:
            if activate:
                seen = s.execute(select(ActiveRow.version, ActiveRow.generation)
                                 .where(ActiveRow.name == name)).first()
                row.seen_version, row.seen_generation = tuple(seen) if seen else (0, 0)
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

    def claim_job(self, worker: str | None = None) -> JobRecord | None:
        """Atomically move the oldest queued job to running, owned by `worker`, and return it
        (None if none is queued)."""
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
                    .values(state="running", started_at=now, heartbeat_at=now, worker=worker,
                            attempts=JobRow.attempts + 1, stage="starting")).rowcount
            if claimed == 1:
                return self.get_job(job_id)
        return None

    def update_job(self, job_id: str, progress: float, stage: str | None,
                   worker: str | None = None) -> bool:
        """Record progress of a running job (also its heartbeat); False when the job is no
        longer running (or, given `worker`, no longer that worker's)."""
        with self._tx() as s:
            return s.execute(update(JobRow).where(JobRow.id == job_id, *_owned(worker))
                             .values(progress=max(0.0, min(1.0, progress)),
                                     stage=_text(stage, 200), heartbeat_at=utcnow())
                             ).rowcount == 1

    def fail_job(self, job_id: str, error: str, worker: str | None = None) -> bool:
        """Mark a queued or running job (given `worker`: a job that worker runs) failed with
        its error message; nothing else changes. False when it was not such a job."""
        owned = _owned(worker) if worker is not None else (
            JobRow.state.in_(("queued", "running")),)
        with self._tx() as s:
            return s.execute(update(JobRow).where(JobRow.id == job_id, *owned)
                             .values(state="failed", error=_text(error, 4000),
                                     finished_at=utcnow(), stage="failed")).rowcount == 1

    def complete_job(self, job_id: str, profile_json: str,
                     worker: str | None = None) -> ProfileRecord:
        """In one transaction: write the job's profile version, activate it if the job asked
        to and the active pointer is still the one it saw, and mark the job succeeded.

        Raises JobLostError, landing nothing, when the job is not running (or, given
        `worker`, is run by another worker: it was re-queued meanwhile)."""
        for attempt in range(5):
            try:
                with self._tx() as s:
                    job = s.get(JobRow, job_id)
                    if job is None:
                        raise NotFoundError(f"job {job_id!r} does not exist")
                    # Lock first, then read the job again: nobody re-queues it under us.
                    self._serialize(s, "profile", job.name)
                    s.refresh(job, with_for_update=True)
                    if job.state != "running" or (worker is not None and job.worker != worker):
                        raise JobLostError(f"job {job_id} is {job.state} (worker "
                                           f"{job.worker}), not running here; result dropped")
                    record, refused = self._insert_version(
                        s, job.name, profile_json, job.dump_sha256, job.id, job.activate,
                        job.seen_generation)
                    job.state, job.progress, job.stage = "succeeded", 1.0, "done"
                    job.finished_at, job.profile_id = utcnow(), record.id
                    if job.activate:
                        job.activation = "activated" if refused is None else (
                            f"not activated: {refused} (it saw "
                            f"{_seen(job.name, job.seen_version)}); {record.ref} landed "
                            f"inactive, activate it to serve it")
                    return record
            except IntegrityError:
                if attempt == 4:
                    raise
        raise AssertionError("unreachable")

    def running_workers(self) -> set[str]:
        """The workers that have running jobs (None for jobs claimed without a worker id)."""
        with self._session() as s:
            return set(s.scalars(select(JobRow.worker).distinct()
                                 .where(JobRow.state == "running", JobRow.worker.is_not(None))))

    def requeue_stale(self, older_than: timedelta | None, max_attempts: int = 3,
                      dead_workers: Collection[str] = (),
                      why: str = "its worker process died") -> int:
        """Re-queue running jobs whose heartbeat is older than `older_than`, or whose worker is
        in `dead_workers` (known gone, `why`: no need to wait); a job already tried
        `max_attempts` times fails instead. How many jobs were re-queued or failed.

        Each change is one UPDATE whose WHERE checks the job is still running, so a job that
        lands meanwhile is never re-queued."""
        cases = []
        if dead_workers:
            cases.append((JobRow.worker.in_(sorted(dead_workers)), why))
        if older_than is not None:
            cutoff = utcnow() - older_than
            cases.append((or_(JobRow.heartbeat_at.is_(None), JobRow.heartbeat_at < cutoff),
                          f"no heartbeat for {older_than.total_seconds():g} s"))
        n = 0
        with self._tx() as s:
            for condition, reason in cases:
                stale = (JobRow.state == "running", condition)
                if s.scalar(select(JobRow.id).where(*stale).limit(1)) is None:
                    continue                        # the usual case: no write at all
                n += s.execute(update(JobRow).where(*stale, JobRow.attempts >= max_attempts)
                               .values(state="failed", stage="failed", worker=None,
                                       finished_at=utcnow(),
                                       error="interrupted " + cast(JobRow.attempts, String)
                                       + f" times (worker stopped: {reason})")).rowcount
                n += s.execute(update(JobRow).where(*stale)
                               .values(state="queued", worker=None,
                                       stage=f"re-queued: interrupted ({reason})")).rowcount
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


def _owned(worker: str | None) -> tuple[Any, ...]:
    """WHERE terms of a job that is running (and, given `worker`, run by that worker)."""
    running = JobRow.state == "running"
    return (running,) if worker is None else (running, JobRow.worker == worker)


def _move(active: ActiveRow, row: ProfileRow) -> None:
    """Point `active` at `row` (a new generation, even if it is the version already active)."""
    active.profile_id, active.version, active.activated_at = row.id, row.version, utcnow()
    active.generation = (active.generation or 0) + 1


def _seen(name: str, version: int | None) -> str:
    return f"{name}@{version}" if version else "no active version"


def _text(value: str | None, limit: int) -> str | None:
    """`value` cut to `limit` characters, without NUL (Postgres text cannot hold it)."""
    return None if value is None else value.replace("\x00", "")[:limit]


def _profile(row: ProfileRow, active_version: int | None) -> ProfileRecord:
    return ProfileRecord(id=row.id, name=row.name, version=row.version,
                         created_at=aware(row.created_at) or datetime.min,
                         sha256=row.sha256, dump_sha256=row.dump_sha256, job_id=row.job_id,
                         active=row.version == active_version, json=row.json)
