"""Models of GET /v1/audit."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from app.store import AUDIT_ACTIONS


class AuditOut(BaseModel):
    """One write, recorded once it was done (append-only)."""

    id: int = Field(description="Increasing entry number (page with `before`).")
    at: datetime
    action: str = Field(description=" | ".join(AUDIT_ACTIONS), examples=["alias"])
    target: str = Field(examples=["lidar@challenger"])
    token_id: str = Field(description="Id of the admin token that wrote it (`tok-` + 12 hex "
                                      "digits of its sha256; never the token).",
                          examples=["tok-3f2a9c1b7d4e"])
    detail: dict[str, Any] = Field(examples=[{"version": 3, "previous": 2}])


class AuditPage(BaseModel):
    """The newest entries first; `next_before` pages on (null: no older entries)."""

    entries: list[AuditOut]
    next_before: int | None
