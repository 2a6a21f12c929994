"""What the bases of `Store` (aliases, health, ...) use from it, declared once."""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.store.audit import AuditEntry
from app.store.models import ProfileRow
from app.store.records import NotFoundError


def version_row(s: Session, name: str, version: int) -> ProfileRow:
    """The stored row of version `version` of `name`; NotFoundError if there is none."""
    row = s.scalar(select(ProfileRow).where(ProfileRow.name == name,
                                            ProfileRow.version == version))
    if row is None:
        raise NotFoundError(f"profile {name!r} has no version {version}")
    return row


class StorePart:
    """A base of `Store`: `Store` provides the session factory, transactions, the per-name
    locks (`_serialize`) and the audit log (`_audit`)."""

    _session: sessionmaker[Session]

    def _tx(self) -> AbstractContextManager[Session]:
        raise NotImplementedError

    def _serialize(self, conn: Any, scope: str, name: str) -> None:
        raise NotImplementedError

    def _audit(self, s: Session, entry: AuditEntry | None) -> None:
        raise NotImplementedError

    def _audit_previous(self, s: Session, entry: AuditEntry | None,
                        previous: int | None) -> None:
        raise NotImplementedError
