"""2-D (image-plane) detections as an Apache Arrow record batch, and calibrated 2-D detections
back: the binary transport of POST /v1/calibrate for a 2-D profile (docs/formats.md, "2-D
detections as an Arrow batch"). The 3-D batch format is `calibrators.io.arrow_batch`.

A request batch has one row per detection (N rows):

    image_id       integer                   required; the detection's image, echoed back
    id             any type (`arrow_safe`)   optional; echoed back as it came
    category_id    integer                   required; a COCO category of the profile
    bbox           list [4] of numbers       required; COCO `x, y, w, h` in pixels
    score          number in [0, 1]          required; the detector's confidence
    logits         list [C'] of numbers      optional; class logits, the profile's order
    layer_boxes    list [L] of lists [4]     optional; the box of every decoder layer
    width, height  whole numbers > 0         optional, both or neither; the size in pixels
                                             of the row's image (default: the profile's)

Lists may be fixed-size or variable-size Arrow lists, every row of a column the same length;
numbers may be any integer or float type; no value may be null. The bytes are read by
`arrow_batch.read_stream` (the bounded, validating reader of `arrow_safe`), the columns by
`arrow_batch`'s column readers, and the values are checked by `Detections2D` (finite boxes,
`w, h >= 0`, ...). A bad column is a FieldError naming it, with the row where one is at fault.

The response batch (`calibrated_boxes2d_batch`) has one row per request row, in request order:
`image_id`, `row` (int64, the request row), `id` (when sent): the detection's identity; then
`category_id`, `bbox` [4], `score` (calibrated), `score_raw` (the detector's), and per served
level q one struct column `region_<q>` (`<q>` as `str(float(q))`, e.g. `region_0.9`) with
`inner` [4] and `outer` [4] (both null where the level is unbounded), `guarantee` (string)
and `calibration_n` (int64), as the COCO results records of `Calibrated2D.records()`. Its
schema metadata key `detcal` holds JSON: the caller's `metadata` and `levels`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from calibrators.boxes2d import BoxRegions, Calibrated2D, Detections2D
from calibrators.core.checks import check_probabilities
from calibrators.core.errors import FieldError
from calibrators.io.arrow_batch import check_known, check_no_nulls, column_numbers, fixed_column

__all__ = ["BOXES2D_COLUMNS", "Boxes2DRequest", "boxes2d_request", "calibrated_boxes2d_batch"]

#: The columns of a 2-D request batch, and what each required one holds.
BOXES2D_COLUMNS = frozenset({"image_id", "id", "category_id", "bbox", "score", "logits",
                             "layer_boxes", "width", "height"})
_REQUIRED = {"image_id": "integers", "category_id": "integers",
             "bbox": "lists of 4 numbers: x, y, w, h in pixels",
             "score": "numbers in [0, 1]"}
_INT64_MAX = np.iinfo(np.int64).max


@dataclass(frozen=True, eq=False)
class Boxes2DRequest:
    """The N detections of a 2-D request batch, row i being request row i.

    detections  Detections2D [N]      the values, checked
    rows        [N] int64             the request row of each detection
    ids         pa.Array [N] | None   the `id` column as it came (None: not sent)
    image_size  [N, 2] float | None   width and height of each row's image (None: not sent)
    """

    detections: Detections2D
    rows: np.ndarray
    ids: pa.Array | None
    image_size: np.ndarray | None

    def __len__(self) -> int:
        return len(self.detections)


def boxes2d_request(batch: pa.RecordBatch) -> Boxes2DRequest:
    """The `Boxes2DRequest` of a request `batch` (module docstring: columns and rules, one
    FieldError naming the column, and the row, that breaks them)."""
    names = batch.schema.names
    check_known(names, BOXES2D_COLUMNS)
    for name, holds in _REQUIRED.items():
        if name not in names:
            raise FieldError(name, f"the batch needs a {name} column ({holds})")
    optional = {}
    if "logits" in names:
        optional["logits"] = column_numbers("logits", batch.column("logits"), (None,))
    if "layer_boxes" in names:
        optional["layer_boxes"] = column_numbers("layer_boxes", batch.column("layer_boxes"),
                                                 (None, 4))
    detections = Detections2D(
        image_id=_ints("image_id", batch.column("image_id")),
        category_id=_ints("category_id", batch.column("category_id")),
        bbox=column_numbers("bbox", batch.column("bbox"), (4,)),
        score=column_numbers("score", batch.column("score"), ()), **optional)
    check_probabilities("score", detections.score)
    return Boxes2DRequest(detections, np.arange(batch.num_rows, dtype=np.int64),
                          batch.column("id") if "id" in names else None,
                          _image_size(batch, names))


def calibrated_boxes2d_batch(request: Boxes2DRequest, served: Calibrated2D,
                             metadata: Mapping[str, Any]) -> pa.RecordBatch:
    """The response batch (module docstring) of `served`, `calibrate_2d` of
    `request.detections`: each row with its identity (`image_id`, `row`, `id` when sent);
    `metadata` is stored as JSON under the schema key `detcal`, with the served `levels`
    (null when the profile serves no regions)."""
    if served.detections is not request.detections:
        raise ValueError("served must be calibrate_2d of request.detections")
    det = request.detections
    columns: dict[str, pa.Array] = {"image_id": pa.array(det.image_id, pa.int64()),
                                    "row": pa.array(request.rows, pa.int64())}
    if request.ids is not None:
        columns["id"] = request.ids
    columns["category_id"] = pa.array(det.category_id, pa.int64())
    columns["bbox"] = fixed_column(det.bbox)
    columns["score"] = pa.array(served.score, pa.float64())
    columns["score_raw"] = pa.array(det.score, pa.float64())
    levels = None
    if served.regions is not None:
        levels = [float(q) for q in served.regions.levels.tolist()]
        for j, q in enumerate(levels):
            columns[f"region_{q}"] = _region_struct(served.regions, j)
    schema = pa.schema([pa.field(k, v.type) for k, v in columns.items()],
                       metadata={"detcal": json.dumps({**metadata, "levels": levels})})
    return pa.RecordBatch.from_arrays(list(columns.values()), schema=schema)


def _ints(name: str, arr: pa.Array) -> np.ndarray:
    """`[N]` int64 of an integer column (an id may not exceed int64)."""
    check_no_nulls(name, arr)
    if not pa.types.is_integer(arr.type):
        raise FieldError(name, f"{name} must be integers, got {arr.type}")
    values = arr.to_numpy(zero_copy_only=False)
    if values.dtype == np.uint64 and (values > _INT64_MAX).any():
        row = int(np.argmax(values > _INT64_MAX))
        raise FieldError(name, f"{name} at row {row} is {int(values[row])}, beyond int64",
                         row=row)
    return values.astype(np.int64)


def _image_size(batch: pa.RecordBatch, names: list[str]) -> np.ndarray | None:
    """`[N, 2]` width and height of the `width` and `height` columns (None when neither is
    sent), each a whole number of pixels > 0 (as a JSON request's image size)."""
    sent = [k for k in ("width", "height") if k in names]
    if not sent:
        return None
    if len(sent) == 1:
        other = "height" if sent == ["width"] else "width"
        raise FieldError(other, f"give the width and height columns together (the batch has "
                                f"only {sent[0]})")
    size = np.stack([column_numbers(k, batch.column(k), ()) for k in ("width", "height")],
                    axis=1)
    with np.errstate(invalid="ignore"):
        bad = ~(np.isfinite(size) & (size >= 1) & (size == np.round(size)))
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        name = ("width", "height")[col]
        raise FieldError(name, f"{name} at row {row} must be a whole number of pixels > 0, "
                               f"got {size[row, col]}", row=row)
    return size


def _region_struct(regions: BoxRegions, j: int) -> pa.StructArray:
    """The regions at level index j as a struct column (`inner`, `outer` null where the level
    is unbounded, as the COCO records write them)."""
    inner, outer = regions.inner[:, j], regions.outer[:, j]
    bounded = np.isfinite(inner).all(axis=1) & np.isfinite(outer).all(axis=1)
    mask = pa.array(~bounded)

    def boxes(values: np.ndarray) -> pa.FixedSizeListArray:
        flat = np.where(bounded[:, None], values, 0.0).astype(np.float64).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat), 4, mask=mask)

    fields = [boxes(inner), boxes(outer), pa.array(regions.guarantee[:, j].tolist(), pa.string()),
              pa.array(regions.calibration_n[:, j], pa.int64())]
    return pa.StructArray.from_arrays(fields, names=["inner", "outer", "guarantee",
                                                     "calibration_n"])
