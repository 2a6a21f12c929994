"""Conformity scores of a detected box against its true box, and the box region a radius
gives back (puncc's `SplitBoxWise`, with the four edges joined by their maximum).

With `e = edges(true) − edges(detected)` over (x1, y1, x2, y2) (`_edges`), in pixels:

- additive: `s = max_j |e_j|`; the region of radius r moves every edge by r;
- scaled: `s = max_j |e_j| / σ_j` with the detector's own standard deviation `σ [4]` per
  edge (`edge_sigma`); the region moves edge j by `r·σ_j`.

Either way `s <= r` exactly when every true edge lies within its detected edge ± r (or ± r·σ_j):
the true box contains the inner box (edges moved inwards) and lies inside the outer box (edges
moved outwards). Taking the maximum over the edges makes one quantile cover all four jointly
and exactly; puncc's Bonferroni split (each edge at level 1 − α/4) bounds the joint miss rate
by the sum of the four.

A region's inner box has a negative width (or height) where the moved edges cross: no box is
then certain to lie inside the true one, and only the outer box and the edge bounds hold. An
infinite radius (a level that a group's scores cannot certify) gives an outer box of infinite
extent and an inner box of infinitely negative size.
"""

from __future__ import annotations

import numpy as np

from calibrators.boxes2d._boxes import check_bbox
from calibrators.boxes2d._edges import box_edges, edges_box
from calibrators.core.checks import as_float_array, check_choice, check_length
from calibrators.core.errors import FieldError

__all__ = ["BOX_SCORES", "REGION_SCORES", "box_scores", "box_sizes", "check_sigma",
           "conformity_score", "region_boxes"]

#: The conformity scores: pixels, or pixels over a per-edge σ.
BOX_SCORES: tuple[str, ...] = ("additive", "scaled")
#: The box regions a 2-D profile serves: additive; scaled by the σ of the decoder layers'
#: spread; adaptive: scaled by the fitted edge-error scale (`EdgeErrorScale`).
REGION_SCORES: tuple[str, ...] = ("additive", "scaled", "adaptive")


def conformity_score(region_score: str) -> str:
    """The conformity score (`BOX_SCORES`) behind a `REGION_SCORES` entry: `scaled` for
    both σ-scaled kinds, whatever gives the σ."""
    check_choice("region_score", region_score, REGION_SCORES)
    return "additive" if region_score == "additive" else "scaled"


def check_sigma(sigma: object, n: int, score: str) -> np.ndarray | None:
    """`sigma` as `[n, 4]` float64, each finite and > 0 (the scaled score divides by it), or
    None for the additive score (which does not read it); FieldError otherwise."""
    check_choice("score", score, BOX_SCORES)
    if score == "additive":
        return None
    if sigma is None:
        raise FieldError("sigma", "the scaled score needs sigma [N, 4], the standard deviation "
                                  "of each box edge (edge_sigma)")
    s = as_float_array("sigma", sigma, ndim=2)
    if s.shape[1:] != (4,):
        raise FieldError("sigma", f"sigma must have shape [N, 4] (x1, y1, x2, y2), got {s.shape}")
    check_length("sigma", s, n, "boxes")
    bad = ~(s > 0).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError("sigma", f"sigma[{i}] must be > 0 (floor it: edge_covariance's "
                                  f"min_sigma), got {s[i].tolist()}", row=i)
    return s


def box_scores(boxes: np.ndarray, true_boxes: np.ndarray, sigma: np.ndarray | None = None,
               score: str = "additive") -> np.ndarray:
    """`[M]` conformity score (module docstring) of detected `boxes [M, 4]` against
    `true_boxes [M, 4]` (COCO x, y, w, h), `sigma [M, 4]` for the scaled score."""
    det = check_bbox("boxes", boxes, None)
    true = check_bbox("true_boxes", true_boxes, len(det), "boxes")
    s = check_sigma(sigma, len(det), score)
    err = np.abs(box_edges(true) - box_edges(det))
    if s is not None:
        err = err / s
    return err.max(axis=1) if len(err) else np.zeros(0)


def region_boxes(boxes: np.ndarray, radii: np.ndarray, sigma: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Inner and outer COCO boxes `[N, Q, 4]` of checked `boxes [N, 4]` at `radii [N, Q]`,
    each edge moved by r (sigma None) or r·σ_j (`sigma [N, 4]`)."""
    edges = box_edges(boxes)[:, None, :]                      # [N, 1, 4]
    reach = radii[:, :, None] * (1.0 if sigma is None else sigma[:, None, :])
    inward = np.array([1.0, 1.0, -1.0, -1.0])                 # x1, y1 move right/down
    # an infinite reach gives x2 - x1 = -inf - inf (inner) or inf + inf (outer): never NaN
    return edges_box(edges + inward * reach), edges_box(edges - inward * reach)


def box_sizes(boxes: np.ndarray) -> np.ndarray:
    """`[N]` size `sqrt(w·h)` (pixels) of checked COCO `boxes [N, 4]`: the quantity COCO's
    small / medium / large ranges bound (32² and 96² px² of area)."""
    return np.sqrt(boxes[:, 2] * boxes[:, 3])
