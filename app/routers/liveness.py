"""Liveness (/healthz) and readiness (/readyz: store open, default profile loaded)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.http.deps import CacheDep, SettingsDep, StoreDep
from app.schemas.liveness import Health, Readiness
from app.store import NotFoundError
from calibrators.core.vocab import PROFILE_KINDS

router = APIRouter(tags=["health"])


@router.get("/healthz")
async def healthz() -> Health:
    """The process is up and serving HTTP."""
    # async: answered on the event loop itself, with no hand-off to a worker thread that
    # would queue behind the threads calibrating large requests.
    return Health()


@router.get("/readyz", responses={503: {"model": Readiness,
                                        "description": "Not ready; `checks` says why."}})
def readyz(store: StoreDep, cache: CacheDep, settings: SettingsDep, response: Response
           ) -> Readiness:
    """Ready when the store answers and the default profile's active version is loaded."""
    checks: dict[str, str] = {}
    ok = store.ping()
    checks["store"] = "ok" if ok else "unreachable"
    if ok:
        try:
            loaded = cache.resolve(settings.default_profile, settings.default_profile,
                                   kinds=PROFILE_KINDS)
            checks["profile"] = loaded.record.ref
        except NotFoundError as exc:
            ok, checks["profile"] = False, str(exc)
        except ValueError as exc:
            ok, checks["profile"] = False, f"stored profile does not load: {exc}"
    if not ok:
        response.status_code = 503
    return Readiness(status="ready" if ok else "not ready", checks=checks)
