"""One calibrate request, from the raw body to the response bytes.

`CalibrateEngine.run(call)` parses the body (strictly, as `app.body.parse_json`), resolves the
profile, calibrates (`app.calibration`, `app.nuscenes_results`) and serialises the response;
an error becomes the same 4xx body the app's exception handlers write (`app.errors`). It
needs nothing from the request but the `CalibrateCall`, so the same code runs in a thread of
the server process or in a calibrate worker process (`app.offload`), which has its own
store connection and profile cache.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from fastapi.exceptions import RequestValidationError

from app.body import dumps_json, parse_json
from app.cache import ProfileCache
from app.calibration import calibrate_frames
from app.errors import RequestError, error_body
from app.nuscenes_results import calibrate_results
from app.schemas.calibrate import DEFAULT_LEVELS, CalibrateRequest
from app.schemas.nuscenes import NuScenesResults
from app.store import NotFoundError

CallKind = Literal["calibrate", "nuscenes"]


@dataclass(frozen=True)
class CalibrateCall:
    """What a calibrate request carries: the raw JSON body and, for the nuScenes route, the
    query's already validated options (the plain route has them in its body)."""

    kind: CallKind
    body: bytes
    profile: str | None = None
    ellipse_confidence: float = 0.95
    levels: tuple[float, ...] | None = None


@dataclass(frozen=True)
class CallOutcome:
    """The response: status, JSON bytes, and for metrics the profile name and detections."""

    status: int
    content: bytes
    profile: str | None = None
    detections: int = 0


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
            return self._calibrate(call)
        except (RequestValidationError, RequestError, NotFoundError) as exc:
            status, body = error_body(exc)
            return CallOutcome(status, dumps_json(body))

    def _calibrate(self, call: CalibrateCall) -> CallOutcome:
        body = parse_json(CalibrateRequest, call.body)
        loaded = self.cache.resolve(body.profile, self.default_profile)
        rows = calibrate_frames(loaded, body.frames, body.ellipse_confidence,
                                levels=body.levels, max_detections=self.max_detections)
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
        doc, n = calibrate_results(loaded, body, call.ellipse_confidence, levels,
                                   max_detections=self.max_detections)
        return CallOutcome(200, dumps_json(doc), loaded.record.name, n)
