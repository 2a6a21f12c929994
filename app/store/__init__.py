"""Persistence: SQLAlchemy tables and the `Store` repository."""

from app.store.aliases import CHAMPION, AliasRecord
from app.store.audit import AUDIT_ACTIONS, AuditEntry, AuditRecord
from app.store.feedback_health import HealthChunk, HealthOverview, HealthRecord
from app.store.records import (
    CleanReport,
    DumpRecord,
    JobLostError,
    JobRecord,
    NameSummary,
    NotFoundError,
    ProfileRecord,
)
from app.store.repository import Store

__all__ = ["AUDIT_ACTIONS", "CHAMPION", "AliasRecord", "AuditEntry", "AuditRecord",
           "CleanReport", "DumpRecord", "HealthChunk", "HealthOverview", "HealthRecord",
           "JobLostError", "JobRecord", "NameSummary", "NotFoundError", "ProfileRecord",
           "Store"]
