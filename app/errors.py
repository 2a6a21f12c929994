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


def install_handlers(app: FastAPI) -> None:
    """Map validation errors -> 422, RequestError -> its status, NotFoundError -> 404."""

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": validation_items(exc)}, status_code=422)

    @app.exception_handler(RequestError)
    async def _request_error(_: Request, exc: RequestError) -> JSONResponse:
        return JSONResponse(exc.body(), status_code=exc.status)

    @app.exception_handler(NotFoundError)
    async def _not_found(_: Request, exc: NotFoundError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=404)
