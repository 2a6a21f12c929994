"""Read a validation dump stored as a Parquet dataset (docs/formats.md, "Parquet dataset").

A dataset is a folder: `detcal.json` (classes, score mode, shapes, the parts and the frames
each holds), `frames.parquet` (one row per frame) and, per part, `detections/<part>.parquet`
and `ground_truth/<part>.parquet` with the rows of the part's frames `[first, stop)` only.
`open_parquet` checks the metadata and every part's schema (columns, list sizes, types)
without reading data; `ParquetDataset.read_part(i)` reads one part as a `Dump` of its
frames (what a streamed fit works on); `load_parquet` reads everything into one `Dump`.
Every error is a `FieldError` naming the column (or `dataset`) and the file.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from calibrators.core.errors import FieldError
from calibrators.data import Dump, concat_frames

FORMAT = "detcal-parquet"
VERSION = 1
META_FILE = "detcal.json"
_FLOATS = (pa.float32(), pa.float64())


@dataclass(frozen=True)
class PartInfo:
    """One part: its file stem, the frames `[first, stop)` it holds, its row counts."""

    name: str
    first: int
    stop: int
    n_detections: int
    n_ground_truth: int


@dataclass(frozen=True)
class ParquetDataset:
    """An opened (metadata and schemas checked) Parquet dataset; see the module docstring."""

    path: Path
    classes: tuple[str, ...]
    score_mode: str
    cov_dims: tuple[str, ...]
    n_layers: int
    has_cov: bool
    has_ego: bool
    n_frames: int
    n_detections: int
    n_ground_truth: int
    source_sha256: str
    parts: tuple[PartInfo, ...]
    n_hypotheses: int = 0
    has_label: bool = False   # a `label` column: the class each detection asserts

    @property
    def n_columns(self) -> int:
        """C': logit columns per decoder layer."""
        return len(self.classes) + (1 if self.score_mode == "softmax" else 0)

    def empty_dump(self) -> Dump:
        """A `Dump` with the dataset's classes, mode, layers and optional arrays but no row
        (what option checks such as `check_fit_input` need to know)."""
        d, h = len(self.cov_dims), self.n_hypotheses
        return Dump(classes=self.classes, score_mode=self.score_mode, frame_ids=np.zeros(0),
                    det_frame=np.zeros(0, int),
                    det_logits=np.zeros((0, self.n_layers, self.n_columns)),
                    det_boxes=np.zeros((0, self.n_layers, 9)), gt_frame=np.zeros(0, int),
                    gt_labels=np.zeros(0, int), gt_boxes=np.zeros((0, 9)),
                    det_cov=np.zeros((0, d, d)) if self.has_cov else None,
                    cov_dims=self.cov_dims,
                    det_hyp_boxes=np.zeros((0, h, 9)) if h else None,
                    det_hyp_scores=np.zeros((0, h)) if h else None,
                    det_label=np.zeros(0, int) if self.has_label else None)

    def frames(self) -> tuple[np.ndarray, np.ndarray | None]:
        """`(frame_ids [F] str, ego_translation [F, 3] | None)` from `frames.parquet`."""
        file = self.path / "frames.parquet"
        table = _read(file, ["frame_id", *(["ego_translation"] if self.has_ego else [])])
        ids = table.column("frame_id")
        if not pa.types.is_string(ids.type) and not pa.types.is_large_string(ids.type):
            raise FieldError("frame_id", f"{file.name}: column 'frame_id' must be strings, "
                                         f"got {ids.type}")
        if len(ids) != self.n_frames or ids.null_count:
            raise FieldError("frame_id", f"{file.name}: column 'frame_id' must hold "
                                         f"{self.n_frames} frame ids without nulls")
        ego = _floats(table, "ego_translation", 3, file) if self.has_ego else None
        return np.asarray(ids.to_pylist(), dtype=str), ego

    def read_part(self, index: int, frames: tuple[np.ndarray, np.ndarray | None] | None = None,
                  logits_only: bool = False) -> Dump:
        """Part `index` as a `Dump` of its frames `[first, stop)` (frame `first + i` is its
        frame i). `frames`: the part's own `(frame_ids, ego_translation)` rows when the caller
        already has them (else `frames.parquet` is read). `logits_only`: read only the
        detections' frames and logits (zero boxes, no covariance, no ground truth): what
        scores and temperature-scaling logits need, at a fraction of the cost."""
        part = self.parts[index]
        if frames is None:
            ids, ego = self.frames()
            ids, ego = ids[part.first:part.stop], None if ego is None else ego[part.first:part.stop]
        else:
            ids, ego = frames
        det_file = self.path / "detections" / f"{part.name}.parquet"
        gt_file = self.path / "ground_truth" / f"{part.name}.parquet"
        n_cols, d = self.n_columns, len(self.cov_dims)
        label = ["label"] if self.has_label else []
        if logits_only:
            det = _read(det_file, ["frame", "logits", *label])
            logits = _floats(det, "logits", self.n_layers * n_cols, det_file)
            return self._dump(part, ids, ego, {
                "det_frame": _frames(det, part, det_file),
                "det_logits": logits.reshape(-1, self.n_layers, n_cols),
                "det_boxes": np.zeros((len(logits), self.n_layers, 9)),
                "det_label": _integers(det, "label", det_file) if label else None,
                "gt_frame": np.zeros(0, int), "gt_labels": np.zeros(0, int),
                "gt_boxes": np.zeros((0, 9))})
        h = self.n_hypotheses
        det = _read(det_file, ["frame", "logits", "boxes", *(["cov"] if self.has_cov else []),
                               *(["hyp_boxes", "hyp_scores"] if h else []), *label])
        gt = _read(gt_file, ["frame", "label", "box"])
        fields: dict[str, Any] = {
            "det_frame": _frames(det, part, det_file),
            "det_logits": _floats(det, "logits", self.n_layers * n_cols, det_file).reshape(
                -1, self.n_layers, n_cols),
            "det_boxes": _floats(det, "boxes", self.n_layers * 9, det_file).reshape(
                -1, self.n_layers, 9),
            "det_cov": _floats(det, "cov", d * d, det_file).reshape(-1, d, d)
            if self.has_cov else None,
            "gt_frame": _frames(gt, part, gt_file),
            "gt_labels": _integers(gt, "label", gt_file),
            "gt_boxes": _floats(gt, "box", 9, gt_file)}
        if h:
            fields["det_hyp_boxes"] = _floats(det, "hyp_boxes", h * 9, det_file).reshape(-1, h, 9)
            fields["det_hyp_scores"] = _floats(det, "hyp_scores", h, det_file)
        if label:
            fields["det_label"] = _integers(det, "label", det_file)
        return self._dump(part, ids, ego, fields)

    def _dump(self, part: PartInfo, ids: np.ndarray, ego: np.ndarray | None,
              fields: dict[str, Any]) -> Dump:
        try:
            return Dump(classes=self.classes, score_mode=self.score_mode, frame_ids=ids,
                        ego_translation=ego, cov_dims=self.cov_dims, **fields)
        except FieldError as exc:
            raise FieldError(exc.field, f"part {part.name}: {exc}", exc.row) from None
        except ValueError as exc:
            raise FieldError("dataset", f"part {part.name}: {exc}") from None

    def load(self) -> Dump:
        """Every part in one `Dump` (frame i of the dataset is frame i of the dump)."""
        ids, ego = self.frames()
        parts = [self.read_part(i, (ids[p.first:p.stop],
                                    None if ego is None else ego[p.first:p.stop]))
                 for i, p in enumerate(self.parts)]
        return concat_frames(parts) if parts else self.empty_dump()


