"""Persistence: SQLAlchemy tables and the `Store` repository."""

from app.store.records import JobRecord, NameSummary, NotFoundError, ProfileRecord
from app.store.repository import Store

__all__ = ["JobRecord", "NameSummary", "NotFoundError", "ProfileRecord", "Store"]
