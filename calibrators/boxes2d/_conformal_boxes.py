"""Split-conformal box regions per class × box-size bin: an inner and an outer box such that
the true box lies between them (all four edges jointly) with probability >= q.

Fit on matched true positives of a calibration split (disjoint from what the detector and the
score calibration were fit on): each has a conformity score (`_box_scores`: additive pixels or
scaled by the detector's σ per edge). The Mondrian groups and their radii are
`calibrators.regions.ConformalRegions` on those scores, with the box size `sqrt(w·h)` of the
detected box in place of the distance: the size bins are COCO's small / medium / large
(`[0, 32)`, `[32, 96)`, `[96, inf)` pixels; a size of exactly 32 is medium), explicit edges, or
`k` quantile bins of the calibration boxes' sizes. A group's radius at level q is the
`⌈(n+1)·q⌉`-th smallest of its n scores; a class × bin cell with fewer than `min_group`
scores is merged with its neighbouring bins, a class too small as a whole is pooled with the
other small classes, and below that all scores serve (what each cell gets is recorded:
`guarantees`, "cell", "pooled" or "marginal", with its calibration count). Coverage >= q
holds per group on exchangeable data, on average over the calibration draw; a cell pooled
with others is covered only on average over its pool.

The size is the detected box's (known when serving), not the ground truth's COCO `area`.
With quantile bins the edges come from the calibration scores' own boxes: the partition then
depends (weakly) on the calibration draw.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibrators.boxes2d._box_scores import (
    BOX_SCORES,
    box_scores,
    box_sizes,
    check_sigma,
    region_boxes,
)
from calibrators.boxes2d._boxes import check_bbox
from calibrators.core.bins import check_n_bins
from calibrators.core.checks import check_choice, check_fitted, check_length
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable
from calibrators.regions import ConformalRegions, check_distance_edges, check_levels

__all__ = ["COCO_SIZE_EDGES", "BoxRegions", "ConformalBoxes"]

#: COCO's small / medium / large box sizes `sqrt(area)` (pixels) as bin edges.
COCO_SIZE_EDGES: tuple[float, ...] = (0.0, 32.0, 96.0, float("inf"))


@dataclass(frozen=True, eq=False)
class BoxRegions:
    """Served regions of N detections at Q levels.

    levels [Q]                  the coverage levels q
    inner, outer [N, Q, 4]      COCO boxes x, y, w, h (an inner box with w < 0 or h < 0 is
                                empty; an unbounded level has infinite extents)
    guarantee [N, Q] str        what holds for the detection's class × size cell: "cell",
                                "pooled" or "marginal" (`ConformalRegions.guarantee_table`)
    calibration_n [N, Q] int64  the calibration scores behind that guarantee
    """

    levels: np.ndarray
    inner: np.ndarray
    outer: np.ndarray
    guarantee: np.ndarray
    calibration_n: np.ndarray

    def __len__(self) -> int:
        return len(self.inner)


class ConformalBoxes:
    """Split-conformal inner / outer boxes per class × box-size bin (module docstring).

    Parameters
    ----------
    score : "additive" (pixels) or "scaled" (pixels / σ of each edge).
    size_edges : increasing bin edges of `sqrt(w·h)` in pixels (>= 0; the last may be inf),
        default COCO's; or an int k >= 1: k bins at the quantiles of the calibration boxes.
    min_group, n_exact, max_ranks : as `ConformalRegions`.

    Fitted: `size_edges_ [B + 1]` and `conformal_` (the `ConformalRegions` of the scores:
    its `classes_`, `counts_ [C, B]`, `groups_`, `serving_`, `reasons_`).
    """

    def __init__(self, score: str = "additive",
                 size_edges: Sequence[float] | int = COCO_SIZE_EDGES, min_group: int = 100,
                 n_exact: int = 500, max_ranks: int = 600) -> None:
        self.score = score
        self.size_edges = size_edges
        self.min_group = min_group
        self.n_exact = n_exact
        self.max_ranks = max_ranks

    def fit(self, boxes: np.ndarray, true_boxes: np.ndarray, labels: np.ndarray,
            sigma: np.ndarray | None = None, all_classes: Sequence[Hashable] | None = None
            ) -> ConformalBoxes:
        """Fit on matched true positives: detected `boxes [M, 4]`, their `true_boxes [M, 4]`
        (COCO x, y, w, h), class `labels [M]` (ints or names) and, for the scaled score,
        `sigma [M, 4]` (> 0 per edge); `all_classes` lists every class to serve (default:
        those in `labels`). Returns self."""
        check_choice("score", self.score, BOX_SCORES)
        det = check_bbox("boxes", boxes, None)
        scores = box_scores(det, true_boxes, sigma, self.score)
        sizes = box_sizes(det)
        edges = self._edges(sizes)
        labels = np.asarray(labels)
        if labels.ndim != 1:
            raise FieldError("labels", f"labels must have 1 dimension, got shape {labels.shape}")
        check_length("labels", labels, len(det), "boxes")
        self.conformal_ = ConformalRegions(
            distance_edges=tuple(edges.tolist()), min_group=self.min_group,
            n_exact=self.n_exact, max_ranks=self.max_ranks).fit(scores, labels, sizes,
                                                                 all_classes)
        self.size_edges_ = self.conformal_.edges_
        return self

    def radii(self, levels: Sequence[float], boxes: np.ndarray, labels: np.ndarray
              ) -> np.ndarray:
        """Radii `[N, Q]` (pixels, or multiples of σ) at `levels [Q]` for detected
        `boxes [N, 4]` of class `labels [N]` (a class unseen at fit: all scores' group)."""
        check_fitted(self, "conformal_")
        det = check_bbox("boxes", boxes, None)
        return self.conformal_.radii(levels, _labels(labels, len(det)), box_sizes(det))

    def regions(self, boxes: np.ndarray, labels: np.ndarray, sigma: np.ndarray | None,
                levels: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """Inner and outer COCO boxes `[N, Q, 4]` of detected `boxes [N, 4]` of class
        `labels [N]`, with `sigma [N, 4]` for the scaled score (unused by the additive one),
        at `levels [Q]`: the true box lies between them with probability >= q."""
        served = self.serve(boxes, labels, sigma, levels)
        return served.inner, served.outer

    def serve(self, boxes: np.ndarray, labels: np.ndarray, sigma: np.ndarray | None,
              levels: Sequence[float]) -> BoxRegions:
        """The regions of `regions` with, per detection and level, the guarantee of its cell
        and the calibration count behind it."""
        check_fitted(self, "conformal_")
        q = check_levels(levels)
        det = check_bbox("boxes", boxes, None)
        s = check_sigma(sigma, len(det), self.score)
        group = self.conformal_.group_index(_labels(labels, len(det)), box_sizes(det))
        radii = self.conformal_.radius_table(q)[group]
        names, counts = self.conformal_.guarantee_table(q)
        inner, outer = region_boxes(det, radii, s)
        return BoxRegions(q, inner, outer, names[group].astype(str), counts[group])

    def scores(self, boxes: np.ndarray, true_boxes: np.ndarray,
               sigma: np.ndarray | None = None) -> np.ndarray:
        """`[M]` conformity scores of this estimator's `score` type (`box_scores`)."""
        return box_scores(boxes, true_boxes, sigma, self.score)

    def guarantees(self, levels: Sequence[float]) -> list[dict[str, Any]]:
        """One row per class × size bin: `class`, `bin`, `size_range` [lo, hi] (pixels; an
        infinite edge is None), `count` (calibration scores in the cell), `group_n` (in the
        group serving it) and `guarantee` {level: "cell" | "pooled" | "marginal"}."""
        check_fitted(self, "conformal_")
        rows = self.conformal_.guarantees(levels)
        edges = to_jsonable(self.size_edges_)
        return [{**row, "size_range": edges[row["bin"]:row["bin"] + 2]} for row in rows]

    def to_dict(self) -> dict[str, Any]:
        """Strict-JSON-able plain dict; `from_dict` serves identically."""
        check_fitted(self, "conformal_")
        return to_jsonable({"hyper": {"score": self.score, "size_edges": _edges_json(
            self.size_edges), "min_group": self.min_group, "n_exact": self.n_exact,
            "max_ranks": self.max_ranks}, "conformal": self.conformal_.to_dict()})

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ConformalBoxes:
        """The fitted estimator `to_dict` wrote; ValueError naming a missing or bad key."""
        if not isinstance(data, dict):
            raise ValueError(f"conformal boxes must be a dict, got {type(data).__name__}")
        missing = [k for k in ("hyper", "conformal") if k not in data]
        if missing:
            raise ValueError(f"conformal boxes dict lacks {missing[0]!r}")
        hyper = dict(data["hyper"])
        if isinstance(hyper.get("size_edges"), list):
            hyper["size_edges"] = tuple(float("inf") if v is None else float(v)
                                        for v in hyper["size_edges"])
        try:
            self = cls(**hyper)
        except TypeError as exc:
            raise ValueError(f"hyper has a bad key: {exc}") from None
        check_choice("score", self.score, BOX_SCORES)
        self.conformal_ = ConformalRegions.from_dict(data["conformal"])
        self.size_edges_ = self.conformal_.edges_
        return self

    def _edges(self, sizes: np.ndarray) -> np.ndarray:
        """The size bin edges `[B + 1]`: the given ones, or k quantile bins of `sizes [M]`
        (duplicate quantiles merged)."""
        if isinstance(self.size_edges, int | np.integer) and not isinstance(self.size_edges,
                                                                              bool):
            k = check_n_bins("size_edges", self.size_edges, minimum=1)
            inner = np.quantile(sizes, np.arange(1, k) / k) if len(sizes) else np.zeros(0)
            return np.unique(np.r_[0.0, inner[inner > 0], np.inf])
        return check_distance_edges(self.size_edges, "size_edges")


def _labels(labels: np.ndarray, n: int) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.ndim != 1:
        raise FieldError("labels", f"labels must have 1 dimension, got shape {arr.shape}")
    check_length("labels", arr, n, "boxes")
    return arr


def _edges_json(edges: Sequence[float] | int) -> Any:
    return int(edges) if isinstance(edges, int | np.integer) else [float(e) for e in edges]
