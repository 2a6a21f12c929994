"""Calibrated detections as a COCO results list, and its JSON file.

Record i is detection i (the input's row order: identity is kept by position in the list):

    {"image_id", "category_id", "bbox": [x, y, w, h],
     "score": the calibrated score, "score_raw": the detector's score (when calibrated),
     "logits", "layer_boxes" (when the detections carry them),
     "region_<q>": {"inner": [x, y, w, h], "outer": [x, y, w, h],
                    "guarantee": "cell" | "pooled" | "marginal", "calibration_n": int}}

one `region_<q>` per served level, `<q>` as `str(float(q))` (`region_0.9`). An unbounded
level (its group's scores cannot certify q) writes `"inner": null, "outer": null`. An inner
box with a negative width or height is written as it is: the edges' intervals cross, and only
the outer box and the edge bounds hold. Reading the file back (`read_coco_results`) gives the
same detections, with the calibrated score as `score`.
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from calibrators.boxes2d._boxes import Detections2D
from calibrators.boxes2d._conformal_boxes import BoxRegions
from calibrators.core.checks import as_float_array, check_length, check_probabilities
from calibrators.core.errors import FieldError
from calibrators.io.atomic import atomic_write

__all__ = ["coco_results", "write_coco_results"]


def coco_results(detections: Detections2D, scores: np.ndarray | None = None,
                 regions: BoxRegions | None = None) -> list[dict[str, Any]]:
    """The COCO results list of `detections` (module docstring) with calibrated
    `scores [N]` in [0, 1] (None: the detections' own, and no `score_raw`) and `regions`
    (`ConformalBoxes.serve` of the same detections, or None)."""
    if not isinstance(detections, Detections2D):
        raise FieldError("detections", "detections must be a Detections2D")
    n = len(detections)
    columns: dict[str, list[Any]] = {
        "image_id": detections.image_id.tolist(), "category_id": detections.category_id.tolist(),
        "bbox": detections.bbox.tolist()}
    if scores is None:
        columns["score"] = detections.score.tolist()
    else:
        calibrated = as_float_array("scores", scores, ndim=1)
        check_length("scores", calibrated, n, "detections")
        check_probabilities("scores", calibrated)
        columns["score"] = calibrated.tolist()
        columns["score_raw"] = detections.score.tolist()
    for key in ("logits", "layer_boxes"):
        value = getattr(detections, key)
        if value is not None:
            columns[key] = value.tolist()
    if regions is not None:
        if not isinstance(regions, BoxRegions) or len(regions) != n:
            raise FieldError("regions", f"regions must be the BoxRegions of the {n} detections")
        for j, level in enumerate(regions.levels.tolist()):
            columns[f"region_{float(level)}"] = _region_column(regions, j)
    keys = list(columns)
    return [dict(zip(keys, row, strict=True)) for row in zip(*columns.values(), strict=True)]


def write_coco_results(path: str | os.PathLike[str], detections: Detections2D,
                       scores: np.ndarray | None = None, regions: BoxRegions | None = None
                       ) -> None:
    """Write `coco_results(detections, scores, regions)` as strict JSON to `path`, replacing
    the file in one rename (never half written)."""
    records = coco_results(detections, scores, regions)
    with atomic_write(path) as fh:
        json.dump(records, fh, allow_nan=False, separators=(",", ":"))


def _region_column(regions: BoxRegions, j: int) -> list[dict[str, Any]]:
    """`[N]` region objects at level index j (None boxes where the radius is unbounded)."""
    inner, outer = regions.inner[:, j], regions.outer[:, j]
    bounded = np.isfinite(outer).all(axis=1) & np.isfinite(inner).all(axis=1)
    inner_list, outer_list = inner.tolist(), outer.tolist()
    return [{"inner": i if ok else None, "outer": o if ok else None, "guarantee": g,
             "calibration_n": c}
            for i, o, ok, g, c in zip(inner_list, outer_list, bounded.tolist(),
                                      regions.guarantee[:, j].tolist(),
                                      regions.calibration_n[:, j].tolist(), strict=True)]
