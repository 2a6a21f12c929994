"""Validated request detections (JSON frames, a nuScenes results document) through the
library's calibrate batch, and the library's errors at the request's field paths.

The request's detections become JSON records (`calibrators.profile._detections`), one
`Detections` batch per evidence form; each batch is calibrated and written back with
`to_records()` / `to_nuscenes()`, every output detection placed by its own identity (its
input row), never by position. Every check against the profile lives in the library: a
`FieldError` it raises names the argument and the row, mapped here to the request's field
path and a 422. A calibrated number that is not finite (inputs so large that Σ' or an
ellipse overflows float64) is a 422 at the detection's `covariance` (or `box`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from app.calibrate.cache import LoadedProfile
from app.http.errors import RequestError
from app.schemas.calibrate import FrameIn
from app.schemas.nuscenes import NuScenesResults
from calibrators.core.defaults import DEFAULT_LEVELS
from calibrators.core.errors import FieldError
from calibrators.io.nuscenes_batch import calibrated_document, detections_from_nuscenes
from calibrators.profile import (
    WIRE_NAMES,
    CalibratedDetections,
    Detections,
    detections_from_records,
)
from calibrators.regions import check_levels

Locate = Callable[[int, int], list[str | int]]
#: A results document's box keys for the library's fields where they differ from the wire's.
_BOX_KEY = {"score": "detection_score", "label": "detection_name", "logits": "detection_logits",
            "box": "translation"}


def _default_locate(fi: int, di: int) -> list[str | int]:
    return ["body", "frames", fi, "detections", di]


def _mismatch(loc: Sequence[str | int], msg: str) -> RequestError:
    return RequestError(loc, msg, kind="value_error.profile_mismatch")


def _checked(levels: Sequence[float], total: int, max_detections: int | None, where: str
             ) -> list[float]:
    """`levels` checked by the library, and the request's size against the limit."""
    if max_detections is not None and total > max_detections:
        raise RequestError([where, "frames"], f"the request carries {total} detections; at "
                           f"most {max_detections} are calibrated per request "
                           f"(DETCAL_MAX_DETECTIONS): split it", status=413)
    try:
        return check_levels(levels).tolist()
    except FieldError as exc:
        loc = [where, "levels"] + ([] if exc.row is None else [exc.row])
        raise RequestError(loc, str(exc)) from None


def _served(batches: list[Detections], loaded: LoadedProfile, confidence: float,
            levels: list[float],
            fault: Callable[[Detections, int, str, str], RequestError]
            ) -> list[CalibratedDetections]:
    """Each batch calibrated; `fault(batch, row, field, message)` is the 422 of a library
    error about `field` ("" for none) at a batch row (its first row when the error is about
    the whole batch)."""
    out = []
    for batch in batches:
        try:
            out.append(batch.calibrate(loaded.profile, ellipse_confidence=confidence,
                                       levels=levels))
        except FieldError as exc:
            row = exc.row if exc.row is not None and 0 <= exc.row < len(batch) else 0
            raise fault(batch, row, exc.field, f"profile {loaded.record.ref}: {exc}") from None
        except ValueError as exc:   # a library check that names no field
            raise fault(batch, 0, "", f"profile {loaded.record.ref}: {exc}") from None
    return out


