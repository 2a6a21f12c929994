"""Image-plane (2-D) boxes: COCO-form detections and ground truth, IoU, the COCO box metrics
exactly as pycocotools computes them, vectorised, and the calibration of 2-D detectors.

COCO evaluation:
- `_boxes`: `Detections2D` (with optional `logits`, `layer_boxes`), `GroundTruth2D`
  (`image_id`, `category_id`, `bbox` `x, y, w, h`, `score`; `area`, `iscrowd`, `ignore`),
  validated, and `from_coco` for COCO dicts, each field checked by `_coco_records`.
- `_iou`: `box_iou`, pycocotools' `maskUtils.iou` for boxes (crowd rule included).
- `_match`, `_accumulate`: `COCOeval.evaluateImg` matching and `accumulate` curves.
- `_coco_eval`: `evaluate_coco` -> `CocoEvaluation` (the 12 `summarize()` stats, precision
  and recall arrays, per-category AP / AP50 / AP75).
- `_params`: the COCO thresholds, area ranges and caps.

Calibration (docs/boxes2d.md):
- `_labels`: `match_labels` -> `MatchLabels`, each detection's true-positive label at one IoU
  threshold and the ground truth it took, by the COCO rule.
- `_edges`, `_features`: box edges `x1, y1, x2, y2`; position features `cx, cy, w, h`
  relative to the image (`box_features`).
- `_calibration_errors`: `detection_ece_2d` (D-ECE over box features), `localisation_ece_2d`
  (LaECE).
- `_score_inputs`: `score_inputs`, the label's logit and class index for the per-class score
  calibrators of `calibrators.scores`; `_position`: `PositionCalibrator`, logistic
  calibration with box-position terms.
- `_layer_spread`: `edge_covariance`, the covariance of the box edges across decoder layers.
- `_box_scores`, `_conformal_boxes`: `ConformalBoxes`, split-conformal inner / outer boxes per
  class × box size (`BoxRegions`); `_error_scale`: `EdgeErrorScale`, the fitted scale of
  each edge's error that adaptive regions divide by.
- `_coco_instances`, `_coco_read`, `_coco_write`: COCO results and instances files in, and
  calibrated COCO results out.

A 2-D profile (docs/boxes2d.md, "A 2-D profile"):
- `_fit_options`: `FitOptions2D`, every option of a 2-D fit.
- `_score_fit`: the score stage, candidates chosen by held-out NLL (`ScoreStage2D`).
- `_profile2d`: `Profile2D`, the fitted 2-D calibration as versioned JSON (`kind: boxes2d`).
- `_fit2d`: `fit_profile_2d`, the fit: image splits, score stage, box regions, report
  (`_fit_report`, with what the dashboard draws: `_report_scores` reliability and position
  cells, `_report_regions` coverage per category × size, `_report_sample` one image).
- `_calibrate2d`: `calibrate_2d`, serving a profile (`Calibrated2D`).
- `_synthetic`: `synthetic_coco`, a synthetic COCO validation set for tests and tours.
"""

from calibrators.boxes2d._box_scores import BOX_SCORES, REGION_SCORES, box_scores
from calibrators.boxes2d._boxes import Detections2D, GroundTruth2D
from calibrators.boxes2d._calibrate2d import Calibrated2D, calibrate_2d
from calibrators.boxes2d._calibration_errors import (
    DECE_BINS,
    detection_ece_2d,
    localisation_ece_2d,
)
from calibrators.boxes2d._coco_eval import CocoEvaluation, evaluate_coco
from calibrators.boxes2d._coco_instances import CocoInstances, parse_instances
from calibrators.boxes2d._coco_read import (
    MAX_COCO_BYTES,
    read_coco_instances,
    read_coco_results,
)
from calibrators.boxes2d._coco_write import coco_results, write_coco_results
from calibrators.boxes2d._conformal_boxes import COCO_SIZE_EDGES, BoxRegions, ConformalBoxes
from calibrators.boxes2d._edges import EDGE_NAMES, box_edges, edges_box
from calibrators.boxes2d._error_scale import EdgeErrorScale
from calibrators.boxes2d._features import BOX_FEATURES, box_features
from calibrators.boxes2d._fit2d import MIN_SCALE_FIT, check_fit_input_2d, fit_profile_2d
from calibrators.boxes2d._fit_options import SCORE_METHODS_2D, FitOptions2D
from calibrators.boxes2d._fit_report import REPORT_LEVELS
from calibrators.boxes2d._iou import box_iou
from calibrators.boxes2d._labels import MatchLabels, match_labels
from calibrators.boxes2d._layer_spread import MIN_SIGMA, edge_covariance, edge_sigma
from calibrators.boxes2d._params import (
    AREA_LABELS,
    AREA_RANGES,
    IOU_THRESHOLDS,
    MAX_DETS,
    RECALL_THRESHOLDS,
    STAT_NAMES,
)
from calibrators.boxes2d._position import PositionCalibrator
from calibrators.boxes2d._profile2d import PROFILE_2D_VERSIONS, Profile2D
from calibrators.boxes2d._score_fit import ScoreStage2D
from calibrators.boxes2d._score_inputs import ScoreInputs, category_index, score_inputs
from calibrators.boxes2d._synthetic import SYNTHETIC_CATEGORIES, synthetic_coco

__all__ = ["AREA_LABELS", "AREA_RANGES", "BOX_FEATURES", "BOX_SCORES", "COCO_SIZE_EDGES",
           "DECE_BINS", "EDGE_NAMES", "IOU_THRESHOLDS", "MAX_COCO_BYTES", "MAX_DETS",
           "MIN_SCALE_FIT", "MIN_SIGMA", "PROFILE_2D_VERSIONS", "RECALL_THRESHOLDS",
           "REGION_SCORES", "REPORT_LEVELS", "SCORE_METHODS_2D", "STAT_NAMES",
           "SYNTHETIC_CATEGORIES", "BoxRegions", "Calibrated2D", "CocoEvaluation", "CocoInstances",
           "ConformalBoxes", "Detections2D", "EdgeErrorScale", "FitOptions2D", "GroundTruth2D",
           "MatchLabels", "PositionCalibrator", "Profile2D", "ScoreInputs", "ScoreStage2D",
           "box_edges", "box_features", "box_iou", "box_scores", "calibrate_2d", "category_index",
           "check_fit_input_2d", "coco_results", "detection_ece_2d", "edge_covariance",
           "edge_sigma", "edges_box", "evaluate_coco", "fit_profile_2d", "localisation_ece_2d",
           "match_labels", "parse_instances", "read_coco_instances", "read_coco_results",
           "score_inputs", "synthetic_coco", "write_coco_results"]
