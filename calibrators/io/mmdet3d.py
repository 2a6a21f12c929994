"""MMDetection3D `pred_instances_3d` saved as plain arrays (one NPZ) -> `Dump`.

MMDetection3D's `Det3DDataSample.pred_instances_3d` holds, per sample, `bboxes_3d`
(`LiDARInstance3DBoxes`), `scores_3d` and `labels_3d`; its `sample_idx` names the sample.
Saved for detcal as one NPZ over all samples (`np.savez`, no pickles), one row per detection:

    classes        [C] str          the dataset's metainfo `classes`, in label order (required)
    sample_idx     [N] int | str    sample of each detection
    bboxes_3d      [N, 7 | 9]       `bboxes_3d.tensor`: x y z dx dy dz yaw [vx vy], LiDAR
                                    frame, z = bottom centre (origin (0.5, 0.5, 0)), dx length
                                    along yaw, dy width, dz height, yaw from +x anticlockwise
    scores_3d      [N] float        score of the label (a probability)
    labels_3d      [N] int          0-based index into classes
    cls_scores_3d  [N, C] float     optional: every class's probability (sigmoid heads);
                                    its label's column must equal scores_3d (to 1e-4)
    cls_logits_3d  [N, C] float     optional, instead: every class's raw logit
    frames         [F] int | str    optional: every evaluated sample, with detections or not
    box_type_3d    str              optional: must be "LiDAR" (the default)

The ground truth (`ground_truth=`) is a second NPZ with `sample_idx [G]`, `gt_bboxes_3d
[G, 7 | 9]` and `gt_labels_3d [G]` (MMDetection3D's `-1`, a class outside the dataset's,
is not read), and optionally `classes`, which must then equal the predictions'.
"""

from __future__ import annotations

import math
import os
import zipfile
from collections.abc import Mapping

import numpy as np

from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.io.reader_files import ByteBudget, check_file
from calibrators.io.reader_rows import Rows, check_scores, class_list, rows_to_dump
from calibrators.scores import probability_logit

PRED_KEYS = ("classes", "sample_idx", "bboxes_3d", "scores_3d", "labels_3d", "cls_scores_3d",
             "cls_logits_3d", "frames", "box_type_3d")
GT_KEYS = ("classes", "sample_idx", "gt_bboxes_3d", "gt_labels_3d")
#: How far scores_3d may be from the label's per-class score (float32 rounding).
SCORE_TOLERANCE = 1e-4


def load_mmdet3d(path: str | os.PathLike[str],
                 ground_truth: str | os.PathLike[str] | None = None, *,
                 max_bytes: int | None = None) -> Dump:
    """Read `pred_instances_3d` arrays (and optionally ground-truth arrays) into a `Dump`.

    Per-class scores or logits, when saved, become the dump's sigmoid logits; otherwise the
    label's score does (`reader_rows.score_logits`). Errors are FieldErrors naming the file
    and the key; at most `max_bytes` (default 2 GiB) are inflated.
    """
    budget = ByteBudget(max_bytes)
    pred_path = check_file(path, "predictions")
    pred = _read_npz(pred_path, PRED_KEYS, budget)
    name = pred_path.name
    classes = class_list(_strings(pred, "classes", name, required=True), None)[0]
    box_type = str(pred["box_type_3d"]) if "box_type_3d" in pred else "LiDAR"
    if box_type != "LiDAR":
        raise FieldError("box_type_3d", f"{name}: box_type_3d is {box_type!r}; only LiDAR boxes "
                                        "are read (convert camera or depth boxes first)")
    det = _rows(pred, name, "bboxes_3d", "labels_3d", len(classes))
    frames = _strings(pred, "frames", name) if "frames" in pred else None
    if ground_truth is None:
        return rows_to_dump(classes, det, None, frames=frames, source=name)
    gt_path = check_file(ground_truth, "ground truth")
    truth = _read_npz(gt_path, GT_KEYS, budget)
    if "classes" in truth and tuple(_strings(truth, "classes", gt_path.name)) != classes:
        raise FieldError("classes", f"{gt_path.name}: classes differ from the predictions' "
                                    f"{list(classes)}")
    gt = _rows(truth, gt_path.name, "gt_bboxes_3d", "gt_labels_3d", len(classes))
    return rows_to_dump(classes, det, gt, frames=frames, source=name)


def _read_npz(path: os.PathLike[str], keys: tuple[str, ...], budget: ByteBudget
              ) -> dict[str, np.ndarray]:
    """Arrays of an NPZ (no pickles), its inflated size charged to `budget` before loading."""
    name = path.name  # type: ignore[attr-defined]
    try:
        with zipfile.ZipFile(path) as archive:
            inflated = sum(max(info.file_size, _declared_bytes(archive, info))
                           for info in archive.infolist())
    except Exception:  # noqa: BLE001  a corrupt zip fails in zlib, zipfile or numpy, any way
        raise FieldError("npz", f"{name}: not an NPZ archive (a zip of .npy arrays, as "
                                "numpy.savez writes)") from None
    if inflated > budget.left:
        raise FieldError("npz", f"{name}: inflates to {inflated} bytes, more than the limit of "
                                f"{budget.limit} bytes (max_bytes)")
    budget.left -= inflated
    try:
        with np.load(path, allow_pickle=False) as npz:
            unknown = [k for k in npz.files if k not in keys]
            if unknown:
                raise FieldError(unknown[0], f"{name}: unknown key {unknown[0]!r}; known: "
                                             f"{list(keys)}")
            return {k: npz[k] for k in npz.files}
    except FieldError:
        raise
    except Exception as exc:  # noqa: BLE001  as above: corrupt members fail in many ways
        raise FieldError("npz", f"{name}: an array cannot be read: {str(exc)[:160]}") from None