def calibrate_frames(loaded: LoadedProfile, frames: Sequence[FrameIn],
                     confidence: float, locate: Locate = _default_locate, *,
                     levels: Sequence[float] = DEFAULT_LEVELS, options_in: str = "body",
                     max_detections: int | None = None) -> list[list[dict[str, object]]]:
    """Calibrated detection rows (response dicts) per frame, in request order, with the
    ellipse at `confidence` and the regions at `levels`; each row has its `row` (position in
    its frame's detections) and `id` (the request's).

    `locate(frame_index, detection_index)` gives the field path used in error messages;
    `options_in` is where the request carries `levels` and `ellipse_confidence` ("body" or
    "query").
    """
    levels = _checked(levels, sum(len(f.detections) for f in frames), max_detections,
                      options_in)
    prof = loaded.profile
    records: list[dict[str, Any]] = []
    where: list[tuple[int, int]] = []
    for fi, frame in enumerate(frames):
        for di, det in enumerate(frame.detections):
            records.append({**det.__dict__, "frame_id": frame.frame_id,
                            "ego_translation": frame.ego_translation})
            where.append((fi, di))

    def at(flat: int, field: str) -> list[str | int]:
        fi, di = where[flat]
        if field == "ego_xy":
            return locate(fi, di)[:-2] + ["ego_translation"]
        if field == "logits":   # whichever evidence field the detection used
            field = next(k for k in ("logits", "layer_logits", "scores", "score")
                         if records[flat].get(k) is not None)
        return [*locate(fi, di), WIRE_NAMES.get(field, field)]

    def fault(batch: Detections, row: int, field: str, message: str) -> RequestError:
        return _mismatch(at(int(batch.rows[row]), field) if field else
                         locate(*where[int(batch.rows[row])]), message)

    try:
        batches = detections_from_records(records, prof.classes, prof.score_mode)
    except FieldError as exc:
        raise _mismatch(at(exc.row or 0, exc.field), str(exc)) from None
    out: list[list[dict[str, object]]] = [[{}] * len(f.detections) for f in frames]
    for res in _served(batches, loaded, confidence, levels, fault):
        for record in res.to_records():
            fi, di = where[record.pop("row")]
            del record["frame_id"]
            out[fi][di] = {"row": di, **record}
    return out


def calibrate_results(loaded: LoadedProfile, doc: NuScenesResults, confidence: float,
                      levels: Sequence[float], max_detections: int | None = None
                      ) -> tuple[dict[str, Any], int]:
    """The calibrated results document (`calibrators.io.nuscenes_batch`'s output contract)
    and the number of boxes calibrated; `levels` are the query's."""
    body = doc.model_dump(exclude_none=True)
    levels = _checked(levels, sum(map(len, body["results"].values())), max_detections,
                      "query")
    prof = loaded.profile
    flat = [(t, i) for t, boxes in body["results"].items() for i in range(len(boxes))]

    def at(token: str, i: int, field: str) -> list[str | int]:
        return ["body", "results", token, i, *([_BOX_KEY.get(WIRE_NAMES.get(field, field),
                                                             WIRE_NAMES.get(field, field))]
                                               if field else [])]

    def fault(batch: Detections, row: int, field: str, message: str) -> RequestError:
        return _mismatch(at(str(batch.frame_ids[row]), int(batch.rows[row]), field), message)

    try:
        batches = detections_from_nuscenes(body, prof.classes, prof.score_mode)
    except FieldError as exc:
        raise RequestError(at(*flat[exc.row or 0], exc.field), str(exc),
                           kind="value_error.profile_mismatch" if exc.field == "labels"
                           else "value_error") from None
    served = _served(batches, loaded, confidence, levels, fault)
    out = calibrated_document(served, {"profile": loaded.ref(),
                                       "ellipse_confidence": confidence, "levels": levels},
                              body.get("meta"))
    rest = {k: v for k, v in body.items() if k not in ("meta", "results")}
    return {**rest, **out}, len(flat)


def check_classes(loaded: LoadedProfile, classes: Sequence[str] | None) -> None:
    """A 422 at `body.classes` when the client's class list (its logits' column order) is not
    the profile's: the columns would be read as other classes."""
    if classes is None:
        return
    want = list(loaded.profile.classes)
    got = list(classes)
    if got == want:
        return
    missing = [c for c in want if c not in got]
    extra = [c for c in got if c not in want]
    if missing or extra:
        why = "; ".join(part for part in (
            f"missing {', '.join(missing)}" if missing else "",
            f"not in the profile: {', '.join(extra)}" if extra else "") if part)
    else:
        first = next(i for i, (a, b) in enumerate(zip(got, want, strict=True)) if a != b)
        why = (f"same classes in another order (column {first} is {got[first]!r}, the profile's "
               f"is {want[first]!r})")
    raise RequestError(["body", "classes"], f"classes do not match profile "
                                            f"{loaded.record.ref} ({', '.join(want)}): {why}")
