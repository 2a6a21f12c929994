"""Sampling baselines for uncertainty (thesis 2.6, 4.2, 4.3): merging of N stochastic outputs.

MC dropout, deep ensembles and deep sub-ensembles all produce N sets of detections per frame;
these functions merge them into one set with a cluster covariance (numpy, shapely, sklearn):

- `iou_merge`: IoU-and-average merging over given clusters (Algorithm 1);
- `dbscan_merge`: class-wise DBSCAN on `1 − BEV IoU` (Algorithm 2);
- `MergedDetections`: the result; `merged_dump` writes merged frames as a validation dump;
- `pairwise_bev_iou` / `paired_bev_iou`: rotated-box BEV IoU with shapely 2.
"""

from detectors.baselines.bev_iou import paired_bev_iou, pairwise_bev_iou
from detectors.baselines.cluster import MergedDetections
from detectors.baselines.dbscan_merge import NOISE_MODES, dbscan_merge
from detectors.baselines.iou_merge import iou_merge
from detectors.baselines.todump import merged_dump

__all__ = [
    "NOISE_MODES",
    "MergedDetections",
    "dbscan_merge",
    "iou_merge",
    "merged_dump",
    "paired_bev_iou",
    "pairwise_bev_iou",
]
