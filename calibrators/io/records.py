"""Detections as JSON records, and calibrated detections back (the JSON form of
POST /v1/calibrate, /v1/detect and a results document's boxes; docs/api.md).

A record is a mapping with the wire names of `calibrators.detections.WIRE_NAMES`: `frame_id`,
optional `id`, exactly one of `logits [C']`, `layer_logits [L][C']`, `scores [C']` (per-class
probabilities) or `score` (with `label`); `label` (class name or index), `box [9|7]` or
`layer_boxes [L][9]`, optional `covariance [D][D]`, `ego_translation [3|2]`,
`hypothesis_boxes [H][9]` with `hypothesis_scores [H]`, and `source` (a dict echoed back by
`to_nuscenes`). Records of several forms become one `Detections` per form
(`detections_from_records`); each keeps its identity. The rules every front end shares live
here: `label_index` (a class name or index against the profile's classes) and `box9` (a box
without velocity gets zeros).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from calibrators.detections import Detections
from calibrators.exceptions import FieldError
from calibrators.scores import probabilities_logits
from calibrators.vocab import BOX_FIELDS

__all__ = ["box9", "calibrated_records", "detections_from_records", "label_index"]

_OPTIONAL = (("covariance", "covariances"), ("layer_boxes", "layer_boxes"),
             ("hypothesis_boxes", "hyp_boxes"), ("hypothesis_scores", "hyp_scores"))


def label_index(label: str | int, classes: Sequence[str], row: int | None = None) -> int:
    """The class index of a class name or index; FieldError("labels", row) if the profile has
    no such class."""
    if isinstance(label, int | np.integer) and not isinstance(label, bool):
        if not 0 <= label < len(classes):
            raise FieldError("labels", f"label index {label} is out of range for the profile's "
                                       f"{len(classes)} classes", row=row)
        return int(label)
    try:
        return list(classes).index(label)
    except ValueError:
        raise FieldError("labels", f"unknown class {label!r}; the profile's classes are "
                                   f"{list(classes)}", row=row) from None


def box9(box: Sequence[float]) -> list[float]:
    """A box of every field (`x y z w l h yaw vx vy`): one without velocity gets zeros."""
    return list(box) if len(box) == len(BOX_FIELDS) else [*box, 0.0, 0.0]


def _form(record: Mapping[str, Any]) -> tuple:
    """The form and shape of a record's arrays (records of one form stack)."""
    def size(key: str) -> int:
        value = record.get(key)
        return 0 if value is None else len(value)

    evidence = next(k for k in ("score", "layer_logits", "logits", "scores")
                    if record.get(k) is not None)
    width = 0 if evidence == "score" else len(
        record[evidence][-1] if evidence == "layer_logits" else record[evidence])
    return (evidence, width, size("layer_logits"), size("covariance"), size("layer_boxes"),
            size("hypothesis_boxes"), size("hypothesis_scores"),
            record.get("label") is not None)


def detections_from_records(records: Sequence[Mapping[str, Any]], classes: Sequence[str],
                            score_mode: str, rows: Sequence[int] | None = None
                            ) -> list[Detections]:
    """One `Detections` per form of `records` (module docstring), each detection with its
    frame id and row (`rows[i]`, default its position in `records`). A FieldError names the
    wire field and, as `row`, the record's position in `records`."""
    groups: dict[tuple, list[int]] = {}
    labels = [None if r.get("label") is None else label_index(r["label"], classes, i)
              for i, r in enumerate(records)]
    for i, record in enumerate(records):
        groups.setdefault(_form(record), []).append(i)
    row_of = np.arange(len(records)) if rows is None else np.asarray(rows, dtype=np.int64)
    return [_batch(records, index, key, labels, score_mode, row_of[index])
            for key, index in groups.items()]


