"""POST /v1/detect: run a bundled detector on a simulated frame (or points) and calibrate."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response

from app.bundled_detectors import DetectorService, DetectorUnavailable, detections_of
from app.calibrate.documents import calibrate_frames
from app.calibrate.profile_match import profile_for_sensor
from app.http.deps import CacheDep, MetricsDep, SettingsDep
from app.http.json_body import body_doc, json_body, json_response
from app.schemas.calibrate import DetectRequest, DetectResponse, FrameIn
from app.schemas.types import ErrorResponse

router = APIRouter(prefix="/v1", tags=["detect"], responses={
    code: {"model": ErrorResponse} for code in (404, 413, 415, 422, 503)})


async def _detectors(request: Request) -> DetectorService:
    return request.app.state.detectors


DetectorsDep = Annotated[DetectorService, Depends(_detectors)]


@router.post("/detect", response_model=DetectResponse, openapi_extra=body_doc(DetectRequest))
def detect(body: Annotated[DetectRequest, Depends(json_body(DetectRequest))], cache: CacheDep,
           settings: SettingsDep, metrics: MetricsDep,
           detectors: DetectorsDep) -> Response:
    """Detect on a simulated frame with a bundled detector and calibrate with a profile."""
    loaded, warnings = profile_for_sensor(cache, body.profile, body.sensor,
                                          settings.default_profile)
    try:
        out = detectors.run(body.sensor, body.seed or 0, body.points, body.min_score)
    except DetectorUnavailable as exc:
        return JSONResponse({"detail": str(exc)}, status_code=503)
    seed = None if body.points is not None else (body.seed or 0)
    frame = FrameIn.model_construct(frame_id=f"{body.sensor}-{seed}", ego_translation=None,
                                    detections=detections_of(out, loaded))
    rows = calibrate_frames(loaded, [frame], body.ellipse_confidence, levels=body.levels,
                            max_detections=settings.max_detections)[0]
    metrics.detections.labels(loaded.record.name).inc(len(rows))
    prof = loaded.profile
    gt = [{"label": prof.classes[int(c)], "box": b} for c, b in
          zip(out.gt_labels.tolist(), out.gt_boxes.tolist(), strict=True)]
    return json_response({
        "profile": loaded.ref(), "classes": list(prof.classes), "cov_dims": list(prof.cov_dims),
        "ellipse_confidence": body.ellipse_confidence, "sensor": body.sensor,
        "seed": seed,
        "frames": [{"frame_id": frame.frame_id, "detections": rows}],
        "ground_truth": gt if body.points is None else None, "warnings": warnings,
    })
