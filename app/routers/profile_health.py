"""GET /v1/profiles/{name}/health: calibration health of a profile version from feedback."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from app.feedback.health_document import health_document
from app.http.deps import CacheDep, SettingsDep, StoreDep
from app.http.errors import RequestError
from app.schemas.profile_health import HealthDocument
from app.schemas.types import ALIAS_PATTERN, ErrorResponse, ProfileName, Version

router = APIRouter(prefix="/v1/profiles", tags=["health"])


@router.get("/{name}/health", response_model=HealthDocument,
            responses={404: {"model": ErrorResponse}})
def profile_health(
    name: ProfileName, store: StoreDep, cache: CacheDep, settings: SettingsDep,
    version: Annotated[Version | None, Query(description="A version (default: the "
                                                         "champion).")] = None,
    alias: Annotated[str | None, Query(description="An alias instead of a version.",
                                       min_length=1, max_length=64, pattern=ALIAS_PATTERN,
                                       examples=["champion"])] = None,
) -> dict:
    """Status (ok | degraded | insufficient) and figures of a version's calibration health."""
    if version is not None and alias is not None:
        raise RequestError(["query", "alias"], "give version or alias, not both")
    ref = name if version is None and alias is None else f"{name}@{version or alias}"
    loaded = cache.resolve(ref, settings.default_profile, loc=("path", "name"))
    return health_document(store, loaded, settings.health_window_frames)
