"""GET /v1/audit: the append-only log of every write (admin only)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from app.http.deps import AdminDep, StoreDep
from app.schemas.audit import AuditOut, AuditPage
from app.schemas.types import ErrorResponse, ProfileName
from app.store import AUDIT_ACTIONS

router = APIRouter(prefix="/v1", tags=["audit"])


@router.get("/audit", responses={401: {"model": ErrorResponse}, 403: {"model": ErrorResponse}})
def audit_log(
    store: StoreDep, _: AdminDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    before: Annotated[int | None, Query(ge=1, le=2**62, description="Only entries with a "
                                                                    "smaller id (paging).")] = None,
    action: Annotated[Literal[AUDIT_ACTIONS] | None, Query()] = None,  # type: ignore[valid-type]
    name: Annotated[ProfileName | None, Query(description="Only writes to this profile name "
                                                          "(its versions and aliases).")] = None,
) -> AuditPage:
    """Every write (fit, activate, alias, alias.delete, feedback), newest first: when, what and
    which admin token (by id)."""
    entries = store.audit_log(limit, before, action, name)
    return AuditPage(entries=[AuditOut(**vars(e)) for e in entries],
                     next_before=entries[-1].id if len(entries) == limit else None)