def open_parquet(path: str | os.PathLike[str]) -> ParquetDataset:
    """Open the dataset folder `path`: check `detcal.json` and every part's schema (a
    `FieldError` naming the key or column and the file otherwise)."""
    root = Path(path)
    if not root.is_dir():
        raise FieldError("dataset", f"{root} is not a folder: a Parquet dataset is a folder "
                                    f"with {META_FILE} (detcal convert writes one)")
    meta_file = root / META_FILE
    try:
        meta = json.loads(meta_file.read_text())
    except FileNotFoundError:
        raise FieldError("dataset", f"{root} has no {META_FILE}: not a detcal Parquet "
                                    f"dataset") from None
    except (OSError, ValueError) as exc:
        raise FieldError("dataset", f"{META_FILE} cannot be read as JSON: {exc}") from None
    ds = _dataset(root, meta)
    for part in ds.parts:
        _check_schema(root / "detections" / f"{part.name}.parquet", {
            "frame": "int", "logits": ds.n_layers * ds.n_columns, "boxes": ds.n_layers * 9,
            **({"cov": len(ds.cov_dims) ** 2} if ds.has_cov else {}),
            **({"hyp_boxes": ds.n_hypotheses * 9, "hyp_scores": ds.n_hypotheses}
               if ds.n_hypotheses else {}),
            **({"label": "int"} if ds.has_label else {})})
        _check_schema(root / "ground_truth" / f"{part.name}.parquet",
                      {"frame": "int", "label": "int", "box": 9})
    return ds


def load_parquet(path: str | os.PathLike[str]) -> Dump:
    """The whole Parquet dataset at `path` as one in-memory `Dump`."""
    return open_parquet(path).load()


