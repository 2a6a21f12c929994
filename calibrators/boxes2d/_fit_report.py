"""The report of a 2-D fit on its held-out images: raw against calibrated scores, and how
often the served box regions hold the true box, per category.

On the held-out images' counted detections (COCO's ignored ones left out), with their COCO
match at the profile's IoU threshold:

- `ece`: the ECE of the raw and the calibrated scores against "is a true positive";
- `d_ece`: the D-ECE over (confidence, box centre) (`SELECTION_FEATURES`, `detection_ece_2d`);
- `laece`: LaECE_0 (`localisation_ece_2d`), null when no category with ground truth is left;
- `per_class`: per category its detections, true positives and the two ECEs;
- `regions` (profiles with box regions): at `REPORT_LEVELS`, the fraction of the held-out true
  positives whose true box lies between the inner and the outer box (all four edges), overall
  and per category, with the counts behind them; `per_class_size`: the same per category ×
  box size cell of the regions, with covered counts and sampling intervals (`_report_regions`).

What the dashboard draws (reports written before these keys lack them):

- `reliability`: reliability diagrams, raw and calibrated, overall and per category;
- `position`: calibration per cell of the box centre on the D-ECE's position bins
  (`_report_scores`);
- `sample`: one held-out image, its detections with their scores and regions at 0.9 and its
  ground truth (`_report_sample`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibrators import metrics
from calibrators.boxes2d._boxes import GroundTruth2D
from calibrators.boxes2d._calibrate2d import calibrate_2d, served_sigma
from calibrators.boxes2d._calibration_errors import localisation_ece_2d
from calibrators.boxes2d._profile2d import Profile2D
from calibrators.boxes2d._report_regions import size_coverage
from calibrators.boxes2d._report_sample import sample_image
from calibrators.boxes2d._report_scores import position_report, reliability_report
from calibrators.boxes2d._score_fit import SELECTION_FEATURES, ScoreData, selection_dece
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable

__all__ = ["REPORT_LEVELS", "holdout_report"]

#: The region levels a fit report measures.
REPORT_LEVELS: tuple[float, ...] = (0.5, 0.8, 0.9, 0.95)


def holdout_report(profile: Profile2D, data: ScoreData, truth: GroundTruth2D,
                   held: np.ndarray, held_truth: np.ndarray) -> dict[str, Any]:
    """The report (module docstring) of the detections at the mask `held [N]` (their counted
    ones) against the ground truth at `held_truth [G]` (the same images)."""
    rows = held & ~data.match.ignored
    dets, tp = data.detections.take(rows), data.match.true_positive[rows]
    size = data.image_size[rows]
    regions = profile.box_regions
    served = calibrate_2d(profile, dets, REPORT_LEVELS if regions is not None else None, size)
    raw, cal = dets.score, served.score
    names = dict(zip(profile.category_ids, profile.category_names, strict=True))
    out: dict[str, Any] = {
        "n_images": int(len(np.unique(truth.image_id[held_truth]))),
        "n_detections": int(rows.sum()), "n_true_positives": int(tp.sum()),
        "ece": {"raw": metrics.expected_calibration_error(raw, tp),
                "calibrated": metrics.expected_calibration_error(cal, tp)},
        "d_ece": {"features": list(SELECTION_FEATURES),
                  "raw": selection_dece(data, rows, raw),
                  "calibrated": selection_dece(data, rows, cal)},
        "laece": {"raw": _laece(data, rows, truth, held_truth, raw),
                  "calibrated": _laece(data, rows, truth, held_truth, cal)},
        "per_class": _per_class(profile, dets.category_id, tp, raw, cal),
        "regions": None,
        "reliability": reliability_report(dets.category_id, tp, raw, cal, profile.category_ids,
                                          profile.category_names),
        "position": position_report(dets.bbox, size, tp, raw, cal),
        "sample": sample_image(dets, tp, cal, size, served.regions, truth.take(held_truth),
                               names)}
    if regions is not None and tp.any():
        hit = np.flatnonzero(tp)
        boxes = dets.take(hit)
        true = truth.bbox[data.match.gt_row[rows][hit]]
        scores = regions.scores(boxes.bbox, true, served_sigma(profile, boxes, size[hit]))
        radii = regions.radii(REPORT_LEVELS, boxes.bbox, boxes.category_id)
        out["regions"] = {
            **_coverage(profile, boxes.category_id, scores[:, None] <= radii),
            "per_class_size": size_coverage(regions, boxes.bbox, boxes.category_id, scores,
                                            radii, REPORT_LEVELS, names)}
    return to_jsonable(out)


def _laece(data: ScoreData, rows: np.ndarray, truth: GroundTruth2D, held_truth: np.ndarray,
           scores: np.ndarray) -> float | None:
    try:
        return localisation_ece_2d(data.detections.take(rows), truth.take(held_truth),
                                   scores=scores).value
    except FieldError:   # no held-out detection of a category with ground truth
        return None


def _per_class(profile: Profile2D, category: np.ndarray, tp: np.ndarray, raw: np.ndarray,
               cal: np.ndarray) -> dict[str, dict[str, Any]]:
    out = {}
    for cid, name in zip(profile.category_ids, profile.category_names, strict=True):
        mine = category == cid
        n = int(mine.sum())
        out[name] = {"n": n, "true_positives": int(tp[mine].sum()),
                     "ece_raw": metrics.expected_calibration_error(raw[mine], tp[mine])
                     if n else None,
                     "ece_calibrated": metrics.expected_calibration_error(cal[mine], tp[mine])
                     if n else None}
    return out


def _coverage(profile: Profile2D, category: np.ndarray, covered: np.ndarray
              ) -> dict[str, Any]:
    """Coverage `[Q]` overall and per category of the true positives' `covered [M, Q]`."""
    per_class = {}
    for cid, name in zip(profile.category_ids, profile.category_names, strict=True):
        mine = category == cid
        per_class[name] = {"n": int(mine.sum()),
                           "coverage": covered[mine].mean(axis=0) if mine.any() else None}
    return {"levels": list(REPORT_LEVELS), "n": int(len(covered)),
            "overall": covered.mean(axis=0), "per_class": per_class}
