"""Plain records the store hands out (detached from any database session)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

JOB_STATES = ("queued", "running", "succeeded", "failed")


def aware(ts: datetime | None) -> datetime | None:
    """`ts` with UTC attached when the database returned it naive (SQLite)."""
    if ts is None or ts.tzinfo is not None:
        return ts
    return ts.replace(tzinfo=UTC)


class NotFoundError(LookupError):
    """A profile, version or job that does not exist."""


class JobLostError(RuntimeError):
    """A job this worker no longer owns: re-queued (its worker was taken for dead) or
    finished by someone else; its result must not land."""


@dataclass(frozen=True)
class ProfileRecord:
    """One stored profile version; `json` is the CalibrationProfile JSON text."""

    id: int
    name: str
    version: int
    created_at: datetime
    sha256: str
    dump_sha256: str | None
    job_id: str | None
    active: bool
    json: str

    @property
    def ref(self) -> str:
        """The public id of this version: `name@version`."""
        return f"{self.name}@{self.version}"


@dataclass(frozen=True)
class NameSummary:
    """A profile name with its active version and how many versions it has."""

    name: str
    active_version: int | None
    n_versions: int
    latest_version: int


@dataclass(frozen=True)
class DumpRecord:
    """An uploaded file kept content-addressed on disk."""

    sha256: str
    kind: str
    size: int
    created: bool


@dataclass(frozen=True)
class CleanReport:
    """What a clean-up of the dumps directory removed (`skipped`: an upload held the lock)."""

    partial: int = 0
    dumps: int = 0
    bytes: int = 0
    skipped: bool = False


class JobFields(BaseModel):
    """A fit job's public fields, defined once: what the store hands out and the API returns."""

    id: str
    name: str
    state: str = Field(description=" | ".join(JOB_STATES))
    progress: float = Field(ge=0.0, le=1.0)
    stage: str | None
    error: str | None
    options: dict[str, Any]
    dump_sha256: str
    gt_sha256: str | None
    activate: bool
    attempts: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    activation: str | None = Field(
        None, description="Jobs with `activate`, once landed: `activated`, or `not activated: "
                          "<why>` when the profile's active version was changed after the job "
                          "was submitted (the new version then lands inactive); else null.")


class JobRecord(JobFields):
    """A fit job and, when it succeeded, the profile version it wrote."""

    model_config = ConfigDict(frozen=True)

    profile_id: int | None
    profile_version: int | None
    worker: str | None = None

    @classmethod
    def from_row(cls, row: Any, version: int | None) -> JobRecord:
        return cls(id=row.id, name=row.name, state=row.state, progress=row.progress,
                   stage=row.stage, error=row.error, options=json.loads(row.options),
                   dump_sha256=row.dump_sha256, gt_sha256=row.gt_sha256,
                   activate=bool(row.activate), attempts=row.attempts,
                   created_at=aware(row.created_at), started_at=aware(row.started_at),
                   finished_at=aware(row.finished_at), activation=row.activation,
                   profile_id=row.profile_id, profile_version=version, worker=row.worker)
