"""Labelled feedback: JSON frames to a library `Dump`, and recording a dump's evidence.

`frames_dump` turns the frames of a JSON feedback request (raw detections in the calibrate
request's form, with `logits` or `layer_logits`, plus every ground-truth box) into a `Dump`
the library matches and calibrates; `record_feedback` feeds the dump to
`calibrators.monitoring.collect_evidence` and the version's `DriftMonitor`, and appends the new
cumulative sums to the store (with its audit entry, in one transaction).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from app.calibrate.cache import LoadedProfile
from app.http.errors import RequestError
from app.schemas.calibrate import DetectionIn
from app.schemas.feedback import FeedbackFrame
from app.store import AuditEntry, HealthChunk, HealthRecord, Store
from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.monitoring import (
    AlarmRule,
    DriftMonitor,
    FrameEvidence,
    HealthCounts,
    collect_evidence,
)
from calibrators.profile import box9, label_index
from calibrators.scores import predict

#: The alarm rule the service applies.
RULE = AlarmRule()

#: Where in the request body a field is.
Loc = list[str | int]


def _form(shape: tuple[int, bool, int]) -> str:
    layers, cov, hyp = shape
    return (f"{layers} layer(s), {'a' if cov else 'no'} covariance, {hyp} box hypotheses")


def _label(label: str | int, classes: Sequence[str], loc: Loc) -> int:
    """The library's `label_index`, its error at `loc`."""
    try:
        return label_index(label, classes)
    except FieldError as exc:
        raise RequestError(loc, str(exc)) from None


def _det_layers(det: DetectionIn, loc: Loc) -> tuple[list[list[float]], list[list[float]], int]:
    """A detection's per-layer logits and boxes and their layer count; a 422 at `loc` when it
    has no logits or its logits and boxes disagree in layers."""
    if det.layer_logits is not None:
        z = det.layer_logits
    elif det.logits is not None:
        z = [det.logits]
    else:
        raise RequestError([*loc, "score" if det.score is not None else "scores"],
                           "feedback needs each detection's logits or layer_logits "
                           "(what the profile calibrates from)")
    b = det.layer_boxes if det.layer_boxes is not None else [box9(det.box or [])]
    n_layers = max(len(z), len(b))
    if len(z) not in (1, n_layers) or len(b) not in (1, n_layers):
        raise RequestError([*loc, "layer_boxes"], f"layer_logits has {len(z)} layers "
                           f"but layer_boxes {len(b)}")
    return z, b, n_layers


def _n_hypotheses(det: DetectionIn, loc: Loc) -> int:
    """How many box hypotheses a detection has; a 422 when its scores do not match them."""
    n_hyp = 0 if det.hypothesis_boxes is None else len(det.hypothesis_boxes)
    if n_hyp and len(det.hypothesis_scores or ()) != n_hyp:
        raise RequestError([*loc, "hypothesis_scores"], f"hypothesis_scores has "
                           f"{len(det.hypothesis_scores or ())} scores but "
                           f"hypothesis_boxes {n_hyp} boxes")
    return n_hyp


def _same_form(this: tuple[int, bool, int], shape: tuple[int, bool, int] | None,
               loc: Loc) -> tuple[int, bool, int]:
    """The form every detection must share (the first one's); a 422 when `this` differs."""
    if shape is None:
        return this
    if this != shape:
        raise RequestError(loc, f"every detection of a feedback request must have the "
                                f"same number of layers, all or none a covariance and "
                                f"the same number of box hypotheses; this one has "
                                f"{_form(this)}, the first {_form(shape)}")
    return shape


