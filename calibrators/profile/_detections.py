"""`Detections`: the one batch type at the calibrate boundary, each detection with its identity.

A front end turns what it received into `Detections` with an adapter (`Detections.from_dump`,
`detections_from_records` below, `calibrators.io.arrow_batch.batch_request`,
`calibrators.io.nuscenes_batch.detections_from_nuscenes`), calibrates it (`Detections.calibrate` ->
`CalibratedDetections`, which keeps the batch it came from) and writes the result with
`CalibratedDetections.to_records()`, `.to_arrow()` or `.to_nuscenes()`. Every output
detection carries its identity: its frame token plus its input row (or the user's
`detection_id`), so nothing is ever paired across representations by position.

Shapes (N detections, C' logit columns, L layers, D covariance dims, H hypotheses):

    frame_ids      [N]            frame (sample) token of each detection (str or int)
    rows           [N] int64      the detection's row in its input: the dump's detection
                                  index, the Arrow row, the record's position in the request,
                                  the box's position in its frame's list of a results document
    boxes          [N, 9]         final box x y z w l h yaw vx vy
    ego_xy         [N, 2]         ego position of the detection's frame (zeros: ego frame)
    logits         [N, C'] | None        final-layer logits
    layer_logits   [N, L, C'] | None     every decoder layer's logits (last = final)
    scores         [N] | None            the score of `labels` only
    labels         [N] int64 | None      the class each detection asserts (None: arg-max)
    covariances    [N, D, D] | None      given Σ over the profile's cov_dims
    layer_boxes    [N, L, 9] | None      every decoder layer's box (covariance source `layers`)
    hyp_boxes      [N, H, 9] | None      group heads' boxes, with hyp_scores [N, H]
    detection_ids  [N] | None            the user's id of each detection, echoed back
    sources        [N] dict | None       each input record's own keys, echoed back (a
                                         results document's boxes keep every key)
    frame_tokens   [F] | None            every frame of the input in order, frames without
                                         detections included (a results document lists them)

Exactly one of `logits`, `layer_logits`, `scores` is given (`scores` with `labels`).

JSON records: a record is a mapping with the wire names of `WIRE_NAMES`: `frame_id`,
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
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from calibrators.core.checks import check_finite
from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable
from calibrators.core.vocab import BOX_FIELDS
from calibrators.covariance import source_arrays
from calibrators.profile._calibrate import CalibratedDetections, calibrate_detections
from calibrators.scores import probabilities_logits

if TYPE_CHECKING:
    from calibrators.data import Dump
    from calibrators.profile._profile import CalibrationProfile

__all__ = ["WIRE_NAMES", "Detections", "box9", "calibrated_records", "detections_from_records",
           "ellipses_json", "label_index", "unbounded_none"]

#: Argument of `CalibrationProfile.calibrate` -> the wire name of the same value (a JSON
#: detection's key, an Arrow request column). The one map every front end uses.
WIRE_NAMES = {"logits": "logits", "layer_logits": "layer_logits", "scores": "score",
              "labels": "label", "boxes": "box", "distances": "box",
              "covariances": "covariance", "layer_boxes": "layer_boxes",
              "ego_xy": "ego_translation", "hyp_boxes": "hypothesis_boxes",
              "hyp_scores": "hypothesis_scores"}

#: The array fields that are passed to `CalibrationProfile.calibrate` as they are.
_CALIBRATE_ARGS = ("logits", "layer_logits", "scores", "labels", "boxes", "ego_xy",
                   "covariances", "layer_boxes", "hyp_boxes", "hyp_scores")


@dataclass(frozen=True, eq=False)
class Detections:
    """N detections to calibrate, each with its identity (module docstring: every shape)."""

    frame_ids: np.ndarray
    rows: np.ndarray
    boxes: np.ndarray
    ego_xy: np.ndarray
    logits: np.ndarray | None = None
    layer_logits: np.ndarray | None = None
    scores: np.ndarray | None = None
    labels: np.ndarray | None = None
    covariances: np.ndarray | None = None
    layer_boxes: np.ndarray | None = None
    hyp_boxes: np.ndarray | None = None
    hyp_scores: np.ndarray | None = None
    detection_ids: Sequence[Any] | None = None
    sources: Sequence[dict[str, Any]] | None = None
    frame_tokens: Sequence[Any] | None = None

    def __post_init__(self) -> None:
        n = len(self.rows)
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name != "frame_tokens" and value is not None and len(value) != n:
                raise FieldError(WIRE_NAMES.get(f.name, f.name),
                                 f"{f.name} has {len(value)} rows but rows has {n}")

    def __len__(self) -> int:
        return len(self.rows)

    @classmethod
    def from_dump(cls, dump: Dump, cov_source: str) -> Detections:
        """The final-layer detections of `dump` (rows = detection index, frame ids = the
        dump's frame tokens) with every decoder layer's logits, the labels the dump asserts
        and the raw Σ of `cov_source` (`source_arrays`)."""
        return cls(frame_ids=np.asarray(dump.frame_ids)[dump.det_frame],
                   rows=np.arange(dump.n_detections, dtype=np.int64),
                   boxes=dump.final_boxes, ego_xy=dump.ego_xy(dump.det_frame),
                   layer_logits=dump.det_logits, labels=dump.det_label,
                   frame_tokens=list(np.asarray(dump.frame_ids).tolist()),
                   **source_arrays(dump, cov_source))

    @staticmethod
    def from_records(records: Sequence[Mapping[str, Any]], classes: Sequence[str],
                     score_mode: str) -> list[Detections]:
        """JSON records as one batch per evidence form (`detections_from_records`)."""
        return detections_from_records(records, classes, score_mode)

    @staticmethod
    def from_nuscenes(document: Mapping[str, Any], classes: Sequence[str], score_mode: str
                      ) -> list[Detections]:
        """A results document's boxes as one batch per evidence form
        (`calibrators.io.nuscenes_batch.detections_from_nuscenes`)."""
        from calibrators.io.nuscenes_batch import detections_from_nuscenes

        return detections_from_nuscenes(document, classes, score_mode)

    @staticmethod
    def from_arrow(batch: Any, classes: Sequence[str]) -> Detections:
        """An Arrow request batch (`calibrators.io.arrow_batch.batch_request`; pyarrow)."""
        from calibrators.io.arrow_batch import batch_request

        return batch_request(batch, classes)

    def calibrate_arguments(self) -> dict[str, np.ndarray]:
        """The keyword arguments of `CalibrationProfile.calibrate` (the arrays given)."""
        return {k: getattr(self, k) for k in _CALIBRATE_ARGS if getattr(self, k) is not None}

    def calibrate(self, profile: CalibrationProfile, *,
                  ellipse_confidence: float = ELLIPSE_CONFIDENCE,
                  levels: Sequence[float] | None = None) -> CalibratedDetections:
        """These detections calibrated with `profile` (`_calibrate`), in this order;
        the result keeps this batch (`.detections`) for its identity and boxes."""
        out = calibrate_detections(profile, **self.calibrate_arguments(),
                                   ellipse_confidence=ellipse_confidence, levels=levels)
        return replace(out, detections=self)




# -- JSON records ----------------------------------------------------------------------------
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


def box9(box: Sequence[float] | np.ndarray) -> np.ndarray:
    """A box `[9]` (or boxes `[N, 9]`) of every field, `x y z w l h yaw vx vy`: a box of 7
    values (no velocity) gets zero velocity."""
    arr = np.asarray(box, dtype=np.float64)
    if arr.shape[-1] == len(BOX_FIELDS):
        return arr
    return np.concatenate([arr, np.zeros((*arr.shape[:-1], 2))], axis=-1)


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
             for r in picked]   # mixed 7 / 9 values stack after padding
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


def ellipses_json(calibrated: CalibratedDetections) -> list[dict[str, dict[str, Any]] | None]:
    """Per detection of `calibrated` (`CalibrationProfile.calibrate(..., levels=...)`), its
    served regions as JSON: `{str(float(q)): {"semi_major": m, "semi_minor": m, "angle": rad,
    "method": "conformal" | "gaussian", "group": "car 15-30 m" | None, "guarantee": "cell" |
    "scaled" | "pooled" | "marginal" | "none", "calibration_n": int | None}}` for each level `q`
    (the group and count are None for gaussian regions), or None when the profile's cov_dims
    lack x or y.

    The angle is the major axis's from +x (`calibrators.regions`). The semi-axes of an
    unbounded region (a level beyond what its conformal group certifies: infinite radius) are
    None. Raises a FieldError naming the level and the detection (`row`) of any other
    semi-axis that is not finite.
    """
    n = len(calibrated)
    method = calibrated.region_method
    if method is None:
        return [None] * n
    groups = calibrated.region_groups or [None] * n
    columns = []
    for level, region in calibrated.regions.items():
        key = str(float(level))
        radii = calibrated.region_radii.get(level)
        unbounded = (np.zeros(n, dtype=bool) if radii is None
                     else np.isinf(np.asarray(radii, dtype=np.float64).reshape(n)))
        arrays = [np.asarray(a, dtype=np.float64).reshape(n) for a in region]
        for name, arr in zip(("semi_major", "semi_minor", "angle"), arrays, strict=True):
            check_finite(f"ellipses[{key!r}].{name}", np.where(unbounded, 0.0, arr))
        holds = calibrated.region_guarantees.get(level)
        counts = calibrated.region_counts.get(level)
        columns.append((key, *(unbounded_none(a, unbounded) for a in arrays[:2]),
                        arrays[2].tolist(), [None] * n if holds is None else holds.tolist(),
                        [None] * n if counts is None else
                        [None if c < 0 else c for c in counts.tolist()]))
    return [{key: {"semi_major": major[i], "semi_minor": minor[i], "angle": angle[i],
                   "method": method, "group": groups[i], "guarantee": hold[i],
                   "calibration_n": count[i]}
             for key, major, minor, angle, hold, count in columns} for i in range(n)]


def unbounded_none(values: np.ndarray, unbounded: np.ndarray) -> list[float | None]:
    """`values [N]` as a list with None where `unbounded [N]` (JSON has no infinity)."""
    return to_jsonable(np.where(unbounded, np.inf, np.asarray(values, dtype=np.float64)))
