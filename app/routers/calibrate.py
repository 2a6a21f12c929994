"""POST /v1/calibrate (detections) and POST /v1/calibrate/nuscenes (a nuScenes results JSON)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response

from app.body import body_doc, json_body, json_response
from app.calibration import calibrate_frames
from app.deps import CacheDep, MetricsDep, SettingsDep
from app.nuscenes_results import calibrate_results
from app.schemas.calibrate import (
    DEFAULT_LEVELS,
    LEVELS_SCHEMA,
    LEVELS_TEXT,
    CalibrateRequest,
    CalibrateResponse,
)
from app.schemas.common import ErrorResponse, ProfileRefText
from app.schemas.nuscenes import NuScenesResults

router = APIRouter(prefix="/v1", tags=["calibrate"],
                   responses={404: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                              415: {"model": ErrorResponse}, 422: {"model": ErrorResponse}})


@router.post("/calibrate", response_model=CalibrateResponse,
             openapi_extra=body_doc(CalibrateRequest))
def calibrate(body: Annotated[CalibrateRequest, Depends(json_body(CalibrateRequest))],
              cache: CacheDep, settings: SettingsDep, metrics: MetricsDep) -> Response:
    """Calibrate raw detections with the active (or a named) profile version."""
    loaded = cache.resolve(body.profile, settings.default_profile)
    rows = calibrate_frames(loaded, body.frames, body.ellipse_confidence, levels=body.levels,
                            max_detections=settings.max_detections)
    metrics.detections.labels(loaded.record.name).inc(sum(len(r) for r in rows))
    prof = loaded.profile
    return json_response({
        "profile": loaded.ref(), "classes": list(prof.classes), "cov_dims": list(prof.cov_dims),
        "ellipse_confidence": body.ellipse_confidence,
        "frames": [{"frame_id": f.frame_id, "detections": r} for f, r in zip(body.frames, rows,
                                                                                strict=True)],
    })


@router.post("/calibrate/nuscenes", response_model=NuScenesResults,
             openapi_extra=body_doc(NuScenesResults))
def calibrate_nuscenes(
    body: Annotated[NuScenesResults, Depends(json_body(NuScenesResults))], cache: CacheDep,
    settings: SettingsDep, metrics: MetricsDep,
    profile: Annotated[ProfileRefText | None, Query(description="`name` or `name@version`")
                      ] = None,
    ellipse_confidence: Annotated[float, Query(gt=0.0, lt=1.0)] = 0.95,
    levels: Annotated[list[float] | None, Query(
        json_schema_extra=LEVELS_SCHEMA,
        description=f"{LEVELS_TEXT} Repeat it: `?levels=0.5&levels=0.9`; default "
                    f"{list(DEFAULT_LEVELS)}.")] = None,
) -> Response:
    """Calibrate a nuScenes results document; scores replaced, raw score, Σ', ellipses added."""
    loaded = cache.resolve(profile, settings.default_profile, loc=("query", "profile"))
    doc, n = calibrate_results(loaded, body, ellipse_confidence,
                               DEFAULT_LEVELS if levels is None else levels,
                               max_detections=settings.max_detections)
    metrics.detections.labels(loaded.record.name).inc(n)
    return json_response(doc)
