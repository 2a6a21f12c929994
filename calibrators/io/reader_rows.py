"""What the format readers share: rows of boxes -> `Dump`, class lists, scores as logits.

Each reader (KITTI text, OpenPCDet pickle, MMDetection3D arrays, Argoverse 2 feather) parses
its own fields into two `Rows` (detections, ground truth) already in detcal's box layout and
frame tokens, then `rows_to_dump` builds the validated `Dump`. Frames are the sorted set of
tokens (so the order or interleaving of the input never changes a frame's index); detections
and ground truth keep their input order.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from calibrators.core.checks import check_probabilities
from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.scores import probability_logit

#: Probability given to the classes a scores-only detection does not name (as nuScenes JSON).
OTHER_CLASS_PROB = 1e-6


@dataclass(frozen=True)
class Rows:
    """Boxes of one kind (detections or ground truth), one row each.

        frames  [N] str     frame token of each row
        labels  [N] int     index into the reader's class list
        boxes   [N, 9]      x y z w l h yaw vx vy (z = centre), ego / lidar frame
        scores  [N] | None  detection score: a probability, or a logit with `score_is_logit`
        logits  [N, C'] | None  per-class logits (or class scores) when the format has them
    """

    frames: np.ndarray
    labels: np.ndarray
    boxes: np.ndarray
    scores: np.ndarray | None = None
    logits: np.ndarray | None = None


def empty_rows() -> Rows:
    """Rows with N = 0 (e.g. no ground truth)."""
    return Rows(np.zeros(0, dtype=str), np.zeros(0, dtype=np.int64), np.zeros((0, 9)))


def check_scores(scores: np.ndarray, where: str, key: str) -> None:
    """Raise a FieldError on `key` naming `where` and the first score outside [0, 1]."""
    bad = np.flatnonzero((scores < 0) | (scores > 1))
    if len(bad):
        raise FieldError(key, f"{where}: {key}[{bad[0]}] = {scores[bad[0]]:g} is not a "
                              "probability in [0, 1]", row=int(bad[0]))


def score_logits(scores: np.ndarray, labels: np.ndarray, n_classes: int,
                 score_is_logit: bool = False) -> np.ndarray:
    """`[N, C]` sigmoid-mode logits of detections that carry one score for their label.

    The label's column is `logit(score)` (or the score itself when it already is a logit);
    every other column `logit(OTHER_CLASS_PROB)`, or one less than the label's logit when that
    is lower, so the arg-max is the label and the score is recovered exactly.
    """
    scores = np.asarray(scores, dtype=np.float64)
    if not score_is_logit:
        check_probabilities("score", scores)
    z = scores if score_is_logit else probability_logit(scores)
    others = np.minimum(probability_logit(np.array([OTHER_CLASS_PROB]))[0], z - 1.0)
    out = others[:, None] * np.ones((len(z), n_classes))
    out[np.arange(len(z)), np.asarray(labels, dtype=np.int64)] = z
    return out


def rows_to_dump(classes: tuple[str, ...], det: Rows, gt: Rows | None = None, *,
                 score_is_logit: bool = False, score_mode: str = "sigmoid",
                 frames: np.ndarray | None = None, source: str = "input") -> Dump:
    """A `Dump` (L = 1) of detections `det` and ground truth `gt` (None: none) over the sorted
    frame tokens (those of the rows and `frames`, the input's frames that may have neither).
    A value the `Dump` refuses (e.g. a box that overflowed to Inf) is a FieldError naming
    `source`, the file read.

    Logits: `det.logits` when given (`score_mode` says how to read them), else built from
    `det.scores` by `score_logits` in sigmoid mode. The label is kept as `det_label` when it
    is not the arg-max of the given logits.
    """
    gt = empty_rows() if gt is None else gt
    known = set() if frames is None else set(np.asarray(frames, dtype=str).tolist())
    tokens = np.array(sorted(set(det.frames.tolist()) | set(gt.frames.tolist()) | known),
                      dtype=str)
    index = {t: i for i, t in enumerate(tokens.tolist())}
    det_frame = np.array([index[t] for t in det.frames.tolist()], dtype=np.int64)
    gt_frame = np.array([index[t] for t in gt.frames.tolist()], dtype=np.int64)
    labels = np.asarray(det.labels, dtype=np.int64)
    if det.logits is None:
        scores = np.zeros(0) if det.scores is None else det.scores
        logits, score_mode, det_label = score_logits(scores, labels, len(classes),
                                                     score_is_logit), "sigmoid", None
    else:
        logits = np.asarray(det.logits, dtype=np.float64)
        argmax = np.argmax(logits[:, :len(classes)], axis=1) if len(logits) else labels
        det_label = None if np.array_equal(argmax, labels) else labels
    try:
        return Dump(classes=classes, score_mode=score_mode, frame_ids=tokens,
                    det_frame=det_frame, det_logits=logits.reshape(len(labels), 1, -1)
                    if len(labels) else np.zeros((0, 1, len(classes) + (score_mode == "softmax"))),
                    det_boxes=np.asarray(det.boxes, dtype=np.float64).reshape(-1, 1, 9),
                    det_label=det_label, gt_frame=gt_frame, gt_labels=gt.labels,
                    gt_boxes=np.asarray(gt.boxes, dtype=np.float64).reshape(-1, 9))
    except ValueError as exc:
        raise FieldError(getattr(exc, "field", "dump"), f"{source}: {exc}") from None


def class_index(classes: tuple[str, ...], class_map: dict[str, str] | None
                ) -> dict[str, int]:
    """Source name -> index into `classes`: every class by its own name, then `class_map`'s
    source names (a name mapped to a class outside `classes` is refused)."""
    index = {c: i for i, c in enumerate(classes)}
    for source, target in (class_map or {}).items():
        if target not in index:
            raise FieldError("class_map", f"class_map maps {source!r} to {target!r}, which is "
                                          f"not one of the classes {list(classes)}")
        index[str(source)] = index[target]
    return index


def class_list(classes: object, class_map: Mapping[str, str] | None
               ) -> tuple[tuple[str, ...], dict[str, int]]:
    """(`check_classes(classes)`, `class_index` of it and `class_map`): a reader's classes."""
    checked = check_classes(classes)
    return checked, class_index(checked, dict(class_map or {}))


def check_classes(classes: object) -> tuple[str, ...]:
    """A non-empty tuple of distinct class names (FieldError on `classes` otherwise)."""
    if isinstance(classes, str) or not hasattr(classes, "__iter__"):
        raise FieldError("classes", f"classes must be a list of names, got {classes!r}")
    out = tuple(str(c) for c in classes)  # type: ignore[union-attr]
    if not out or len(set(out)) != len(out):
        raise FieldError("classes", f"classes must be distinct names, at least one: {out}")
    return out
