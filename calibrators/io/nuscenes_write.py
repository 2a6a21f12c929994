"""Writing nuScenes results JSON: a `Dump` as a results document (`save_nuscenes`), and
calibrated scores and covariances written into an existing document by reading order
(`calibrate_results_document`, kept for compatibility: calibrated results go through
`calibrators.io.nuscenes_batch.calibrated_document`). Reading lives in
`calibrators.io.nuscenes`; docs/formats.md describes the format.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

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
    calibrate an existing results document and keep all its fields, use
    `calibrate_results_document`.
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


def calibrate_results_document(document: dict, scores: np.ndarray,
                               covariances: np.ndarray | None = None,
                               cov_dims: Sequence[str] = ("x", "y"), *,
                               ellipses: Sequence[Mapping[str, Any] | None] | None = None
                               ) -> dict:
    """A copy of a results `document` with calibrated scores (and covariances) written in, by
    reading order: the caller must have computed them on `load_nuscenes(document)`'s boxes in
    that order. Kept for compatibility; `calibrated_document` (the calibrated-results
    contract of `detcal calibrate` and the service) carries each box's identity instead.

    Boxes are taken in the order `load_nuscenes` reads them (sample tokens in file order, boxes
    in list order), so `scores [N]` and `covariances [N, D, D]` computed on the loaded dump
    line up. Each box gets `detection_score = scores[i]` and keeps its raw score in
    `detection_score_raw` (an existing `detection_score_raw` is kept: it is the detector's);
    with `covariances` it gets `covariance` over `cov_dims`, recorded in `meta.cov_dims`;
    with `ellipses` (`[N]`, e.g. `ellipses_json(calibrated)`) it gets `ellipses = ellipses[i]`
    (an existing `ellipses` key is replaced).
    Every other key of the document, its meta and its boxes (attribute_name, num_pts,
    detection_logits, unknown extensions) is kept as it is. `document` is not modified.
    """
    if not isinstance(document, dict) or not isinstance(document.get("results"), dict):
        raise ValueError("document must be a results document: an object with a 'results' "
                         "object mapping sample tokens to lists of boxes")
    out = copy.deepcopy(document)
    boxes = []
    for token, items in out["results"].items():
        if not isinstance(items, list) or not all(isinstance(b, dict) for b in items):
            raise ValueError(f"document results[{token!r}] must be a list of box objects")
        boxes.extend(items)
    scores = _check_scores(scores, len(boxes), "document (boxes)")
    cov = None
    if covariances is not None:
        dims = _check_cov_dims(cov_dims)
        cov = _check_cov_array(covariances, len(boxes), len(dims))
        meta = out.get("meta") if isinstance(out.get("meta"), dict) else {}
        out["meta"] = {**meta, "cov_dims": list(dims)}
    if ellipses is not None:
        ellipses = list(ellipses)
        if len(ellipses) != len(boxes):
            raise ValueError(f"ellipses has {len(ellipses)} rows but document (boxes) has "
                             f"{len(boxes)}")
    for i, box in enumerate(boxes):
        if "detection_score_raw" not in box and "detection_score" in box:
            box["detection_score_raw"] = box["detection_score"]
        box["detection_score"] = float(scores[i])
        if cov is not None:
            box["covariance"] = cov[i].tolist()
        if ellipses is not None:
            box["ellipses"] = None if ellipses[i] is None else dict(ellipses[i])
    return out


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
