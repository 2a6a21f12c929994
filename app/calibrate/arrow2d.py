"""The Arrow body of a POST /v1/calibrate request to a 2-D profile: one 2-D detection per row
(`calibrators.io.arrow_boxes2d`), read by the same bounded, validating reader as a 3-D batch,
calibrated by `calibrators.boxes2d.calibrate_2d`, and answered as an Arrow stream (one row per
request row, `calibrated_boxes2d_batch`) or, when `Accept` takes JSON but not Arrow, as the
document a JSON `images` request gets (`images2d.document_2d`: the detections grouped by
`image_id` in order of first appearance, each with `row`, its row in the batch, and `id`).

Imported only when an Arrow body meets a 2-D profile: the 3-D calibrate path never loads it.
A 3-D batch (a `frame_id` column) is a 422 at that column saying what the profile wants, as a
JSON `frames` body is; `ellipse_confidence` (an option of 3-D profiles) a 422 at the query. A
library `FieldError` is a 422 at the column (and row) at fault, as for a 3-D batch
(`engine.batch_error`).
"""

from __future__ import annotations

from typing import Any

from app.calibrate.cache import LoadedProfile
from app.calibrate.engine import CalibrateCall, batch_error
from app.calibrate.images2d import document_2d, profile_fields_2d, three_d_option
from app.http.content_types import accepts
from app.http.errors import RequestError
from app.http.json_body import dumps_json
from calibrators.boxes2d import Calibrated2D, calibrate_2d
from calibrators.core.errors import FieldError
from calibrators.io.arrow_batch import ARROW_STREAM, read_stream, write_stream
from calibrators.io.arrow_boxes2d import (
    BOXES2D_COLUMNS,
    Boxes2DRequest,
    boxes2d_request,
    calibrated_boxes2d_batch,
)

#: Library argument -> request column, where they differ.
_COLUMNS = {"boxes": "bbox", "image_size": "width"}


def calibrate_arrow_2d(loaded: LoadedProfile, call: CalibrateCall, max_detections: int | None
                       ) -> tuple[bytes, int, str]:
    """The answer to the Arrow `call` to the 2-D profile `loaded`: its bytes, the number of
    detections calibrated and its media type (module docstring)."""
    ref = loaded.record.ref
    try:
        batch = read_stream(call.body, max_detections)
    except FieldError as exc:
        raise batch_error(exc, columns=_COLUMNS) from None
    names = batch.schema.names
    if "frame_id" in names:
        raise RequestError(["body", "frame_id"], f"profile {ref} is a 2-D (boxes2d) profile: "
                                                 "send 2-D detections as rows with `image_id` "
                                                 "(docs/api.md)")
    if call.ellipse_confidence is not None:
        raise three_d_option("ellipse_confidence", ref, "query")
    try:
        request = boxes2d_request(batch)
    except FieldError as exc:
        raise batch_error(exc, columns=_COLUMNS) from None
    try:
        served = calibrate_2d(loaded.profile, request.detections, call.levels,
                              request.image_size)
    except FieldError as exc:
        column = _COLUMNS.get(exc.field, exc.field)
        if column in BOXES2D_COLUMNS and column not in names:   # one the profile needs
            exc = FieldError(exc.field, str(exc))
        raise batch_error(exc, ref, _COLUMNS) from None
    except ValueError as exc:   # a library check that names no field
        raise RequestError(["body"], f"profile {ref}: {exc}") from None
    if accepts(call.accept, ARROW_STREAM):
        out = calibrated_boxes2d_batch(request, served, profile_fields_2d(loaded))
        return write_stream(out), len(served), ARROW_STREAM
    doc = document_2d(loaded, served, _images(request, served))
    return dumps_json(doc), len(served), "application/json"


def _images(request: Boxes2DRequest, served: Calibrated2D) -> list[dict[str, Any]]:
    """The calibrated records grouped by image (in order of first appearance), each with its
    request `row` and `id`."""
    ids = [None] * len(request) if request.ids is None else request.ids.to_pylist()
    images: dict[int, list[dict[str, Any]]] = {}
    for row, record in zip(request.rows.tolist(), served.records(), strict=True):
        images.setdefault(record["image_id"], []).append({"row": row, "id": ids[row],
                                                          **record})
    return [{"image_id": i, "detections": d} for i, d in images.items()]
