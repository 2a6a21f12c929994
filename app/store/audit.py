"""The append-only audit log (a base of `Store`): every write once it is done, in the write's
own transaction, so a write that fails or is refused leaves no entry."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.store.models import AuditRow, utcnow
from app.store.records import aware

#: The actions the log records.
AUDIT_ACTIONS = ("fit", "activate", "alias", "alias.delete", "feedback")


@dataclass(frozen=True)
class AuditEntry:
    """A write to record: `action` (one of `AUDIT_ACTIONS`) on `target` (`name`, `name@3`,
    `name@alias`) by the admin token `token_id`, with JSON-able `detail`."""

    action: str
    target: str
    token_id: str
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class AuditRecord:
    """A stored entry: its id (increasing) and time."""

    id: int
    at: datetime
    action: str
    target: str
    token_id: str
    detail: dict[str, Any]


class AuditLog:
    """Append and read the audit log (`Store` provides the sessions)."""

    _session: sessionmaker[Session]

    def _tx(self) -> AbstractContextManager[Session]:
        raise NotImplementedError

    @staticmethod
    def _audit(s: Session, entry: AuditEntry | None) -> None:
        """Add `entry` to the transaction of `s` (nothing for None)."""
        if entry is None:
            return
        if entry.action not in AUDIT_ACTIONS:
            raise ValueError(f"unknown audit action {entry.action!r}")
        s.add(AuditRow(at=utcnow(), action=entry.action, target=entry.target[:200],
                       token_id=entry.token_id[:64],
                       detail=json.dumps(entry.detail, sort_keys=True, default=str)))

    @staticmethod
    def _audit_previous(s: Session, entry: AuditEntry | None, previous: int | None) -> None:
        """Add `entry` with `detail.previous` set to `previous`: the version the pointer held
        as read inside the write's own transaction (under the name's lock), so concurrent
        writers never record a stale one."""
        if entry is not None:
            entry = replace(entry, detail={**entry.detail, "previous": previous})
        AuditLog._audit(s, entry)

    def append_audit(self, entry: AuditEntry) -> None:
        """Record a write done outside the store's other methods."""
        with self._tx() as s:
            self._audit(s, entry)

    def audit_log(self, limit: int = 100, before: int | None = None,
                  action: str | None = None, target: str | None = None) -> list[AuditRecord]:
        """The newest entries first (ids below `before`, of `action`, of `target` or of the
        versions and aliases of that name)."""
        q = select(AuditRow).order_by(AuditRow.id.desc()).limit(limit)
        if before is not None:
            q = q.where(AuditRow.id < before)
        if action is not None:
            q = q.where(AuditRow.action == action)
        if target is not None:
            q = q.where((AuditRow.target == target)
                        | AuditRow.target.startswith(target + "@", autoescape=True))
        with self._session() as s:
            return list(_records(s.scalars(q).all()))


def _records(rows: Any) -> Iterator[AuditRecord]:
    for r in rows:
        yield AuditRecord(id=r.id, at=aware(r.at) or utcnow(), action=r.action,
                          target=r.target, token_id=r.token_id, detail=json.loads(r.detail))
