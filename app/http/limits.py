"""Request body size limits: a 413 before the body is read when Content-Length is too big,
and while streaming when it is absent or lies. Every refusal (a 4xx other than 404) is logged
on `detcal.http` with its method, path and status (never a header: no token); a client that
goes away before its body is complete is logged, not an error."""

from __future__ import annotations

import json
import logging

from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("detcal.http")


class _TooLarge(HTTPException):
    """Raised from `receive`: an HTTPException, so the framework answers 413 itself."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body exceeds the limit of {limit} bytes")


class BodySizeLimitMiddleware:
    """Refuse bodies over `max_bytes`, or over `upload_bytes` for multipart bodies (dump
    uploads) to the paths in `upload_paths`."""

    def __init__(self, app: ASGIApp, max_bytes: int, upload_bytes: int,
                 upload_paths: tuple[str, ...] = ("/v1/fit", "/v1/feedback")) -> None:
        self.app, self.max_bytes, self.upload_bytes = app, max_bytes, upload_bytes
        self.upload_paths = upload_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.upload_bytes if (scope["path"] in self.upload_paths
                                      and _multipart(scope)) else self.max_bytes
        for key, value in scope.get("headers", []):
            if key == b"content-length":
                try:
                    length = int(value)
                except ValueError:
                    await _reply(send, 400, "Content-Length is not an integer")
                    return
                if length > limit:
                    _log_refusal(scope, 413)
                    await _reply(send, 413, f"request body of {length} bytes exceeds the "
                                            f"limit of {limit} bytes")
                    return
        seen = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise _TooLarge(limit)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                _log_refusal(scope, message["status"])
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _TooLarge as exc:
            if not started:
                _log_refusal(scope, 413)
                await _reply(send, 413, str(exc.detail))
        except ClientDisconnect:
            log.info("%s %s: the client went away before its body was complete",
                     scope["method"], scope["path"])


def _log_refusal(scope: Scope, status: int) -> None:
    """Log a refused request (4xx but 404): method, path and status only."""
    if 400 <= status < 500 and status != 404:
        log.info("refused %s %s: %d", scope["method"], scope["path"][:200], status)


def _multipart(scope: Scope) -> bool:
    for key, value in scope.get("headers", []):
        if key == b"content-type":
            return value.split(b";", 1)[0].strip().lower() == b"multipart/form-data"
    return False


async def _reply(send: Send, status: int, msg: str) -> None:
    body = json.dumps({"detail": msg}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
