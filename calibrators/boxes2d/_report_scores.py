"""What a 2-D fit report keeps of its held-out scores for drawing: reliability diagrams and the
calibration over the image position, raw against calibrated.

- `reliability_report`: `metrics.reliability_diagram` (`RELIABILITY_BINS` equal-width bins of
  the confidence) of the raw and the calibrated scores against "is a true positive", overall
  and per category (null for a category without held-out detections): per bin the mean
  `confidence`, the `accuracy` (the precision) and the `count`; the bin edges once.
- `position_report`: the detections in cells of their box centre (`SELECTION_FEATURES`: cx,
  cy relative to the image, `box_features`), the D-ECE's own position bins (`DECE_BINS[1]`
  equal-width bins of [0, 1] per feature, `core.bins.bin_index`, a centre outside the image
  in the nearest cell). Per cell: detections, true positives, precision, mean raw and
  calibrated confidence, and the cell's D-ECE raw and calibrated: the ECE of its detections on
  the D-ECE's confidence bins (`DECE_BINS[0]`). Weighted by their counts, the cells' D-ECEs
  sum to the report's `d_ece`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from calibrators import metrics
from calibrators.boxes2d._calibration_errors import DECE_BINS
from calibrators.boxes2d._features import box_features
from calibrators.boxes2d._score_fit import SELECTION_FEATURES
from calibrators.core.bins import bin_index

__all__ = ["RELIABILITY_BINS", "position_report", "reliability_report"]

#: Confidence bins of the reliability diagrams (`reliability_diagram`'s default).
RELIABILITY_BINS = 10


def reliability_report(category: np.ndarray, tp: np.ndarray, raw: np.ndarray, cal: np.ndarray,
                       category_ids: Sequence[int], category_names: Sequence[str]
                       ) -> dict[str, Any]:
    """`{"bin_edges" [M + 1], "overall": {"raw", "calibrated"}, "per_class": {name: {"raw",
    "calibrated"} | None}}` (module docstring) of detections of `category [N]` with outcome
    `tp [N]` and scores `raw [N]`, `cal [N]`; each diagram `{"confidence", "accuracy",
    "count"}` `[M]`."""
    def pair(rows: np.ndarray) -> dict[str, Any] | None:
        if not rows.any():
            return None
        return {name: _diagram(scores[rows], tp[rows])
                for name, scores in (("raw", raw), ("calibrated", cal))}

    edges = np.linspace(0.0, 1.0, RELIABILITY_BINS + 1)
    return {"bin_edges": edges, "overall": pair(np.ones(len(tp), dtype=bool)),
            "per_class": {name: pair(category == cid)
                          for cid, name in zip(category_ids, category_names, strict=True)}}


def position_report(bbox: np.ndarray, image_size: np.ndarray, tp: np.ndarray, raw: np.ndarray,
                    cal: np.ndarray) -> dict[str, Any]:
    """The cells (module docstring) of detections `bbox [N, 4]` in images of `image_size
    [N, 2]` with outcome `tp [N]` and scores `raw [N]`, `cal [N]`: `features`, `edges [B + 1]`
    (the same for each feature) and per cell figure a `[B, B]` grid, row = cy bin (the top of
    the image first), column = cx bin, null in an empty cell."""
    n_bins = DECE_BINS[1]
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    feats = box_features(bbox, image_size, SELECTION_FEATURES)
    cell = bin_index(feats[:, 1], edges) * n_bins + bin_index(feats[:, 0], edges)
    size = n_bins * n_bins
    count = np.bincount(cell, minlength=size)
    hits = np.bincount(cell, weights=tp.astype(np.float64), minlength=size)

    def mean(values: np.ndarray) -> np.ndarray:
        total = np.bincount(cell, weights=values, minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0, total / count, np.nan)

    def dece(scores: np.ndarray) -> np.ndarray:
        out = np.full(size, np.nan)
        for c in np.flatnonzero(count):
            mine = cell == c
            out[c] = metrics.expected_calibration_error(scores[mine], tp[mine], DECE_BINS[0])
        return out

    def grid(values: np.ndarray) -> np.ndarray:
        return values.reshape(n_bins, n_bins)

    return {"features": list(SELECTION_FEATURES), "edges": edges,
            "count": grid(count), "true_positives": grid(hits.astype(np.int64)),
            "precision": grid(mean(tp.astype(np.float64))),
            "confidence_raw": grid(mean(raw)), "confidence_calibrated": grid(mean(cal)),
            "d_ece_raw": grid(dece(raw)), "d_ece_calibrated": grid(dece(cal))}


def _diagram(scores: np.ndarray, tp: np.ndarray) -> dict[str, Any]:
    d = metrics.reliability_diagram(scores, tp, RELIABILITY_BINS)
    return {"confidence": d.confidence, "accuracy": d.accuracy, "count": d.count}
