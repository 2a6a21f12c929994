"""`?fields=a,b.c`: the summary form of a large answer (jobs, profiles, health).

A job with its report is ~190 KB, a profile version ~290 KB; `?fields=state,profile` keeps
only the named keys of the JSON answer (`a.b` reaches into an object; applied to each item
of a list). The routers that take it declare the parameter through `fields_query` (so the
API docs show it); `FieldsMiddleware` trims the answer. An unknown name is a 422 that lists
the names the answer has.
"""

from __future__ import annotations

import json
from typing import Annotated, Any
from urllib.parse import parse_qs

from fastapi import Query
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: Names separated by commas; each name dotted keys.
FIELDS_PATTERN = r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*(,[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*)*$"
#: The paths whose answers can be trimmed.
PREFIXES = ("/v1/jobs", "/v1/profiles")


def fields_query(fields: Annotated[str | None, Query(
        pattern=FIELDS_PATTERN, max_length=1000,
        description="Summary form: keep only these keys of the answer, comma-separated; "
                    "`a.b` keeps key `b` of object `a` (e.g. `state,profile` of a job, "
                    "`status,window.ece` of a health document).")] = None) -> None:
    """Declare `fields` on a route (validated here, applied by `FieldsMiddleware`)."""


class UnknownField(ValueError):
    """A requested name the answer does not have."""


def pick(doc: Any, names: list[str]) -> Any:
    """`doc` with only the dotted `names` (each item of a list trimmed alike)."""
    if isinstance(doc, list):
        return [pick(item, names) for item in doc]
    out: dict[str, Any] = {}
    for name in names:
        head, _, rest = name.partition(".")
        if not isinstance(doc, dict) or head not in doc:
            have = ", ".join(sorted(doc)) if isinstance(doc, dict) else "no keys"
            raise UnknownField(f"unknown field {head!r}; this answer has: {have}")
        if not rest:
            out[head] = doc[head]
            continue
        inner = pick(doc[head], [rest]) if doc[head] is not None else None
        if isinstance(out.get(head), dict) and isinstance(inner, dict):
            out[head] = {**out[head], **inner}
        else:
            out[head] = inner
    return out


class FieldsMiddleware:
    """Trim the JSON answer of a request under `PREFIXES` that names `fields`."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        names = self._names(scope)
        if names is None:
            await self.app(scope, receive, send)
            return
        start: Message = {}
        chunks: list[bytes] = []

        async def capture(message: Message) -> None:
            nonlocal start
            if message["type"] == "http.response.start":
                start = message
            elif message["type"] == "http.response.body":
                chunks.append(message.get("body", b""))
                if not message.get("more_body", False):
                    await self._send(start, b"".join(chunks), names, send)
            else:
                await send(message)

        await self.app(scope, receive, capture)

    @staticmethod
    def _names(scope: Scope) -> list[str] | None:
        if scope["type"] != "http" or not scope["path"].startswith(PREFIXES):
            return None
        raw = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("fields")
        if not raw or len(raw) != 1 or not raw[0]:
            return None
        return raw[0].split(",")

    @staticmethod
    async def _send(start: Message, body: bytes, names: list[str], send: Send) -> None:
        headers = [(k, v) for k, v in start.get("headers", []) if k != b"content-length"]
        status = start.get("status", 200)
        kind = next((v for k, v in headers if k == b"content-type"), b"")
        if status == 200 and kind.startswith(b"application/json"):
            try:
                body = json.dumps(pick(json.loads(body), names),
                                  separators=(",", ":")).encode()
            except UnknownField as exc:
                status, body = 422, json.dumps({"detail": [{
                    "loc": ["query", "fields"], "msg": str(exc),
                    "type": "value_error"}]}).encode()
        headers.append((b"content-length", str(len(body)).encode()))
        await send({**start, "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
