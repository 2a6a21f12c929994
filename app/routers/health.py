"""Liveness (/healthz) and readiness (/readyz: store open, default profile loaded)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from app.deps import CacheDep, SettingsDep, StoreDep
from app.store import NotFoundError

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz() -> dict[str, str]:
    """The process is up and serving HTTP."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"description": "Not ready; `checks` says why."}})
def readyz(store: StoreDep, cache: CacheDep, settings: SettingsDep) -> JSONResponse:
    """Ready when the store answers and the default profile's active version is loaded."""
    checks: dict[str, str] = {}
    ok = store.ping()
    checks["store"] = "ok" if ok else "unreachable"
    if ok:
        try:
            loaded = cache.resolve(settings.default_profile, settings.default_profile)
            checks["profile"] = loaded.record.ref
        except NotFoundError as exc:
            ok, checks["profile"] = False, str(exc)
        except ValueError as exc:
            ok, checks["profile"] = False, f"stored profile does not load: {exc}"
    return JSONResponse({"status": "ready" if ok else "not ready", "checks": checks},
                        status_code=200 if ok else 503)
