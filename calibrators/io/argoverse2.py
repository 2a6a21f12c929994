"""Argoverse 2 detections and annotations (Feather) -> `Dump`.

The columns of `av2.evaluation.detection` (detections) and of a sensor log's
`annotations.feather` (ground truth), one cuboid per row:

    log_id            string   the log
    timestamp_ns      int      the lidar sweep (nanoseconds); frame token `log_id/timestamp_ns`
    category          string   the class (e.g. REGULAR_VEHICLE)
    tx_m, ty_m, tz_m  float    cuboid centre (m) in the ego-vehicle frame of that sweep
                               (x forward, y left, z up; z is the centre)
    length_m          float    extent along the cuboid's x axis (its heading)
    width_m           float    extent along its y axis
    height_m          float    extent along its z axis
    qw, qx, qy, qz    float    rotation ego <- cuboid as a quaternion; yaw about +z
    score             float    detections only: confidence in [0, 1]
    num_interior_pts  int      annotations (optional): lidar points inside; 0 is not evaluated

Other columns (`track_uuid`, ...) are ignored. Files are Feather v2 (Arrow IPC files, LZ4 or
ZSTD compressed or not; dictionary-encoded columns, as pandas writes a `category` dtype,
are decoded), each record batch validated in full before any column is read.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa

from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.io.reader_files import ByteBudget, check_file
from calibrators.io.reader_rows import Rows, check_scores, class_list, rows_to_dump

#: The 26 categories of the AV2 3D object detection competition: the default class list.
AV2_CATEGORIES = (
    "REGULAR_VEHICLE", "PEDESTRIAN", "BICYCLIST", "MOTORCYCLIST", "WHEELED_RIDER", "BOLLARD",
    "CONSTRUCTION_CONE", "SIGN", "CONSTRUCTION_BARREL", "STOP_SIGN",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN", "LARGE_VEHICLE", "BUS", "BOX_TRUCK", "TRUCK",
    "VEHICULAR_TRAILER", "TRUCK_CAB", "SCHOOL_BUS", "ARTICULATED_BUS", "MESSAGE_BOARD_TRAILER",
    "BICYCLE", "MOTORCYCLE", "WHEELED_DEVICE", "WHEELCHAIR", "STROLLER", "DOG")
FLOAT_COLUMNS = ("tx_m", "ty_m", "tz_m", "length_m", "width_m", "height_m", "qw", "qx", "qy",
                 "qz")
_MAGIC = b"ARROW1"


def load_av2(path: str | os.PathLike[str], ground_truth: str | os.PathLike[str] | None = None,
             *, classes: Sequence[str] = AV2_CATEGORIES,
             class_map: Mapping[str, str] | None = None, max_bytes: int | None = None) -> Dump:
    """Read AV2 detections (and optionally annotations) Feather files into a `Dump`.

    A detection's category must be one of `classes` (or `class_map`); annotations of other
    categories, and with `num_interior_pts == 0`, are not read. Only the annotations of the
    detections' logs are read: `ground_truth` is one annotations file (several logs'
    concatenated) or a split folder holding `<log_id>/annotations.feather`. At most
    `max_bytes` (default 2 GiB) are read and decoded. Errors are FieldErrors naming the file,
    the column and the row.
    """
    classes, index = class_list(classes, class_map)
    budget = ByteBudget(max_bytes)
    det_path = check_file(path, "detections")
    table = _read(det_path, budget, scored=True)
    det = _rows(table, det_path.name, index, detections=True)
    frames = _tokens(table)
    if ground_truth is None:
        return rows_to_dump(classes, det, None, frames=frames, source=det_path.name)
    logs = sorted(set(table.column("log_id").to_pylist()))
    gt, gt_frames = _truth(check_file(ground_truth, "annotations"), logs, budget, index)
    return rows_to_dump(classes, det, gt, frames=np.concatenate([frames, gt_frames]),
                        source=det_path.name)


def _truth(root: Path, logs: list[str], budget: ByteBudget, index: Mapping[str, int]
           ) -> tuple[Rows, np.ndarray]:
    """Ground-truth rows of the detections' `logs` and every frame token they name, from one
    annotations file or a split folder of `<log_id>/annotations.feather` (AV2's layout)."""
    if root.is_dir():
        files = [(root / log / "annotations.feather", f"{root.name}/{log}/annotations.feather")
                 for log in logs]
        for path, name in files:
            if not path.is_file():
                raise FieldError("annotations", f"{name} is missing (the detections have log "
                                                f"{path.parent.name!r})")
    else:
        files = [(root, root.name)]
    wanted = set(logs)
    parts, frames = [], []
    for path, name in files:
        tab = _read(path, budget, scored=False, name=name)
        tab = tab.filter(pa.array([v in wanted for v in tab.column("log_id").to_pylist()]))
        parts.append(_rows(tab, name, index, detections=False))
        frames.append(_tokens(tab))
    return Rows(np.concatenate([r.frames for r in parts]),
                np.concatenate([r.labels for r in parts]),
                np.concatenate([r.boxes for r in parts])), np.concatenate(frames)


def _read(path: Path, budget: ByteBudget, scored: bool, name: str | None = None
          ) -> pa.Table:
    """The file's columns, checked: required columns present, of the right types, no nulls
    (`name`, default the file's, in messages)."""
    name = path.name if name is None else name
    data = budget.read(path, name)
    if not data.startswith(_MAGIC) or not data.endswith(_MAGIC):
        raise FieldError("feather", f"{name}: not a Feather v2 (Arrow IPC) file")
    table = _decoded(data, name, budget)
    want = {"log_id": "string", "timestamp_ns": "integer", "category": "string",
            **{c: "float" for c in FLOAT_COLUMNS}, **({"score": "float"} if scored else {})}
    if not scored and "num_interior_pts" in table.column_names:
        want["num_interior_pts"] = "integer"
    for column, kind in want.items():
        if column not in table.column_names:
            raise FieldError(column, f"{name}: missing column {column!r}")
        arr = table.column(column)
        ok = {"string": pa.types.is_string(arr.type) or pa.types.is_large_string(arr.type),
              "integer": pa.types.is_integer(arr.type),
              "float": pa.types.is_floating(arr.type) or pa.types.is_integer(arr.type)}[kind]
        if not ok:
            raise FieldError(column, f"{name}: column {column!r} must be {kind}, got {arr.type}")
        if arr.null_count:
            row = int(np.flatnonzero(arr.is_null().to_numpy(zero_copy_only=False))[0])
            raise FieldError(column, f"{name}: column {column!r} is null at row {row}", row=row)
    return table


def _tokens(table: pa.Table) -> np.ndarray:
    """`[N]` frame token `log_id/timestamp_ns` of every row."""
    logs = table.column("log_id").to_pylist()
    stamps = table.column("timestamp_ns").to_pylist()
    return np.array([f"{log}/{t}" for log, t in zip(logs, stamps, strict=True)], dtype=str)


def _rows(table: pa.Table, name: str, index: Mapping[str, int], detections: bool) -> Rows:
    values = {c: table.column(c).to_numpy().astype(np.float64) for c in FLOAT_COLUMNS}
    for column, arr in values.items():
        bad = np.flatnonzero(~np.isfinite(arr))
        if len(bad):
            raise FieldError(column, f"{name}: column {column!r} is {arr[bad[0]]} at row "
                                     f"{bad[0]}", row=int(bad[0]))
    names = table.column("category").to_pylist()
    labels = np.array([index.get(c, -1) for c in names], dtype=np.int64)
    if detections and np.any(labels < 0):
        row = int(np.flatnonzero(labels < 0)[0])
        raise FieldError("category", f"{name}: category {names[row]!r} at row {row} is not one "
                                     "of the classes (nor class_map)", row=row)
    keep = labels >= 0
    if not detections and "num_interior_pts" in table.column_names:
        keep &= table.column("num_interior_pts").to_numpy() > 0
    size = np.stack([values["width_m"], values["length_m"], values["height_m"]], axis=1)
    if np.any(size[keep] <= 0):
        row = int(np.flatnonzero(keep & np.any(size <= 0, axis=1))[0])
        raise FieldError("length_m", f"{name}: length_m, width_m, height_m must be > 0, row "
                                     f"{row} has {size[row].tolist()}", row=row)
    quat = np.stack([values[c] for c in ("qw", "qx", "qy", "qz")], axis=1)
    scale = np.max(np.abs(quat), axis=1, keepdims=True)  # no overflow in the squares below
    zero = np.flatnonzero(keep & (scale[:, 0] == 0))
    qw, qx, qy, qz = (quat / np.where(scale > 0, scale, 1.0)).T
    if len(zero):
        raise FieldError("qw", f"{name}: row {zero[0]} has the zero quaternion (no rotation)",
                         row=int(zero[0]))
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), qw ** 2 + qx ** 2 - qy ** 2 - qz ** 2)
    boxes = np.column_stack([values["tx_m"], values["ty_m"], values["tz_m"], size, yaw,
                             np.zeros((len(yaw), 2))])
    scores = None
    if detections:
        scores = table.column("score").to_numpy().astype(np.float64)
        bad = np.flatnonzero(~np.isfinite(scores))
        if len(bad):
            raise FieldError("score", f"{name}: column 'score' is {scores[bad[0]]} at row "
                                      f"{bad[0]}", row=int(bad[0]))
        check_scores(scores, name, "score")
    return Rows(_tokens(table)[keep], labels[keep], boxes[keep],
                scores=None if scores is None else scores[keep])


def _decoded(data: bytes, name: str, budget: ByteBudget) -> pa.Table:
    """The Feather file `data` as a table: every record batch charged to `budget` (decoded
    bytes) and validated in full before the next is read, dictionary columns decoded."""
    try:
        reader = pa.ipc.open_file(pa.BufferReader(data))
        batches = []
        for i in range(reader.num_record_batches):
            batch = reader.get_batch(i)
            if batch.nbytes > budget.left:
                raise FieldError("feather", f"{name}: decoding it would pass the limit of "
                                            f"{budget.limit} bytes for one load (max_bytes)")
            budget.left -= batch.nbytes
            batch.validate(full=True)
            batches.append(batch)
        table = pa.Table.from_batches(batches, schema=reader.schema)
        for i, field in enumerate(table.schema):
            if pa.types.is_dictionary(field.type):
                table = table.set_column(i, field.name,
                                         table.column(i).cast(field.type.value_type))
    except FieldError:
        raise
    except (ValueError, TypeError, pa.ArrowException, OSError) as exc:
        raise FieldError("feather", f"{name}: not a readable Feather v2 file: "
                                    f"{str(exc).splitlines()[0][:200]}") from None
    return table
