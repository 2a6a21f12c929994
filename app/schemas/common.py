"""Shared pydantic types: finite floats, references to profile versions, error bodies."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import BaseModel, Field

Finite = Annotated[float, Field(allow_inf_nan=False)]
Probability = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
ProfileName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$",
                                   examples=["lidar"])]


class ProfileRef(BaseModel):
    """The profile version a response was computed with."""

    id: str = Field(description="`name@version`", examples=["lidar@2"])
    name: str = Field(examples=["lidar"])
    version: int = Field(examples=[2])
    sha256: str = Field(description="sha256 of the stored profile JSON")


class ErrorItem(BaseModel):
    """One problem with a request: where (`loc`) and why (`msg`)."""

    loc: list[str | int] = Field(examples=[["body", "frames", 0, "detections", 3, "covariance"]])
    msg: str = Field(examples=["covariance is not positive semi-definite"])
    type: str = Field(examples=["value_error"])


class ErrorResponse(BaseModel):
    """The body of every 4xx: a message or a list of located problems."""

    detail: str | list[ErrorItem]


class Timestamped(BaseModel):
    """Mixin for records with a creation time."""

    created_at: datetime
