"""Turn validated request detections into library arrays, calibrate, and build response rows.

Detections of one request may mix evidence forms (logits, per-layer logits, per-class scores,
one score + label) and uncertainty forms (covariance, layer boxes, box hypotheses, none);
they are grouped by form and shape (`GroupKey`), each group goes through
`CalibrationProfile.calibrate` once, and the rows come back in request order. Every check
against the profile (column width, the covariance the profile's source needs, PSD,
modulation's layers, the served levels) lives in the library: a `FieldError` it raises is
mapped here to the request's field path (`locate`, or the request's `levels` /
`ellipse_confidence`) and a 422. A calibrated number that is not finite (inputs so large that
Σ' or an ellipse overflows float64) is a 422 at the detection's `covariance` (or `box`),
never a non-JSON `Infinity`.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from app.cache import LoadedProfile
from app.errors import RequestError
from app.schemas.calibrate import DEFAULT_LEVELS, DetectionIn, FrameIn
from calibrators.exceptions import FieldError
from calibrators.io import ellipses_json, unbounded_none
from calibrators.levels import check_levels
from calibrators.serving import CalibratedDetections

_EPS = 1e-12


class GroupKey(NamedTuple):
    """The form and shape shared by the detections of one group (so their arrays stack)."""

    evidence: str        # request field holding the class evidence: logits | layer_logits | ...
    width: int           # its columns (0 for score + label)
    n_logit_layers: int  # L of layer_logits (0 otherwise)
    cov_dim: int         # D of a given covariance (0: none given)
    n_box_layers: int    # L of layer_boxes (0: none given)
    n_hyp_boxes: int     # H of hypothesis_boxes (0: none given)
    n_hyp_scores: int    # H of hypothesis_scores (0: none given; the library checks the pair)
    labelled: bool       # a label is given (always with score; with logits: the class the
                         # detection asserts, top-K (query, class) decoding)


@dataclass
class _Group:
    """Arrays of the detections that share one `GroupKey`."""

    index: list[int] = field(default_factory=list)
    evidence: list = field(default_factory=list)   # logits rows, [L, C'] layer logits, or score
    labels: list[int] = field(default_factory=list)
    boxes: list[list[float]] = field(default_factory=list)
    covariances: list[list[list[float]]] = field(default_factory=list)
    layer_boxes: list[list[list[float]]] = field(default_factory=list)
    hyp_boxes: list[list[list[float]]] = field(default_factory=list)
    hyp_scores: list[list[float]] = field(default_factory=list)
    ego_xy: list[list[float]] = field(default_factory=list)


def _mismatch(loc: Sequence[str | int], msg: str) -> RequestError:
    return RequestError(loc, msg, kind="value_error.profile_mismatch")


def _label_index(label: str | int, classes: Sequence[str], at: tuple[int, int, Locate]
                 ) -> int:
    """The class index of a request's `label`; `at` = (frame, detection, locate) names it in
    a 422 (the path is only built for an error: this runs once per detection)."""
    fi, di, locate = at
    if isinstance(label, int):
        if label >= len(classes):
            raise _mismatch([*locate(fi, di), "label"], f"label index {label} is out of range "
                                                        f"for the profile's {len(classes)} classes")
        return label
    try:
        return list(classes).index(label)
    except ValueError:
        raise _mismatch([*locate(fi, di), "label"], f"unknown class {label!r}; the profile's "
                                                    f"classes are {list(classes)}") from None


def _scores_to_logits(scores: list[float], mode: str) -> list[float]:
    p = np.clip(np.asarray(scores, dtype=np.float64), _EPS, 1.0 - _EPS)
    z = np.log(p) - np.log1p(-p) if mode == "sigmoid" else np.log(p)
    return z.tolist()


def _box9(box: list[float]) -> list[float]:
    return box if len(box) == 9 else [*box, 0.0, 0.0]


Locate = Callable[[int, int], list[str | int]]


def _default_locate(fi: int, di: int) -> list[str | int]:
    return ["body", "frames", fi, "detections", di]


def calibrate_frames(loaded: LoadedProfile, frames: Sequence[FrameIn],
                     confidence: float, locate: Locate = _default_locate, *,
                     levels: Sequence[float] = DEFAULT_LEVELS, options_in: str = "body",
                     max_detections: int | None = None) -> list[list[dict[str, object]]]:
    """Calibrated detection rows (response dicts) per frame, in request order, with the
    ellipse at `confidence` and the regions at `levels`.

    `locate(frame_index, detection_index)` gives the field path used in error messages;
    `options_in` is where the request carries `levels` and `ellipse_confidence` ("body" or
    "query").
    """
    total = sum(len(frame.detections) for frame in frames)
    if max_detections is not None and total > max_detections:
        raise RequestError([options_in, "frames"], f"the request carries {total} detections; at "
                           f"most {max_detections} are calibrated per request "
                           f"(DETCAL_MAX_DETECTIONS): split it", status=413)
    try:
        levels = check_levels(levels).tolist()
    except FieldError as exc:
        loc = [options_in, "levels"] + ([] if exc.row is None else [exc.row])
        raise RequestError(loc, str(exc)) from None
    prof = loaded.profile
    groups: dict[GroupKey, _Group] = defaultdict(_Group)
    flat: list[DetectionIn] = []
    where: list[tuple[int, int]] = []
    for fi, frame in enumerate(frames):
        ego = (frame.ego_translation or [0.0, 0.0, 0.0])[:2]
        for di, det in enumerate(frame.detections):
            key, evidence, label = _evidence(det, (fi, di, locate), prof.classes,
                                             prof.score_mode)
            g = groups[key]
            g.index.append(len(flat))
            g.evidence.append(evidence)
            g.labels.append(label)
            g.boxes.append(_box9(det.box) if det.box is not None
                           else det.layer_boxes[-1])  # type: ignore[index]
            if det.covariance is not None:
                g.covariances.append(det.covariance)
            if det.layer_boxes is not None:
                g.layer_boxes.append(det.layer_boxes)
            if det.hypothesis_boxes is not None:
                g.hyp_boxes.append(det.hypothesis_boxes)
            if det.hypothesis_scores is not None:
                g.hyp_scores.append(det.hypothesis_scores)
            g.ego_xy.append(ego)
            flat.append(det)
            where.append((fi, di))

    rows: list[dict[str, object] | None] = [None] * len(flat)
    for key, g in groups.items():
        kwargs = _arrays(key, g, confidence)
        try:
            res = prof.calibrate(**kwargs, levels=levels)  # type: ignore[arg-type]
        except FieldError as exc:
            raise _located(exc, key, g, where, locate, loaded.record.ref) from None
        except ValueError as exc:   # a library check that names no field: the group's first
            fi, di = where[g.index[0]]
            raise _mismatch(locate(fi, di), f"profile {loaded.record.ref}: {exc}") from None
        _rows(res, prof.classes, g, confidence, flat, rows)
    out: list[list[dict[str, object]]] = [[] for _ in frames]
    for i, row in enumerate(rows):
        out[where[i][0]].append(row)  # type: ignore[arg-type]
    return out


def _evidence(det: DetectionIn, at: tuple[int, int, Locate], classes: Sequence[str], mode: str
              ) -> tuple[GroupKey, list, int]:
    """Group key, class evidence and label index (-1: the arg-max of the logits) of one
    detection."""
    n_logit_layers = 0
    label = -1 if det.label is None else _label_index(det.label, classes, at)
    if det.score is not None:
        kind, evidence = "score", [det.score]
    elif det.layer_logits is not None:
        kind, evidence, n_logit_layers = "layer_logits", det.layer_logits, len(det.layer_logits)
    elif det.logits is not None:
        kind, evidence = "logits", det.logits
    else:
        kind, evidence = "scores", _scores_to_logits(det.scores or [], mode)
    width = 0 if kind == "score" else len(evidence[-1] if n_logit_layers else evidence)
    key = GroupKey(kind, width, n_logit_layers,
                   0 if det.covariance is None else len(det.covariance),
                   0 if det.layer_boxes is None else len(det.layer_boxes),
                   0 if det.hypothesis_boxes is None else len(det.hypothesis_boxes),
                   0 if det.hypothesis_scores is None else len(det.hypothesis_scores),
                   label >= 0)
    return key, evidence, label


#: Library argument -> request field (`logits` is whatever evidence field the group used).
_REQUEST_FIELD = {"scores": "score", "labels": "label", "boxes": "box", "distances": "box",
                  "covariances": "covariance", "layer_boxes": "layer_boxes",
                  "layer_logits": "layer_logits", "hyp_boxes": "hypothesis_boxes",
                  "hyp_scores": "hypothesis_scores"}


def _located(exc: FieldError, key: GroupKey, g: _Group, where: list[tuple[int, int]],
             locate: Locate, ref: str) -> RequestError:
    """The library's error on one group, at the request field of the detection at fault (the
    group's first detection when the error is about the whole group)."""
    row = exc.row if exc.row is not None and 0 <= exc.row < len(g.index) else 0
    fi, di = where[g.index[row]]
    if exc.field == "ego_xy":
        return _mismatch(locate(fi, di)[:-2] + ["ego_translation"], f"profile {ref}: {exc}")
    name = key.evidence if exc.field == "logits" else _REQUEST_FIELD.get(exc.field, exc.field)
    return _mismatch([*locate(fi, di), name], f"profile {ref}: {exc}")


