"""Feedback health rows (a base of `Store`): per profile version, one row per chunk of feedback
frames with the version's cumulative sums and drift state after it.

The store keeps JSON text and knows nothing of the statistics: `append_health` locks the
profile name, hands the version's latest row to `advance` (which computes the new rows from it)
and writes what it returns in the same transaction, so two feedback requests for one version
never interleave their sums.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.store.audit import AuditEntry
from app.store.base import StorePart
from app.store.models import ActiveRow, HealthRow, ProfileRow, utcnow
from app.store.records import aware


@dataclass(frozen=True)
class HealthChunk:
    """A row to append: cumulative frames, sums (JSON), drift state (JSON, "" = unchanged
    since... only the last row of a request carries it), status and alarms so far."""

    frames_total: int
    counts: str
    drift: str
    status: str
    alarms_total: int


@dataclass(frozen=True)
class HealthRecord(HealthChunk):
    """A stored row."""

    seq: int
    created_at: datetime


@dataclass(frozen=True)
class HealthOverview:
    """The latest row of a profile version (for /metrics)."""

    name: str
    version: int
    active: bool
    latest: HealthRecord
    profile_id: int


class HealthStore(StorePart):
    """Append and read feedback health (`Store` provides sessions, locks and the audit)."""

    def append_health(self, name: str, profile_id: int,
                      advance: Callable[[HealthRecord | None], list[HealthChunk]],
                      audit: AuditEntry | None = None,
                      dump_sha256: str | None = None) -> list[HealthRecord]:
        """Append the rows `advance(latest row or None)` returns, under the name's lock (the
        last one referencing the kept feedback dump `dump_sha256`, if any)."""
        with self._tx() as s:
            self._serialize(s, "profile", name)
            latest = _latest(s, profile_id)
            chunks = advance(latest)
            seq = 0 if latest is None else latest.seq
            now = utcnow()
            out = []
            for i, chunk in enumerate(chunks):
                seq += 1
                s.add(HealthRow(profile_id=profile_id, seq=seq, created_at=now,
                                frames_total=chunk.frames_total, counts=chunk.counts,
                                drift=chunk.drift, status=chunk.status,
                                alarms_total=chunk.alarms_total,
                                dump_sha256=dump_sha256 if i == len(chunks) - 1 else None))
                out.append(HealthRecord(**vars(chunk), seq=seq, created_at=now))
            self._audit(s, audit)
        return out

    def latest_health(self, profile_id: int) -> HealthRecord | None:
        """The newest row of a version (the one carrying its drift state), or None."""
        with self._session() as s:
            return _latest(s, profile_id)

    def health_at_most(self, profile_id: int, frames_total: int) -> HealthRecord | None:
        """The newest row with at most `frames_total` cumulative frames (a window's base)."""
        with self._session() as s:
            row = s.scalar(select(HealthRow).where(HealthRow.profile_id == profile_id,
                                                   HealthRow.frames_total <= frames_total)
                           .order_by(HealthRow.seq.desc()).limit(1))
        return None if row is None else _record(row)

    def health_before(self, profile_id: int, when: datetime) -> HealthRecord | None:
        """The newest row written before `when` (the base of "since activation")."""
        with self._session() as s:
            row = s.scalar(select(HealthRow).where(HealthRow.profile_id == profile_id,
                                                   HealthRow.created_at < when)
                           .order_by(HealthRow.seq.desc()).limit(1))
        return None if row is None else _record(row)

    def health_series(self, profile_id: int, limit: int = 500) -> list[HealthRecord]:
        """The newest `limit` rows of a version, oldest first (the time series)."""
        with self._session() as s:
            rows = s.scalars(select(HealthRow).where(HealthRow.profile_id == profile_id)
                             .order_by(HealthRow.seq.desc()).limit(limit)).all()
        return [_record(r) for r in reversed(rows)]

    def feedback_dumps(self, profile_id: int) -> list[str]:
        """The kept feedback dumps of a version, oldest first."""
        with self._session() as s:
            return list(s.scalars(select(HealthRow.dump_sha256)
                                  .where(HealthRow.profile_id == profile_id,
                                         HealthRow.dump_sha256.is_not(None))
                                  .order_by(HealthRow.seq)).all())

    def activated_at(self, name: str, version: int) -> datetime | None:
        """When `version` became the active one of `name`, None if it is not active."""
        with self._session() as s:
            row = s.get(ActiveRow, name)
        return None if row is None or row.version != version else aware(row.activated_at)

    def health_overview(self) -> list[HealthOverview]:
        """The latest row of every version that has feedback."""
        with self._session() as s:
            last = (select(HealthRow.profile_id, func.max(HealthRow.seq).label("seq"))
                    .group_by(HealthRow.profile_id).subquery())
            rows = s.execute(
                select(HealthRow, ProfileRow.name, ProfileRow.version, ActiveRow.version)
                .join(last, (last.c.profile_id == HealthRow.profile_id)
                      & (last.c.seq == HealthRow.seq))
                .join(ProfileRow, ProfileRow.id == HealthRow.profile_id)
                .join(ActiveRow, ActiveRow.name == ProfileRow.name, isouter=True)
                .order_by(ProfileRow.name, ProfileRow.version)).all()
        return [HealthOverview(name, version, version == active, _record(row), row.profile_id)
                for row, name, version, active in rows]


def _latest(s: Session, profile_id: int) -> HealthRecord | None:
    row = s.scalar(select(HealthRow).where(HealthRow.profile_id == profile_id)
                   .order_by(HealthRow.seq.desc()).limit(1))
    return None if row is None else _record(row)


def _record(row: HealthRow) -> HealthRecord:
    return HealthRecord(frames_total=row.frames_total, counts=row.counts, drift=row.drift,
                        status=row.status, alarms_total=row.alarms_total, seq=row.seq,
                        created_at=aware(row.created_at) or utcnow())
