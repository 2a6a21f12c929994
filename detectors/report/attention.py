"""Seed 000's attention-spread analysis on a bundled detector (test split, vanilla passes).

C_K is the weighted covariance of a query's top-K (6) cross-attention cells
(`detectors.uncertainty.attention_spread`). Our token grid is coarse (3.2 m cells) and a
trained decoder often puts almost all of a query's top-K attention on one cell or on cells
along one line, where det C_K is 0 up to float noise; so the spread reported is
AS = det(C_K + cell²/12 · I) (m⁴), with the same within-cell variance the dump writer adds
to the attention covariance (floor (cell²/12)² for a single-cell query), and each group also
gives the share of *rank-deficient* queries (raw det C_K below 1e-6 of that floor).
Detections taking part: raw final-layer score >= `min_score` (0.3 by default; most of the
100 kept queries are background). Three statistics, each as median and 25th / 75th percentiles:

- vs IoU (seed 000 Fig. 3): BEV IoU of the final box with the closest ground truth of its
  frame (by centre distance), IoU 0 left out, 10 bins of width 0.1; final-layer AS;
- vs distance from the ego (Fig. 4 uses a 20 × 20 BEV map; we bin the BEV distance in
  10 m rings); final-layer AS;
- per decoder layer (Fig. 5).

`box_errors` says what sets a kept box's IoU: its centre, yaw, length and width errors
against that closest ground truth (`detectors.report.iou_bins` sets them beside AS).

`Binned` holds one statistic: labels [B] str, n [B], p25 / median / p75 [B] (NaN if empty),
collapsed [B] share of rank-deficient queries (NaN if empty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators import Dump
from detectors.baselines import paired_bev_iou

IOU_EDGES = np.round(np.linspace(0.0, 1.0, 11), 1)
DISTANCE_EDGES = np.arange(0.0, 80.0, 10.0)


@dataclass(frozen=True)
class Binned:
    """Median and quartiles of a quantity in B groups (module docstring)."""

    labels: tuple[str, ...]
    n: np.ndarray
    p25: np.ndarray
    median: np.ndarray
    p75: np.ndarray
    collapsed: np.ndarray


@dataclass(frozen=True)
class AttentionStats:
    """The three seed-000 statistics and how many detections took part."""

    vs_iou: Binned
    vs_distance: Binned
    per_layer: Binned
    n_detections: int
    min_score: float
    # The rows behind vs_iou and vs_distance (for bootstrap intervals of their trends):
    # final-layer AS [n] of the kept detections, their IoU bin [n] (-1: IoU 0, left out)
    # and distance bin [n]; and the values binned: IoU [n] with the closest ground truth
    # and distance [n] from the ego (m).
    final_as: np.ndarray | None = None
    iou_bin: np.ndarray | None = None
    distance_bin: np.ndarray | None = None
    iou: np.ndarray | None = None
    distance: np.ndarray | None = None
    # How far each kept final box is from that closest ground truth (what sets its IoU).
    errors: BoxErrors | None = None


def spread(cov: np.ndarray) -> np.ndarray:
    """AS = det C `[...]` of covariances `[..., 2, 2]`."""
    return cov[..., 0, 0] * cov[..., 1, 1] - cov[..., 0, 1] * cov[..., 1, 0]


def closest_gt_index(dump: Dump) -> np.ndarray:
    """`[N]` index into `dump.gt_*` of the ground truth of its frame closest (BEV centre
    distance) to each final box; -1 where the frame has no ground truth."""
    index = np.full(dump.n_detections, -1, dtype=np.int64)
    for f in range(dump.n_frames):
        det = np.flatnonzero(dump.det_frame == f)
        gt = np.flatnonzero(dump.gt_frame == f)
        if len(det) == 0 or len(gt) == 0:
            continue
        diff = dump.final_boxes[det, None, :2] - dump.gt_boxes[None, gt, :2]   # [n, g, 2]
        index[det] = gt[np.argmin(np.hypot(diff[..., 0], diff[..., 1]), axis=1)]
    return index


def closest_gt_iou(dump: Dump, index: np.ndarray | None = None) -> np.ndarray:
    """`[N]` BEV IoU of each final box with the closest ground truth (centre distance) of
    its frame; 0 where the frame has no ground truth. `index` is `closest_gt_index(dump)`
    when the caller has it."""
    index = closest_gt_index(dump) if index is None else index
    iou = np.zeros(dump.n_detections)
    has = index >= 0
    if has.any():
        iou[has] = paired_bev_iou(dump.final_boxes[has], dump.gt_boxes[index[has]])
    return iou


@dataclass(frozen=True)
class BoxErrors:
    """How far each box is from the ground truth closest to its final box
    (`closest_gt_index`), NaN where the frame has no ground truth: `layer_centre [n, L]` the
    BEV centre distance of every decoder layer's box (m), and of the final box `yaw`
    |difference| wrapped to [0, pi] (rad), `length` and `width` |difference| (m), `[n]`
    each; `centre [n]` is the final layer's column of `layer_centre`."""

    layer_centre: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """`[n]` BEV centre distance of the final box (m)."""
        return self.layer_centre[:, -1]

    def select(self, rows: np.ndarray) -> BoxErrors:
        """The errors of `rows` (bool mask or indices)."""
        return BoxErrors(self.layer_centre[rows], self.yaw[rows], self.length[rows],
                         self.width[rows])


