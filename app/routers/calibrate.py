"""POST /v1/calibrate (detections) and POST /v1/calibrate/nuscenes (a nuScenes results JSON)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response

from app.calibrate.engine import CalibrateCall
from app.calibrate.runner import CalibrateRunner
from app.http.content_types import accept, body_media
from app.http.deps import MetricsDep, require_json
from app.http.json_body import body_doc, register_body_model
from app.http.metrics import ServiceMetrics
from app.schemas.calibrate import (
    LEVELS_SCHEMA,
    LEVELS_TEXT,
    CalibrateRequest,
    CalibrateResponse,
)
from app.schemas.calibrate_2d import CalibrateResponse2D
from app.schemas.calibrate_query import CalibrateQuery
from app.schemas.nuscenes import NuScenesResults
from app.schemas.types import ErrorResponse, ProfileRefText
from calibrators.core.defaults import DEFAULT_LEVELS, ELLIPSE_CONFIDENCE
from calibrators.io.arrow_batch import ARROW_STREAM

router = APIRouter(prefix="/v1", tags=["calibrate"],
                   responses={404: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                              415: {"model": ErrorResponse}, 422: {"model": ErrorResponse},
                              503: {"model": ErrorResponse}})


async def _calibrator(request: Request) -> CalibrateRunner:
    return request.app.state.calibrator


CalibratorDep = Annotated[CalibrateRunner, Depends(_calibrator)]


async def _serve(runner: CalibrateRunner, metrics: ServiceMetrics, call: CalibrateCall
                 ) -> Response:
    out = await runner.serve(call, metrics)
    return Response(out.content, status_code=out.status, media_type=out.media_type)


_BINARY = {"schema": {"type": "string", "format": "binary"}}
_CALIBRATE_BODY = body_doc(register_body_model(CalibrateRequest))
_CALIBRATE_BODY["requestBody"]["content"][ARROW_STREAM] = _BINARY


@router.post("/calibrate", response_model=CalibrateResponse | CalibrateResponse2D,
             openapi_extra=_CALIBRATE_BODY,
             responses={200: {"content": {ARROW_STREAM: _BINARY}},
                        406: {"model": ErrorResponse}})
async def calibrate(
    request: Request, calibrator: CalibratorDep, metrics: MetricsDep,
    query: Annotated[CalibrateQuery, Query()],
) -> Response:
    """Calibrate raw detections with the active (or a named) profile version: a JSON body
    (`CalibrateRequest`: `frames` for a 3-D profile, `images` for a 2-D one, answered with
    `CalibrateResponse` or `CalibrateResponse2D`), or an Arrow IPC stream of one detection
    per row (3-D or, for a 2-D profile, 2-D columns) answered with an Arrow stream, or for a
    2-D profile with `CalibrateResponse2D` when `Accept` takes only JSON (columns in
    docs/api.md). Arrow bodies are answered by the same engine below FastAPI's routing
    (`app.calibrate.arrow_route`); this route documents them and serves JSON."""
    body = await request.body()
    arrow = body_media(request, ARROW_STREAM) == ARROW_STREAM
    if arrow:   # answered in Arrow, or in JSON by a 2-D profile (the engine decides)
        accept(request, ARROW_STREAM, "application/json")
    else:
        accept(request, "application/json")
    call = CalibrateCall("arrow" if arrow else "calibrate", body, query.profile,
                         query.ellipse_confidence,
                         None if query.levels is None else tuple(query.levels),
                         request.headers.get("accept", "") if arrow else "")
    return await _serve(calibrator, metrics, call)


@router.post("/calibrate/nuscenes", response_model=NuScenesResults,
             openapi_extra=body_doc(register_body_model(NuScenesResults)))
async def calibrate_nuscenes(
    request: Request, calibrator: CalibratorDep, metrics: MetricsDep,
    profile: Annotated[ProfileRefText | None, Query(description="`name` or `name@version`")
                      ] = None,
    ellipse_confidence: Annotated[float, Query(gt=0.0, lt=1.0)] = ELLIPSE_CONFIDENCE,
    levels: Annotated[list[float] | None, Query(
        json_schema_extra=LEVELS_SCHEMA,
        description=f"{LEVELS_TEXT} Repeat it: `?levels=0.5&levels=0.9`; default "
                    f"{list(DEFAULT_LEVELS)}.")] = None,
) -> Response:
    """Calibrate a nuScenes results document; scores replaced, raw score, Σ', ellipses added."""
    require_json(request)
    call = CalibrateCall("nuscenes", await request.body(), profile, ellipse_confidence,
                         None if levels is None else tuple(levels))
    return await _serve(calibrator, metrics, call)