def _arrays(key: GroupKey, g: _Group, confidence: float) -> dict[str, object]:
    """Keyword arguments of `CalibrationProfile.calibrate` for the detections of one group."""
    kwargs: dict[str, object] = {
        "boxes": np.asarray(g.boxes, dtype=np.float64),
        "ego_xy": np.asarray(g.ego_xy, dtype=np.float64),
        "ellipse_confidence": confidence,
    }
    if key.evidence == "score":
        kwargs["scores"] = np.asarray(g.evidence, dtype=np.float64)[:, 0]
        kwargs["labels"] = np.asarray(g.labels, dtype=np.int64)
    else:   # [N, L, C'] layer logits, or final-layer logits [N, C']
        kwargs["layer_logits" if key.n_logit_layers else "logits"] = np.asarray(
            g.evidence, dtype=np.float64)
        if key.labelled:
            kwargs["labels"] = np.asarray(g.labels, dtype=np.int64)
    if key.cov_dim:
        kwargs["covariances"] = np.asarray(g.covariances, dtype=np.float64)
    if key.n_box_layers:
        kwargs["layer_boxes"] = np.asarray(g.layer_boxes, dtype=np.float64)
    if key.n_hyp_boxes:
        kwargs["hyp_boxes"] = np.asarray(g.hyp_boxes, dtype=np.float64)
    if key.n_hyp_scores:
        kwargs["hyp_scores"] = np.asarray(g.hyp_scores, dtype=np.float64)
    return kwargs


