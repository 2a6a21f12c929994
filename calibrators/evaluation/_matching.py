"""nuScenes detection matching (devkit `accumulate`), vectorised over all classes and frames.

The rule, exactly as `nuscenes.eval.detection.algo.accumulate` applies it per class:
predictions of a class are pooled over all frames and visited by descending score; each takes
the nearest ground truth of the same class and frame that no earlier prediction took (2D centre
distance, ties to the first ground truth in input order); it is a true positive iff that
distance is `< threshold`, and only then is the ground truth taken.

Ties in score are ordered as the devkit orders them when its boxes are listed frame by frame
(frame index ascending) and in input order within a frame: it sorts `(score, position)` pairs
ascending and reverses, so among equal scores the *later* box comes first.

Vectorisation: a ground truth at distance `>= threshold` can never be taken, so only candidate
pairs closer than the threshold matter: every same-class, same-frame pair, or those a k-d tree
finds when there are too many.
The greedy pass then runs in rounds over all groups at once: a prediction's best remaining
candidate is final as soon as no earlier unresolved prediction still has that ground truth as a
candidate. Each round resolves at least the earliest open prediction of every group, and in
practice a handful of rounds resolve everything.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from calibrators.core.checks import as_float_array, as_int_array, check_length, check_positive
from calibrators.core.defaults import MATCH_THRESHOLD

# nuScenes `detection_cvpr_2019` class ranges in metres (BEV distance from the ego).
DEFAULT_CLASS_RANGE: Mapping[str, float] = {
    "car": 50.0, "truck": 50.0, "bus": 50.0, "trailer": 50.0, "construction_vehicle": 50.0,
    "pedestrian": 40.0, "motorcycle": 40.0, "bicycle": 40.0,
    "traffic_cone": 30.0, "barrier": 30.0,
}


# Above this many same-class, same-frame (detection, ground truth) pairs, candidates come from a
# k-d tree instead of enumerating every pair.
DENSE_PAIR_LIMIT = 2_000_000


class MatchResult(NamedTuple):
    """Outcome of `match` for each of the N detections.

    gt_index  [N] int64   matched ground-truth row, -1 if unmatched
    distance  [N] float   2D centre distance to the matched ground truth, inf if unmatched
    tp        [N] bool    True iff matched (distance < threshold)
    """

    gt_index: np.ndarray
    distance: np.ndarray
    tp: np.ndarray


class Candidates(NamedTuple):
    """Candidate (detection, ground truth) pairs of the same class and frame within a radius.

    det, gt [P] int64 rows; distance [P] float; sorted by (detection rank, distance, gt).
    """

    det: np.ndarray
    gt: np.ndarray
    distance: np.ndarray


def match(det_frame: np.ndarray, det_labels: np.ndarray, det_scores: np.ndarray,
          det_xy: np.ndarray, gt_frame: np.ndarray, gt_labels: np.ndarray, gt_xy: np.ndarray,
          threshold: float = MATCH_THRESHOLD) -> MatchResult:
    """Match detections to ground truth by the nuScenes devkit rule (see the module docstring).

    det_frame [N] int, det_labels [N] int, det_scores [N] float, det_xy [N, 2] float;
    gt_frame [G] int, gt_labels [G] int, gt_xy [G, 2] float; `threshold` in metres (> 0).
    """
    det_frame = as_int_array("det_frame", det_frame)
    n = len(det_frame)
    det_labels = as_int_array("det_labels", det_labels)
    det_scores = as_float_array("det_scores", det_scores, ndim=1)
    det_xy = _xy("det_xy", det_xy)
    for name, arr in (("det_labels", det_labels), ("det_scores", det_scores), ("det_xy", det_xy)):
        check_length(name, arr, n, "det_frame")
    gt_frame = as_int_array("gt_frame", gt_frame)
    gt_labels = as_int_array("gt_labels", gt_labels)
    gt_xy = _xy("gt_xy", gt_xy)
    check_length("gt_labels", gt_labels, len(gt_frame), "gt_frame")
    check_length("gt_xy", gt_xy, len(gt_frame), "gt_frame")
    threshold = _threshold(threshold)
    for name, arr in (("det_frame", det_frame), ("det_labels", det_labels),
                      ("gt_frame", gt_frame), ("gt_labels", gt_labels)):
        if arr.size and arr.min() < 0:
            raise ValueError(f"{name}[{int(np.argmin(arr))}] is negative")

    rank = devkit_rank(det_scores, det_frame)
    pairs = candidate_pairs(rank, det_frame, det_labels, det_xy, gt_frame, gt_labels, gt_xy,
                            threshold)
    return greedy_match(rank, pairs, threshold, len(gt_frame))


def devkit_rank(scores: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """`[N]` int64 position of each detection in the devkit's visiting order (0 = first).

    Descending score; ties by descending (frame, input index), as the devkit's reversed sort.
    """
    order = np.lexsort((np.arange(len(scores)), frame, scores))[::-1]
    rank = np.empty(len(scores), dtype=np.int64)
    rank[order] = np.arange(len(scores))
    return rank


def candidate_pairs(rank: np.ndarray, det_frame: np.ndarray, det_labels: np.ndarray,
                    det_xy: np.ndarray, gt_frame: np.ndarray, gt_labels: np.ndarray,
                    gt_xy: np.ndarray, radius: float) -> Candidates:
    """All same-class, same-frame pairs with centre distance `< radius`, sorted for matching."""
    empty = np.zeros(0, dtype=np.int64)
    if len(rank) == 0 or len(gt_frame) == 0:
        return Candidates(empty, empty, np.zeros(0))
    n_frames = int(max(det_frame.max(), gt_frame.max())) + 1
    det_key = det_labels * n_frames + det_frame
    gt_key = gt_labels * n_frames + gt_frame
    gt_order = np.argsort(gt_key, kind="stable")
    sorted_key = gt_key[gt_order]
    lo = np.searchsorted(sorted_key, det_key, side="left")
    counts = np.searchsorted(sorted_key, det_key, side="right") - lo
    total = int(counts.sum())
    if total <= DENSE_PAIR_LIMIT:
        det = np.repeat(np.arange(len(det_key)), counts)
        start = np.repeat(lo - (np.cumsum(counts) - counts), counts)
        gt = gt_order[start + np.arange(total)]
    else:
        det, gt = _tree_pairs(det_key, det_xy, gt_key, gt_xy, radius)
    distance = center_distance(det_xy[det], gt_xy[gt])
    keep = distance < radius
    det, gt, distance = det[keep], gt[keep], distance[keep]
    order = np.lexsort((gt, distance, rank[det]))
    return Candidates(det[order], gt[order], distance[order])


def _tree_pairs(det_key: np.ndarray, det_xy: np.ndarray, gt_key: np.ndarray, gt_xy: np.ndarray,
                radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Same-group pairs within about `radius` from one k-d tree over (x, y, group).

    Groups sit a whole number of radii apart on the third axis, so no pair crosses groups;
    the caller recomputes exact distances.
    """
    spacing = float(np.ceil(radius)) + 1.0
    det_tree = cKDTree(np.column_stack([det_xy, det_key * spacing]))
    gt_tree = cKDTree(np.column_stack([gt_xy, gt_key * spacing]))
    slack = radius * (1.0 + 1e-9) + 1e-9
    found = det_tree.sparse_distance_matrix(gt_tree, slack, output_type="ndarray")
    det = found["i"].astype(np.int64)
    gt = found["j"].astype(np.int64)
    keep = det_key[det] == gt_key[gt]
    return det[keep], gt[keep]


