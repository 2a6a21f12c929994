"""IoU-and-average merging (thesis Algorithm 1) of stochastic detections of one frame.

The clusters are given: typically the query index, since a DETR query describes the same
object in every MC-dropout pass (`groups = query index` of each pooled detection). Within a
cluster the member with the highest score is the reference; the members whose BEV IoU with
it is *higher* than `iou_threshold` are the positives (the reference always is), the others
are ignored (`cluster == -1` in the result). The positives are merged by
`detectors.baselines.cluster` (mean box, circular-mean yaw, mean score, label by vote,
sample covariance, averaged class distributions). The overlap test ignores the labels, so
a cluster can mix labels and the vote decides.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.core.checks import as_int_array, check_length
from detectors.baselines.bev_iou import paired_bev_iou
from detectors.baselines.cluster import MergedDetections, check_inputs, summarise


def iou_merge(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, groups: np.ndarray,
              *, iou_threshold: float = 0.5, dims: Sequence[str] = ("x", "y"),
              layer_logits: np.ndarray | None = None, layer_boxes: np.ndarray | None = None,
              score_mode: str = "sigmoid") -> MergedDetections:
    """Merge M pooled detections by the given clusters (Algorithm 1; module docstring).

    boxes [M, 9] final boxes; scores [M] scores of their labels; labels [M] int class index;
    groups [M] int cluster id of each detection (e.g. its query index); iou_threshold in
    [0, 1): a member needs IoU > it with its cluster's top-scoring member; dims: box fields of
    the covariances; layer_logits [M, L, C'] and layer_boxes [M, L, 9]: optional per-layer
    outputs, merged too (needed to write a dump); score_mode: "sigmoid" or "softmax" (how the
    logits are averaged). Returns one merged detection per cluster.
    """
    data = check_inputs(boxes, scores, labels, layer_logits, layer_boxes, dims, score_mode)
    group = as_int_array("groups", groups)
    check_length("groups", group, len(data.scores), "boxes")
    threshold = float(iou_threshold)
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"iou_threshold must be in [0, 1), got {iou_threshold}")
    reference = _top_member(group, data.scores)
    iou = paired_bev_iou(data.boxes, data.boxes[reference])
    positive = (iou > threshold) | (np.arange(len(group)) == reference)
    return summarise(data, np.where(positive, group, -1))


def _top_member(group: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """`[M]` row of the highest-scoring member of each row's group (ties: the first row)."""
    order = np.lexsort((np.arange(len(group)), -scores, group))   # by group, score desc, row
    first = np.r_[True, np.diff(group[order]) != 0] if len(order) else np.zeros(0, bool)
    top = order[first]
    top_of = np.empty(len(group), dtype=np.int64)
    group_id = np.cumsum(first) - 1
    top_of[order] = top[group_id]
    return top_of
