"""Models of the alias endpoints."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from app.schemas.types import Version


class AliasIn(BaseModel):
    """Where to point an alias."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"version": 1}]})

    version: Version = Field(description="The immutable version the alias points at.")


class AliasOut(BaseModel):
    """An alias of a profile name and the version it points at (`champion` is the active
    version)."""

    name: str = Field(examples=["lidar"])
    alias: str = Field(examples=["challenger"])
    version: int = Field(examples=[3])
    id: str = Field(description="`name@version` it points at", examples=["lidar@3"])
    updated_at: datetime


class AliasList(BaseModel):
    """Every alias of a profile name, `champion` first."""

    name: str
    aliases: list[AliasOut]
