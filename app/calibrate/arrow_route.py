"""POST /v1/calibrate with an Arrow body, answered below FastAPI's routing and dependency
injection.

The binary path exists for throughput: a 300-detection frame costs the calibrate engine well
under a millisecond, and FastAPI's machinery around it (route matching, dependency solving,
a worker-thread hop per `def` dependency, the response object) cost about as much again.
This middleware answers exactly the requests whose body is an Arrow stream, with the rules
of the documented route: the same query model (`CalibrateQuery`), the same `Accept` rule
(`check_accept`: Arrow, or JSON from a 2-D profile), the same engine and detection counter
(`CalibrateRunner.serve`), the same error bodies (`error_body`). It sits inside the
body-size, admin and metrics middlewares, so their limits, counters and `Server-Timing` apply
unchanged, and it labels the request with the route's template as the router would. Every
other request goes on to FastAPI.
"""

from __future__ import annotations

import json
from types import SimpleNamespace
from urllib.parse import parse_qsl

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Receive, Scope, Send

from app.calibrate.engine import CalibrateCall, CallOutcome
from app.http.content_types import check_accept, media_type
from app.http.errors import error_body
from app.schemas.calibrate_query import CalibrateQuery
from calibrators.io.arrow_batch import ARROW_STREAM

PATH = "/v1/calibrate"
_ROUTE = SimpleNamespace(path=PATH)


class ArrowCalibrateMiddleware:
    """Serve `POST /v1/calibrate` with `Content-Type: application/vnd.apache.arrow.stream`
    from `app.state.calibrator` (see the module docstring); pass everything else on."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (scope["type"] != "http" or scope["method"] != "POST" or scope["path"] != PATH
                or media_type(_header(scope, b"content-type")) != ARROW_STREAM):
            await self.app(scope, receive, send)
            return
        state = scope["app"].state
        scope["route"] = _ROUTE   # what the metrics read: the route template, as routed
        accept = _header(scope, b"accept")
        try:
            check_accept(accept, ARROW_STREAM, "application/json")
            query = _query(scope)
        except (HTTPException, RequestValidationError) as exc:
            await _send(send, _error(exc))
            return
        body = await _body(receive)
        call = CalibrateCall("arrow", body, query.profile, query.ellipse_confidence,
                             None if query.levels is None else tuple(query.levels), accept)
        await _send(send, await state.calibrator.serve(call, state.metrics))


def _header(scope: Scope, name: bytes) -> str:
    for key, value in scope["headers"]:
        if key == name:
            return value.decode("latin-1")
    return ""


def _query(scope: Scope) -> CalibrateQuery:
    """The validated query, or a RequestValidationError located under `query`."""
    pairs = parse_qsl(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True)
    try:
        return CalibrateQuery.from_pairs(pairs)
    except ValidationError as exc:
        raise RequestValidationError(
            [{**e, "loc": ("query", *e["loc"])} for e in exc.errors()]) from None


async def _body(receive: Receive) -> bytes:
    """The whole request body (the size limit is enforced by the enclosing middleware)."""
    chunks = []
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            break
        chunks.append(message.get("body", b""))
        if not message.get("more_body", False):
            break
    return b"".join(chunks)


def _error(exc: HTTPException | RequestValidationError) -> CallOutcome:
    if isinstance(exc, HTTPException):
        return CallOutcome(exc.status_code, json.dumps({"detail": exc.detail}).encode())
    status, body = error_body(exc)
    return CallOutcome(status, json.dumps(body).encode())


async def _send(send: Send, out: CallOutcome) -> None:
    await send({"type": "http.response.start", "status": out.status,
                "headers": [(b"content-type", out.media_type.encode()),
                            (b"content-length", str(len(out.content)).encode())]})
    await send({"type": "http.response.body", "body": out.content})
