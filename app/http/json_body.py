"""JSON request bodies parsed straight from bytes by pydantic (one pass in Rust, no
intermediate dict) and JSON responses serialised by pydantic-core: the hot path of
/v1/calibrate. Errors keep FastAPI's 422 shape (`loc` starting with "body").

Bodies are validated in strict mode: a number given as a string or a boolean, or an integer
given as a float (`"1.5"`, `false`, `1.0`), is refused with the field named."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import orjson
import pydantic_core
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import Response
from pydantic import BaseModel, ValidationError
from starlette.concurrency import run_in_threadpool

from app.http.deps import require_json

M = TypeVar("M", bound=BaseModel)
_BODY_MODELS: list[type[BaseModel]] = []


def json_body(model: type[M]) -> Callable[[Request], Awaitable[M]]:
    """A dependency that validates the raw JSON body as `model`, strictly (415 unless JSON)."""
    _BODY_MODELS.append(model)

    async def parse(request: Request) -> M:
        require_json(request)
        raw = await request.body()
        # parsing a large body takes a while: off the event loop, /healthz stays quick
        return await run_in_threadpool(parse_json, model, raw)

    parse.__name__ = f"parse_{model.__name__}"
    return parse


def register_body_model(model: type[M]) -> type[M]:
    """Declare `model` as a raw-parsed request body (its schema joins the OpenAPI
    components); for routes that read the body themselves."""
    _BODY_MODELS.append(model)
    return model


def parse_json(model: type[M], raw: bytes) -> M:
    """`raw` validated strictly as `model`; a `RequestValidationError` (422, `loc` starting
    with "body") if it is not."""
    try:
        return model.model_validate_json(raw, strict=True)
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_input=False, include_context=False)
        raise RequestValidationError(
            [{**e, "loc": ("body", *e["loc"])} for e in errors]) from None


def body_doc(model: type[BaseModel]) -> dict[str, Any]:
    """`openapi_extra` declaring `model` as the JSON request body."""
    return {"requestBody": {"required": True, "content": {"application/json": {
        "schema": {"$ref": f"#/components/schemas/{model.__name__}"}}}}}


def dumps_json(body: Any) -> bytes:
    """`body` as strict JSON bytes, serialised by orjson (shortest float repr; numpy arrays
    and scalars directly; pydantic models through pydantic-core). A non-finite float never
    reaches it from the calibrate path (the library refuses or nulls them first); orjson
    would write it as null, never as the non-JSON `NaN` / `Infinity`."""
    try:
        return orjson.dumps(body, option=orjson.OPT_SERIALIZE_NUMPY,
                            default=pydantic_core.to_jsonable_python)
    except orjson.JSONEncodeError:   # an integer beyond 64 bits, echoed from a client's meta
        return pydantic_core.to_json(body, inf_nan_mode="null", fallback=_numpy_plain)


def _numpy_plain(value: Any) -> Any:
    """A numpy array or scalar as plain Python (the fallback serialiser's numpy support)."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def json_response(body: Any, status_code: int = 200) -> Response:
    """A JSON response of `body` (`dumps_json`)."""
    return Response(dumps_json(body), status_code=status_code, media_type="application/json")


def install_openapi(app: FastAPI) -> None:
    """Add the raw-parsed body models to the OpenAPI components."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(title=app.title, version=app.version,
                             description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in _BODY_MODELS:
            js = model.model_json_schema(ref_template="#/components/schemas/{model}")
            for name, sub in js.pop("$defs", {}).items():
                components.setdefault(name, sub)
            components[model.__name__] = js
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
