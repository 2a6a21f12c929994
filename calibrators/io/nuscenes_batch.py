"""A nuScenes results document as `Detections`, and calibrated detections as a results
document: the one output contract of `detcal calibrate` and POST /v1/calibrate/nuscenes
(docs/formats.md, "Calibrated results").

Reading: each box is a detection of its sample token, its row the box's position in that
token's list; its class evidence is `detection_logits` (with `detection_name` the class it
asserts) or `detection_score` with `detection_name`; its centre is taken relative to the ego
(`ego_translation`, or `translation` minus the frame's ego position when one is given);
`covariance` is its Σ. Every key of the box is kept and written back.

Writing (`calibrated_document`): boxes grouped by sample token (every frame of the input,
those without boxes included), in input row order within a token. Each box keeps its keys and
gets `detection_name` (the served label), `detection_score` (calibrated),
`detection_score_raw` (the raw score the profile calibrated), `covariance` (Σ' over
`calibration.cov_dims`), `ellipse` (at the ellipse confidence), `ellipses` (per level) and its
identity: `detection_row` and, when the input had one, `detection_id`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from calibrators.core.errors import FieldError
from calibrators.profile import Detections, calibrated_records, detections_from_records

if TYPE_CHECKING:
    from calibrators.profile import CalibratedDetections

__all__ = ["DEVKIT_META", "calibrated_document", "detections_from_nuscenes", "devkit_box"]

#: The devkit's `meta` flags of a document written from a dump (detcal knows no sensors).
DEVKIT_META = {"use_camera": False, "use_lidar": False, "use_radar": False, "use_map": False,
                "use_external": False}

def detections_from_nuscenes(document: Mapping[str, Any], classes: Sequence[str],
                             score_mode: str, ego: Mapping[str, Sequence[float]] | None = None
                             ) -> list[Detections]:
    """The boxes of a results `document` (`{"results": {token: [box, ...]}}`, boxes already
    validated: `load_nuscenes` or the service's schema) as one `Detections` per evidence form;
    `ego` maps a token to its ego position (else each box's `ego_translation`). A FieldError's
    `row` is the box's position in reading order (tokens in order, boxes in list order)."""
    records, rows = [], []
    tokens = list(document["results"])
    for token in tokens:
        for i, box in enumerate(document["results"][token]):
            records.append(_record(token, box, None if ego is None else ego.get(token),
                                   len(records)))
            rows.append(i)
    batches = detections_from_records(records, classes, score_mode, rows=rows)
    if not batches:
        return [Detections(frame_ids=np.zeros(0, dtype=object), rows=np.zeros(0, np.int64),
                           boxes=np.zeros((0, 9)), ego_xy=np.zeros((0, 2)),
                           scores=np.zeros(0), labels=np.zeros(0, np.int64),
                           frame_tokens=tokens)]
    return [_with_tokens(b, tokens) for b in batches]


def _with_tokens(batch: Detections, tokens: list[str]) -> Detections:
    from dataclasses import replace

    return replace(batch, frame_tokens=tokens)


def _record(token: str, box: Mapping[str, Any], ego: Sequence[float] | None, row: int
            ) -> dict[str, Any]:
    """The wire record of one box (records module docstring)."""
    try:
        yaw = quaternion_yaw(*box["rotation"])
    except ValueError as exc:
        raise FieldError("rotation", str(exc), row=row) from None
    rel = box.get("ego_translation")
    if ego is not None:
        centre, ego_xy = list(box["translation"]), list(ego)[:2]
    else:   # zeros: unset
        centre = rel if rel is not None and any(rel) else list(box["translation"])
        ego_xy = None
    logits = box.get("detection_logits")
    record: dict[str, Any] = {
        "frame_id": token, "source": dict(box), "label": box["detection_name"],
        "box": [*centre, *box["size"], yaw, *box.get("velocity", (0.0, 0.0))],
        "ego_translation": ego_xy, "covariance": box.get("covariance"),
        "id": box.get("detection_id")}
    if logits is not None:
        record["logits"] = logits
    else:
        record["score"] = box["detection_score"]
    return record


def calibrated_document(calibrated: CalibratedDetections | Sequence[CalibratedDetections],
                        calibration: Mapping[str, Any] | None = None,
                        meta: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The results document of `calibrated` (one result or several, e.g. one per evidence
    form of a document) in the output contract of the module docstring: `meta` is kept (its
    `cov_dims`, if any, set to the dims of the covariances written; None: the devkit's `use_*`
    flags, `classes` and `cov_dims`), `calibration` is written as the document's top-level
    `calibration` key with the covariances' `cov_dims`."""
    parts = [calibrated] if not isinstance(calibrated, Sequence) else list(calibrated)
    tokens: dict[Any, list[tuple[int, dict[str, Any]]]] = {}
    for part in parts:
        det = part.detections
        if det is None:
            raise ValueError("calibrated_document needs detections calibrated through "
                             "Detections.calibrate (their identity)")
        for token in det.frame_tokens or ():
            tokens.setdefault(str(token), [])
        sources = det.sources
        logits = det.layer_logits[:, -1] if det.layer_logits is not None else det.logits
        for i, rec in enumerate(calibrated_records(part)):
            if sources is None or sources[i] is None:
                ego = np.array([*det.ego_xy[i], 0.0])
                box = devkit_box(np.asarray(rec["box"]), str(rec["frame_id"]), ego,
                                 rec["label"], 0.0)
                if logits is not None:
                    box["detection_logits"] = logits[i].tolist()
            else:
                box = dict(sources[i])
            box.update(sample_token=str(rec["frame_id"]), detection_name=rec["label"],
                       detection_score=rec["score"], detection_score_raw=rec["score_raw"],
                       covariance=rec["covariance"], ellipse=rec["ellipse"],
                       ellipses=rec["ellipses"], detection_row=rec["row"])
            if rec["id"] is not None:
                box["detection_id"] = rec["id"]
            tokens.setdefault(str(rec["frame_id"]), []).append((rec["row"], box))
    first = parts[0] if parts else None
    out_meta = dict(meta) if meta is not None else dict(DEVKIT_META)
    if first is not None and (meta is None or "cov_dims" in meta):   # the dims written
        out_meta.update({} if meta is not None else {"classes": list(first.classes)},
                        cov_dims=list(first.cov_dims))
    doc: dict[str, Any] = {
        "meta": out_meta,
        "results": {t: [b for _, b in sorted(boxes, key=lambda rb: rb[0])]
                    for t, boxes in tokens.items()}}
    if calibration is not None:
        doc["calibration"] = {**calibration,
                              "cov_dims": None if first is None else list(first.cov_dims)}
    return doc


def devkit_box(row: np.ndarray, token: str, ego: np.ndarray, name: str, score: float) -> dict:
    """A devkit `DetectionBox` of box `row [9]` in frame `token` whose ego position is `ego
    [3]` (num_pts and attribute unknown: -1 and "")."""
    yaw = float(row[6])
    return {
        "sample_token": str(token),
        "translation": [float(v) for v in row[:3]],
        "size": [float(v) for v in row[3:6]],
        "rotation": [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))],
        "velocity": [float(row[7]), float(row[8])],
        "ego_translation": [float(v) for v in row[:3] - ego],
        "num_pts": -1,
        "detection_name": name,
        "detection_score": score,
        "attribute_name": "",
    }


def quaternion_yaw(w: float, x: float, y: float, z: float) -> float:
    """Yaw about +z of the rotation quaternion (w, x, y, z), as the nuScenes devkit's
    `quaternion_yaw`; a non-unit quaternion gives the yaw of its normalised rotation.

    Raises ValueError for the zero quaternion (no rotation is defined).
    """
    if w * w + x * x + y * y + z * z == 0:
        raise ValueError("rotation is the zero quaternion")
    return float(math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z))
