"""One calibrate request, from the raw body to the response bytes.

`CalibrateEngine.run(call)` parses the body (JSON strictly, as `app.http.json_body.parse_json`;
an Arrow IPC stream with `calibrators.io.arrow_batch`), resolves the profile, calibrates
(`app.calibrate.documents` for JSON and nuScenes bodies, the library's `Detections` for a
batch; a 2-D profile's `images` in `app.calibrate.images2d` and its Arrow batch in
`app.calibrate.arrow2d`, both imported only when a 2-D profile is met) and
serialises the response in the body's format;
an error becomes the same 4xx body the app's exception handlers write (`app.http.errors`). It
needs nothing from the request but the `CalibrateCall`, so the same code runs in a thread of
the server process or in a calibrate worker process (`app.calibrate.runner`), which has its own
store connection and profile cache.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import pyarrow as pa
from fastapi.exceptions import HTTPException, RequestValidationError

from app.calibrate.cache import ProfileCache
from app.calibrate.documents import calibrate_frames, calibrate_results, check_classes
from app.http.content_types import check_accept
from app.http.errors import RequestError, error_body
from app.http.json_body import dumps_json, parse_json
from app.schemas.calibrate import CalibrateRequest
from app.schemas.nuscenes import NuScenesResults
from app.store import NotFoundError
from calibrators.core.defaults import DEFAULT_LEVELS, ELLIPSE_CONFIDENCE
from calibrators.core.errors import FieldError
from calibrators.core.vocab import PROFILE_KINDS
from calibrators.io.arrow_batch import (
    ARROW_STREAM,
    LIBRARY_TO_COLUMN,
    batch_request,
    read_stream,
    write_stream,
)

CallKind = Literal["calibrate", "nuscenes", "arrow"]
log = logging.getLogger("detcal.calibrate")
_UNAVAILABLE = dumps_json({"detail": "the Arrow body could not be processed now; retry it"})


@dataclass(frozen=True)
class CalibrateCall:
    """What a calibrate request carries: the raw body (JSON, or an Arrow stream for `arrow`),
    the query's already validated options (a JSON calibrate body's own fields take
    precedence over them) and, for an Arrow body, its `Accept` header (answered in Arrow when
    it takes Arrow; else in JSON by a 2-D profile, with a 406 by a 3-D one)."""

    kind: CallKind
    body: bytes
    profile: str | None = None
    ellipse_confidence: float | None = None    # None: ELLIPSE_CONFIDENCE
    levels: tuple[float, ...] | None = None    # None: DEFAULT_LEVELS
    accept: str = ""                           # "": no Accept header


@dataclass(frozen=True)
class CallOutcome:
    """The response: status, bytes of `media_type`, and for metrics the profile name and the
    detections calibrated."""

    status: int
    content: bytes
    profile: str | None = None
    detections: int = 0
    media_type: str = "application/json"


class CalibrateEngine:
    """Runs `CalibrateCall`s against a profile cache with the service's limits."""

    def __init__(self, cache: ProfileCache, default_profile: str, max_detections: int) -> None:
        self.cache = cache
        self.default_profile = default_profile
        self.max_detections = max_detections

    def run(self, call: CalibrateCall) -> CallOutcome:
        """The response to `call`; a request error is a 4xx outcome, never an exception."""
        try:
            if call.kind == "nuscenes":
                return self._nuscenes(call)
            if call.kind == "arrow":
                return self._arrow_guarded(call)
            return self._calibrate(call)
        except (RequestValidationError, RequestError, NotFoundError) as exc:
            status, body = error_body(exc)
            return CallOutcome(status, dumps_json(body))

    def _arrow_guarded(self, call: CalibrateCall) -> CallOutcome:
        """`_arrow(call)`, where a library error the reader did not name (pyarrow, numpy) is
        a 422 at the body, running out of memory a 503, and anything else a logged 503:
        client bytes never make a 500."""
        try:
            return self._arrow(call)
        except (RequestValidationError, RequestError, NotFoundError):
            raise
        except (pa.ArrowException, ValueError, TypeError, IndexError, OverflowError) as exc:
            raise RequestError(["body"], f"the Arrow batch could not be read: "
                                         f"{str(exc)[:300]}") from None
        except MemoryError:
            log.error("out of memory on an Arrow calibrate body of %d bytes", len(call.body))
            return CallOutcome(503, _UNAVAILABLE)
        except Exception:
            log.exception("Arrow calibrate body of %d bytes failed", len(call.body))
            return CallOutcome(503, _UNAVAILABLE)

    def _calibrate(self, call: CalibrateCall) -> CallOutcome:
        parsed = parse_json(CalibrateRequest, call.body)
        body = _with_query(parsed, call)
        from_query = {"profile", "levels", "ellipse_confidence"} - parsed.model_fields_set
        try:
            loaded = self.cache.resolve(body.profile, self.default_profile,
                                        loc=_where("profile", from_query), kinds=PROFILE_KINDS)
            if loaded.kind != "3d" or body.frames is None:   # 2-D: loaded only when used
                from app.calibrate.images2d import calibrate_images

                given = body.model_fields_set
                doc, n = calibrate_images(loaded, body, given, self.max_detections)
                return CallOutcome(200, dumps_json(doc), loaded.record.name, n)
            check_classes(loaded, body.classes)
            rows = calibrate_frames(loaded, body.frames, body.ellipse_confidence,
                                    levels=body.levels, max_detections=self.max_detections)
        except RequestError as exc:   # an option the query gave is located in the query
            if len(exc.loc) > 1 and exc.loc[0] == "body" and exc.loc[1] in from_query:
                exc.loc[0] = "query"
            raise
        prof = loaded.profile
        doc = {"profile": loaded.ref(), "classes": list(prof.classes),
               "cov_dims": list(prof.cov_dims), "ellipse_confidence": body.ellipse_confidence,
               "frames": [{"frame_id": f.frame_id, "detections": r}
                          for f, r in zip(body.frames, rows, strict=True)]}
        return CallOutcome(200, dumps_json(doc), loaded.record.name, sum(map(len, rows)))

    def _nuscenes(self, call: CalibrateCall) -> CallOutcome:
        body = parse_json(NuScenesResults, call.body)
        loaded = self.cache.resolve(call.profile, self.default_profile, loc=("query", "profile"))
        levels = DEFAULT_LEVELS if call.levels is None else call.levels
        doc, n = calibrate_results(loaded, body, _confidence(call), levels,
                                   max_detections=self.max_detections)
        return CallOutcome(200, dumps_json(doc), loaded.record.name, n)

    def _arrow(self, call: CalibrateCall) -> CallOutcome:
        loaded = self.cache.resolve(call.profile, self.default_profile, loc=("query", "profile"),
                                    kinds=PROFILE_KINDS)
        if loaded.kind != "3d":   # 2-D: loaded only when used
            from app.calibrate.arrow2d import calibrate_arrow_2d

            doc, n, media = calibrate_arrow_2d(loaded, call, self.max_detections)
            return CallOutcome(200, doc, loaded.record.name, n, media)
        try:
            check_accept(call.accept, ARROW_STREAM)
        except HTTPException as exc:
            return CallOutcome(exc.status_code, dumps_json({"detail": exc.detail}))
        prof = loaded.profile
        levels = DEFAULT_LEVELS if call.levels is None else call.levels
        try:
            batch = read_stream(call.body, self.max_detections)
            if "image_id" in batch.schema.names:
                raise RequestError(["body", "image_id"], f"profile {loaded.record.ref} is a 3-D "
                                   "profile: send its detections as rows with `frame_id` "
                                   "(docs/api.md)")
            request = batch_request(batch, prof.classes)
        except FieldError as exc:
            raise batch_error(exc) from None
        try:
            res = request.calibrate(prof, ellipse_confidence=_confidence(call), levels=levels)
        except FieldError as exc:
            raise batch_error(exc, loaded.record.ref) from None
        except ValueError as exc:   # a library check that names no field
            raise RequestError(["body"], f"profile {loaded.record.ref}: {exc}") from None
        meta = {"profile": loaded.ref(), "classes": list(prof.classes),
                "cov_dims": list(prof.cov_dims)}
        out = res.to_arrow(meta)
        return CallOutcome(200, write_stream(out), loaded.record.name, len(res), ARROW_STREAM)


