"""Box uncertainty from the decoder layers: the covariance of a detection's four box edges
across the boxes its query predicts at each of the L decoder layers (the thesis' layer spread,
`calibrators.covariance.sample_spread`, in image-plane edge coordinates).

    Σ = sample covariance (ddof = 1) of the L edge vectors (x1, y1, x2, y2)    [4, 4]
    Σ' = Σ + diag(max(min_sigma² − Σ_jj, 0))

The floor raises an edge's variance to `min_sigma²` (pixels²) where the layers agree more
closely than that (they can agree exactly), so that a σ-scaled conformal score never divides
by zero; a larger diagonal keeps Σ' positive semi-definite, and edges already above the floor
keep their variance.
"""

from __future__ import annotations

import numpy as np

from calibrators.boxes2d._boxes import check_layer_boxes
from calibrators.boxes2d._edges import box_edges
from calibrators.core.checks import as_float_array, check_covariances
from calibrators.core.errors import FieldError
from calibrators.covariance import sample_spread

__all__ = ["MIN_SIGMA", "edge_covariance", "edge_sigma"]

#: Default floor (pixels) on each edge's standard deviation.
MIN_SIGMA: float = 1.0


def edge_covariance(layer_boxes: np.ndarray, min_sigma: float = MIN_SIGMA) -> np.ndarray:
    """`[N, 4, 4]` covariance Σ' of the edges (x1, y1, x2, y2) of each detection's boxes
    `layer_boxes [N, L, 4]` (COCO x, y, w, h per decoder layer, L >= 2), with each edge's
    variance at least `min_sigma²` (`min_sigma` >= 0, pixels)."""
    arr = as_float_array("layer_boxes", layer_boxes, ndim=3)
    boxes = check_layer_boxes(arr, len(arr))
    if boxes.shape[1] < 2:
        raise FieldError("layer_boxes", f"layer_boxes has {boxes.shape[1]} decoder layer(s); the "
                                        "spread across layers needs L >= 2")
    floor = float(as_float_array("min_sigma", min_sigma, ndim=0))
    if floor < 0:
        raise FieldError("min_sigma", f"min_sigma must be >= 0, got {floor}")
    cov = sample_spread(box_edges(boxes))
    diag = np.einsum("nii->ni", cov)
    cov[:, np.arange(4), np.arange(4)] = np.maximum(diag, floor * floor)
    return cov


def edge_sigma(covariance: np.ndarray) -> np.ndarray:
    """`[N, 4]` standard deviation of each edge: the square roots of the diagonal of
    `covariance [N, 4, 4]` (symmetric, positive semi-definite)."""
    cov = as_float_array("covariance", covariance, ndim=3)
    check_covariances("covariance", cov, dim=4)
    return np.sqrt(np.maximum(np.einsum("nii->ni", cov), 0.0))
