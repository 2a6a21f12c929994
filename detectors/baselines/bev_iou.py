"""Bird's-eye-view IoU of rotated boxes with shapely 2's vectorised array API.

Boxes are `x, y, z, w, l, h, yaw[, vx, vy]` (nuScenes convention: `l` along the heading `yaw`,
ego frame); only `x, y, w, l, yaw` enter. Each box becomes a shapely polygon of its four BEV
corners (`detectors.sim.geometry.bev_corners`), and intersections and areas are computed by
`shapely.intersection` / `shapely.area` over whole arrays of polygons, never box by box.
"""

from __future__ import annotations

import numpy as np
import shapely

from calibrators.core.checks import as_float_array
from detectors.sim.geometry import bev_corners


def check_boxes(name: str, boxes: np.ndarray) -> np.ndarray:
    """`boxes` as float64 `[M, >=7]` with finite values and `w, l > 0` (else ValueError)."""
    arr = as_float_array(name, boxes, ndim=2)
    if arr.shape[1] < 7:
        raise ValueError(f"{name} must have shape [M, 9] (x y z w l h yaw vx vy), "
                         f"got {arr.shape}")
    bad = (arr[:, 3] <= 0) | (arr[:, 4] <= 0)
    if bad.any():
        raise ValueError(f"{name}[{int(np.argmax(bad))}] has a non-positive width or length")
    return arr


def paired_bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """BEV IoU `[K]` of each box of `a [K, 9]` with the box of `b [K, 9]` in the same row."""
    a, b = check_boxes("a", a), check_boxes("b", b)
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"a has {a.shape[0]} rows but b has {b.shape[0]}")
    return _iou(a, b)


def pairwise_bev_iou(boxes: np.ndarray) -> np.ndarray:
    """Symmetric BEV IoU matrix `[M, M]` of `boxes [M, 9]` (diagonal 1).

    Only pairs whose circumscribed circles overlap are intersected; every other pair is 0.
    """
    boxes = check_boxes("boxes", boxes)
    m = len(boxes)
    iou = np.eye(m)
    if m < 2:
        return iou
    i, j = np.triu_indices(m, k=1)
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    gap = np.hypot(boxes[i, 0] - boxes[j, 0], boxes[i, 1] - boxes[j, 1])
    near = gap < radius[i] + radius[j]
    i, j = i[near], j[near]
    values = _iou(boxes[i], boxes[j])
    iou[i, j] = values
    iou[j, i] = values
    return iou


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise IoU of two validated `[K, >=7]` box arrays."""
    if len(a) == 0:
        return np.zeros(0)
    pa, pb = shapely.polygons(bev_corners(a)), shapely.polygons(bev_corners(b))
    inter = shapely.area(shapely.intersection(pa, pb))
    union = a[:, 3] * a[:, 4] + b[:, 3] * b[:, 4] - inter
    return np.clip(inter / union, 0.0, 1.0)
