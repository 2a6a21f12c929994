"""The coverage of a 2-D profile's box regions per category × box size on held-out true
positives, with its sampling intervals: what the dashboard's coverage table prints.

The cells are the regions' own (`ConformalBoxes.size_edges_`, the detected box's size
`sqrt(w·h)`, bins `[lo, hi)` as the regions bin it); a true positive is covered at level q
when its conformity score is at most its served radius (`metrics.coverage_table`). Each level's
share comes with its covered count and its Clopper-Pearson interval (`metrics.
proportion_bounds`, `INTERVAL_CONFIDENCE`), and each cell with what its regions guarantee at
that level and the calibration scores behind it (`ConformalBoxes.guarantees`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from calibrators import metrics
from calibrators.boxes2d._box_scores import box_sizes
from calibrators.boxes2d._conformal_boxes import ConformalBoxes

__all__ = ["size_coverage"]


def size_coverage(regions: ConformalBoxes, bbox: np.ndarray, category: np.ndarray,
                  scores: np.ndarray, radii: np.ndarray, levels: Sequence[float],
                  names: dict[int, str]) -> dict[str, Any]:
    """Coverage (module docstring) of true positives with detected `bbox [M, 4]` (M >= 1) of
    `category [M]` (ids, named by `names`), conformity `scores [M]` and served `radii [M, Q]`
    at `levels [Q]`: `{"levels", "size_edges" [B + 1] (an infinite edge is null),
    "interval_confidence", "overall": {...}, "rows": [{"class", "bin", "size_range", ...}]}`,
    one row per category × size cell with true positives, each with `count`, `covered [Q]`,
    `coverage [Q]`, `interval [Q][2]`, and for a row `calibration_count` and `guarantee`
    {level: "cell" | "pooled" | "marginal"}."""
    table = metrics.coverage_table(scores, radii, levels, category, box_sizes(bbox),
                                   regions.size_edges_)
    promised = {(row["class"], row["bin"]): row for row in regions.guarantees(levels)}
    rows = []
    for row in table.rows:
        cell = promised.get((row["class"], row["bin"]), {})
        rows.append({"class": names.get(row["class"], str(row["class"])), "bin": row["bin"],
                     "size_range": row["distance_range"],
                     **_shares(np.asarray(row["coverage"]), row["count"]),
                     "calibration_count": cell.get("count"),
                     "guarantee": cell.get("guarantee")})
    return {"levels": list(levels), "size_edges": regions.size_edges_,
            "interval_confidence": metrics.INTERVAL_CONFIDENCE,
            "overall": _shares(table.overall, table.count), "rows": rows}


def _shares(coverage: np.ndarray, count: int) -> dict[str, Any]:
    """`count`, `covered [Q]`, `coverage [Q]` and `interval [Q][2]` of shares `coverage [Q]`
    of `count` true positives."""
    covered = np.rint(coverage * count).astype(np.int64)
    lo, hi = metrics.proportion_bounds(covered, np.full_like(covered, count))
    return {"count": int(count), "covered": covered, "coverage": coverage,
            "interval": np.stack([lo, hi], axis=1)}
