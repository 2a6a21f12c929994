"""Covariance source `hypotheses`: the group-score-weighted spread of a detection's H box
hypotheses (seed 001's group regression heads, one box per class group).

A detector with group regression heads gives every query H boxes, one per group head, and a
group score per box (the summed class probabilities of the group's classes). Weighting the
hypotheses by their normalised group scores `w_h = s_h / sum_h s_h` gives a mixture whose
mean and covariance are

    mu = sum_h w_h b_h
    C  = sum_h w_h (b_h - mu)(b_h - mu)^T          (over the chosen box dims)

— a detection whose groups agree (or whose score sits on one group) gets a small C, one torn
between a car and a bicycle hypothesis several metres apart a large one. All-zero scores
weigh the hypotheses equally. `yaw` deviations are wrapped to (-pi, pi] around the yaw of
the highest-scoring hypothesis. C has rank at most H - 1 and is often near zero, so (like
the layer spread) it is meant to go through depth scaling `C + k d I` before it is served.

Shapes: hyp_boxes [N, H, 9], hyp_scores [N, H] -> covariance [N, D, D] (D = len(dims)).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.core.checks import as_float_array
from calibrators.core.errors import FieldError
from calibrators.core.vocab import BOX_FIELDS, BOX_INDEX, check_dims, wrap_angle


def check_hypotheses(hyp_boxes: object, hyp_scores: object, n: int | None = None,
                     names: tuple[str, str] = ("hyp_boxes", "hyp_scores")
                     ) -> tuple[np.ndarray, np.ndarray]:
    """`hyp_boxes [N, H, 9]` and `hyp_scores [N, H]` as float64 (N = `n` when given, H >= 1,
    finite, scores >= 0), or a FieldError naming the array (`names`) and the row at fault."""
    box_name, score_name = names
    boxes = as_float_array(box_name, hyp_boxes, ndim=3)
    if ((n is not None and boxes.shape[0] != n) or boxes.shape[2] != len(BOX_FIELDS)
            or boxes.shape[1] < 1):
        raise FieldError(box_name, f"{box_name} must have shape [{'N' if n is None else n}, H, "
                                   f"9] with H >= 1, got {list(boxes.shape)}")
    scores = as_float_array(score_name, hyp_scores, ndim=2)
    if scores.shape != boxes.shape[:2]:
        raise FieldError(score_name, f"{score_name} must have shape {list(boxes.shape[:2])}, "
                                     f"got {list(scores.shape)}")
    if (scores < 0).any():
        row = int(np.argwhere(scores < 0)[0][0])
        raise FieldError(score_name, f"{score_name} has a negative score at row {row} (group "
                                     f"scores are sums of probabilities: a negative group "
                                     f"score is not one)", row=row)
    return boxes, scores


def hypotheses_covariance(hyp_boxes: np.ndarray, hyp_scores: np.ndarray,
                          dims: Sequence[str] = ("x", "y")) -> np.ndarray:
    """Group-score-weighted covariance `[N, D, D]` of each detection's H box hypotheses.

    `hyp_boxes [N, H, 9]` (a dump's `det_hyp_boxes`), `hyp_scores [N, H]` non-negative group
    scores (`det_hyp_scores`), `dims` the D box fields (`calibrators.core.vocab.BOX_FIELDS`) in
    the covariance's order. See the module docstring for the formula.
    """
    names = check_dims(dims)
    boxes, scores = check_hypotheses(hyp_boxes, hyp_scores)
    weights = _weights(scores)
    values = boxes[:, :, [BOX_INDEX[d] for d in names]]
    top = scores.argmax(axis=1)
    for j, name in enumerate(names):
        if name == "yaw":
            ref = values[np.arange(len(values)), top, j][:, None]
            values[:, :, j] = ref + wrap_angle(values[:, :, j] - ref)
    mean = np.einsum("nh,nhd->nd", weights, values)
    centred = values - mean[:, None]
    cov = np.einsum("nh,nhi,nhj->nij", weights, centred, centred)
    return 0.5 * (cov + cov.transpose(0, 2, 1))


def _weights(scores: np.ndarray) -> np.ndarray:
    """`[N, H]` scores -> weights summing to one per row (equal where a row sums to 0)."""
    total = scores.sum(axis=1, keepdims=True)
    equal = np.full_like(scores, 1.0 / max(scores.shape[1], 1))
    with np.errstate(invalid="ignore", divide="ignore"):
        w = scores / total
    return np.where(total > 0, w, equal)
