"""Persistence: SQLAlchemy tables and the `Store` repository."""

from app.store.records import (
    CleanReport,
    JobLostError,
    JobRecord,
    NameSummary,
    NotFoundError,
    ProfileRecord,
)
from app.store.repository import Store

__all__ = ["CleanReport", "JobLostError", "JobRecord", "NameSummary", "NotFoundError",
           "ProfileRecord", "Store"]