def _dataset(root: Path, meta: Any) -> ParquetDataset:
    def get(key: str, kind: type | tuple[type, ...]) -> Any:
        if not isinstance(meta, dict) or key not in meta:
            raise FieldError(key, f"{META_FILE} has no {key!r}")
        value = meta[key]
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is int):
            raise FieldError(key, f"{META_FILE}: {key!r} has the wrong type "
                                  f"({type(value).__name__})")
        return value

    if get("format", str) != FORMAT or get("version", int) != VERSION:
        raise FieldError("format", f"{META_FILE} is not a {FORMAT} v{VERSION} dataset")
    parts, expect = [], 0
    for i, p in enumerate(get("parts", list)):
        try:
            part = PartInfo(str(p["name"]), int(p["frames"][0]), int(p["frames"][1]),
                            int(p["n_detections"]), int(p["n_ground_truth"]))
        except (KeyError, IndexError, TypeError, ValueError):
            raise FieldError("parts", f"{META_FILE}: parts[{i}] must have name, frames "
                                      f"[first, stop], n_detections, n_ground_truth") from None
        if part.first != expect or part.stop <= part.first or "/" in part.name:
            raise FieldError("parts", f"{META_FILE}: parts[{i}] must hold the frames from "
                                      f"{expect} on, in order")
        expect = part.stop
        parts.append(part)
    n_frames = get("n_frames", int)
    if expect != n_frames:
        raise FieldError("parts", f"{META_FILE}: the parts hold {expect} frames, n_frames "
                                  f"says {n_frames}")
    ds = ParquetDataset(
        path=root, classes=tuple(get("classes", list)), score_mode=get("score_mode", str),
        cov_dims=tuple(get("cov_dims", list)), n_layers=get("n_layers", int),
        has_cov=get("has_cov", bool), has_ego=get("has_ego", bool), n_frames=n_frames,
        n_detections=get("n_detections", int), n_ground_truth=get("n_ground_truth", int),
        source_sha256=get("source_sha256", str), parts=tuple(parts),
        n_hypotheses=get("n_hypotheses", int) if "n_hypotheses" in meta else 0,
        has_label=get("has_label", bool) if "has_label" in meta else False)
    try:
        ds.empty_dump()   # classes, score mode, layers and cov_dims as a Dump checks them
    except FieldError as exc:
        raise FieldError(exc.field, f"{META_FILE}: {exc}") from None
    except ValueError as exc:
        raise FieldError("dataset", f"{META_FILE}: {exc}") from None
    return ds


def _check_schema(file: Path, columns: dict[str, str | int]) -> None:
    """Each column present: `int` an integer column, a number a fixed-size list of that many
    floats."""
    try:
        schema = pq.read_schema(file)
    except FileNotFoundError:
        raise FieldError("dataset", f"part file {file.parent.name}/{file.name} is missing"
                         ) from None
    except (OSError, pa.ArrowException) as exc:
        raise FieldError("dataset", f"{file.parent.name}/{file.name} is not a Parquet file: "
                                    f"{exc}") from None
    where = f"{file.parent.name}/{file.name}"
    for name, want in columns.items():
        if name not in schema.names:
            raise FieldError(name, f"{where} has no column {name!r}")
        kind = schema.field(name).type
        if want == "int":
            if not pa.types.is_integer(kind):
                raise FieldError(name, f"{where}: column {name!r} must be integers, got {kind}")
        elif not (pa.types.is_fixed_size_list(kind) and kind.list_size == want
                  and kind.value_type in _FLOATS):
            raise FieldError(name, f"{where}: column {name!r} must be fixed_size_list<float32 "
                                   f"or float64>[{want}], got {kind}")


def _read(file: Path, columns: list[str]) -> pa.Table:
    try:
        return pq.read_table(file, columns=columns)
    except FileNotFoundError:
        raise FieldError("dataset", f"part file {file.parent.name}/{file.name} is missing"
                         ) from None
    except (OSError, pa.ArrowException) as exc:
        raise FieldError("dataset", f"{file.parent.name}/{file.name} cannot be read: {exc}"
                         ) from None


def _column(table: pa.Table, name: str, file: Path) -> pa.Array:
    col = table.column(name).combine_chunks()
    if col.null_count:
        row = int(np.flatnonzero(np.asarray(col.is_null()))[0])
        raise FieldError(name, f"{file.parent.name}/{file.name}: column {name!r} has a null "
                               f"at row {row}", row)
    return col


def _floats(table: pa.Table, name: str, size: int, file: Path) -> np.ndarray:
    """`[rows, size]` float64 values of a fixed-size list column."""
    col = _column(table, name, file)
    if not pa.types.is_fixed_size_list(col.type) or col.type.list_size != size:
        raise FieldError(name, f"{file.parent.name}/{file.name}: column {name!r} must be a "
                               f"fixed-size list of {size} floats, got {col.type}")
    values = col.flatten()
    if values.null_count:
        raise FieldError(name, f"{file.parent.name}/{file.name}: column {name!r} has a null "
                               f"value")
    return np.asarray(values.to_numpy(zero_copy_only=False), dtype=np.float64).reshape(-1, size)


def _integers(table: pa.Table, name: str, file: Path) -> np.ndarray:
    col = _column(table, name, file)
    if not pa.types.is_integer(col.type):
        raise FieldError(name, f"{file.parent.name}/{file.name}: column {name!r} must be "
                               f"integers, got {col.type}")
    return col.to_numpy().astype(np.int64)


def _frames(table: pa.Table, part: PartInfo, file: Path) -> np.ndarray:
    """The part-local frame index `[rows]` of a `frame` column (global index - first)."""
    frame = _integers(table, "frame", file)
    bad = (frame < part.first) | (frame >= part.stop)
    if bad.any():
        row = int(np.argmax(bad))
        raise FieldError("frame", f"{file.parent.name}/{file.name}: frame {frame[row]} at row "
                                  f"{row} is outside the part's frames [{part.first}, "
                                  f"{part.stop})", row)
    return frame - part.first
