"""Write a validation dump as a Parquet dataset (docs/formats.md, "Parquet dataset").

`save_parquet(out_dir, dump)` writes a whole in-memory `Dump`; `ParquetWriter` appends parts
one at a time (a generator of dumps larger than memory writes each chunk of frames as it
goes). A part holds whole frames: the frames `[first, last)` of the dataset, their
detections in `detections/part-NNNNN.parquet` and their ground truth in
`ground_truth/part-NNNNN.parquet`, so a frame never spans two files. `detcal.json` is
written last: a folder without it is not a dataset.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from calibrators.data import Dump
from calibrators.io.atomic import atomic_write
from calibrators.io.parquet import FORMAT, META_FILE, VERSION

#: Default detections per part: about 0.5 GB of float64 columns at L = 3, C' = 11.
ROWS_PER_PART = 1_000_000


def _fixed_list(values: np.ndarray, dtype: Any) -> pa.FixedSizeListArray:
    """`values [N, ...]` as a fixed-size list column of `prod(...)` values per row."""
    n = values.shape[0]
    width = int(np.prod(values.shape[1:], dtype=np.int64))   # -1 fails on 0 rows
    flat = np.ascontiguousarray(values, dtype=dtype).reshape(n, width)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[1])


class ParquetWriter:
    """Write a Parquet dataset part by part: `add(dump)` appends the dump's frames as new
    frames of the dataset (one part, or several of about `rows_per_part` detections, each of
    whole frames), `close()` writes `frames.parquet` and `detcal.json`.

    Every added dump must share classes, score mode, decoder layers, cov_dims and whether it
    has covariances and ego translations. `float_dtype`: the stored float type of logits,
    boxes and covariances (`float64`, lossless; `float32` halves the files, and the dataset
    then holds the float32-rounded values). `source_sha256`: recorded as the dataset's
    provenance hash (the source file's; default: a hash of the metadata and part sizes).
    """

    def __init__(self, out_dir: str | os.PathLike[str], *, rows_per_part: int = ROWS_PER_PART,
                 float_dtype: str = "float64", source_sha256: str | None = None) -> None:
        if float_dtype not in ("float32", "float64"):
            raise ValueError(f"float_dtype must be 'float32' or 'float64', got {float_dtype!r}")
        if isinstance(rows_per_part, bool) or not isinstance(rows_per_part, int) \
                or rows_per_part < 1:
            raise ValueError(f"rows_per_part must be an integer >= 1, got {rows_per_part!r}")
        self.out = Path(out_dir)
        if (self.out / META_FILE).exists():
            raise ValueError(f"{self.out} already holds a Parquet dataset ({META_FILE}); "
                             f"choose an empty folder")
        (self.out / "detections").mkdir(parents=True, exist_ok=True)
        (self.out / "ground_truth").mkdir(parents=True, exist_ok=True)
        self.rows_per_part, self.dtype = rows_per_part, np.dtype(float_dtype)
        self.source_sha256 = source_sha256
        self.head: dict[str, Any] | None = None
        self.parts: list[dict[str, Any]] = []
        self.frame_ids: list[np.ndarray] = []
        self.ego: list[np.ndarray] = []
        self.n_frames = 0

    def add(self, dump: Dump) -> None:
        """Append the frames of `dump` (with their detections and ground truth)."""
        head = {"classes": list(dump.classes), "score_mode": dump.score_mode,
                "cov_dims": list(dump.cov_dims), "n_layers": dump.n_layers,
                "has_cov": dump.det_cov is not None,
                "has_ego": dump.ego_translation is not None,
                "n_hypotheses": dump.n_hypotheses, "has_label": dump.det_label is not None}
        if self.head is None:
            self.head = head
        elif head != self.head:
            diff = [k for k in head if head[k] != self.head[k]]
            raise ValueError(f"this dump differs from the dataset's first one in {diff}")
        order = np.argsort(dump.det_frame, kind="stable")
        g_order = np.argsort(dump.gt_frame, kind="stable")
        det_frame, gt_frame = dump.det_frame[order], dump.gt_frame[g_order]
        per_frame = np.bincount(det_frame, minlength=dump.n_frames)
        start = 0
        while start < dump.n_frames:   # whole frames, about rows_per_part detections each
            total = np.cumsum(per_frame[start:])
            stop = start + max(1, int(np.searchsorted(total, self.rows_per_part, side="right")))
            d = slice(*np.searchsorted(det_frame, [start, stop]))
            g = slice(*np.searchsorted(gt_frame, [start, stop]))
            self._write_part(dump, order[d], det_frame[d], g_order[g], gt_frame[g], start, stop)
            start = stop
        self.frame_ids.append(np.asarray(dump.frame_ids, dtype=str))
        if dump.ego_translation is not None:
            self.ego.append(dump.ego_translation)
        self.n_frames += dump.n_frames

    def _write_part(self, dump: Dump, rows: np.ndarray, det_frame: np.ndarray,
                    g_rows: np.ndarray, gt_frame: np.ndarray, start: int, stop: int) -> None:
        name = f"part-{len(self.parts):05d}"
        offset = self.n_frames
        det = {"frame": pa.array(det_frame + offset, type=pa.int64()),
               "logits": _fixed_list(dump.det_logits[rows], self.dtype),
               "boxes": _fixed_list(dump.det_boxes[rows], self.dtype)}
        if dump.det_cov is not None:
            det["cov"] = _fixed_list(dump.det_cov[rows], self.dtype)
        if dump.det_hyp_boxes is not None and dump.det_hyp_scores is not None:
            det["hyp_boxes"] = _fixed_list(dump.det_hyp_boxes[rows], self.dtype)
            det["hyp_scores"] = _fixed_list(dump.det_hyp_scores[rows], self.dtype)
        if dump.det_label is not None:
            det["label"] = pa.array(dump.det_label[rows], type=pa.int64())
        pq.write_table(pa.table(det), self.out / "detections" / f"{name}.parquet")
        gt = {"frame": pa.array(gt_frame + offset, type=pa.int64()),
              "label": pa.array(dump.gt_labels[g_rows], type=pa.int64()),
              "box": _fixed_list(dump.gt_boxes[g_rows], self.dtype)}
        pq.write_table(pa.table(gt), self.out / "ground_truth" / f"{name}.parquet")
        self.parts.append({"name": name, "frames": [start + offset, stop + offset],
                           "n_detections": len(rows), "n_ground_truth": len(g_rows)})

    def close(self) -> Path:
        """Write `frames.parquet` and `detcal.json`; returns the dataset folder."""
        if self.head is None:
            raise ValueError("no dump was added: a dataset needs at least one frame")
        frames = {"frame": pa.array(np.arange(self.n_frames), type=pa.int64()),
                  "frame_id": pa.array(np.concatenate(self.frame_ids).tolist(), type=pa.string())}
        if self.head["has_ego"]:
            frames["ego_translation"] = _fixed_list(np.concatenate(self.ego), np.float64)
        pq.write_table(pa.table(frames), self.out / "frames.parquet")
        meta = {"format": FORMAT, "version": VERSION, **self.head,
                "float_dtype": self.dtype.name, "n_frames": self.n_frames,
                "n_detections": sum(p["n_detections"] for p in self.parts),
                "n_ground_truth": sum(p["n_ground_truth"] for p in self.parts),
                "parts": self.parts}
        meta["source_sha256"] = self.source_sha256 or _meta_digest(meta)
        with atomic_write(self.out / META_FILE) as fh:
            json.dump(meta, fh, indent=1)
        return self.out


def save_parquet(out_dir: str | os.PathLike[str], dump: Dump, *,
                 rows_per_part: int = ROWS_PER_PART, float_dtype: str = "float64",
                 source_sha256: str | None = None) -> Path:
    """Write `dump` as a Parquet dataset in `out_dir` (see `ParquetWriter`); returns it."""
    if not isinstance(dump, Dump):
        raise ValueError(f"dump must be a calibrators.Dump, got {type(dump).__name__}")
    writer = ParquetWriter(out_dir, rows_per_part=rows_per_part, float_dtype=float_dtype,
                           source_sha256=source_sha256)
    writer.add(dump)
    return writer.close()


def _meta_digest(meta: dict[str, Any]) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(meta, sort_keys=True).encode()).hexdigest()
