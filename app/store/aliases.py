"""Profile aliases (a base of `Store`): mutable names pointing at immutable versions.

`champion` is the active pointer itself (`active_profiles`): setting it is an activation, so
clients that call `activate` or calibrate with a bare name keep working. Every other alias is a
row of `profile_aliases`. Moves serialize per profile name like activations.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.store.audit import AuditEntry
from app.store.base import StorePart, version_row
from app.store.models import ActiveRow, AliasRow, utcnow
from app.store.records import NotFoundError, ProfileRecord, aware

log = logging.getLogger("detcal.store")

#: The alias that is the active pointer.
CHAMPION = "champion"


@dataclass(frozen=True)
class AliasRecord:
    """An alias of a profile name and the version it points at."""

    name: str
    alias: str
    version: int
    updated_at: datetime


class AliasStore(StorePart):
    """Set, move, delete and read aliases (`Store` provides sessions, locks and activation)."""

    def activate(self, name: str, version: int, audit: AuditEntry | None = None
                 ) -> ProfileRecord:
        raise NotImplementedError

    def set_alias(self, name: str, alias: str, version: int,
                  audit: AuditEntry | None = None) -> AliasRecord:
        """Point `alias` of `name` at `version` (created or moved; `champion` activates it);
        NotFoundError if the version does not exist. `audit` is recorded in the same
        transaction, its `detail.previous` the version the alias pointed at before (None)."""
        if alias == CHAMPION:
            record = self.activate(name, version, audit)
            return AliasRecord(name, alias, record.version, utcnow())
        with self._tx() as s:
            self._serialize(s, "profile", name)
            row = version_row(s, name, version)
            current = s.get(AliasRow, (name, alias))
            previous = None if current is None else current.version
            record = self._point_alias(s, name, alias, row.id, version)
            self._audit_previous(s, audit, previous)
        log.info("alias %s@%s -> %d (was %s)", name, alias, version, previous)
        return record

    @staticmethod
    def _point_alias(s: Session, name: str, alias: str, profile_id: int, version: int
                     ) -> AliasRecord:
        """Create or move `alias` (not champion) in the transaction of `s` (the caller holds
        the name's lock)."""
        current = s.get(AliasRow, (name, alias))
        now = utcnow()
        if current is None:
            s.add(AliasRow(name=name, alias=alias, profile_id=profile_id, version=version,
                           updated_at=now))
        else:
            current.profile_id, current.version, current.updated_at = profile_id, version, now
        return AliasRecord(name, alias, version, now)

    def delete_alias(self, name: str, alias: str, audit: AuditEntry | None = None) -> AliasRecord:
        """Remove `alias` of `name` (not `champion`: activate another version instead);
        NotFoundError if it does not exist."""
        with self._tx() as s:
            self._serialize(s, "profile", name)
            row = s.get(AliasRow, (name, alias))
            if row is None:
                raise NotFoundError(f"profile {name!r} has no alias {alias!r}")
            record = AliasRecord(name, alias, row.version, aware(row.updated_at) or utcnow())
            s.delete(row)
            self._audit_previous(s, audit, row.version)
        log.info("alias %s@%s deleted (was %d)", name, alias, record.version)
        return record

    def aliases(self, name: str) -> list[AliasRecord]:
        """Every alias of `name`, `champion` first (if the name has an active version)."""
        with self._session() as s:
            active = s.get(ActiveRow, name)
            rows = s.scalars(select(AliasRow).where(AliasRow.name == name)
                             .order_by(AliasRow.alias)).all()
        out = [] if active is None else [
            AliasRecord(name, CHAMPION, active.version, aware(active.activated_at) or utcnow())]
        return out + [AliasRecord(r.name, r.alias, r.version, aware(r.updated_at) or utcnow())
                      for r in rows]

    def alias_version(self, name: str, alias: str) -> int:
        """The version `alias` of `name` points at; NotFoundError if none."""
        with self._session() as s:
            if alias == CHAMPION:
                version = s.scalar(select(ActiveRow.version).where(ActiveRow.name == name))
            else:
                version = s.scalar(select(AliasRow.version).where(AliasRow.name == name,
                                                                   AliasRow.alias == alias))
        if version is None:
            raise NotFoundError(f"profile {name!r} has no alias {alias!r}")
        return version
