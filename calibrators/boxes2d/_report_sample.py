"""One held-out image of a 2-D fit report, as the dashboard draws it (a profile holds no
pixels: the image is its size, its boxes and what the profile served for them).

The image is the held-out image with the most true positives (then the most detections, then
the smallest id). It keeps its counted detections with a calibrated score of at least
`SAMPLE_MIN_SCORE`, the `SAMPLE_MAX_DETECTIONS` highest, each with its raw and calibrated
score, its category, whether it is a true positive, and its region at `SAMPLE_LEVEL` (inner
and outer box; an inner box is null where it is empty, an outer one where it is unbounded),
and the image's ground truth (at most `SAMPLE_MAX_TRUTH` boxes; crowd and ignored ones
marked).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from calibrators.boxes2d._boxes import Detections2D, GroundTruth2D
from calibrators.boxes2d._conformal_boxes import BoxRegions

__all__ = ["SAMPLE_LEVEL", "SAMPLE_MAX_DETECTIONS", "SAMPLE_MAX_TRUTH", "SAMPLE_MIN_SCORE",
           "sample_image"]

#: The level of the sample's regions, the least calibrated score it shows, and its caps.
SAMPLE_LEVEL = 0.9
SAMPLE_MIN_SCORE = 0.1
SAMPLE_MAX_DETECTIONS = 30
SAMPLE_MAX_TRUTH = 100


def sample_image(dets: Detections2D, tp: np.ndarray, cal: np.ndarray, image_size: np.ndarray,
                 regions: BoxRegions | None, truth: GroundTruth2D,
                 names: dict[int, str]) -> dict[str, Any] | None:
    """The sample (module docstring) among counted held-out detections `dets [N]` (N >= 0) with
    outcome `tp [N]`, calibrated scores `cal [N]`, `image_size [N, 2]` and served `regions`
    (levels including `SAMPLE_LEVEL`, or None) against the held-out `truth`; None when there
    is no detection. `{"image_id", "width", "height", "n_detections", "min_score", "level",
    "detections": [{"category", "bbox", "score_raw", "score", "true_positive", "inner",
    "outer"}], "truth": [{"category", "bbox", "ignored"}]}`."""
    if len(dets) == 0:
        return None
    ids, first, codes = np.unique(dets.image_id, return_index=True, return_inverse=True)
    tps = np.bincount(codes, weights=tp.astype(np.float64))
    found = np.bincount(codes)
    best = int(np.lexsort((ids, -found, -tps))[0])
    mine = np.flatnonzero(codes == best)
    mine = mine[cal[mine] >= SAMPLE_MIN_SCORE]
    mine = mine[np.argsort(-cal[mine], kind="stable")][:SAMPLE_MAX_DETECTIONS]
    q = None if regions is None else int(np.flatnonzero(np.isclose(regions.levels,
                                                                   SAMPLE_LEVEL))[0])
    width, height = image_size[first[best]]
    shown = [{"category": names.get(int(dets.category_id[i]), str(dets.category_id[i])),
              "bbox": dets.bbox[i], "score_raw": dets.score[i], "score": cal[i],
              "true_positive": bool(tp[i]),
              "inner": None if q is None else _box(regions.inner[i, q]),
              "outer": None if q is None else _box(regions.outer[i, q])} for i in mine]
    gt = np.flatnonzero(truth.image_id == ids[best])[:SAMPLE_MAX_TRUTH]
    return {"image_id": int(ids[best]), "width": float(width), "height": float(height),
            "n_detections": int(found[best]), "min_score": SAMPLE_MIN_SCORE,
            "level": None if q is None else SAMPLE_LEVEL, "detections": shown,
            "truth": [{"category": names.get(int(truth.category_id[g]),
                                             str(truth.category_id[g])),
                       "bbox": truth.bbox[g], "ignored": bool(truth.iscrowd[g]
                                                              | truth.ignore[g])}
                      for g in gt]}


def _box(box: Sequence[float]) -> list[float] | None:
    """A served COCO box, or None when it is empty or unbounded."""
    b = np.asarray(box, dtype=np.float64)
    if not np.isfinite(b).all() or b[2] < 0 or b[3] < 0:
        return None
    return b.tolist()
