"""`Annotated` dependency aliases: settings, store, profile cache, job runner, metrics, admin."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.cache import ProfileCache
from app.jobs import JobRunner
from app.prometheus import ServiceMetrics
from app.settings import Settings
from app.store import Store

_bearer = HTTPBearer(auto_error=False, description="DETCAL_ADMIN_TOKEN")


def _settings(request: Request) -> Settings:
    return request.app.state.settings


def _store(request: Request) -> Store:
    return request.app.state.store


def _cache(request: Request) -> ProfileCache:
    return request.app.state.cache


def _runner(request: Request) -> JobRunner:
    return request.app.state.runner


def _metrics(request: Request) -> ServiceMetrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(_settings)]
StoreDep = Annotated[Store, Depends(_store)]
CacheDep = Annotated[ProfileCache, Depends(_cache)]
RunnerDep = Annotated[JobRunner, Depends(_runner)]
MetricsDep = Annotated[ServiceMetrics, Depends(_metrics)]


def require_admin(settings: SettingsDep, credentials: Annotated[
        HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Admit only a request bearing the configured admin token (constant-time comparison)."""
    if settings.admin_token is None:
        raise HTTPException(status.HTTP_403_FORBIDDEN, "admin token not configured")
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "admin bearer token required",
                            headers={"WWW-Authenticate": "Bearer"})
    expected = settings.admin_token.get_secret_value().encode()
    if not hmac.compare_digest(credentials.credentials.encode(), expected):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong admin token")


AdminDep = Annotated[None, Depends(require_admin)]


def require_json(request: Request) -> None:
    """Refuse a body that is not declared as JSON (415), before it is validated."""
    ctype = request.headers.get("content-type", "")
    media = ctype.split(";", 1)[0].strip().lower()
    if media != "application/json" and not media.endswith("+json"):
        raise HTTPException(status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
                            f"Content-Type must be application/json, got {ctype or 'none'!r}")