def box_errors(dump: Dump, index: np.ndarray | None = None) -> BoxErrors:
    """`BoxErrors` of `dump`'s final boxes (`index` as in `closest_gt_iou`)."""
    index = closest_gt_index(dump) if index is None else index
    has = index >= 0
    det, gt = dump.final_boxes[has], dump.gt_boxes[index[has]]
    layers = np.full(dump.det_boxes.shape[:2], np.nan)                       # [N, L]
    diff = dump.det_boxes[has, :, :2] - gt[:, None, :2]
    layers[has] = np.hypot(diff[..., 0], diff[..., 1])
    out = np.full((3, dump.n_detections), np.nan)
    out[0, has] = np.abs((det[:, 6] - gt[:, 6] + np.pi) % (2 * np.pi) - np.pi)
    out[1, has] = np.abs(det[:, 4] - gt[:, 4])
    out[2, has] = np.abs(det[:, 3] - gt[:, 3])
    return BoxErrors(layers, *out)


def binned(values: np.ndarray, groups: np.ndarray, n_groups: int, labels: tuple[str, ...],
           collapsed: np.ndarray | None = None) -> Binned:
    """Median and quartiles of `values [N]` per group index `groups [N]` in [0, n_groups),
    and the mean of the bool `collapsed [N]` per group (NaN without it)."""
    n = np.zeros(n_groups, dtype=np.int64)
    q = np.full((4, n_groups), np.nan)
    for b in range(n_groups):
        rows = groups == b
        n[b] = int(rows.sum())
        if n[b]:
            q[:3, b] = np.percentile(values[rows], [25, 50, 75])
            if collapsed is not None:
                q[3, b] = float(np.mean(collapsed[rows]))
    return Binned(labels=labels, n=n, p25=q[0], median=q[1], p75=q[2], collapsed=q[3])


def attention_stats(dump: Dump, attn_cov: np.ndarray, cell: float, min_score: float = 0.3
                    ) -> AttentionStats:
    """Seed 000's statistics of `dump`'s detections; `attn_cov [N, L, 2, 2]` raw C_K per
    layer, `cell` the token cell size in metres."""
    if attn_cov.shape[:1] != (dump.n_detections,):
        raise ValueError(f"attn_cov has {attn_cov.shape[0]} rows but the dump has "
                         f"{dump.n_detections} detections")
    keep = dump.det_scores >= min_score
    floor = cell ** 2 / 12.0
    as_layers = spread(attn_cov[keep] + np.eye(2) * floor)         # [n, L]
    single = spread(attn_cov[keep]) < 1e-6 * floor ** 2             # [n, L] rank-deficient
    final, final_single = as_layers[:, -1], single[:, -1]
    index = closest_gt_index(dump)
    iou = closest_gt_iou(dump, index)[keep]
    positive = iou > 0
    iou_bin = np.minimum((iou[positive] * 10).astype(int), 9)
    iou_labels = tuple(f"{a:.1f}-{b:.1f}" for a, b in zip(IOU_EDGES[:-1], IOU_EDGES[1:],
                                                           strict=True))
    dist = dump.det_distance[keep]
    d_bin = np.minimum(np.searchsorted(DISTANCE_EDGES, dist, side="right") - 1,
                       len(DISTANCE_EDGES) - 1)
    d_labels = tuple([f"{int(a)}-{int(b)} m" for a, b in
                      zip(DISTANCE_EDGES[:-1], DISTANCE_EDGES[1:], strict=True)]
                     + [f">= {int(DISTANCE_EDGES[-1])} m"])
    n_layers = attn_cov.shape[1]
    layer_values = as_layers.T.reshape(-1)
    layer_groups = np.repeat(np.arange(n_layers), as_layers.shape[0])
    return AttentionStats(
        vs_iou=binned(final[positive], iou_bin, 10, iou_labels, final_single[positive]),
        vs_distance=binned(final, d_bin, len(d_labels), d_labels, final_single),
        per_layer=binned(layer_values, layer_groups, n_layers,
                         tuple(f"layer {i + 1}" for i in range(n_layers)),
                         single.T.reshape(-1)),
        n_detections=int(keep.sum()), min_score=float(min_score), final_as=final,
        iou_bin=np.where(positive, np.minimum((iou * 10).astype(int), 9), -1),
        distance_bin=d_bin, iou=iou, distance=dist,
        errors=box_errors(dump, index).select(keep))