def _rows(res: CalibratedDetections, classes: Sequence[str], g: _Group, confidence: float,
          flat: list[DetectionIn], rows: list[dict[str, object] | None]) -> None:
    """Response rows of one calibrated group, written at their request positions."""
    labels = res.labels.tolist()
    scores = res.scores.tolist()
    raw = res.scores_raw.tolist()
    cls_scores = res.class_scores.tolist() if res.class_scores is not None else None
    covs = res.covariances.tolist()
    el = res.ellipses
    if el is not None:   # an unbounded ellipse (inf semi-axes, see serving) has null axes
        major, minor = (unbounded_none(a, np.isinf(a)) for a in (el.semi_major, el.semi_minor))
        angle = el.angle.tolist()
    regions = ellipses_json(res)
    dist = res.distances.tolist()
    for j, i in enumerate(g.index):
        rows[i] = {
            "id": flat[i].id,
            "label": classes[labels[j]],
            "label_index": labels[j],
            "score": scores[j],
            "score_raw": raw[j],
            "class_scores": None if cls_scores is None else cls_scores[j],
            "box": g.boxes[j],
            "covariance": covs[j],
            "ellipse": None if el is None else {
                "semi_major": major[j], "semi_minor": minor[j], "angle": angle[j],
                "confidence": confidence},
            "ellipses": regions[j],
            "distance": dist[j],
        }