def _declared_bytes(archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> int:
    """Bytes the `.npy` header of a member declares (0 for a member that is no `.npy`: np.load
    refuses it later); read before any array is allocated."""
    with archive.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) \
                else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(fh, max_header_size=10_000)
        except ValueError:
            return 0
    return math.prod(shape) * dtype.itemsize


def _strings(arrays: Mapping[str, np.ndarray], key: str, name: str,
             required: bool = False) -> np.ndarray:
    if key not in arrays:
        if required:
            raise FieldError(key, f"{name}: missing key {key!r}")
        return np.zeros(0, dtype=str)
    arr = arrays[key]
    if arr.dtype.kind not in "USiu" or arr.ndim != 1:
        raise FieldError(key, f"{name}: {key} must be a 1-d array of strings or integers, got "
                              f"{arr.dtype} of shape {arr.shape}")
    return arr.astype(str)


def _numeric(arrays: Mapping[str, np.ndarray], key: str, name: str, shape: tuple,
             kinds: str = "iuf") -> np.ndarray:
    if key not in arrays:
        raise FieldError(key, f"{name}: missing key {key!r}")
    arr = arrays[key]
    if arr.dtype.kind not in kinds:
        raise FieldError(key, f"{name}: {key} must be numeric, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != a
                                     for s, a in zip(shape, arr.shape, strict=True)):
        want = ", ".join("N" if s is None else str(s) for s in shape)
        raise FieldError(key, f"{name}: {key} must have shape [{want}], got {arr.shape}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise FieldError(key, f"{name}: {key} has NaN or Inf at {bad}", row=bad[0])
    return arr


def _rows(arrays: Mapping[str, np.ndarray], name: str, box_key: str, label_key: str,
          n_classes: int) -> Rows:
    """Rows of detections (`scores_3d` present) or ground truth (labels -1 dropped)."""
    frames = _strings(arrays, "sample_idx", name, required=True)
    n = len(frames)
    raw = _numeric(arrays, box_key, name, (n, None)).astype(np.float64)
    if raw.shape[1] not in (7, 9):
        raise FieldError(box_key, f"{name}: {box_key} must have 7 or 9 columns, got "
                                  f"{raw.shape[1]}")
    labels = _numeric(arrays, label_key, name, (n,), "iu").astype(np.int64)
    detections = box_key == "bboxes_3d"
    low = 0 if detections else -1
    bad = np.flatnonzero((labels < low) | (labels >= n_classes))
    if len(bad):
        raise FieldError(label_key, f"{name}: {label_key}[{bad[0]}] = {labels[bad[0]]} is not "
                                    f"an index into the {n_classes} classes", row=int(bad[0]))
    if np.any(raw[:, 3:6] <= 0):
        row = int(np.argwhere(raw[:, 3:6] <= 0)[0, 0])
        raise FieldError(box_key, f"{name}: {box_key}[{row}] has a size (dx dy dz) <= 0",
                         row=row)
    boxes = np.zeros((n, 9))
    boxes[:, 0], boxes[:, 1], boxes[:, 2] = raw[:, 0], raw[:, 1], raw[:, 2] + raw[:, 5] / 2
    boxes[:, 3], boxes[:, 4], boxes[:, 5], boxes[:, 6] = raw[:, 4], raw[:, 3], raw[:, 5], raw[:, 6]
    boxes[:, 7:] = raw[:, 7:9] if raw.shape[1] == 9 else 0.0
    keep = labels >= 0
    if not detections:
        return Rows(frames[keep], labels[keep], boxes[keep])
    scores = _numeric(arrays, "scores_3d", name, (n,), "f").astype(np.float64)
    logits = _class_logits(arrays, name, n, n_classes)
    check_scores(scores, name, "scores_3d")
    if logits is not None and n:
        own = 1.0 / (1.0 + np.exp(-logits[np.arange(n), labels]))
        off = np.flatnonzero(np.abs(own - scores) > SCORE_TOLERANCE)
        if len(off):
            raise FieldError("scores_3d", f"{name}: scores_3d[{off[0]}] = {scores[off[0]]:.6g} "
                                          f"but the per-class arrays give its label "
                                          f"{own[off[0]]:.6g}: are their columns in the order "
                                          "of classes?", row=int(off[0]))
    return Rows(frames, labels, boxes, scores=scores, logits=logits)


def _class_logits(arrays: Mapping[str, np.ndarray], name: str, n: int, c: int
                  ) -> np.ndarray | None:
    """`[N, C]` sigmoid logits from cls_logits_3d or cls_scores_3d (at most one), else None."""
    given = [k for k in ("cls_scores_3d", "cls_logits_3d") if k in arrays]
    if len(given) == 2:
        raise FieldError("cls_logits_3d", f"{name}: give cls_scores_3d or cls_logits_3d, not "
                                          "both")
    if not given:
        return None
    arr = _numeric(arrays, given[0], name, (n, c), "f").astype(np.float64)
    if given[0] == "cls_logits_3d":
        return arr
    bad = np.argwhere((arr < 0) | (arr > 1))
    if len(bad):
        raise FieldError("cls_scores_3d", f"{name}: cls_scores_3d{bad[0].tolist()} is not a "
                                          "probability in [0, 1]", row=int(bad[0][0]))
    return probability_logit(arr)
