"""DBSCAN merging (thesis Algorithm 2) of stochastic detections of one frame.

The M detections pooled from the N outputs are clustered per class (`classwise=True`, the
thesis's choice) or all together, by scikit-learn's `DBSCAN(metric="precomputed")` on the
distance `1 − BEV IoU` (`detectors.baselines.bev_iou`). Two boxes are neighbours when
`1 − IoU <= eps`, i.e. `IoU >= 1 − eps`. Each DBSCAN cluster is merged by
`detectors.baselines.cluster` (mean box, circular-mean yaw, mean score, label by vote,
sample covariance, averaged class distributions).

`min_samples` is DBSCAN's: the number of detections, *the point itself included*, a
detection's neighbourhood needs for it to be a core point. With `min_samples=1` every
detection is a core point and the clusters are the connected groups of the overlap graph;
with the default 2, a detection that overlaps nothing is a DBSCAN noise point. Noise
points are handled by `noise`: `"keep"` (default) makes each one a single-member cluster
(its covariance is zero and `n_members == 1` says so; depth scaling gives it a proper
covariance later); `"drop"` discards them (`cluster == -1` in the result), e.g. to keep only
objects that at least two passes agree on.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sklearn.cluster import DBSCAN

from calibrators.core.checks import check_choice
from detectors.baselines.bev_iou import pairwise_bev_iou
from detectors.baselines.cluster import MergedDetections, check_inputs, summarise

NOISE_MODES = ("keep", "drop")


def dbscan_merge(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, *,
                 eps: float = 0.5, min_samples: int = 2, classwise: bool = True,
                 noise: str = "keep", dims: Sequence[str] = ("x", "y"),
                 layer_logits: np.ndarray | None = None, layer_boxes: np.ndarray | None = None,
                 score_mode: str = "sigmoid") -> MergedDetections:
    """Merge M pooled detections by DBSCAN on `1 − BEV IoU` (Algorithm 2; module docstring).

    boxes [M, 9] final boxes; scores [M] scores of their labels; labels [M] int class index;
    eps in (0, 1): neighbours have IoU >= 1 − eps; min_samples >= 1: DBSCAN's core-point
    count (self included); classwise: cluster each label separately; noise: "keep" (single
    clusters) or "drop"; dims: box fields of the covariances; layer_logits [M, L, C'] and
    layer_boxes [M, L, 9]: optional per-layer outputs, merged too (needed to write a dump);
    score_mode: "sigmoid" or "softmax" (how the logits are averaged).
    """
    data = check_inputs(boxes, scores, labels, layer_logits, layer_boxes, dims, score_mode)
    radius = float(eps)
    if not 0.0 < radius < 1.0:
        raise ValueError(f"eps must be in (0, 1) (a 1 − IoU distance), got {eps}")
    if isinstance(min_samples, bool) or int(min_samples) != min_samples or min_samples < 1:
        raise ValueError(f"min_samples must be an integer >= 1, got {min_samples}")
    check_choice("noise", noise, NOISE_MODES)
    parts = np.unique(data.labels) if classwise else np.zeros(1, dtype=np.int64)
    cluster = np.full(len(data.scores), -1, dtype=np.int64)
    next_id = 0
    for part in parts:
        rows = np.flatnonzero(data.labels == part) if classwise else np.arange(len(cluster))
        if len(rows) == 0:
            continue
        found = _dbscan(data.boxes[rows], radius, int(min_samples))
        if noise == "keep":
            lone = found < 0
            found[lone] = found.max(initial=-1) + 1 + np.arange(int(lone.sum()))
        cluster[rows] = np.where(found >= 0, found + next_id, -1)
        next_id += int(found.max(initial=-1)) + 1
    return summarise(data, cluster)


def _dbscan(boxes: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """DBSCAN labels `[m]` (−1 = noise) of boxes `[m, 9]` on the distance 1 − BEV IoU."""
    distance = 1.0 - pairwise_bev_iou(boxes)
    np.fill_diagonal(distance, 0.0)
    model = DBSCAN(eps=eps, min_samples=min_samples, metric="precomputed")
    return model.fit_predict(distance).astype(np.int64)
