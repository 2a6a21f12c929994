"""The parameters of pycocotools' `COCOeval` for iouType='bbox' (`Params.setDetParams`), built
with the same numpy calls so that every threshold has the same bits."""

from __future__ import annotations

import numpy as np

#: T = 10 IoU thresholds .50:.05:.95 (`np.linspace`, not `arange`, as pycocotools).
IOU_THRESHOLDS = np.linspace(.5, 0.95, int(np.round((0.95 - .5) / .05)) + 1, endpoint=True)
#: R = 101 recall thresholds 0:.01:1.
RECALL_THRESHOLDS = np.linspace(.0, 1.00, int(np.round((1.00 - .0) / .01)) + 1, endpoint=True)
#: M = 3 caps on the detections per image and category, ascending.
MAX_DETS = (1, 10, 100)
#: A = 4 closed area ranges `[low, high]` (px²) on a ground truth's `area` field and on a
#: detection's box area `w·h`.
AREA_RANGES = ((0.0, 1e5 ** 2), (0.0, 32.0 ** 2), (32.0 ** 2, 96.0 ** 2), (96.0 ** 2, 1e5 ** 2))
AREA_LABELS = ("all", "small", "medium", "large")
#: A match needs IoU >= min(t, 1 - 1e-10): pycocotools' cap, so that t = 1 still matches
#: boxes whose IoU rounds just below 1.
IOU_CAP = 1 - 1e-10
#: The 12 numbers of `COCOeval.summarize()` for boxes, in its order.
STAT_NAMES = ("AP", "AP50", "AP75", "AP_small", "AP_medium", "AP_large",
              "AR1", "AR10", "AR100", "AR_small", "AR_medium", "AR_large")

for _array in (IOU_THRESHOLDS, RECALL_THRESHOLDS):
    _array.flags.writeable = False
