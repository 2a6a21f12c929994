"""One merged detection per cluster of stochastic detections (shared by both merging methods).

Given `M` detections pooled from N stochastic outputs of one frame (MC-dropout passes,
ensemble members, sub-ensemble heads) and a cluster id per detection, `summarise` reduces
every cluster to one detection (thesis 4.2):

- box: the mean of the members' boxes; `yaw` is averaged on the circle
  (`atan2(Σ sin, Σ cos)`, so 179° and −179° average to 180°, not 0°; two exactly opposite
  yaws have no mean direction and give 0);
- score: the mean of the members' scores;
- label: majority vote; ties go to the tied label with the larger summed score, then to the
  smaller class index;
- covariance `[D, D]` over `dims`: the sample covariance (ddof = 1) of the members' boxes,
  yaw deviations wrapped to (−π, π] around the circular mean. A single-member cluster has no
  spread to measure: its covariance is all zeros (never NaN) and `n_members == 1` flags it;
  depth scaling (`Σ + k·d·I`) then gives it a proper covariance;
- per-layer logits `[L, C']` (optional): the members' class distributions are averaged in
  probability space, layer by layer (thesis Eq. 2-15), and written back as logits:
  sigmoid `logit(mean σ(z))` per column, softmax `log(mean softmax(z))` (defined up to a
  constant per row, which softmax ignores). Computed with log-sum-exp, always finite;
- per-layer boxes `[L, 9]` (optional): averaged layer by layer like the box.

Merged detections are ordered by descending score (stable).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import log_expit, log_softmax

from calibrators.core.checks import as_float_array, as_int_array, check_choice, check_length
from calibrators.core.vocab import BOX_INDEX as DIM_INDEX
from calibrators.core.vocab import SCORE_MODES, wrap_angle
from calibrators.covariance import dim_indices
from detectors.baselines.bev_iou import check_boxes

_YAW = DIM_INDEX["yaw"]


@dataclass(frozen=True, eq=False)
class MergedDetections:
    """K merged detections of one frame, from M input detections.

    boxes [K, 9]; scores [K]; labels [K] int64; covariances [K, D, D] over `dims` (zeros where
    `n_members == 1`); n_members [K] int64; cluster [M] int64: the merged detection each input
    went to, −1 if it was dropped; dims: the D box fields of the covariances;
    layer_logits [K, L, C'] | None; layer_boxes [K, L, 9] | None.
    """

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray
    covariances: np.ndarray
    n_members: np.ndarray
    cluster: np.ndarray
    dims: tuple[str, ...]
    layer_logits: np.ndarray | None = None
    layer_boxes: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.scores)


@dataclass(frozen=True)
class Inputs:
    """Validated merge inputs: boxes [M, 9], scores [M], labels [M], optional per-layer arrays."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray
    layer_logits: np.ndarray | None
    layer_boxes: np.ndarray | None
    dims: tuple[str, ...]
    score_mode: str


def check_inputs(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray,
                 layer_logits: np.ndarray | None, layer_boxes: np.ndarray | None,
                 dims: Sequence[str], score_mode: str) -> Inputs:
    """Validate the arrays every merge takes; errors name the argument."""
    box = check_boxes("boxes", boxes)
    if box.shape[1] != 9:
        raise ValueError(f"boxes must have shape [M, 9], got {box.shape}")
    m = len(box)
    score = as_float_array("scores", scores, ndim=1)
    check_length("scores", score, m, "boxes")
    label = as_int_array("labels", labels)
    check_length("labels", label, m, "boxes")
    if label.size and label.min() < 0:
        raise ValueError(f"labels[{int(np.argmin(label))}] is negative")
    dims = tuple(dims)
    dim_indices(dims)
    check_choice("score_mode", score_mode, SCORE_MODES)
    logits = None
    if layer_logits is not None:
        logits = as_float_array("layer_logits", layer_logits, ndim=3)
        check_length("layer_logits", logits, m, "boxes")
    lboxes = None
    if layer_boxes is not None:
        lboxes = as_float_array("layer_boxes", layer_boxes, ndim=3)
        check_length("layer_boxes", lboxes, m, "boxes")
        if lboxes.shape[2] != 9:
            raise ValueError(f"layer_boxes must have shape [M, L, 9], got {lboxes.shape}")
    return Inputs(box, score, label, logits, lboxes, dims, score_mode)


def summarise(data: Inputs, cluster: np.ndarray) -> MergedDetections:
    """Merge `data` by `cluster [M]` (any int ids; −1 = drop the detection); module docstring."""
    keep = np.flatnonzero(cluster >= 0)
    k = np.unique(cluster[keep], return_inverse=True)[1]
    order = np.argsort(k, kind="stable")
    rows, k = keep[order], k[order]
    starts = np.flatnonzero(np.r_[True, np.diff(k) != 0]) if len(k) else np.zeros(0, int)
    n = np.diff(np.r_[starts, len(k)]).astype(np.int64)

    boxes = _mean_boxes(data.boxes[rows], starts, n)
    scores = np.add.reduceat(data.scores[rows], starts) / n if len(n) else np.zeros(0)
    labels = _vote(data.labels[rows], data.scores[rows], k, len(n))
    cov = _covariance(data.boxes[rows], boxes, k, n, dim_indices(data.dims))
    logits = None
    if data.layer_logits is not None:
        logits = _mean_distribution(data.layer_logits[rows], starts, n, data.score_mode)
    lboxes = None
    if data.layer_boxes is not None:
        lboxes = _mean_boxes(data.layer_boxes[rows], starts, n)

    rank = np.argsort(-scores, kind="stable")
    new_index = np.empty(len(rank), dtype=np.int64)
    new_index[rank] = np.arange(len(rank))
    out_cluster = np.full(len(cluster), -1, dtype=np.int64)
    out_cluster[rows] = new_index[k]
    return MergedDetections(
        boxes=boxes[rank], scores=scores[rank], labels=labels[rank], covariances=cov[rank],
        n_members=n[rank], cluster=out_cluster, dims=data.dims,
        layer_logits=None if logits is None else logits[rank],
        layer_boxes=None if lboxes is None else lboxes[rank])


def _mean_boxes(boxes: np.ndarray, starts: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Cluster means `[K, ..., 9]` of boxes `[M, ..., 9]` sorted by cluster (yaw on the circle)."""
    if len(n) == 0:
        return np.zeros((0, *boxes.shape[1:]))
    mean = np.add.reduceat(boxes, starts, axis=0) / n.reshape(-1, *[1] * (boxes.ndim - 1))
    mean[..., _YAW] = np.arctan2(np.add.reduceat(np.sin(boxes[..., _YAW]), starts, axis=0),
                                 np.add.reduceat(np.cos(boxes[..., _YAW]), starts, axis=0))
    return mean


def _vote(labels: np.ndarray, scores: np.ndarray, k: np.ndarray, n_clusters: int) -> np.ndarray:
    """Majority label `[K]`; ties: larger summed score, then smaller label."""
    if n_clusters == 0:
        return np.zeros(0, dtype=np.int64)
    width = int(labels.max()) + 1
    votes = np.zeros((n_clusters, width))
    mass = np.zeros((n_clusters, width))
    np.add.at(votes, (k, labels), 1.0)
    np.add.at(mass, (k, labels), scores)
    tied = votes == votes.max(axis=1, keepdims=True)
    return np.argmax(np.where(tied, mass, -np.inf), axis=1).astype(np.int64)


def _covariance(boxes: np.ndarray, means: np.ndarray, k: np.ndarray, n: np.ndarray,
                cols: list[int]) -> np.ndarray:
    """Sample covariance `[K, D, D]` (ddof = 1) per cluster; zeros for single members."""
    dev = boxes[:, cols] - means[k][:, cols]
    for j, c in enumerate(cols):
        if c == _YAW:
            dev[:, j] = wrap_angle(dev[:, j])
    cov = np.zeros((len(n), len(cols), len(cols)))
    np.add.at(cov, k, dev[:, :, None] * dev[:, None, :])
    return cov / np.maximum(n - 1, 1)[:, None, None]


def _mean_distribution(layer_logits: np.ndarray, starts: np.ndarray, n: np.ndarray,
                       score_mode: str) -> np.ndarray:
    """Logits `[K, L, C']` of the members' mean class distribution, layer by layer."""
    if len(n) == 0:
        return np.zeros((0, *layer_logits.shape[1:]))
    log_n = np.log(n)[:, None, None]

    def log_mean(logp: np.ndarray) -> np.ndarray:
        """log of the cluster mean of exp(logp): a log-sum-exp per cluster, `[K, L, C']`."""
        peak = np.maximum.reduceat(logp, starts, axis=0)
        total = np.add.reduceat(np.exp(logp - np.repeat(peak, n, axis=0)), starts, axis=0)
        return peak + np.log(total) - log_n

    if score_mode == "sigmoid":
        return log_mean(log_expit(layer_logits)) - log_mean(log_expit(-layer_logits))
    return log_mean(log_softmax(layer_logits, axis=2))
