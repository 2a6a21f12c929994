"""POST /v1/feedback: labelled frames for a profile version (JSON, or a validation dump upload)."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter, Request, status
from fastapi.responses import Response
from pydantic import TypeAdapter
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from app.calibrate.cache import LoadedProfile
from app.feedback.evidence import frames_dump, record_feedback
from app.fitting.refit import keep_feedback, queue_refit
from app.fitting.uploads import check_declared, declared_npz, load_upload
from app.http.deps import CacheDep, FeedbackIdDep, RunnerDep, SettingsDep, StoreDep
from app.http.errors import RequestError
from app.http.json_body import json_response, parse_json, register_body_model
from app.schemas.feedback import FeedbackRequest, FeedbackResult
from app.schemas.types import ErrorResponse, ProfileRefText
from app.settings import Settings
from app.store import AuditEntry, Store
from calibrators.data import Dump

router = APIRouter(prefix="/v1", tags=["feedback"])
log = logging.getLogger("detcal.feedback")
register_body_model(FeedbackRequest)

_FORM = {"type": "object", "required": ["dump"], "properties": {
    "dump": {"type": "string", "format": "binary",
             "description": "Validation dump v1 (NPZ) of frames the version calibrated."},
    "profile": {**TypeAdapter(ProfileRefText).json_schema(),
                "description": "`name`, `name@version` or `name@alias` (default: the "
                               "configured default name)."}}}
BODY = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/FeedbackRequest"}},
    "multipart/form-data": {"schema": _FORM}}}}
FIELDS = frozenset(_FORM["properties"])  # type: ignore[arg-type]


@router.post("/feedback", response_model=FeedbackResult, openapi_extra=BODY,
             responses={code: {"model": ErrorResponse}
                        for code in (401, 403, 404, 413, 415, 422)})
async def feedback(request: Request, token: FeedbackIdDep, store: StoreDep, cache: CacheDep,
                   settings: SettingsDep, runner: RunnerDep) -> Response:
    """Match labelled frames to their ground truth and add them to the version's health."""
    media = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    form = media in ("multipart/form-data", "application/x-www-form-urlencoded")
    if form:
        loaded, dump = await _upload(request, cache, settings)
    elif media == "application/json" or media.endswith("+json"):
        body = await run_in_threadpool(parse_json, FeedbackRequest, await request.body())
        _check_frames(body, settings.max_feedback_detections)
        loaded = await run_in_threadpool(cache.resolve, body.profile, settings.default_profile)
        dump = await run_in_threadpool(frames_dump, body.frames, loaded)
    else:
        raise RequestError(["header", "content-type"], "send application/json (frames) or "
                           "multipart/form-data (a `dump` upload)", status=415)
    out = await run_in_threadpool(_record, store, loaded, dump, settings, token,
                                  "dump" if form else "frames")
    if out["refit_job"] is not None:
        runner.notify()
    return json_response(out, status.HTTP_200_OK)


def _check_frames(body: FeedbackRequest, limit: int) -> None:
    """A 413 at `frames` when the JSON frames carry more detections or ground-truth boxes
    than `DETCAL_MAX_FEEDBACK_DETECTIONS`."""
    dets = sum(len(f.detections) for f in body.frames)
    gts = sum(len(f.ground_truth) for f in body.frames)
    if max(dets, gts) > limit:
        raise RequestError(["body", "frames"], f"the feedback carries {dets} detections and "
                           f"{gts} ground-truth boxes, more than the limit of {limit} per "
                           f"request (DETCAL_MAX_FEEDBACK_DETECTIONS)", status=413)


async def _upload(request: Request, cache: CacheDep, settings: Settings
                  ) -> tuple[LoadedProfile, Dump]:
    """The profile and dump of a multipart feedback upload (422s name the form field; a dump
    whose headers declare more than the per-request limits is a 413 before it is read)."""
    from calibrators.io import load_dump

    try:
        form = await request.form()
    except HTTPException as exc:   # starlette: malformed multipart
        raise RequestError(["body"], f"not a valid form: {exc.detail}") from None
    for key, value in form.multi_items():
        if key not in FIELDS:
            raise RequestError(["body", key], f"unknown field {key!r}; the form takes "
                                              f"{sorted(FIELDS)}")
        if isinstance(value, str) and value == "":
            raise RequestError(["body", key], f"{key} is empty; leave the field out to get "
                                              f"its default")
    upload, ref = form.get("dump"), form.get("profile")
    if not isinstance(upload, UploadFile):
        raise RequestError(["body", "dump"], "dump must be a file (an NPZ validation dump)")
    if ref is not None and not isinstance(ref, str):
        raise RequestError(["body", "profile"], "profile must be a text field")
    declared = await run_in_threadpool(declared_npz, upload.file)
    check_declared(declared, max_bytes=settings.max_dump_bytes,
                   max_detections=settings.max_feedback_detections, field="dump",
                   what="feedback")
    loaded = await run_in_threadpool(cache.resolve, ref, settings.default_profile)
    dump = await run_in_threadpool(
        load_upload, lambda: load_dump(upload.file, max_bytes=settings.max_dump_bytes), "dump")
    return loaded, dump


def _record(store: Store, loaded: LoadedProfile, dump: Dump, settings: Settings, token: str,
            field: str) -> dict[str, Any]:
    """Record the feedback (and, with auto_refit, keep it and queue the challenger fit when it
    first degrades the champion); a dump that does not fit the profile is a 422 at `field`."""
    if dump.n_frames == 0:
        raise RequestError(["body", field], "feedback needs at least one frame")
    audit = AuditEntry("feedback", loaded.record.ref, token, {
        "frames": dump.n_frames, "detections": dump.n_detections, "gt": len(dump.gt_labels)})
    try:
        kept = keep_feedback(store, dump) if settings.auto_refit else None
        rec = record_feedback(store, loaded, dump, settings.health_chunk_frames, audit, kept)
    except ValueError as exc:   # FieldError included: the profile cannot score this dump
        log.warning("feedback for %s refused: %s", loaded.record.ref, exc)
        raise RequestError(["body", field], f"profile {loaded.record.ref}: {exc}") from None
    if rec.new_alarms:
        log.warning("feedback for %s raised drift alarm(s): %s", loaded.record.ref,
                    "; ".join(rec.new_alarms))
    counts, last = rec.evidence.counts(), rec.rows[-1]
    refit = None
    if (settings.auto_refit and rec.new_alarms and not rec.was_degraded
            and store.active_version(loaded.record.name) == loaded.record.version):
        refit = queue_refit(store, loaded, rec.new_alarms[0], settings.max_dump_bytes)
    return FeedbackResult(profile=loaded.ref(), frames=counts.frames,  # type: ignore[arg-type]
                          detections=counts.detections, tp=counts.tp, gt=counts.gt,
                          frames_total=last.frames_total, status=last.status,  # type: ignore
                          new_alarms=rec.new_alarms, refit_job=refit).model_dump()
