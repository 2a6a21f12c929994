"""Detections as an Apache Arrow record batch, and calibrated detections back (the binary
transport of POST /v1/calibrate; columns in docs/api.md).

A request batch has one row per detection:

- `frame_id` (string or integer, required) and `id` (any type, optional): echoed back;
- class evidence, exactly one of: `logits` (list of floats `[C']`), `layer_logits` (list of
  lists `[L][C']`), or `score` (float) with `label` (class name or index); with logits a
  `label` column names the class each detection asserts (default: the arg-max; a top-K
  (query, class) decoder gives one query a detection per class);
- `box` (list `[9]` or `[7]`: no velocity) or `layer_boxes` (list of lists `[L][9]`, the last
  is the final box);
- `covariance` (list `[D·D]`, row-major over the profile's `cov_dims`, optional) and
  `ego_translation` (list `[3]` or `[2]`, optional; default the origin);
- `hypothesis_boxes` (list of lists `[H][9]`, or a list `[H·9]`: each group head's box) with
  `hypothesis_scores` (list `[H]`: their group scores), optional, both or neither.

Lists may be fixed-size or variable-size Arrow lists, but every row of a column must have the
same length; numbers may be any integer or float type and no value may be null. A column that
breaks these rules is a `FieldError` naming it (and the row, where one is at fault). The
response batch (`calibrated_batch`) has `frame_id`, `row` (the request row), `id` (when
given), `label`, `label_index`,
`score`, `score_raw`, `class_scores` (when the profile gives them), `covariance [D·D]`,
`distance`, `ellipse` (a struct at the ellipse confidence) and one struct `ellipse_<q>` per
requested level (`semi_major`, `semi_minor` — null when unbounded —, `angle`, `guarantee`,
`calibration_n` — null for gaussian regions), plus `region_group` for conformal regions; its
schema metadata names the profile.

The column readers (`check_known`, `check_no_nulls`, `column_numbers`, `fixed_column`) are
shared with the 2-D batch format (`calibrators.io.arrow_boxes2d`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from calibrators.core.errors import FieldError
from calibrators.io.arrow_safe import MAX_INFLATED_BYTES, read_safe_stream
from calibrators.profile import WIRE_NAMES, CalibratedDetections, Detections, box9

ARROW_STREAM = "application/vnd.apache.arrow.stream"
EVIDENCE_COLUMNS = ("logits", "layer_logits", "score")
KNOWN_COLUMNS = frozenset({"frame_id", "id", *EVIDENCE_COLUMNS, "label", "box", "layer_boxes",
                           "covariance", "ego_translation", "hypothesis_boxes",
                           "hypothesis_scores"})
#: Library argument of `CalibrationProfile.calibrate` -> request column (the one wire map).
LIBRARY_TO_COLUMN = WIRE_NAMES


def read_stream(data: bytes, max_rows: int | None = None,
                max_bytes: int = MAX_INFLATED_BYTES) -> pa.RecordBatch:
    """The one record batch of an Arrow IPC stream (several batches are concatenated),
    read by `arrow_safe.read_safe_stream`: rows and decoded bytes capped batch by batch
    before decoding (FieldError "rows" / "bytes"), every batch validated in full, the echoed
    identity columns copied; FieldError naming the column (or "body") otherwise."""
    return read_safe_stream(data, max_rows, max_bytes)


def batch_request(batch: pa.RecordBatch, classes: Sequence[str]) -> Detections:
    """The `Detections` of a request `batch` (module docstring): rows are the batch's rows,
    `frame_id` and `id` the columns as they came (echoed back); FieldError naming the column
    (and `row`) that breaks the rules."""
    names = batch.schema.names
    _check_names(names)
    frame = _frame_ids(batch)
    kwargs = _evidence(batch, names, classes)
    kwargs.update(_boxes(batch, names))
    if "covariance" in names:
        kwargs["covariances"] = _covariances(batch.column("covariance"))
    if "hypothesis_boxes" in names:
        kwargs["hyp_boxes"] = _box_rows("hypothesis_boxes", batch.column("hypothesis_boxes"))
    if "hypothesis_scores" in names:
        kwargs["hyp_scores"] = column_numbers("hypothesis_scores",
                                              batch.column("hypothesis_scores"), (None,))
    if "ego_translation" in names:
        kwargs["ego_xy"] = _ego_xy(batch.column("ego_translation"))
    return Detections(frame_ids=frame, rows=np.arange(batch.num_rows, dtype=np.int64),
                      ego_xy=kwargs.pop("ego_xy", np.zeros((batch.num_rows, 2))),
                      detection_ids=batch.column("id") if "id" in names else None, **kwargs)


def _check_names(names: list[str]) -> None:
    """FieldError for an unknown or repeated column, or no `frame_id`."""
    check_known(names, KNOWN_COLUMNS)
    if len(set(names)) != len(names):
        raise FieldError("body", f"repeated column names: {names}")
    if "frame_id" not in names:
        raise FieldError("frame_id", "the batch needs a frame_id column (string or integer)")


def _frame_ids(batch: pa.RecordBatch) -> pa.Array:
    """The `frame_id` column, strings or integers without nulls."""
    frame = batch.column("frame_id")
    if not (pa.types.is_string(frame.type) or pa.types.is_large_string(frame.type)
            or pa.types.is_integer(frame.type)):
        raise FieldError("frame_id", f"frame_id must be strings or integers, got {frame.type}")
    check_no_nulls("frame_id", frame)
    return frame


def _evidence(batch: pa.RecordBatch, names: list[str],
              classes: Sequence[str]) -> dict[str, np.ndarray]:
    """The class evidence (`scores` with `labels`, `logits` or `layer_logits`) and the
    asserted `labels` when given, as `Detections` arguments."""
    evidence = [c for c in EVIDENCE_COLUMNS if c in names]
    if len(evidence) != 1:
        raise FieldError("logits", f"give exactly one of the columns {list(EVIDENCE_COLUMNS)}; "
                                   f"got {evidence or 'none'}")
    kwargs: dict[str, np.ndarray] = {}
    if evidence[0] == "score":
        kwargs["scores"] = column_numbers("score", batch.column("score"), ())
        if "label" not in names:
            raise FieldError("label", "a score column needs a label column (name or index)")
        kwargs["labels"] = _labels(batch.column("label"), classes)
    elif evidence[0] == "logits":
        kwargs["logits"] = column_numbers("logits", batch.column("logits"), (None,))
    else:
        kwargs["layer_logits"] = column_numbers("layer_logits", batch.column("layer_logits"),
                                                (None, None))
    if "label" in names and evidence[0] != "score":   # the class each detection asserts
        kwargs["labels"] = _labels(batch.column("label"), classes)
    return kwargs


def _boxes(batch: pa.RecordBatch, names: list[str]) -> dict[str, np.ndarray]:
    """The final `boxes` (from `box`, else the last of `layer_boxes`) and the `layer_boxes`
    when given, as `Detections` arguments."""
    kwargs: dict[str, np.ndarray] = {}
    if "layer_boxes" in names:
        kwargs["layer_boxes"] = column_numbers("layer_boxes", batch.column("layer_boxes"),
                                               (None, 9))
    if "box" in names:
        box = column_numbers("box", batch.column("box"), (None,))
        if box.shape[1] not in (7, 9):
            raise FieldError("box", f"box must have 9 values (x, y, z, w, l, h, yaw, vx, vy) "
                                    f"or 7 (no velocity), got {box.shape[1]}")
        kwargs["boxes"] = box9(box)
    elif "layer_boxes" in kwargs:
        kwargs["boxes"] = kwargs["layer_boxes"][:, -1]
    else:
        raise FieldError("box", "the batch needs a box (or layer_boxes) column")
    return kwargs


def _covariances(arr: pa.Array) -> np.ndarray:
    """`[N, D, D]` covariances of a column of row-major `[D·D]` lists."""
    flat = column_numbers("covariance", arr, (None,))
    dim = int(round(np.sqrt(flat.shape[1])))
    if dim * dim != flat.shape[1]:
        raise FieldError("covariance", f"covariance rows must hold D·D values (row-major "
                                       f"[D, D]), got {flat.shape[1]}")
    return flat.reshape(len(flat), dim, dim)


def _ego_xy(arr: pa.Array) -> np.ndarray:
    """`[N, 2]` ego positions of an `ego_translation` column of 3 (or 2) values."""
    ego = column_numbers("ego_translation", arr, (None,))
    if ego.shape[1] not in (2, 3):
        raise FieldError("ego_translation", f"ego_translation must have 3 (or 2) values, "
                                            f"got {ego.shape[1]}")
    return np.ascontiguousarray(ego[:, :2])


def calibrated_batch(res: CalibratedDetections, metadata: Mapping[str, Any]) -> pa.RecordBatch:
    """The response batch of `res` (module docstring), each row with its identity
    (`frame_id`, `row`, `id` when given); `metadata` is stored as JSON under the schema key
    `detcal`."""
    n, det = len(res), res.detections
    columns: dict[str, pa.Array] = {}
    if det is not None:
        columns["frame_id"] = _arrow(det.frame_ids)
        columns["row"] = pa.array(det.rows, pa.int64())
        if det.detection_ids is not None:
            columns["id"] = _arrow(det.detection_ids)
    columns["label"] = pa.array(list(res.classes), pa.string()).take(pa.array(res.labels))
    columns["label_index"] = pa.array(res.labels.astype(np.int32))
    columns["score"] = pa.array(res.scores)
    columns["score_raw"] = pa.array(res.scores_raw)
    if res.class_scores is not None:
        columns["class_scores"] = fixed_column(res.class_scores)
    columns["covariance"] = fixed_column(res.covariances.reshape(n, -1))
    columns["distance"] = pa.array(res.distances)
    if res.ellipses is not None:
        columns["ellipse"] = _ellipse_struct(res.ellipses)
    for level, region in res.regions.items():
        columns[f"ellipse_{float(level)!r}"] = _ellipse_struct(
            region, res.region_guarantees.get(level), res.region_counts.get(level))
    if res.region_groups is not None:
        columns["region_group"] = pa.array(res.region_groups, pa.string())
    meta = {"confidence": res.ellipse_confidence, "levels": [float(q) for q in res.regions],
            "region_method": res.region_method, "cov_source": res.cov_source, **metadata}
    schema = pa.schema([pa.field(k, v.type) for k, v in columns.items()],
                       metadata={"detcal": json.dumps(meta)})
    return pa.RecordBatch.from_arrays(list(columns.values()), schema=schema)


def write_stream(batch: pa.RecordBatch) -> bytes:
    """`batch` as an Arrow IPC stream."""
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    return sink.getvalue().to_pybytes()


# -- columns ------------------------------------------------------------------------------------


def check_known(names: Sequence[str], known: frozenset[str]) -> None:
    """FieldError naming the first (in sorted order) of `names` that is not a `known` column."""
    unknown = sorted(set(names) - known)
    if unknown:
        raise FieldError(unknown[0], f"unknown column {unknown[0]!r}; the columns are "
                                     f"{sorted(known)}")


def check_no_nulls(name: str, arr: pa.Array) -> None:
    """FieldError naming column `name` and the row of its first null, if it has one."""
    if arr.null_count:
        row = int(pc.index(pc.is_null(arr), True).as_py())
        raise FieldError(name, f"{name} has a null at row {row}", row=row)


def column_numbers(name: str, arr: pa.Array, shape: tuple[int | None, ...]) -> np.ndarray:
    """Float64 `[N, *shape]` of a number column (`()`) or of (nested) lists; None in `shape`
    is any length, the same in every row."""
    check_no_nulls(name, arr)
    values, dims = arr, []
    for want in shape:
        if not _is_list(values.type):
            raise FieldError(name, f"{name} must be a list column{'s of lists' * (len(shape) > 1)}"
                                   f" of numbers, got {arr.type}")
        if pa.types.is_fixed_size_list(values.type):
            width = values.type.list_size
            values = values.flatten()
        else:
            lengths = pc.list_value_length(values).to_numpy(zero_copy_only=False)
            width = int(lengths[0]) if len(lengths) else 0
            if (lengths != width).any():
                row = int(np.argmax(lengths != width))
                raise FieldError(name, f"every row of {name} must have the same length: row "
                                       f"{row} has {int(lengths[row])}, row 0 has {width}",
                                 row=row)
            values = values.flatten()
        if want is not None and width != want:
            raise FieldError(name, f"{name} rows must hold {want} values, got {width}")
        check_no_nulls(name, values)
        dims.append(width)
    if not (pa.types.is_floating(values.type) or pa.types.is_integer(values.type)):
        raise FieldError(name, f"{name} must hold numbers (integer or float), got "
                               f"{values.type}")
    out = values.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
    return out.reshape(len(arr), *dims)


def _box_rows(name: str, arr: pa.Array) -> np.ndarray:
    """`[N, H, 9]` boxes of a list-of-lists column (`[H][9]`) or of a flat list column
    (`[H·9]`, row-major)."""
    values = arr.type.value_type if _is_list(arr.type) else None
    if values is not None and _is_list(values):
        return column_numbers(name, arr, (None, 9))
    flat = column_numbers(name, arr, (None,))
    if flat.shape[1] % 9:
        raise FieldError(name, f"{name} rows must hold H·9 values (H boxes x y z w l h yaw "
                               f"vx vy, row-major) or H lists of 9, got {flat.shape[1]}")
    return flat.reshape(len(flat), -1, 9)


def _is_list(kind: pa.DataType) -> bool:
    return (pa.types.is_list(kind) or pa.types.is_large_list(kind)
            or pa.types.is_fixed_size_list(kind))


def _labels(arr: pa.Array, classes: Sequence[str]) -> np.ndarray:
    """Class indices `[N]` of a label column of names (or indices, checked by the library)."""
    check_no_nulls("label", arr)
    if pa.types.is_integer(arr.type):
        return arr.to_numpy(zero_copy_only=False).astype(np.int64)
    if not (pa.types.is_string(arr.type) or pa.types.is_large_string(arr.type)
            or pa.types.is_dictionary(arr.type)):
        raise FieldError("label", f"label must be class names or indices, got {arr.type}")
    index = pc.index_in(arr.cast(pa.string()), value_set=pa.array(list(classes), pa.string()))
    if index.null_count:
        row = int(pc.index(pc.is_null(index), True).as_py())
        raise FieldError("label", f"unknown class {arr[row].as_py()!r} at row {row}; the "
                                  f"profile's classes are {list(classes)}", row=row)
    return index.to_numpy(zero_copy_only=False).astype(np.int64)


def _arrow(values: Any) -> pa.Array:
    """An Arrow column as it came, or numpy / Python values as one."""
    return values if isinstance(values, pa.Array | pa.ChunkedArray) else pa.array(values)


def fixed_column(values: np.ndarray) -> pa.FixedSizeListArray:
    """`[N, W]` float64 as a fixed-size list column."""
    flat = np.ascontiguousarray(values, dtype=np.float64)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[1])


def _ellipse_struct(el: Any, holds: np.ndarray | None = None,
                    counts: np.ndarray | None = None) -> pa.StructArray:
    """semi_major, semi_minor (null where unbounded: inf) and angle of ellipses `[N]`; with
    `holds [N]` and `counts [N]` of a served level, its guarantee and calibration_n (null
    where negative: gaussian)."""
    major, minor = (np.asarray(a, dtype=np.float64) for a in (el.semi_major, el.semi_minor))
    fields = [pa.array(a, mask=np.isinf(a)) for a in (major, minor)]
    fields.append(pa.array(np.asarray(el.angle, np.float64)))
    names = ["semi_major", "semi_minor", "angle"]
    if holds is not None and counts is not None:
        fields += [pa.array(holds.tolist(), pa.string()), pa.array(counts, mask=counts < 0)]
        names += ["guarantee", "calibration_n"]
    return pa.StructArray.from_arrays(fields, names=names)
