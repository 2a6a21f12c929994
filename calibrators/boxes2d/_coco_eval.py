"""`evaluate_coco`: pycocotools' `COCOeval(iouType='bbox')` evaluate + accumulate + summarize,
vectorised, with the same numbers (see `_match` and `_accumulate` for the rules).

Which images and categories count, as `COCOeval.params.imgIds` / `catIds`: by default every
id that a detection or a ground truth carries (an image or category with neither changes
nothing; a category without ground truth gets -1, as in pycocotools). Given explicitly, rows
on other ids are left out. What differs from pycocotools, on purpose:
- `GroundTruth2D.ignore` is honoured (pycocotools overwrites a COCO `ignore` key with
  `iscrowd`); with it all False the numbers are pycocotools' own;
- ground truth has no ids, so a match is a match (pycocotools counts a match to an
  annotation of id 0 as none);
- no detections is a valid input (pycocotools' `loadRes` fails on an empty list).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.boxes2d._accumulate import accumulate
from calibrators.boxes2d._boxes import Detections2D, GroundTruth2D
from calibrators.boxes2d._match import match, rank_detections
from calibrators.boxes2d._params import (
    AREA_LABELS,
    IOU_THRESHOLDS,
    MAX_DETS,
    STAT_NAMES,
)
from calibrators.core.bins import ResultMixin
from calibrators.core.checks import as_int_array
from calibrators.core.errors import FieldError

__all__ = ["CocoEvaluation", "evaluate_coco", "grouped"]

#: `summarize()`'s 12 settings: (AP or AR, IoU threshold or None for all, area, maxDets).
_SUMMARY = ((True, None, "all", 100), (True, .5, "all", 100), (True, .75, "all", 100),
            (True, None, "small", 100), (True, None, "medium", 100), (True, None, "large", 100),
            (False, None, "all", 1), (False, None, "all", 10), (False, None, "all", 100),
            (False, None, "small", 100), (False, None, "medium", 100),
            (False, None, "large", 100))


@dataclass(frozen=True, eq=False)
class CocoEvaluation(ResultMixin):
    """The COCO box metrics of `evaluate_coco`; -1 marks "no ground truth" as in pycocotools.

    stats        [12]                `COCOeval.stats`, named by `STAT_NAMES` (`summary()`)
    precision    [T, R, K, A, M]     `COCOeval.eval['precision']` (T = 10 IoU thresholds,
                                     R = 101 recall thresholds, K categories, A = 4 area
                                     ranges, M = 3 caps `MAX_DETS`)
    recall       [T, K, A, M]        `COCOeval.eval['recall']`
    category_ids [K] int64           the categories of the K axis, ascending
    ap, ap50, ap75 [K]               per category: mean precision over IoU .50:.95, at .50,
                                     at .75 (area all, 100 detections), -1 without ground truth
    n_images, n_detections, n_gt     what was evaluated (detections: after the per-image
                                     cap of `MAX_DETS[-1]` per category)
    """

    stats: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    category_ids: np.ndarray
    ap: np.ndarray
    ap50: np.ndarray
    ap75: np.ndarray
    n_images: int
    n_detections: int
    n_gt: int

    def summary(self) -> dict[str, float]:
        """The 12 stats by name (`AP`, `AP50`, ..., `AR_large`)."""
        return dict(zip(STAT_NAMES, self.stats.tolist(), strict=True))

    def format_summary(self) -> str:
        """The 12 lines `COCOeval.summarize()` prints."""
        lines = []
        for value, (is_ap, iou, area, max_det) in zip(self.stats, _SUMMARY, strict=True):
            title, kind = ("Average Precision", "(AP)") if is_ap else ("Average Recall", "(AR)")
            iou_text = f"{IOU_THRESHOLDS[0]:0.2f}:{IOU_THRESHOLDS[-1]:0.2f}" if iou is None \
                else f"{iou:0.2f}"
            lines.append(f" {title:<18} {kind} @[ IoU={iou_text:<9} | area={area:>6s} | "
                         f"maxDets={max_det:>3d} ] = {value:0.3f}")
        return "\n".join(lines)


def evaluate_coco(detections: Detections2D, ground_truth: GroundTruth2D, *,
                  image_ids: object = None, category_ids: object = None) -> CocoEvaluation:
    """COCO box AP/AR of `detections` against `ground_truth`, as pycocotools computes it.

    `image_ids`, `category_ids` (int sequences): what is evaluated, as `params.imgIds` and
    `params.catIds` (module docstring); None: every id present.
    """
    if not isinstance(detections, Detections2D):
        raise FieldError("detections", "detections must be a Detections2D")
    if not isinstance(ground_truth, GroundTruth2D):
        raise FieldError("ground_truth", "ground_truth must be a GroundTruth2D")
    dt, gt = detections, ground_truth
    images = _ids("image_ids", image_ids, dt.image_id, gt.image_id)
    categories = _ids("category_ids", category_ids, dt.category_id, gt.category_id)
    det_rows, det_group = grouped(dt.image_id, dt.category_id, images, categories)
    gt_rows, gt_group = grouped(gt.image_id, gt.category_id, images, categories)

    ranked = rank_detections(det_group, dt.score[det_rows])
    rows = det_rows[ranked.rows]  # input rows of the evaluated detections, by (group, rank)
    group = det_group[ranked.rows]
    category = group // max(len(images), 1)
    # pycocotools' ranking across images: score, then image, then input row (a stable sort of
    # the (category, image, score, row) order by (category, score))
    order = np.lexsort((-dt.score[rows], category))
    slot = np.empty_like(order)
    slot[order] = np.arange(len(order))
    matches = match(group, ranked.rank, dt.bbox[rows], slot, gt_group, gt.bbox[gt_rows],
                    gt.area[gt_rows], gt.iscrowd[gt_rows], gt.ignore[gt_rows])
    n_cat = len(categories)
    n_positive = np.stack([np.bincount(gt_group[~ignored] // max(len(images), 1),
                                       minlength=n_cat)
                           for ignored in matches.gt_ignored], axis=1)  # [K, A]
    curves = accumulate(category[order], ranked.rank[order], matches.in_range,
                        matches.matched, matches.true_positive, n_positive)
    stats = np.array([_summarize(curves.precision if is_ap else curves.recall, is_ap, iou,
                                 AREA_LABELS.index(area), MAX_DETS.index(max_det))
                      for is_ap, iou, area, max_det in _SUMMARY])
    per_class = [np.array([_mean_valid(curves.precision[t, :, k, 0, -1]) for k in range(n_cat)])
                 for t in (slice(None), _threshold_index(.5), _threshold_index(.75))]
    return CocoEvaluation(stats=stats, precision=curves.precision, recall=curves.recall,
                          category_ids=categories, ap=per_class[0], ap50=per_class[1],
                          ap75=per_class[2], n_images=len(images), n_detections=len(rows),
                          n_gt=len(gt_rows))


def _ids(name: str, value: object, *present: np.ndarray) -> np.ndarray:
    """`[K]` sorted distinct ids: `value`, or every id of the `present` arrays if None."""
    if value is None:
        return np.unique(np.concatenate(present))
    return np.unique(as_int_array(name, value))


def grouped(image_id: np.ndarray, category_id: np.ndarray, images: np.ndarray,
            categories: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows on `images` x `categories` (ascending) and each row's group `category index · I +
    image index` (`[n]` int64 each)."""
    img = np.searchsorted(images, image_id)
    cat = np.searchsorted(categories, category_id)
    inside = (img < len(images)) & (cat < len(categories))
    inside[inside] &= (images[img[inside]] == image_id[inside]) \
        & (categories[cat[inside]] == category_id[inside])
    rows = np.flatnonzero(inside)
    return rows, cat[rows] * len(images) + img[rows]


def _threshold_index(iou: float) -> np.ndarray:
    """The T-axis index of `iou` as summarize finds it (`np.where(iouThr == p.iouThrs)`)."""
    return np.where(iou == IOU_THRESHOLDS)[0]


def _summarize(values: np.ndarray, is_ap: bool, iou: float | None, a: int, m: int) -> float:
    """One line of `summarize()`: the mean of the entries > -1 of precision [T, R, K, A, M]
    (AP) or recall [T, K, A, M] (AR) at one area range and cap, or -1 if there are none."""
    s = values if iou is None else values[_threshold_index(iou)]
    s = s[:, :, :, [a], [m]] if is_ap else s[:, :, [a], [m]]
    return _mean_valid(s)


def _mean_valid(s: np.ndarray) -> float:
    valid = s[s > -1]
    return -1.0 if len(valid) == 0 else float(np.mean(valid))