def _where(field: str, from_query: set[str]) -> tuple[str, str]:
    return ("query" if field in from_query else "body", field)


def _confidence(call: CalibrateCall) -> float:
    return ELLIPSE_CONFIDENCE if call.ellipse_confidence is None else call.ellipse_confidence


def _with_query(body: CalibrateRequest, call: CalibrateCall) -> CalibrateRequest:
    """`body` with the query's options where the body does not set its own."""
    query = {"profile": call.profile, "ellipse_confidence": call.ellipse_confidence,
             "levels": None if call.levels is None else list(call.levels)}
    missing = {k: v for k, v in query.items() if v is not None and k not in body.model_fields_set}
    return body.model_copy(update=missing) if missing else body


def batch_error(exc: FieldError, ref: str | None = None,
                columns: Mapping[str, str] = LIBRARY_TO_COLUMN) -> RequestError:
    """The 4xx of a FieldError about an Arrow batch: at the query option, at the body (not a
    stream; 413 for too many rows), or at the column (and row) at fault, `columns` mapping a
    library argument to its column; `ref` names the profile when the library refused the
    arrays against it."""
    row = [] if exc.row is None else [exc.row]
    if exc.field in ("levels", "ellipse_confidence"):
        return RequestError(["query", exc.field, *row], str(exc))
    if exc.field == "rows":
        return RequestError(["body"], f"{exc} (DETCAL_MAX_DETECTIONS): split it", status=413)
    if exc.field == "bytes":
        return RequestError(["body"], f"{exc}: split it", status=413)
    if exc.field == "body":
        return RequestError(["body"], str(exc))
    column = columns.get(exc.field, exc.field)
    if ref is None:
        return RequestError(["body", column, *row], str(exc))
    return RequestError(["body", column, *row], f"profile {ref}: {exc}",
                        kind="value_error.profile_mismatch")
