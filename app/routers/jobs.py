"""GET /v1/jobs/{id}: a fit job's state, progress, and the version and report it produced.

Jobs carry fit options and error text: reading them takes the admin or the feedback token
(the feedback token's requests may queue a challenger fit whose id they are given)."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Path, Query

from app.http.deps import FeedbackIdDep, StoreDep
from app.schemas.profiles import JobOut
from app.schemas.types import ErrorResponse, ProfileRef
from app.store import JobRecord, Store

router = APIRouter(prefix="/v1/jobs", tags=["fit"])
TOKEN_ERRORS = {code: {"model": ErrorResponse} for code in (401, 403)}


def job_out(store: Store, job: JobRecord) -> JobOut:
    """The response body of a job (with the profile's report once it succeeded)."""
    out = JobOut.model_validate(job, from_attributes=True)
    if job.profile_version is not None:
        r = store.get(job.name, job.profile_version)
        out.profile = ProfileRef(id=r.ref, name=r.name, version=r.version, sha256=r.sha256)
        out.report = json.loads(r.json).get("report")
    return out


@router.get("", responses=TOKEN_ERRORS)
def list_jobs(store: StoreDep, _: FeedbackIdDep,
              limit: Annotated[int, Query(ge=1, le=100)] = 20) -> list[JobOut]:
    """The newest fit jobs, newest first (without reports)."""
    return [JobOut.model_validate(j, from_attributes=True) for j in store.recent_jobs(limit)]


@router.get("/{job_id}", responses={404: {"model": ErrorResponse}, **TOKEN_ERRORS})
def get_job(job_id: Annotated[str, Path(pattern=r"^[0-9a-f]{32}$", description=(
                "the job's id: 32 lowercase hex digits, as POST /v1/fit returned it"))],
            store: StoreDep,
            _: FeedbackIdDep) -> JobOut:
    """State, progress and error of a fit job; its version and report when it succeeded."""
    return job_out(store, store.get_job(job_id))
