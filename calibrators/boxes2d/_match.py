"""COCO greedy matching (pycocotools `COCOeval.evaluateImg`, iouType='bbox'), vectorised over
every image, category, area range and IoU threshold at once.

The rule, per image x category, area range and threshold t: detections sorted by descending
score (a stable sort: ties keep input order) and cut to the first `MAX_DETS[-1]`; ground truth
*ignored* when it is a crowd, flagged `ignore`, or its `area` is outside the range. Each
detection in turn scans the ground truth, ignored boxes last, and takes the one of highest IoU
>= min(t, 1 - 1e-10) that no earlier detection took (a crowd can be taken again); an ignored
box is taken only when no unignored one qualifies, and among equal IoUs the later box in that
scan wins (pycocotools replaces its best on `>=`). A detection matched to an ignored box is
ignored, and so is an unmatched one whose own area `w·h` is outside the range.

Vectorisation: a detection's choice depends on earlier ones only through which boxes are
taken, so all groups advance together, one score rank per step (at most `MAX_DETS[-1]` steps).
Each step scores a detection's candidate pairs for all A x T (range, threshold) settings at
once: pairs are pre-sorted by (IoU, ground-truth row) within a detection, so the winner is the
last qualifying pair, unignored ones first, one `maximum.reduceat` per step. Pairs with IoU
below the smallest threshold can never match and are dropped up front.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from calibrators.boxes2d._iou import pair_iou
from calibrators.boxes2d._params import AREA_RANGES, IOU_CAP, IOU_THRESHOLDS, MAX_DETS

#: Detection x ground-truth pairs taken at once (whole image x category groups; a larger
#: group alone): bounds the memory, about 0.5 kB a pair for the A x T settings of a step.
PAIR_CHUNK = 250_000


class Ranked(NamedTuple):
    """The evaluated detections, the first `MAX_DETS[-1]` of each image x category group.

    rows [E] int64   their rows in the input, sorted by (group, rank)
    rank [E] int64   position in the group by descending score (ties: input order), 0 first
    """

    rows: np.ndarray
    rank: np.ndarray


class Matched(NamedTuple):
    """The outcome of `match` for the E ranked detections, each at its `slot`, as
    `evaluateImg` gives it: `dtMatches != 0` is `matched`, and `dtIgnore` is
    `matched & ~true_positive | ~matched & ~in_range`.

    matched [A, T, E] bool         matched to a ground truth, ignored or not
    true_positive [A, T, E] bool   matched to a ground truth that is not ignored
    in_range [A, E] bool           the detection's box area `w·h` inside each area range
    gt_ignored [A, G] bool         `gtIgnore` of each ground truth
    gt [A, T, E] int64 | None      the ground truth each detection took (its position in the
                                   ground-truth arrays given to `match`, -1 for none); only
                                   when `match` is asked for it (`with_gt`)
    """

    matched: np.ndarray
    true_positive: np.ndarray
    in_range: np.ndarray
    gt_ignored: np.ndarray
    gt: np.ndarray | None = None


def rank_detections(group: np.ndarray, score: np.ndarray,
                    max_det: int = MAX_DETS[-1]) -> Ranked:
    """Sort detections by (group, -score, row) and keep the first `max_det` of each group
    (`group [N]` int64, `score [N]` float64)."""
    rows = np.argsort(-score, kind="stable")
    rows = rows[np.argsort(group[rows], kind="stable")]
    sorted_group = group[rows]
    first = np.flatnonzero(np.r_[True, sorted_group[1:] != sorted_group[:-1]])
    rank = np.arange(len(rows)) - np.repeat(first, np.diff(np.r_[first, len(rows)]))
    keep = rank < max_det
    return Ranked(rows[keep], rank[keep])


def area_ignored(area: np.ndarray, area_ranges: Sequence[tuple[float, float]] = AREA_RANGES
                 ) -> np.ndarray:
    """`[A, N]` bool: `area [N]` outside each closed range of `area_ranges` (`[A]` pairs)."""
    bounds = np.asarray(area_ranges, dtype=np.float64).reshape(-1, 2)
    return (area[None, :] < bounds[:, :1]) | (area[None, :] > bounds[:, 1:])


def match(det_group: np.ndarray, det_rank: np.ndarray, det_box: np.ndarray,
          det_slot: np.ndarray, gt_group: np.ndarray, gt_box: np.ndarray, gt_area: np.ndarray,
          gt_crowd: np.ndarray, gt_ignore: np.ndarray, *,
          thresholds: np.ndarray = IOU_THRESHOLDS,
          area_ranges: Sequence[tuple[float, float]] = AREA_RANGES,
          with_gt: bool = False) -> Matched:
    """Match E ranked detections to G ground truths by the module's rule.

    det_group [E] int64 sorted, det_rank [E] (from `rank_detections`), det_box [E, 4],
    det_slot [E] a permutation: where each detection's results go (the accumulation's order);
    gt_group [G] int64, gt_box [G, 4], gt_area [G], gt_crowd [G] bool, gt_ignore [G] bool,
    in input order (the order ties between equal IoUs follow). `thresholds [T]` (in [0, 1])
    and `area_ranges` (`[A]` closed ranges) are the settings (default COCO's); `with_gt`
    also records which ground truth each detection took (`Matched.gt`).
    """
    thresholds = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    n_area, n_thr, n_det = len(area_ranges), len(thresholds), len(det_group)
    gt_ignored = area_ignored(gt_area, area_ranges) | (gt_crowd | gt_ignore)[None, :]
    matched = np.zeros((n_area, n_thr, n_det), dtype=bool)
    true_positive = np.zeros((n_area, n_thr, n_det), dtype=bool)
    taken_gt = np.full((n_area, n_thr, n_det), -1, dtype=np.int64) if with_gt else None
    if n_det and len(gt_group) and n_thr:
        taken = np.zeros((n_area, n_thr, len(gt_group)), dtype=bool)
        gt_order = np.argsort(gt_group, kind="stable")
        first = np.searchsorted(gt_group[gt_order], det_group, side="left")
        count = np.searchsorted(gt_group[gt_order], det_group, side="right") - first
        for lo, hi in _chunks(det_group, count):
            det = np.repeat(np.arange(lo, hi), count[lo:hi])
            start = np.repeat(first[lo:hi] - np.cumsum(count[lo:hi]) + count[lo:hi],
                              count[lo:hi])
            gt = gt_order[start + np.arange(len(det))]
            iou = pair_iou(det_box[det], gt_box[gt], gt_crowd[gt])
            keep = iou >= min(float(thresholds.min()), IOU_CAP)
            _greedy(det[keep], gt[keep], iou[keep], det_rank, det_slot, gt_crowd, gt_ignored,
                    taken, (matched, true_positive, taken_gt), thresholds)
    in_range = np.empty((n_area, n_det), dtype=bool)
    in_range[:, det_slot] = ~area_ignored(det_box[:, 2] * det_box[:, 3], area_ranges)
    return Matched(matched, true_positive, in_range, gt_ignored, taken_gt)


def _chunks(det_group: np.ndarray, count: np.ndarray) -> list[tuple[int, int]]:
    """Row ranges `[lo, hi)` of whole groups with about `PAIR_CHUNK` pairs each."""
    total = np.cumsum(count)
    out, lo = [], 0
    while lo < len(det_group):
        base = total[lo - 1] if lo else 0
        hi = max(int(np.searchsorted(total, base + PAIR_CHUNK, side="right")), lo + 1)
        if hi < len(det_group):  # end on a group boundary
            hi = int(np.searchsorted(det_group, det_group[hi - 1], side="right"))
        out.append((lo, hi))
        lo = hi
    return out


def _greedy(det: np.ndarray, gt: np.ndarray, iou: np.ndarray, det_rank: np.ndarray,
            det_slot: np.ndarray, gt_crowd: np.ndarray, gt_ignored: np.ndarray,
            taken: np.ndarray, out: tuple[np.ndarray, np.ndarray, np.ndarray | None],
            thresholds: np.ndarray) -> None:
    """Resolve candidate pairs `det, gt, iou [P]` rank by rank at `thresholds [T]`; updates
    `taken [A, T, G]` and `out` = (matched, true_positive, gt or None), each `[A, T, E]` (at
    each detection's slot), in place."""
    if len(det) == 0:
        return
    matched, true_positive, taken_gt = out
    n_area, n_thr = matched.shape[:2]
    threshold = np.minimum(thresholds, IOU_CAP)[None, :, None]  # [1, T, 1]
    rank = det_rank[det]
    order = np.lexsort((gt, iou, det, rank))
    det, gt, iou, rank = det[order], gt[order], iou[order], rank[order]
    bounds = np.flatnonzero(np.diff(rank)) + 1
    for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(rank)], strict=True):
        d, g = det[lo:hi], gt[lo:hi]
        n = hi - lo
        seg = np.flatnonzero(np.r_[True, d[1:] != d[:-1]])
        free = ~taken[:, :, g] | gt_crowd[g]
        qualifies = free & (iou[lo:hi] >= threshold)
        # Key of a qualifying pair: its position, plus n when its box is not ignored; the
        # segment maximum is then the scan's winner (unignored first, then IoU, then row).
        key = np.where(qualifies, np.arange(n) + n * ~gt_ignored[:, None, g], -1)
        best = np.maximum.reduceat(key.reshape(n_area * n_thr, n), seg, axis=1)
        a_t, s = np.nonzero(best >= 0)
        pair = best[a_t, s] % n
        a, t = np.divmod(a_t, n_thr)
        taken[a, t, g[pair]] = True
        slot = det_slot[d[seg[s]]]
        matched[a, t, slot] = True
        true_positive[a, t, slot] = ~gt_ignored[a, g[pair]]
        if taken_gt is not None:
            taken_gt[a, t, slot] = g[pair]
