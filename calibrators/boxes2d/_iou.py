"""IoU of COCO boxes exactly as pycocotools' `maskUtils.iou` computes it (its C `bbIou`).

For a detection `d` and a ground truth `g`, both `x, y, w, h`:

    iw = min(d.x + d.w, g.x + g.w) - max(d.x, g.x);  0 if iw <= 0
    ih = min(d.y + d.h, g.y + g.h) - max(d.y, g.y);  0 if ih <= 0
    IoU = iw·ih / u,  u = d.w·d.h + g.w·g.h - iw·ih, or u = d.w·d.h for a crowd g

The crowd rule makes a crowd region's "IoU" the fraction of the detection inside it. The same
float64 operations in the same order give the same bits as the C code.
"""

from __future__ import annotations

import numpy as np

from calibrators.boxes2d._boxes import check_bbox, check_flags
from calibrators.core.errors import FieldError

__all__ = ["box_iou", "pair_iou"]


def box_iou(dt: object, gt: object, iscrowd: object = None) -> np.ndarray:
    """`[N, G]` IoU of every detection box `dt [N, 4]` with every ground-truth box `gt [G, 4]`
    (COCO `x, y, w, h`); `iscrowd [G]` bool marks crowd regions (None: none).

    As `maskUtils.iou(dt, gt, iscrowd)` except that an empty side gives an `[N, G]` array of
    zeros rather than `[]`.
    """
    d = check_bbox("dt", dt, None)
    g = check_bbox("gt", gt, None)
    crowd = check_flags("iscrowd", iscrowd, len(g), "gt")
    return pair_iou(d[:, None, :], g[None, :, :], crowd[None, :])


def pair_iou(d: np.ndarray, g: np.ndarray, crowd: np.ndarray) -> np.ndarray:
    """IoU of boxes `d [..., 4]` and `g [..., 4]` (broadcast against each other, float64) with
    `crowd [...]` bool the crowd flag of `g`; raises FieldError if one is not finite."""
    iw = np.minimum(d[..., 2] + d[..., 0], g[..., 2] + g[..., 0]) \
        - np.maximum(d[..., 0], g[..., 0])
    ih = np.minimum(d[..., 3] + d[..., 1], g[..., 3] + g[..., 1]) \
        - np.maximum(d[..., 1], g[..., 1])
    inter = iw * ih
    d_area = d[..., 2] * d[..., 3]
    union = np.where(crowd, d_area, d_area + g[..., 2] * g[..., 3] - inter)
    overlap = (iw > 0) & (ih > 0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        iou = np.where(overlap, inter / np.where(overlap, union, 1.0), 0.0)
    bad = ~np.isfinite(iou)
    if bad.any():
        # Unreachable for boxes that passed `check_bbox`; kept so that no NaN is ever matched.
        where = np.unravel_index(int(np.argmax(bad)), bad.shape)
        raise FieldError("bbox", f"the IoU of boxes {list(map(int, where))} is not finite")
    return iou
