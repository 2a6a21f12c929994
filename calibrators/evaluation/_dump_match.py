"""A dump matched to its ground truth, and the arrays that follow: the public dump-level API.

`match_dump` (nuScenes matching of the final layer), `tp_residuals` (matched ground truth −
box of the true positives), `raw_covariances` (Σ of every detection from a covariance
source), `resolve_cov_source` and `check_dims`; plus what a fit needs (`ts_labels`,
`ts_logits`, `select_detections`, `split_frames`). Every caller — the fit, the summary, the
CLI, the service and the detectors' report — goes through these, so a rule lives once.

All functions take a validated `Dump` (N detections, G ground-truth boxes, F frames) and use
its final decoder layer.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.vocab import BOX_INDEX, check_dims, wrap_angle
from calibrators.data import Dump
from calibrators.evaluation._matching import MatchResult, match
from calibrators.scores import modulate_logits

__all__ = ["match_dump", "tp_residuals", "ts_labels", "ts_logits"]






def match_dump(dump: Dump, threshold: float = MATCH_THRESHOLD) -> MatchResult:
    """nuScenes matching of the final-layer detections to the ground truth at `threshold` m.

    No class range filter: a profile must calibrate every detection the detector emits,
    and the far ones carry most of the depth signal (see `fit_profile`).
    """
    return match(dump.det_frame, dump.det_labels, dump.det_scores, dump.final_boxes[:, :2],
                 dump.gt_frame, dump.gt_labels, dump.gt_boxes[:, :2], threshold=threshold)


def ts_labels(dump: Dump, tp: np.ndarray) -> np.ndarray:
    """`[N]` temperature-scaling labels from the TP mask `[N]`.

    sigmoid: 1 for a TP of its predicted class, else 0. softmax: the target column, i.e. the
    class of the matched ground truth (= the predicted class, matching is per class) for a TP,
    else the no-object column C.
    """
    tp = np.asarray(tp, dtype=bool)
    if dump.score_mode == "sigmoid":
        return tp.astype(np.int64)
    return np.where(tp, dump.det_labels, len(dump.classes)).astype(np.int64)


def ts_logits(dump: Dump, modulation: bool = False) -> np.ndarray:
    """The logits temperature scaling is fit on: the final layer's `[N, C']`.

    With `modulation`, the modulated final-layer logits (`modulate_logits` over all layers).
    Modulation may move the arg-max, so in sigmoid mode only the column of the detector's
    label (raw arg-max, the class that was matched) is returned, `[N, 1]`: that is the logit
    `CalibrationProfile.calibrate` will score, and the one whose TP label `ts_labels` gives.
    Softmax labels name their target column, so all `C + 1` columns are returned.
    """
    if not modulation:
        if dump.det_label is not None and dump.score_mode == "sigmoid":
            # Given labels need not be the arg-max: the fit must see the label's logit.
            return dump.det_logits[np.arange(dump.n_detections), -1, dump.det_label][:, None]
        return dump.det_logits[:, -1]
    if dump.n_layers < 2:
        raise ValueError(f"modulation needs at least 2 decoder layers, the dump has "
                         f"{dump.n_layers}")
    z = modulate_logits(dump.det_logits)
    if dump.score_mode == "sigmoid":
        return z[np.arange(len(z)), dump.det_labels][:, None]
    return z


def tp_residuals(dump: Dump, matched: MatchResult,
                 dims: str | Sequence[str] = ("x", "y")) -> np.ndarray:
    """`[M, D]` residuals (matched ground truth − final box) over `dims` of the M TPs of
    `matched` (a `match_dump` of this dump), in detection order.

    A yaw residual is wrapped to (−π, π].
    """
    cols = [BOX_INDEX[d] for d in check_dims(dims)]
    tp = np.asarray(matched.tp, dtype=bool)
    res = dump.gt_boxes[np.asarray(matched.gt_index)[tp]][:, cols] - dump.final_boxes[tp][:, cols]
    for j, c in enumerate(cols):
        if c == BOX_INDEX["yaw"]:
            res[:, j] = wrap_angle(res[:, j])
    return res








