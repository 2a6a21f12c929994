"""Image-plane (2-D) boxes: COCO-form detections and ground truth, IoU, and the COCO box
metrics exactly as pycocotools computes them, vectorised.

- `_boxes`: `Detections2D`, `GroundTruth2D` (`image_id`, `category_id`, `bbox` `x, y, w, h`,
  `score`; `area`, `iscrowd`, `ignore`), validated, and `from_coco` for COCO dicts.
- `_iou`: `box_iou`, pycocotools' `maskUtils.iou` for boxes (crowd rule included).
- `_match`, `_accumulate`: `COCOeval.evaluateImg` matching and `accumulate` curves.
- `_coco_eval`: `evaluate_coco` -> `CocoEvaluation` (the 12 `summarize()` stats, precision
  and recall arrays, per-category AP / AP50 / AP75).
- `_params`: the COCO thresholds, area ranges and caps.
"""

from calibrators.boxes2d._boxes import Detections2D, GroundTruth2D
from calibrators.boxes2d._coco_eval import CocoEvaluation, evaluate_coco
from calibrators.boxes2d._iou import box_iou
from calibrators.boxes2d._params import (
    AREA_LABELS,
    AREA_RANGES,
    IOU_THRESHOLDS,
    MAX_DETS,
    RECALL_THRESHOLDS,
    STAT_NAMES,
)

__all__ = ["AREA_LABELS", "AREA_RANGES", "IOU_THRESHOLDS", "MAX_DETS", "RECALL_THRESHOLDS",
           "STAT_NAMES", "CocoEvaluation", "Detections2D", "GroundTruth2D", "box_iou",
           "evaluate_coco"]
