"""Fit jobs in the store (a base of `Store`): queue, claim, progress, fail, land, re-queue.

A fit job is owned by the worker that claimed it: only that worker's progress, failure or
result counts (a re-queued job's late result is refused with JobLostError). A job submitted
with `activate` remembers the active pointer it saw and, when it lands, moves the pointer
only if nobody moved it since (compare-and-set in the landing transaction).
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Collection
from contextlib import AbstractContextManager
from datetime import timedelta
from typing import Any

from sqlalchemy import String, cast, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from app.store.audit import AuditEntry
from app.store.models import ActiveRow, JobRow, ProfileRow, utcnow
from app.store.records import JobLostError, JobRecord, NotFoundError, ProfileRecord


class JobQueue:
    """The fit-job part of `Store`, which provides sessions, the per-name lock and the
    version insert."""

    _session: sessionmaker[Session]

    def _tx(self) -> AbstractContextManager[Session]:
        raise NotImplementedError

    def _serialize(self, conn: Any, scope: str, name: str) -> None:
        raise NotImplementedError

    def _insert_version(self, s: Session, name: str, profile_json: str, *args: Any
                        ) -> tuple[ProfileRecord, str | None]:
        raise NotImplementedError

    def _audit(self, s: Session, entry: AuditEntry | None) -> None:
        raise NotImplementedError

    def _point_alias(self, s: Session, name: str, alias: str, profile_id: int,
                     version: int) -> Any:
        raise NotImplementedError

    def create_job(self, name: str, options: dict[str, Any], dump_sha256: str,
                   gt_sha256: str | None = None, activate: bool = False,
                   audit: AuditEntry | None = None, alias: str | None = None) -> JobRecord:
        """Queue a fit job of `name` on a stored dump; with `activate`, note the active pointer
        now (the job activates its version only if the pointer has not moved when it lands).
        `audit` is recorded with the job's id in its detail, in the same transaction; `alias`
        (not champion) is pointed at the version when it lands."""
        row = JobRow(id=uuid.uuid4().hex, name=name, state="queued", progress=0.0,
                     options=json.dumps(options, sort_keys=True), dump_sha256=dump_sha256,
                     gt_sha256=gt_sha256, activate=activate, attempts=0, created_at=utcnow(),
                     alias=alias)
        with self._tx() as s:
            if activate:
                seen = s.execute(select(ActiveRow.version, ActiveRow.generation)
                                 .where(ActiveRow.name == name)).first()
                row.seen_version, row.seen_generation = tuple(seen) if seen else (0, 0)
            s.add(row)
            if audit is not None:
                self._audit(s, AuditEntry(audit.action, audit.target, audit.token_id,
                                          {**audit.detail, "job_id": row.id}))
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
                    if job.alias:
                        self._point_alias(s, job.name, job.alias, record.id, record.version)
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


def _seen(name: str, version: int | None) -> str:
    return f"{name}@{version}" if version else "no active version"


def _text(value: str | None, limit: int) -> str | None:
    """`value` cut to `limit` characters, without NUL (Postgres text cannot hold it)."""
    return None if value is None else value.replace("\x00", "")[:limit]