@dataclass
class _Rows:
    """The detections and ground truth of the frames, as lists in the `Dump`'s layout."""

    logits: list[list[list[float]]] = field(default_factory=list)
    boxes: list[list[list[float]]] = field(default_factory=list)
    covs: list[list[list[float]]] = field(default_factory=list)
    det_frame: list[int] = field(default_factory=list)
    hyp_boxes: list[list[list[float]]] = field(default_factory=list)
    hyp_scores: list[list[float]] = field(default_factory=list)
    labels: list[int] = field(default_factory=list)
    gt_boxes: list[list[float]] = field(default_factory=list)
    gt_labels: list[int] = field(default_factory=list)
    gt_frame: list[int] = field(default_factory=list)
    shape: tuple[int, bool, int] | None = None

    def add_detection(self, det: DetectionIn, fi: int, di: int, classes: Sequence[str]) -> None:
        loc: Loc = ["body", "frames", fi, "detections", di]
        z, b, n_layers = _det_layers(det, loc)
        n_hyp = _n_hypotheses(det, loc)
        self.shape = _same_form((n_layers, det.covariance is not None, n_hyp), self.shape, loc)
        if n_hyp:
            self.hyp_boxes.append(det.hypothesis_boxes)
            self.hyp_scores.append(det.hypothesis_scores)
        self.logits.append([z[0]] * n_layers if len(z) == 1 else z)
        self.labels.append(-1 if det.label is None else
                           _label(det.label, classes, [*loc, "label"]))
        self.boxes.append([b[0]] * n_layers if len(b) == 1 else b)
        if det.covariance is not None:
            self.covs.append(det.covariance)
        self.det_frame.append(fi)

    def add_ground_truth(self, frame: FeedbackFrame, fi: int, classes: Sequence[str]) -> None:
        for gi, gt in enumerate(frame.ground_truth):
            self.gt_labels.append(_label(gt.label, classes,
                                         ["body", "frames", fi, "ground_truth", gi, "label"]))
            self.gt_boxes.append(box9(gt.box))
            self.gt_frame.append(fi)


def _det_label(rows: _Rows, n_layers: int, width: int, score_mode: str) -> np.ndarray | None:
    """The given labels, the arg-max where none is; None when no detection gives one."""
    if not any(label >= 0 for label in rows.labels):
        return None
    final = np.asarray(rows.logits, dtype=np.float64).reshape(-1, n_layers, width)[:, -1]
    return np.where(np.asarray(rows.labels) >= 0, rows.labels,
                    predict(final, score_mode)[0]).astype(np.int64)


def frames_dump(frames: Sequence[FeedbackFrame], loaded: LoadedProfile) -> Dump:
    """The `Dump` of JSON feedback frames for `loaded`'s profile; a 422 naming the field when a
    detection has no logits, or the detections disagree in layers or covariance."""
    prof = loaded.profile
    rows = _Rows()
    ego = np.zeros((len(frames), 3))
    for fi, frame in enumerate(frames):
        if frame.ego_translation is not None:
            ego[fi] = frame.ego_translation
        for di, det in enumerate(frame.detections):
            rows.add_detection(det, fi, di, prof.classes)
        rows.add_ground_truth(frame, fi, prof.classes)
    n_layers = rows.shape[0] if rows.shape else 1
    width = len(prof.classes) + (1 if prof.score_mode == "softmax" else 0)
    det_label = _det_label(rows, n_layers, width, prof.score_mode)
    try:
        return Dump(
            classes=tuple(prof.classes), score_mode=prof.score_mode,
            frame_ids=np.array([f"{i}:{f.frame_id}" for i, f in enumerate(frames)]),
            det_frame=np.asarray(rows.det_frame, dtype=np.int64),
            det_logits=np.asarray(rows.logits, dtype=np.float64).reshape(-1, n_layers, width)
            if rows.logits else np.zeros((0, n_layers, width)),
            det_boxes=np.asarray(rows.boxes, dtype=np.float64).reshape(-1, n_layers, 9),
            gt_frame=np.asarray(rows.gt_frame, dtype=np.int64),
            gt_labels=np.asarray(rows.gt_labels, dtype=np.int64),
            gt_boxes=np.asarray(rows.gt_boxes, dtype=np.float64).reshape(-1, 9),
            ego_translation=ego,
            det_cov=np.asarray(rows.covs, dtype=np.float64) if rows.covs else None,
            cov_dims=tuple(prof.cov_dims),
            det_hyp_boxes=np.asarray(rows.hyp_boxes, dtype=np.float64)
            if rows.hyp_boxes else None,
            det_hyp_scores=np.asarray(rows.hyp_scores, dtype=np.float64)
            if rows.hyp_boxes else None,
            det_label=det_label)
    except ValueError as exc:
        raise RequestError(["body", "frames"], f"profile {loaded.record.ref}: {exc}") from None


