"""Profiles: list names, list versions, read one version, activate (roll back) a version."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Path

from app.http.deps import AdminIdDep, StoreDep
from app.schemas.profiles import ProfileDetail, ProfileSummary, ProfileVersions, VersionSummary
from app.schemas.types import ErrorResponse, ProfileName, Version
from app.store import AuditEntry, ProfileRecord

router = APIRouter(prefix="/v1/profiles", tags=["profiles"])
NOT_FOUND = {404: {"model": ErrorResponse}}

VersionPath = Annotated[Version, Path()]


def _summary(r: ProfileRecord) -> VersionSummary:
    return VersionSummary(id=r.ref, name=r.name, version=r.version, active=r.active,
                          created_at=r.created_at, sha256=r.sha256, dump_sha256=r.dump_sha256,
                          job_id=r.job_id)


@router.get("")
def list_profiles(store: StoreDep) -> list[ProfileSummary]:
    """Every profile name with its active version."""
    return [ProfileSummary(**vars(s)) for s in store.names()]


@router.get("/{name}", responses=NOT_FOUND)
def list_versions(name: ProfileName, store: StoreDep) -> ProfileVersions:
    """Every version of one profile name, oldest first."""
    versions = store.versions(name)
    active = next((v.version for v in versions if v.active), None)
    return ProfileVersions(name=name, active_version=active,
                           versions=[_summary(v) for v in versions])


@router.get("/{name}/{version}", responses=NOT_FOUND)
def get_version(name: ProfileName, version: VersionPath, store: StoreDep) -> ProfileDetail:
    """One version's parameters and before/after report."""
    r = store.get(name, version)
    return ProfileDetail(**_summary(r).model_dump(), profile=json.loads(r.json))


@router.post("/{name}/{version}/activate",
             responses={**NOT_FOUND, 401: {"model": ErrorResponse},
                        403: {"model": ErrorResponse}})
def activate(name: ProfileName, version: VersionPath, store: StoreDep, token: AdminIdDep
             ) -> VersionSummary:
    """Make a version the active one (alias `champion`) of its name, atomically (rolling back
    = an older one)."""
    # the store adds `previous`, read in the write's own transaction
    audit = AuditEntry("activate", f"{name}@champion", token, {"version": version})
    return _summary(store.activate(name, version, audit))
