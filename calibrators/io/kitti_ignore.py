"""KITTI's evaluation rules for what is neither a true nor a false positive.

KITTI's devkit (`evaluate_object.cpp`, `cleanData` / `computeStatistics`) evaluates one class
at a time and ignores, rather than counts:

- a detection assigned to a ground truth of the class's *neighbouring* class (`Van` for `Car`,
  `Person_sitting` for `Pedestrian`): such a ground truth is "ignored", neither a miss when
  undetected nor a true positive when detected, and the detection on it counts for nothing;
- a detection assigned to no ground truth whose 2D image box lies in a `DontCare` region:
  its intersection with the region over its own area (the devkit's `boxoverlap(det, dc, 0)`)
  above the class's minimum overlap (0.7 for Car, 0.5 otherwise).

With a difficulty level (`easy`, `moderate`, `hard`), the devkit's `cleanData` also ignores
ground truth of the class that is too small, occluded or truncated for the level (2D height
<= 40 / 25 / 25 px, occlusion > 0 / 1 / 2, truncation > 0.15 / 0.30 / 0.50): a detection on
it counts for nothing and it is no miss; and detections lower than the level's minimum
height. Without one, every box counts.

Ground truth of other classes (`Truck`, `Tram`, `Misc`, ... when not among the classes) is
not ground truth and no ignore region: a detection on it is a false positive, as in KITTI.

A `Dump` has no "ignored" state, so `ignored_detections` finds these detections and the
reader drops them. Assignment follows detcal's matching (the nuScenes rule: by score, nearest
BEV centre within `threshold`), against the class's ground truth and its neighbours' pooled.
"""

from __future__ import annotations

import numpy as np

from calibrators.evaluation import match

#: KITTI class -> its neighbouring class, whose ground truth is ignored for it.
NEIGHBOURS = {"Car": "Van", "Pedestrian": "Person_sitting"}
#: Minimum DontCare overlap per KITTI class (the devkit's MIN_OVERLAP); others: 0.5.
DONTCARE_OVERLAP = {"Car": 0.7}
#: KITTI's difficulty levels: (MIN_HEIGHT px, MAX_OCCLUSION, MAX_TRUNCATION) of the devkit.
DIFFICULTY = {"easy": (40.0, 0, 0.15), "moderate": (25.0, 1, 0.30), "hard": (25.0, 2, 0.50)}


def too_hard(bbox: np.ndarray, occluded: np.ndarray, truncated: np.ndarray,
             level: str | None) -> np.ndarray:
    """`[M]` bool: ground truth KITTI ignores at difficulty `level` (None: none), from its 2D
    boxes `[M, 4]` (left top right bottom), occlusion `[M]` and truncation `[M]`."""
    if level is None:
        return np.zeros(len(bbox), dtype=bool)
    min_height, max_occlusion, max_truncation = DIFFICULTY[level]
    height = np.abs(bbox[:, 3] - bbox[:, 1])
    return (occluded > max_occlusion) | (truncated > max_truncation) | (height <= min_height)


def too_small(bbox: np.ndarray, level: str | None) -> np.ndarray:
    """`[N]` bool: detections below the minimum 2D height of `level` (None: none)."""
    if level is None:
        return np.zeros(len(bbox), dtype=bool)
    return np.abs(bbox[:, 3] - bbox[:, 1]) < DIFFICULTY[level][0]


def ignored_detections(det_frame: np.ndarray, det_labels: np.ndarray, det_scores: np.ndarray,
                       det_xy: np.ndarray, det_bbox: np.ndarray, det_min_overlap: np.ndarray,
                       gt_frame: np.ndarray, gt_labels: np.ndarray, gt_xy: np.ndarray,
                       gt_ignored: np.ndarray, dc_frame: np.ndarray, dc_bbox: np.ndarray,
                       threshold: float) -> np.ndarray:
    """`[N]` bool: detections KITTI's evaluation neither counts as true nor false positives.

    det_* `[N]` (xy `[N, 2]`, bbox `[N, 4]` left top right bottom px, min_overlap `[N]`);
    gt_* `[G]` with `gt_ignored` True for neighbouring-class ground truth (already labelled
    with the class it neighbours); dc_frame `[K]`, dc_bbox `[K, 4]` the DontCare regions.
    """
    n = len(det_frame)
    result = match(det_frame, det_labels, det_scores, det_xy, gt_frame, gt_labels, gt_xy,
                   threshold=threshold)
    matched = result.gt_index
    on_neighbour = (matched >= 0) & gt_ignored[np.maximum(matched, 0)] if len(gt_ignored) \
        else np.zeros(n, dtype=bool)
    in_dontcare = np.zeros(n, dtype=bool)
    free = np.flatnonzero(matched < 0)
    for k in range(len(dc_frame)):
        rows = free[det_frame[free] == dc_frame[k]]
        if len(rows):
            overlap = _overlap_over_first(det_bbox[rows], dc_bbox[k])
            in_dontcare[rows[overlap > det_min_overlap[rows]]] = True
    return on_neighbour | in_dontcare


def _overlap_over_first(boxes: np.ndarray, region: np.ndarray) -> np.ndarray:
    """`[M]` area of `boxes [M, 4]` inside `region [4]` over each box's own area (0 when a
    box has no area), boxes as left, top, right, bottom."""
    width = np.clip(np.minimum(boxes[:, 2], region[2]) - np.maximum(boxes[:, 0], region[0]),
                    0.0, None)
    height = np.clip(np.minimum(boxes[:, 3], region[3]) - np.maximum(boxes[:, 1], region[1]),
                     0.0, None)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return np.where(area > 0, width * height / np.where(area > 0, area, 1.0), 0.0)