def center_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`[M]` BEV centre distance between rows of `a` and `b` (`[M, 2]` each), as the devkit
    (its per-pair `np.linalg.norm`, a dot product, may differ in the last bit: with numpy
    2.4.6, 8 % of random pairs are one ulp apart)."""
    d = a - b
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])


def greedy_match(rank: np.ndarray, pairs: Candidates, threshold: float,
                 n_gt: int) -> MatchResult:
    """Resolve the devkit's greedy matching from candidate pairs (any radius >= threshold)."""
    n = len(rank)
    gt_index = np.full(n, -1, dtype=np.int64)
    distance = np.full(n, np.inf)
    keep = pairs.distance < threshold
    det, gt, dist = pairs.det[keep], pairs.gt[keep], pairs.distance[keep]
    det_rank = rank[det]
    while len(det):
        # Pairs are sorted by (rank, distance, gt): a detection's first pair is its best.
        best = np.ones(len(det), dtype=bool)
        best[1:] = det[1:] != det[:-1]
        # The earliest open detection that still wants each ground truth.
        first_rank = np.full(n_gt, np.iinfo(np.int64).max)
        np.minimum.at(first_rank, gt, det_rank)
        win = best & (first_rank[gt] == det_rank)
        gt_index[det[win]] = gt[win]
        distance[det[win]] = dist[win]
        taken = np.zeros(n_gt, dtype=bool)
        taken[gt[win]] = True
        done = np.zeros(n, dtype=bool)
        done[det[win]] = True
        alive = ~(taken[gt] | done[det])
        det, gt, dist, det_rank = det[alive], gt[alive], dist[alive], det_rank[alive]
    return MatchResult(gt_index, distance, gt_index >= 0)


def in_range(xy: np.ndarray, ego_xy: np.ndarray, labels: np.ndarray, classes: Sequence[str],
             class_range: Mapping[str, float] | None = DEFAULT_CLASS_RANGE) -> np.ndarray:
    """`[N]` bool: BEV distance from the ego `< class_range[class]` (devkit filter_eval_boxes).

    xy [N, 2], ego_xy [N, 2], labels [N] int into `classes`. Classes absent from `class_range`
    (or `class_range=None`) are not filtered.
    """
    xy = _xy("xy", xy)
    ego_xy = _xy("ego_xy", ego_xy)
    labels = as_int_array("labels", labels)
    check_length("ego_xy", ego_xy, len(xy), "xy")
    check_length("labels", labels, len(xy), "xy")
    limits = class_limits(classes, class_range)
    if len(labels) and (labels.min() < 0 or labels.max() >= len(classes)):
        raise ValueError(f"labels must index {len(classes)} classes")
    return center_distance(xy, ego_xy) < limits[labels]


def class_limits(classes: Sequence[str], class_range: Mapping[str, float] | None) -> np.ndarray:
    """`[C]` range per class (inf where `class_range` has none); ranges must be > 0."""
    if class_range is None:
        return np.full(len(classes), np.inf)
    for name, value in class_range.items():
        if not float(value) > 0:
            raise ValueError(f"class_range[{name!r}] must be > 0, got {value}")
    return np.array([float(class_range.get(c, np.inf)) for c in classes])


def _xy(name: str, value: np.ndarray) -> np.ndarray:
    arr = as_float_array(name, value, ndim=2)
    if arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape [N, 2], got {arr.shape}")
    return arr


def _threshold(threshold: float) -> float:
    return check_positive("threshold", threshold)
