"""Models of the profile, fit and job endpoints."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from app.schemas.types import ProfileRef
from app.store.records import JobFields


class ProfileSummary(BaseModel):
    """A profile name: its active version and how many versions it has."""

    name: str = Field(examples=["lidar"])
    active_version: int | None = Field(examples=[2])
    n_versions: int = Field(examples=[3])
    latest_version: int = Field(examples=[3])


class VersionSummary(BaseModel):
    """One immutable profile version."""

    id: str = Field(examples=["lidar@2"])
    name: str
    version: int
    active: bool
    created_at: datetime
    sha256: str
    dump_sha256: str | None
    job_id: str | None


class ProfileVersions(BaseModel):
    """Every version of one profile name, oldest first."""

    name: str
    active_version: int | None
    versions: list[VersionSummary]


class ProfileDetail(VersionSummary):
    """A version with its parameters and before/after report (the profile JSON)."""

    profile: dict[str, Any] = Field(description="CalibrationProfile JSON: temperature, depth_k, "
                                                "pooled_k, classes, score_mode, cov_dims, "
                                                "report, provenance, ...; or, with `kind` "
                                                "`boxes2d`, a 2-D profile (Profile2D JSON: "
                                                "categories, score_calibration, regions, "
                                                "report, provenance, ...)")


class FitAccepted(BaseModel):
    """A queued fit job."""

    job_id: str = Field(examples=["6f1c0b9e2d4a4c4f9a3e8d7b1c2a5f60"])
    status_url: str = Field(examples=["/v1/jobs/6f1c0b9e2d4a4c4f9a3e8d7b1c2a5f60"])
    dump_sha256: str
    name: str


class JobOut(JobFields):
    """A fit job's state, progress and, when it succeeded, the version and its report."""

    profile: ProfileRef | None = None
    report: dict[str, Any] | None = None
