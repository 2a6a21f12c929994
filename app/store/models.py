"""SQLAlchemy 2 tables of the profile store: profile versions, active pointers, aliases, dumps,
fit jobs, the audit log and feedback health."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from sqlalchemy import (
    Connection,
    DateTime,
    Float,
    ForeignKey,
    String,
    Text,
    UniqueConstraint,
    inspect,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column


def utcnow() -> datetime:
    """The current time, UTC, timezone-aware."""
    return datetime.now(UTC)


#: A timestamp set to the current time when the row is inserted.
Created = Annotated[datetime, mapped_column(default=utcnow)]
#: A sha256 hex digest.
Sha256 = Annotated[str, mapped_column(String(64))]


class Base(DeclarativeBase):
    """Declarative base of every detcal table: every timestamp is stored with its time zone
    (`int` and `bool` map to Integer and Boolean)."""

    type_annotation_map = {datetime: DateTime(timezone=True)}


class ProfileRow(Base):
    """One immutable profile version: `(name, version)` is unique, `json` never changes."""

    __tablename__ = "profiles"
    __table_args__ = (UniqueConstraint("name", "version", name="uq_profile_name_version"),)

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64), index=True)
    version: Mapped[int]
    created_at: Mapped[Created]
    json: Mapped[str] = mapped_column(Text)
    sha256: Mapped[Sha256]
    dump_sha256: Mapped[str | None] = mapped_column(String(64))
    job_id: Mapped[str | None] = mapped_column(String(32))


class ActiveRow(Base):
    """The active version of each profile name (exactly one row per name that has versions).

    `generation` counts the pointer's moves (1 when created, +1 on every activation, even of
    the version already active): a fit job compares it to the one it saw when submitted.
    """

    __tablename__ = "active_profiles"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    profile_id: Mapped[int] = mapped_column(ForeignKey("profiles.id"))
    version: Mapped[int]
    activated_at: Mapped[Created]
    generation: Mapped[int] = mapped_column(default=1, server_default=text("1"))


class DumpRow(Base):
    """An uploaded file kept on disk under `dumps/<sha256>`."""

    __tablename__ = "dumps"

    sha256: Mapped[Sha256] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    size: Mapped[int]
    created_at: Mapped[Created]
    #: Last upload of these bytes (clean-up keeps a dump this recent even if unreferenced).
    used_at: Mapped[datetime | None]


class JobRow(Base):
    """A fit job: queued -> running -> succeeded | failed.

    `worker` is the runner instance running it; `seen_version` and `seen_generation` are the
    name's active pointer when an `activate` job was submitted (0: no version was active);
    `activation` is what landing did about activation (None without `activate`).
    """

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(64))
    state: Mapped[str] = mapped_column(String(16), index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(200))
    error: Mapped[str | None] = mapped_column(Text)
    options: Mapped[str] = mapped_column(Text)
    dump_sha256: Mapped[str] = mapped_column(ForeignKey("dumps.sha256"))
    gt_sha256: Mapped[str | None] = mapped_column(ForeignKey("dumps.sha256"))
    activate: Mapped[bool] = mapped_column(default=False)
    attempts: Mapped[int] = mapped_column(default=0)
    created_at: Mapped[Created]
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    heartbeat_at: Mapped[datetime | None]
    profile_id: Mapped[int | None] = mapped_column(ForeignKey("profiles.id"))
    worker: Mapped[str | None] = mapped_column(String(128))
    seen_version: Mapped[int | None]
    seen_generation: Mapped[int | None]
    activation: Mapped[str | None] = mapped_column(Text)
    #: An alias the landed version is pointed at (`challenger` for an automatic refit).
    alias: Mapped[str | None] = mapped_column(String(64))


class AliasRow(Base):
    """A mutable alias of a profile name (`challenger`, any name but `champion`, which is the
    active pointer) pointing at one immutable version."""

    __tablename__ = "profile_aliases"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    alias: Mapped[str] = mapped_column(String(64), primary_key=True)
    profile_id: Mapped[int] = mapped_column(ForeignKey("profiles.id"))
    version: Mapped[int]
    updated_at: Mapped[Created]


class AuditRow(Base):
    """One write, appended once it is done and never changed: when, which action on what,
    which admin token (by its id, never the token) and the write's details (JSON)."""

    __tablename__ = "audit_log"

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    action: Mapped[str] = mapped_column(String(32))
    target: Mapped[str] = mapped_column(String(200))
    token_id: Mapped[str] = mapped_column(String(64))
    detail: Mapped[str] = mapped_column(Text)


class HealthRow(Base):
    """A chunk of feedback frames for one profile version, with the version's cumulative sums
    (`calibrators.monitoring.HealthCounts`) and drift-test state (`DriftMonitor`) after it, so a
    window or "since activation" is the difference of two rows."""

    __tablename__ = "feedback_health"
    __table_args__ = (UniqueConstraint("profile_id", "seq", name="uq_health_profile_seq"),)

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    profile_id: Mapped[int] = mapped_column(ForeignKey("profiles.id"), index=True)
    seq: Mapped[int]
    created_at: Mapped[Created]
    frames_total: Mapped[int]
    counts: Mapped[str] = mapped_column(Text)
    drift: Mapped[str] = mapped_column(Text)
    status: Mapped[str] = mapped_column(String(16))
    alarms_total: Mapped[int] = mapped_column(default=0)
    #: The feedback frames themselves, kept while auto_refit is on (last row of a request).
    dump_sha256: Mapped[str | None] = mapped_column(ForeignKey("dumps.sha256"))


def add_missing_columns(conn: Connection) -> list[str]:
    """Add the columns a store created by an older detcal lacks (each nullable or with a
    server default, so ADD COLUMN works on SQLite and Postgres); the `table.column`s added."""
    added = []
    existing = inspect(conn)
    for table in Base.metadata.sorted_tables:
        have = {c["name"] for c in existing.get_columns(table.name)}
        for column in table.columns:
            if column.name in have:
                continue
            ddl = f"ALTER TABLE {table.name} ADD COLUMN {column.name} " + str(
                column.type.compile(conn.dialect))
            if column.server_default is not None:
                ddl += f" NOT NULL DEFAULT {column.server_default.arg.text}"  # type: ignore[attr-defined]
            conn.execute(text(ddl))
            added.append(f"{table.name}.{column.name}")
    return added
