"""Calibration errors of 2-D detections against COCO ground truth.

- `detection_ece_2d`: D-ECE (Küppers et al. 2020, netcal's `ECE(detection=True)`): the
  detection ECE of `calibrators.metrics.detection_ece` over joint bins of the confidence and
  the box position features (`box_features`: cx, cy, w, h relative to the image, or a subset;
  none for the confidence alone), the features binned equal-width over [0, 1]. A detection is
  correct when it is a true positive (`MatchLabels`); COCO's ignored detections are left out.
- `localisation_ece_2d`: LaECE (Kuzucu et al. ECCV 2024; `calibrators.metrics.
  localisation_ece`) as the authors' code computes it on COCO: detections matched by the COCO
  rule at IoU threshold τ (default 0: LaECE_0, any overlap), area "all", at most 100 per image
  and category; ignored detections and the detections of categories without unignored ground
  truth left out; per category, confidence against precision × mean IoU in 25 bins; the mean
  over categories.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.boxes2d._boxes import Detections2D, GroundTruth2D
from calibrators.boxes2d._features import BOX_FEATURES, box_features, check_features
from calibrators.boxes2d._labels import MatchLabels, match_labels
from calibrators.boxes2d._params import MAX_DETS
from calibrators.core.checks import as_float_array, check_length
from calibrators.core.errors import FieldError
from calibrators.metrics import LAECE_BINS, LocalisationECE, detection_ece, localisation_ece

__all__ = ["DECE_BINS", "detection_ece_2d", "localisation_ece_2d"]

#: Default D-ECE bins: 10 of confidence, 5 of each position feature.
DECE_BINS: tuple[int, int] = (10, 5)


def detection_ece_2d(detections: Detections2D, labels: MatchLabels, image_size: np.ndarray, *,
                     scores: np.ndarray | None = None,
                     features: Sequence[str] = BOX_FEATURES,
                     n_bins: int | Sequence[int] | None = None) -> float:
    """D-ECE (module docstring) of `detections` [N] with their `labels` (`match_labels`) in
    images of `image_size [N, 2]` (width, height; `CocoInstances.image_size`). `scores [N]`
    replaces the detections' own (calibrated ones); `features` names the position features
    (empty: confidence only); `n_bins` an int for every dimension or one per dimension
    (confidence first), default 10 and 5 per feature."""
    conf = _scores(detections, scores)
    if not isinstance(labels, MatchLabels) or len(labels) != len(detections):
        raise FieldError("labels", "labels must be the MatchLabels of the same detections")
    names = check_features(features) if len(features) else ()
    keep = ~labels.ignored
    feats = (box_features(detections.bbox, image_size, names) if names
             else np.zeros((len(detections), 0)))
    bins = (DECE_BINS[0], *[DECE_BINS[1]] * len(names)) if n_bins is None else n_bins
    return detection_ece(conf[keep], labels.true_positive[keep], feats[keep], bins,
                         ranges=[(0.0, 1.0)] * len(names) if names else None)


def localisation_ece_2d(detections: Detections2D, ground_truth: GroundTruth2D, *,
                        scores: np.ndarray | None = None, iou_threshold: float = 0.0,
                        n_bins: int = LAECE_BINS, max_dets: int = MAX_DETS[-1]
                        ) -> LocalisationECE:
    """LaECE (module docstring) of `detections` against `ground_truth`; `scores [N]` replaces
    the detections' own. Its `classes` are category ids."""
    conf = _scores(detections, scores)
    labels = match_labels(detections, ground_truth, iou_threshold, max_dets)
    counted = ~(ground_truth.iscrowd | ground_truth.ignore)
    with_truth = np.isin(detections.category_id, ground_truth.category_id[counted])
    keep = ~labels.ignored & with_truth
    if not keep.any():
        raise FieldError("detections", "no detection of a category with ground truth is left "
                                       "to evaluate")
    iou = np.where(labels.true_positive, labels.iou, 0.0)
    return localisation_ece(conf[keep], iou[keep], detections.category_id[keep], n_bins)


def _scores(detections: Detections2D, scores: np.ndarray | None) -> np.ndarray:
    if not isinstance(detections, Detections2D):
        raise FieldError("detections", "detections must be a Detections2D")
    if scores is None:
        return detections.score
    conf = as_float_array("scores", scores, ndim=1)
    check_length("scores", conf, len(detections), "detections")
    return conf