def _batch(records: Sequence[Mapping[str, Any]], index: list[int], key: tuple,
           labels: list[int | None], score_mode: str, rows: np.ndarray) -> Detections:
    """The `Detections` of the records at `index`, all of form `key`."""
    evidence, labelled = key[0], key[-1]
    picked = [records[i] for i in index]
    arrays: dict[str, Any] = {}
    if evidence == "score":
        arrays["scores"] = np.array([r["score"] for r in picked], dtype=np.float64)
    elif evidence == "scores":
        arrays["logits"] = probabilities_logits(
            np.array([r["scores"] for r in picked], dtype=np.float64), score_mode)
    else:
        arrays[evidence] = np.array([r[evidence] for r in picked], dtype=np.float64)
    if labelled:
        arrays["labels"] = np.array([labels[i] for i in index], dtype=np.int64)
    for wire, name in _OPTIONAL:
        if picked[0].get(wire) is not None:
            arrays[name] = np.array([r[wire] for r in picked], dtype=np.float64)
    boxes = [box9(r["box"]) if r.get("box") is not None else r["layer_boxes"][-1]
             for r in picked]
    ego = [(r.get("ego_translation") or (0.0, 0.0))[:2] for r in picked]
    ids = [r.get("id") for r in picked]
    sources = [r.get("source") for r in picked]
    return Detections(
        frame_ids=np.array([r.get("frame_id") for r in picked], dtype=object), rows=rows,
        boxes=np.array(boxes, dtype=np.float64).reshape(-1, 9),
        ego_xy=np.array(ego, dtype=np.float64).reshape(-1, 2),
        detection_ids=None if all(i is None for i in ids) else ids,
        sources=None if all(s is None for s in sources) else sources, **arrays)


def calibrated_records(calibrated: Any) -> list[dict[str, Any]]:
    """One dict per detection of `calibrated` (a `CalibratedDetections`), in its order:
    `frame_id`, `row`, `id` (the identity, when it went through `Detections`), `label`,
    `label_index`, `score`, `score_raw`, `class_scores` (or None), `box`, `covariance`,
    `ellipse` (at `ellipse_confidence`, null axes where unbounded; None without x, y),
    `ellipses` (per requested level, `ellipses_json`) and `distance`."""
    from calibrators.io.nuscenes_write import ellipses_json, unbounded_none

    res, det = calibrated, calibrated.detections
    n = len(res)
    labels = res.labels.tolist()
    names = [res.classes[k] for k in labels] if res.classes else [None] * n
    cls_scores = res.class_scores.tolist() if res.class_scores is not None else [None] * n
    covs = res.covariances.tolist()
    el, ellipses = res.ellipses, ellipses_json(res)
    ellipse: list[dict[str, Any] | None] = [None] * n
    if el is not None:
        major, minor = (unbounded_none(a, np.isinf(a)) for a in (el.semi_major, el.semi_minor))
        ellipse = [{"semi_major": a, "semi_minor": b, "angle": c,
                    "confidence": res.ellipse_confidence}
                   for a, b, c in zip(major, minor, el.angle.tolist(), strict=True)]
    frames = [None] * n if det is None else _plain(det.frame_ids)
    rows = list(range(n)) if det is None else det.rows.tolist()
    ids = [None] * n if det is None or det.detection_ids is None else list(det.detection_ids)
    boxes = [None] * n if det is None else det.boxes.tolist()
    return [{"frame_id": frames[i], "row": rows[i], "id": ids[i], "label": names[i],
             "label_index": labels[i], "score": s, "score_raw": r,
             "class_scores": cls_scores[i], "box": boxes[i], "covariance": covs[i],
             "ellipse": ellipse[i], "ellipses": ellipses[i], "distance": d}
            for i, (s, r, d) in enumerate(zip(res.scores.tolist(), res.scores_raw.tolist(),
                                              res.distances.tolist(), strict=True))]


def _plain(values: Any) -> list[Any]:
    """A list of Python values (numpy scalars become ints and strings)."""
    return np.asarray(values, dtype=object).tolist() if not isinstance(values, list) \
        else values
