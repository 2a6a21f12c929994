"""The inputs of the per-class score calibrators (`calibrators.scores`) for 2-D detections:
each detection's label as an index into a class list the caller states, and the logit of the
label's probability.

With `logits` on the detections and a stated score mode: the label's logit (sigmoid, C
columns in the order of `category_ids`) or `logit(p_label)` of the softmax (C + 1 columns,
the last is no-object), as `calibrators.scores.label_logit`. Without logits: `logit(score)`.
The calibrators then fit and serve as for 3-D detections, without distances:

    z, labels = score_inputs(detections, category_ids)
    calibrator = make_score_calibrator("isotonic").fit(z, labels, tp, len(category_ids))
    calibrated = calibrator.transform(z, labels)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from calibrators.boxes2d._boxes import Detections2D
from calibrators.core.checks import as_int_array, check_choice, check_probabilities
from calibrators.core.errors import FieldError
from calibrators.core.vocab import SCORE_MODES
from calibrators.scores import label_logit, probability_logit

__all__ = ["ScoreInputs", "category_index", "score_inputs"]


class ScoreInputs(NamedTuple):
    """z [N] float64: the logit of each detection's label; labels [N] int64: the label's index
    into the stated `category_ids` (C classes)."""

    z: np.ndarray
    labels: np.ndarray


def category_index(category_id: np.ndarray, category_ids: Sequence[int]) -> np.ndarray:
    """`[N]` int64 position of each of `category_id [N]` in the list `category_ids` (distinct
    ints, any order); FieldError naming the first id not in it."""
    ids = as_int_array("category_ids", category_ids)
    if len(ids) == 0 or len(np.unique(ids)) != len(ids):
        raise FieldError("category_ids", "category_ids must list one or more distinct ids")
    order = np.argsort(ids, kind="stable")
    cat = np.asarray(category_id, dtype=np.int64)
    pos = np.clip(np.searchsorted(ids[order], cat), 0, len(ids) - 1)
    bad = ids[order][pos] != cat
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError("category_id", f"category_id[{i}] = {int(cat[i])} is not in "
                                        "category_ids", row=i)
    return order[pos].astype(np.int64)


def score_inputs(detections: Detections2D, category_ids: Sequence[int],
                 mode: str | None = None) -> ScoreInputs:
    """`(z, labels)` of `detections` (module docstring): `mode` ("sigmoid" or "softmax") is
    required when they carry logits, and unused without them (z = logit(score), each score
    in [0, 1])."""
    if not isinstance(detections, Detections2D):
        raise FieldError("detections", "detections must be a Detections2D")
    labels = category_index(detections.category_id, category_ids)
    if detections.logits is None:
        check_probabilities("score", detections.score)
        return ScoreInputs(probability_logit(detections.score), labels)
    if mode is None:
        raise FieldError("mode", "the detections carry logits: state the score mode, "
                                 f"one of {list(SCORE_MODES)}")
    check_choice("mode", mode, SCORE_MODES)
    width = len(np.asarray(category_ids)) + (mode == "softmax")
    if detections.logits.shape[1] != width:
        raise FieldError("logits", f"logits have {detections.logits.shape[1]} columns but "
                                   f"{mode} mode with {width - (mode == 'softmax')} categories "
                                   f"needs {width}")
    return ScoreInputs(label_logit(detections.logits, labels, mode), labels)
