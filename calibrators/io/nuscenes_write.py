"""Writing nuScenes results JSON: a `Dump` as a results document (`save_nuscenes`).
Calibrated results documents, each box placed by its identity, are written by
`calibrators.io.nuscenes_batch.calibrated_document`; reading lives in `calibrators.io.nuscenes`;
docs/formats.md describes the format.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from calibrators.core.checks import as_float_array, check_choice, check_length, check_probabilities
from calibrators.core.vocab import BOX_FIELDS
from calibrators.data import Dump
from calibrators.io.atomic import atomic_write
from calibrators.io.nuscenes_batch import DEVKIT_META, devkit_box

if TYPE_CHECKING:
    pass


def save_nuscenes(dump: Dump, results_path: str | os.PathLike[str],
                  gt_path: str | os.PathLike[str] | None = None,
                  scores: np.ndarray | None = None, covariances: np.ndarray | None = None,
                  cov_dims: Sequence[str] | None = None) -> None:
    """Write `dump` (final layer) as a results JSON and, if `gt_path` is given, a GT JSON.

    `scores` [N] replace detection_score (the raw one goes to detection_score_raw);
    `covariances` [N, D, D] replace dump.det_cov. They are over `cov_dims` when given (e.g. a
    profile's dims), else over dump.cov_dims; `cov_dims` without `covariances` is refused.
    A dump does not hold num_pts or attribute_name: they are written as -1 and "". To
    calibrate an existing results document and keep all its fields, use `detcal calibrate`
    or `calibrators.io.calibrated_document`.
    """
    if not isinstance(dump, Dump):
        raise ValueError(f"dump must be a calibrators.Dump, got {type(dump).__name__}")
    raw = dump.det_scores
    if scores is not None:
        scores = _check_scores(scores, dump.n_detections, "det_logits")
    if cov_dims is not None and covariances is None:
        raise ValueError("cov_dims is given without covariances; it names the dims of "
                         "`covariances` (dump.det_cov is always over dump.cov_dims)")
    dims = dump.cov_dims if cov_dims is None else _check_cov_dims(cov_dims)
    if covariances is not None:
        covariances = _check_cov_array(covariances, dump.n_detections, len(dims))
    cov = covariances if covariances is not None else dump.det_cov
    ego = (np.zeros((dump.n_frames, 3)) if dump.ego_translation is None
           else dump.ego_translation)
    meta = {**DEVKIT_META, "classes": list(dump.classes), "score_mode": dump.score_mode,
            "cov_dims": list(dims)}

    det_out: dict[str, list] = {str(t): [] for t in dump.frame_ids}
    for i in range(dump.n_detections):
        f = int(dump.det_frame[i])
        box = devkit_box(dump.final_boxes[i], dump.frame_ids[f], ego[f],
                         dump.classes[dump.det_labels[i]],
                         float(raw[i] if scores is None else scores[i]))
        box["detection_logits"] = dump.det_logits[i, -1].tolist()
        if scores is not None:
            box["detection_score_raw"] = float(raw[i])
        if cov is not None:
            box["covariance"] = cov[i].tolist()
        det_out[str(dump.frame_ids[f])].append(box)
    _write_json(results_path, {"meta": meta, "results": det_out})
    if gt_path is None:
        return
    gt_out: dict[str, list] = {str(t): [] for t in dump.frame_ids}
    for j in range(len(dump.gt_boxes)):
        f = int(dump.gt_frame[j])
        gt_out[str(dump.frame_ids[f])].append(
            devkit_box(dump.gt_boxes[j], dump.frame_ids[f], ego[f],
                       dump.classes[dump.gt_labels[j]], -1.0))
    _write_json(gt_path, {"meta": meta, "results": gt_out})




# -- reading ----------------------------------------------------------------------------------


def _check_scores(scores: np.ndarray, n: int, other: str) -> np.ndarray:
    """Float64 probabilities `[n]`."""
    out = as_float_array("scores", scores, ndim=1)
    check_length("scores", out, n, other)
    check_probabilities("scores", out)
    return out


def _check_cov_dims(cov_dims: Sequence[str]) -> tuple[str, ...]:
    dims = (cov_dims,) if isinstance(cov_dims, str) else tuple(str(d) for d in cov_dims)
    for d in dims:
        check_choice("cov_dims", d, BOX_FIELDS)
    if not dims or len(set(dims)) != len(dims):
        raise ValueError(f"cov_dims must name distinct box fields, got {list(dims)}")
    return dims


def _check_cov_array(covariances: np.ndarray, n: int, d: int) -> np.ndarray:
    """Float64 `[n, d, d]` covariances (finite; shape named in the message)."""
    cov = as_float_array("covariances", covariances, ndim=3)
    if cov.shape != (n, d, d):
        raise ValueError(f"covariances must have shape [{n}, {d}, {d}] (cov_dims has {d} "
                         f"entries), got {cov.shape}")
    return cov


def _write_json(path: str | os.PathLike[str], content: dict) -> None:
    with atomic_write(path, "w") as fh:
        json.dump(content, fh, allow_nan=False)
