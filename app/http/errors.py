"""Request errors that become 4xx responses with a field path and a reason."""

from __future__ import annotations

from collections.abc import Sequence

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path
from starlette.types import Scope

from app.http.path_errors import explain
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

    async def _handle(request: Request, exc: Exception) -> JSONResponse:
        status, body = error_body(exc)  # type: ignore[arg-type]
        if isinstance(exc, RequestValidationError):   # path parameters: name and form
            body = {"detail": explain(body["detail"], list(exc.errors()),  # type: ignore
                                      request.scope.get("route"))}
        return JSONResponse(body, status_code=status)

    for kind in (RequestValidationError, RequestError, NotFoundError):
        app.add_exception_handler(kind, _handle)

    async def _http(request: Request, exc: Exception) -> Response:
        response = await http_exception_handler(request, exc)  # type: ignore[arg-type]
        if response.status_code == 405:   # every method of the path, not one route's
            response.headers["Allow"] = ", ".join(allowed_methods(request.app, request.scope))
        return response

    app.add_exception_handler(StarletteHTTPException, _http)


def allowed_methods(app: FastAPI, scope: Scope) -> list[str]:
    """The methods some route serves at the request's path (FastAPI keeps one route per
    method, and Starlette's 405 names only the first route's)."""
    try:
        from fastapi.routing import iter_route_contexts  # FastAPI >= 0.137: a route tree
        routes = [(c.path, c.methods) for c in iter_route_contexts(app.router.routes)]
    except ImportError:
        routes = [(getattr(r, "path", ""), getattr(r, "methods", None)) for r in app.routes]
    path = scope.get("path", "")
    methods: set[str] = set()
    for template, route_methods in routes:
        if route_methods and compile_path(template)[0].match(path):
            methods |= set(route_methods)
    return sorted(methods)
