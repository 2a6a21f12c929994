"""Request errors that become 4xx responses with a field path and a reason."""

from __future__ import annotations

from collections.abc import Sequence

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from app.store import NotFoundError


class RequestError(Exception):
    """A request the service understood but cannot serve: `loc` says where, `msg` why."""

    def __init__(self, loc: Sequence[str | int], msg: str, status: int = 422,
                 kind: str = "value_error") -> None:
        super().__init__(msg)
        self.loc, self.msg, self.status, self.kind = list(loc), msg, status, kind

    def body(self) -> dict[str, object]:
        return {"detail": [{"loc": self.loc, "msg": self.msg, "type": self.kind}]}


def validation_items(exc: RequestValidationError) -> list[dict[str, object]]:
    """`{loc, msg, type}` of each validation error (the offending input is not echoed: it
    may hold NaN/Inf, which strict JSON cannot carry, or be large)."""
    return [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")),
             "type": str(e.get("type", "value_error"))} for e in exc.errors()]


ServiceError = RequestValidationError | RequestError | NotFoundError


def error_body(exc: ServiceError) -> tuple[int, dict[str, object]]:
    """Status and body of an error response: validation errors -> 422, `RequestError` -> its
    status, `NotFoundError` -> 404."""
    if isinstance(exc, RequestValidationError):
        return 422, {"detail": validation_items(exc)}
    if isinstance(exc, RequestError):
        return exc.status, exc.body()
    return 404, {"detail": str(exc)}


def install_handlers(app: FastAPI) -> None:
    """Answer every `ServiceError` with its `error_body`."""

    async def _handle(_: Request, exc: Exception) -> JSONResponse:
        status, body = error_body(exc)  # type: ignore[arg-type]
        return JSONResponse(body, status_code=status)

    for kind in (RequestValidationError, RequestError, NotFoundError):
        app.add_exception_handler(kind, _handle)
