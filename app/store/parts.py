"""What the bases of `Store` (aliases, health, ...) use from it, declared once."""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from app.store.audit import AuditEntry


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
