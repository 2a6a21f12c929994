"""`Annotated` dependency aliases (settings, store, profile cache, job runner, metrics, admin and
its audit id), the admin-token rule, the middleware that applies it before a body is read, and
the request checks every route shares (JSON content type, no empty form fields)."""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.dependencies.models import Dependant
from fastapi.params import Form
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.security.utils import get_authorization_scheme_param
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.calibrate.cache import ProfileCache
from app.fitting.runner import JobRunner
from app.http.errors import RequestError
from app.http.metrics import ServiceMetrics
from app.settings import Settings
from app.store import Store

_bearer = HTTPBearer(auto_error=False, description="DETCAL_ADMIN_TOKEN")

# The accessors of app.state are `async def`: FastAPI runs a plain `def` dependency in a worker
# thread, a hop of ~0.1 ms per dependency and request for a dictionary read.


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


async def _store(request: Request) -> Store:
    return request.app.state.store


async def _cache(request: Request) -> ProfileCache:
    return request.app.state.cache


async def _runner(request: Request) -> JobRunner:
    return request.app.state.runner


async def _metrics(request: Request) -> ServiceMetrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(_settings)]
StoreDep = Annotated[Store, Depends(_store)]
CacheDep = Annotated[ProfileCache, Depends(_cache)]
RunnerDep = Annotated[JobRunner, Depends(_runner)]
MetricsDep = Annotated[ServiceMetrics, Depends(_metrics)]


def admin_refusal(settings: Settings, authorization: str | None) -> HTTPException | None:
    """Why a request with this `Authorization` header is not admitted as admin (401 without
    a bearer token, 403 with a wrong one), or None (constant-time comparison)."""
    if settings.admin_token is None:
        return HTTPException(status.HTTP_403_FORBIDDEN, "admin token not configured")
    scheme, token = get_authorization_scheme_param(authorization)
    if scheme.lower() != "bearer" or not token:
        return HTTPException(status.HTTP_401_UNAUTHORIZED, "admin bearer token required",
                             headers={"WWW-Authenticate": "Bearer"})
    expected = settings.admin_token.get_secret_value().encode()
    if not hmac.compare_digest(token.encode(), expected):
        return HTTPException(status.HTTP_403_FORBIDDEN, "wrong admin token")
    return None


def require_admin(settings: SettingsDep, request: Request, _: Annotated[
        HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Admit only a request bearing the configured admin token."""
    refusal = admin_refusal(settings, request.headers.get("authorization"))
    if refusal is not None:
        raise refusal


AdminDep = Annotated[None, Depends(require_admin)]


def feedback_refusal(settings: Settings, authorization: str | None) -> HTTPException | None:
    """Why a request is not admitted to send feedback: it needs the admin token or the
    feedback-only token (`DETCAL_FEEDBACK_TOKEN`), compared in constant time; or None."""
    refusal = admin_refusal(settings, authorization)
    if refusal is None or settings.feedback_token is None:
        return refusal
    scheme, token = get_authorization_scheme_param(authorization)
    if scheme.lower() != "bearer" or not token:
        return HTTPException(status.HTTP_401_UNAUTHORIZED, "admin or feedback bearer token "
                             "required", headers={"WWW-Authenticate": "Bearer"})
    expected = settings.feedback_token.get_secret_value().encode()
    if hmac.compare_digest(token.encode(), expected):
        return None
    return HTTPException(status.HTTP_403_FORBIDDEN, "wrong token (the admin or the feedback "
                                                    "token is required)")


def token_id(token: str) -> str:
    """The id the audit log records for an admin token (`tok-` and 12 hex digits of its
    sha256): tells tokens apart, never reveals one."""
    return "tok-" + hashlib.sha256(token.encode()).hexdigest()[:12]


def admin_token_id(request: Request, _: AdminDep) -> str:
    """Admit only the admin token (as `require_admin`) and return its audit id."""
    return token_id(get_authorization_scheme_param(request.headers.get("authorization"))[1])


#: An admitted admin request's token id, for the audit log of its write.
AdminIdDep = Annotated[str, Depends(admin_token_id)]


def feedback_token_id(settings: SettingsDep, request: Request, _: Annotated[
        HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str:
    """Admit the admin or the feedback token (`feedback_refusal`) and return its audit id."""
    authorization = request.headers.get("authorization")
    refusal = feedback_refusal(settings, authorization)
    if refusal is not None:
        raise refusal
    return token_id(get_authorization_scheme_param(authorization)[1])


#: A request admitted to send feedback: its token id.
FeedbackIdDep = Annotated[str, Depends(feedback_token_id)]


def _calls(dependant: Dependant) -> set[object]:
    calls = {dependant.call}
    for sub in dependant.dependencies:
        calls |= _calls(sub)
    return calls


class AdminBeforeBodyMiddleware:
    """Check the admin token of a route that depends on `require_admin` (the admin or feedback
    token of one that depends on `feedback_token_id`) before a single byte of its body is
    handed to the app: the check runs when the app first asks for the body.

    FastAPI reads a form body (spooling uploads to disk) before it runs the route's
    dependencies, so without this an unauthenticated upload would be received in full before
    its 401. Which routes need the token is read from their dependencies; the
    refusal is an HTTPException raised from `receive`, answered by the framework.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    @staticmethod
    def needs_admin(route: object) -> bool:
        """Whether `route` depends on `require_admin` (directly or through other dependencies)."""
        return isinstance(route, APIRoute) and require_admin in _calls(route.dependant)

    @staticmethod
    def gate(route: object) -> Callable[[Settings, str | None], HTTPException | None] | None:
        """The token rule `route` is checked with before its body: `admin_refusal` for routes
        that need the admin token, `feedback_refusal` for feedback, None for the others."""
        if not isinstance(route, APIRoute):
            return None
        calls = _calls(route.dependant)
        if require_admin in calls:
            return admin_refusal
        return feedback_refusal if feedback_token_id in calls else None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        checked = False

        async def checked_receive() -> Message:
            nonlocal checked
            if not checked:
                checked = True
                gate = self.gate(scope.get("route"))   # the route is set once matched
                if gate is not None:
                    refusal = gate(scope["app"].state.settings,
                                   Headers(scope=scope).get("authorization"))
                    if refusal is not None:
                        raise refusal
            return await receive()

        await self.app(scope, checked_receive, send)


def require_json(request: Request) -> None:
    """Refuse a body that is not declared as JSON (415), before it is validated."""
    ctype = request.headers.get("content-type", "")
    media = ctype.split(";", 1)[0].strip().lower()
    if media != "application/json" and not media.endswith("+json"):
        raise HTTPException(status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
                            f"Content-Type must be application/json, got {ctype or 'none'!r}")


async def refuse_empty_form_fields(request: Request) -> None:
    """An empty form field (`name=`) is a 422 naming it: FastAPI would take it for an absent
    field and silently use the default. Leave a field out to get its default. (Applies to
    routes with form fields; FastAPI has parsed their form already, so this reads no body.)"""
    route = request.scope.get("route")
    if not isinstance(route, APIRoute) or not any(
            isinstance(p.field_info, Form) for p in route.dependant.body_params):
        return
    form = await request.form()
    for key, value in form.multi_items():
        if isinstance(value, str) and value == "":
            raise RequestError(["body", key], f"{key} is empty; leave the field out to get "
                                              f"its default")
