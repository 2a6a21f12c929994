"""Precision and recall of COCO matches (pycocotools `COCOeval.accumulate`), to the bit.

pycocotools, per category k, area range a, cap m and IoU threshold t: the category's evaluated
detections of every image, each image's first m by score, ranked by descending score across
images (a stable sort of the per-image lists concatenated in image order: ties go to the
earlier image, then the earlier input row); over that list, cumulative true positives `tp` and
false positives `fp` among the detections not ignored, recall `rc = tp / npig` (npig: ground
truth not ignored), precision `pr = tp / (fp + tp + np.spacing(1))` made non-increasing from
the right (the envelope), read at `searchsorted(rc, recall_thresholds, side='left')` (0 past
the end); recall `rc[-1]`. No unignored ground truth: -1 everywhere.

The same numbers from the true positives alone. `rc` only grows at a true positive, so each
threshold lands on the c-th true positive with c the first count where `c / npig` reaches it
(a `searchsorted` on `(1..npig) / npig`, the same divisions); a false positive or ignored
detection never raises `pr` above that of the true positive before it, so the envelope there is
the running maximum of `pr` over the true positives from the right. At the c-th true positive
`tp = c` and `fp = u`, the unmatched detections inside the area range before it (every other
detection is matched, or ignored). So the work is per true positive plus one running count of
in-range detections per area range and cap, instead of a pass over T x A x M x N entries.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from calibrators.boxes2d._params import AREA_RANGES, IOU_THRESHOLDS, MAX_DETS, RECALL_THRESHOLDS


class Accumulated(NamedTuple):
    """precision [T, R, K, A, M] and recall [T, K, A, M]; -1 where a category has no
    unignored ground truth in that area range."""

    precision: np.ndarray
    recall: np.ndarray


def accumulate(category: np.ndarray, rank: np.ndarray, in_range: np.ndarray,
               matched: np.ndarray, true_positive: np.ndarray,
               n_positive: np.ndarray) -> Accumulated:
    """Precision and recall of the E evaluated detections, given in the order pycocotools
    ranks them (module docstring), categories ascending.

    category [E] int64 index into the K categories, rank [E] position in its image x category
    group, in_range [A, E] bool its box area inside each area range, matched and
    true_positive [A, T, E] (`Matched`); n_positive [K, A] int64 unignored ground truth (npig)
    per category and range.
    """
    n_thr, n_area, n_max = len(IOU_THRESHOLDS), len(AREA_RANGES), len(MAX_DETS)
    n_cat = n_positive.shape[0]
    precision = -np.ones((n_thr, len(RECALL_THRESHOLDS), n_cat, n_area, n_max))
    recall = -np.ones((n_thr, n_cat, n_area, n_max))
    valid = n_positive > 0
    precision[:, :, valid, :] = 0.0
    recall[:, valid, :] = 0.0
    a_i, t_i, g_i = np.nonzero(matched)  # sorted by (a, t, g): rows contiguous
    tp_i = true_positive[a_i, t_i, g_i]
    k_i = category[g_i]
    start = np.searchsorted(category, np.arange(n_cat), side="left")
    first_tp = _first_reaching(n_positive)
    for m, max_det in enumerate(MAX_DETS):
        capped = rank < max_det
        # u + c at each true positive: in-range detections up to it (a running count over the
        # category's capped list), less the matched in-range ones, plus the true positives.
        in_count = _running_count(in_range & capped, category, start)
        keep = capped[g_i]
        a, t, g, k, tp = a_i[keep], t_i[keep], g_i[keep], k_i[keep], tp_i[keep]
        row = (a * n_thr + t) * n_cat + k  # one (a, t, k) setting per row, rows ascending
        row_start = np.searchsorted(row, np.arange(n_area * n_thr * n_cat))
        matched_in = _running_count(in_range[a, g], row, row_start)
        c = _running_count(tp, row, row_start)
        a, t, k, row, c = a[tp], t[tp], k[tp], row[tp], c[tp]
        fp = (in_count[a, g[tp]] - matched_in[tp]).astype(float)
        tps = c.astype(float)
        pr = tps / (fp + tps + np.spacing(1))
        first = np.flatnonzero(np.r_[True, row[1:] != row[:-1]]) if len(row) else row
        for lo, hi in zip(first, np.r_[first[1:], len(row)][:len(first)], strict=True):
            aa, tt, kk = int(a[lo]), int(t[lo]), int(k[lo])
            envelope = np.maximum.accumulate(pr[lo:hi][::-1])[::-1]
            reached = first_tp[kk][aa] < hi - lo
            q = np.zeros(len(RECALL_THRESHOLDS))
            q[reached] = envelope[first_tp[kk][aa][reached]]
            precision[tt, :, kk, aa, m] = q
            recall[tt, kk, aa, m] = tps[hi - 1] / int(n_positive[kk, aa])
    return Accumulated(precision, recall)


def _first_reaching(n_positive: np.ndarray) -> list[list[np.ndarray]]:
    """[K][A] of `[R]`: the 0-based index c - 1 of the first true-positive count c whose recall
    `c / npig` reaches each recall threshold (as pycocotools' `searchsorted(rc, ..., 'left')`
    on the recalls it computes; `npig` where none does)."""
    out = []
    for counts in n_positive.tolist():
        out.append([np.searchsorted(np.arange(1, n + 1, dtype=float) / n, RECALL_THRESHOLDS,
                                    side="left") if n else None for n in counts])
    return out


def _running_count(flags: np.ndarray, group: np.ndarray, start: np.ndarray) -> np.ndarray:
    """`[..., N]` int64: the True entries of `flags [..., N]` up to and including each position,
    counted within runs of equal `group [N]` (sorted) that begin at `start` (indexed by group)."""
    total = np.cumsum(flags, axis=-1)
    padded = np.concatenate([np.zeros((*total.shape[:-1], 1), dtype=total.dtype), total],
                            axis=-1)
    return total - padded[..., start[group]]