class DegenerateFeedback(ValueError):
    """Feedback that cannot be evidence about calibration (`degenerate_reason`): refused
    whole, so it never reaches a version's health."""


def degenerate_reason(dump: Dump, counts: HealthCounts | None = None) -> str | None:
    """Why `dump` is synthetic or degenerate feedback, or None. Refused: every detection box
    of zero size, every ground-truth box of zero size, or (given its `counts`) detections and
    ground truth of which not one pair matches (no true positive at all: a detector outage or
    mislabelled frames, not a calibration drift). docs/production.md states the rule."""
    def no_size(boxes: np.ndarray) -> bool:
        return boxes.size > 0 and not np.any(boxes[..., 3:6] != 0)

    if dump.n_detections and no_size(dump.det_boxes[:, -1]):
        return f"all {dump.n_detections} detection boxes have zero size"
    if len(dump.gt_labels) and no_size(dump.gt_boxes):
        return f"all {len(dump.gt_labels)} ground-truth boxes have zero size"
    if counts is not None and counts.detections and counts.gt and counts.tp == 0:
        return (f"none of its {counts.detections} detections matches any of its {counts.gt} "
                f"ground-truth boxes (no true positive)")
    return None


@dataclass(frozen=True)
class Recorded:
    """What one feedback request added, the rows it wrote, the alarms it raised and whether
    the version was already degraded before it."""

    evidence: FrameEvidence
    rows: list[HealthRecord]
    new_alarms: list[str]
    was_degraded: bool


def row_status(n_alarms: int, counts: HealthCounts) -> str:
    """`degraded` with an alarm, else `insufficient` below `RULE.min_frames` frames or without
    a true positive, else `ok`."""
    if n_alarms:
        return "degraded"
    return "insufficient" if counts.frames < RULE.min_frames or counts.tp == 0 else "ok"


def record_feedback(store: Store, loaded: LoadedProfile, dump: Dump, chunk_frames: int,
                    audit: AuditEntry, dump_sha256: str | None = None) -> Recorded:
    """Collect the evidence of `dump` under `loaded`'s profile and append it to the version's
    health in chunks of `chunk_frames` frames, the last row referencing the kept dump
    `dump_sha256` (ValueError / FieldError from the library when the dump does not fit the
    profile)."""
    reason = degenerate_reason(dump)   # before matching: zero-size boxes all tie
    if reason is None:
        ev = collect_evidence(dump, loaded.profile)
        reason = degenerate_reason(dump, ev.counts())
    if reason is not None:
        raise DegenerateFeedback(f"feedback refused, nothing recorded: {reason}")
    new: list[str] = []
    degraded_before = [False]

    def advance(latest: HealthRecord | None) -> list[HealthChunk]:
        if latest is None:
            cum = HealthCounts.zeros(len(ev.classes), ev.n_bins, ev.distance_edges.size - 1,
                                     ev.levels.size)
            monitor = DriftMonitor.for_evidence(ev, RULE)
        else:
            cum = HealthCounts.from_dict(json.loads(latest.counts))
            monitor = DriftMonitor.from_dict(json.loads(latest.drift))
        start_frame, before = monitor.frames, len(monitor.alarms)
        degraded_before[0] = before > 0
        raised = monitor.update(ev)
        new[:] = [a["reason"] for a in raised]
        chunks = []
        for start in range(0, ev.n_frames, chunk_frames):
            stop = min(start + chunk_frames, ev.n_frames)
            cum = cum + ev.counts(start, stop)
            n_alarms = before + sum(a["frame"] <= start_frame + stop for a in raised)
            last = stop == ev.n_frames
            chunks.append(HealthChunk(frames_total=cum.frames, counts=json.dumps(cum.to_dict()),
                                      drift=json.dumps(monitor.to_dict()) if last else "",
                                      status=row_status(n_alarms, cum), alarms_total=n_alarms))
        return chunks

    rows = store.append_health(loaded.record.name, loaded.record.id, advance, audit,
                               dump_sha256)
    return Recorded(ev, rows, new, degraded_before[0])
