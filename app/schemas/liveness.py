"""Models of the liveness and readiness endpoints."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class Health(BaseModel):
    """The process is up."""

    status: Literal["ok"] = "ok"


class Readiness(BaseModel):
    """Whether the service can serve calibrations, and what each check found."""

    status: Literal["ready", "not ready"]
    checks: dict[str, str] = Field(
        description="`store`: ok | unreachable; `profile`: the default profile's active "
                    "version, or why it is not loaded.",
        examples=[{"store": "ok", "profile": "lidar@2"}])
