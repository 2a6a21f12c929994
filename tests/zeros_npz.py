"""A validation dump NPZ of zeros with any number of detections, written member by member
in chunks (never an array in memory): the compression bomb of issue 25 (6.5M detections in
under 1 MiB of upload)."""

from __future__ import annotations

import io
import zipfile

import numpy as np

CHUNK = 8 * 2**20


def _member(archive: zipfile.ZipFile, key: str, shape: tuple[int, ...], dtype: str,
            value: np.ndarray | None = None) -> None:
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
              "shape": shape}
    with archive.open(f"{key}.npy", "w", force_zip64=True) as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        if value is not None:
            fh.write(value.tobytes())
            return
        left = int(np.prod(shape)) * np.dtype(dtype).itemsize
        zeros = bytes(min(CHUNK, left))
        while left:
            fh.write(zeros[:min(CHUNK, left)])
            left -= min(CHUNK, left)


def zeros_npz(n_detections: int, n_gt: int | None = None, n_frames: int = 1,
              classes: tuple[str, ...] = ("car", "truck", "bus", "trailer",
                                          "construction_vehicle", "pedestrian", "motorcycle",
                                          "bicycle", "traffic_cone", "barrier")) -> bytes:
    """Validation dump v1 bytes: `n_detections` detections and `n_gt` ground-truth boxes
    (default as many), every number zero, in `n_frames` frames."""
    n_gt = n_detections if n_gt is None else n_gt
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        _member(archive, "classes", (len(classes),), "<U20",
                np.array(classes, dtype="<U20"))
        _member(archive, "score_mode", (), "<U7", np.array("sigmoid", dtype="<U7"))
        _member(archive, "frame_ids", (n_frames,), "<U8",
                np.array([f"f{i}" for i in range(n_frames)], dtype="<U8"))
        _member(archive, "det_frame", (n_detections,), "<i8")
        _member(archive, "det_logits", (n_detections, 1, len(classes)), "<f4")
        _member(archive, "det_boxes", (n_detections, 1, 9), "<f4")
        _member(archive, "det_cov", (n_detections, 2, 2), "<f4")
        _member(archive, "gt_frame", (n_gt,), "<i8")
        _member(archive, "gt_labels", (n_gt,), "<i8")
        _member(archive, "gt_boxes", (n_gt, 9), "<f4")
    return buf.getvalue()
