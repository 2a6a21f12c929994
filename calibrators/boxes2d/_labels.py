"""Per-detection match labels for calibration: is each detection a true positive at one IoU
threshold, which ground truth did it take, and does COCO leave it out.

The rule is pycocotools' `COCOeval.evaluateImg` (`_match`, run here at one threshold and the
area range "all"): per image x category, detections by descending score (a stable sort: ties
keep input order) each take the unignored ground truth of highest IoU `>= min(t, 1 - 1e-10)`
that no earlier detection took, a crowd any number of times, an ignored box (crowd or
`ignore`) only when no unignored one qualifies. These are `evalImgs[...]['dtMatches']` and
`['dtIgnore']` with `params.iouThrs = [t]`, `areaRng = [all]` and `maxDets = [max_dets]`
(tested against pycocotools).

By default every detection is matched (no per-image cap); with `max_dets` the detections
beyond the first `max_dets` of their image x category are left out, as COCO leaves them out.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

from calibrators.boxes2d._boxes import Detections2D, GroundTruth2D
from calibrators.boxes2d._coco_eval import grouped
from calibrators.boxes2d._iou import pair_iou
from calibrators.boxes2d._match import match, rank_detections
from calibrators.boxes2d._params import AREA_RANGES
from calibrators.core.bins import ResultMixin
from calibrators.core.errors import FieldError

__all__ = ["MatchLabels", "match_labels"]


@dataclass(frozen=True, eq=False)
class MatchLabels(ResultMixin):
    """The match of N detections (rows of the `Detections2D`) at one IoU threshold.

    true_positive [N] bool   took a ground truth that is not ignored: the calibration label
    gt_row [N] int64         the row of the `GroundTruth2D` it took (ignored or not), -1: none
    iou [N] float64          its IoU with that ground truth (a crowd's: the fraction of the
                             detection inside it), 0 when it took none
    ignored [N] bool         COCO leaves it out (`dtIgnore`): it took an ignored ground truth,
                             or took none and its area `w·h` is beyond 1e10, or it is past the
                             `max_dets` cap; neither a true nor a false positive
    iou_threshold float      the threshold t
    """

    true_positive: np.ndarray
    gt_row: np.ndarray
    iou: np.ndarray
    ignored: np.ndarray
    iou_threshold: float

    def __len__(self) -> int:
        return len(self.true_positive)

    @property
    def false_positive(self) -> np.ndarray:
        """`[N]` bool: counted and took no unignored ground truth."""
        return ~self.true_positive & ~self.ignored


def match_labels(detections: Detections2D, ground_truth: GroundTruth2D,
                 iou_threshold: float = 0.5, max_dets: int | None = None) -> MatchLabels:
    """The COCO match of every detection at `iou_threshold` in [0, 1] (module docstring);
    `max_dets` (an int >= 1) caps the detections per image x category as COCO's maxDets."""
    if not isinstance(detections, Detections2D):
        raise FieldError("detections", "detections must be a Detections2D")
    if not isinstance(ground_truth, GroundTruth2D):
        raise FieldError("ground_truth", "ground_truth must be a GroundTruth2D")
    t = _threshold(iou_threshold)
    dt, gt = detections, ground_truth
    n = len(dt)
    if max_dets is not None and (isinstance(max_dets, bool)
                                 or not isinstance(max_dets, numbers.Integral) or max_dets < 1):
        raise FieldError("max_dets", f"max_dets must be an integer >= 1 or None, got {max_dets!r}")
    cap = max(n, 1) if max_dets is None else int(max_dets)
    images = np.unique(np.concatenate([dt.image_id, gt.image_id]))
    categories = np.unique(np.concatenate([dt.category_id, gt.category_id]))
    det_rows, det_group = grouped(dt.image_id, dt.category_id, images, categories)
    gt_rows, gt_group = grouped(gt.image_id, gt.category_id, images, categories)
    ranked = rank_detections(det_group, dt.score[det_rows], cap)
    rows = det_rows[ranked.rows]
    found = match(det_group[ranked.rows], ranked.rank, dt.bbox[rows], np.arange(len(rows)),
                  gt_group, gt.bbox[gt_rows], gt.area[gt_rows], gt.iscrowd[gt_rows],
                  gt.ignore[gt_rows], thresholds=np.array([t]), area_ranges=AREA_RANGES[:1],
                  with_gt=True)
    assert found.gt is not None
    took = found.gt[0, 0]
    matched = took >= 0
    true_positive = np.zeros(n, dtype=bool)
    true_positive[rows] = found.true_positive[0, 0]
    ignored = np.ones(n, dtype=bool)   # past the cap unless evaluated
    ignored[rows] = (matched & ~found.true_positive[0, 0]) | (~matched & ~found.in_range[0])
    gt_row = np.full(n, -1, dtype=np.int64)
    gt_row[rows[matched]] = gt_rows[took[matched]]
    iou = np.zeros(n)
    hit = np.flatnonzero(gt_row >= 0)
    if hit.size:
        g = gt_row[hit]
        iou[hit] = pair_iou(dt.bbox[hit], gt.bbox[g], gt.iscrowd[g])
    return MatchLabels(true_positive, gt_row, iou, ignored, t)


def _threshold(value: object) -> float:
    try:
        t = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        t = float("nan")
    if isinstance(value, bool) or not 0.0 <= t <= 1.0:
        raise FieldError("iou_threshold", f"iou_threshold must be a number in [0, 1], got "
                                          f"{value!r}")
    return t
