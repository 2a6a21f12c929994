"""A COCO box `x, y, w, h` as its four edges `x1, y1, x2, y2` (left, top, right, bottom, in
pixels) and back: the coordinates in which box errors, covariances and regions are stated.

    x1 = x,  y1 = y,  x2 = x + w,  y2 = y + h
"""

from __future__ import annotations

import numpy as np

__all__ = ["EDGE_NAMES", "box_edges", "edges_box"]

#: The four edges of a box, in the column order of every `[..., 4]` edge array.
EDGE_NAMES: tuple[str, ...] = ("x1", "y1", "x2", "y2")


def box_edges(bbox: np.ndarray) -> np.ndarray:
    """Edges `[..., 4]` (x1, y1, x2, y2) of COCO boxes `bbox [..., 4]` (x, y, w, h), float64."""
    b = np.asarray(bbox, dtype=np.float64)
    return np.concatenate([b[..., :2], b[..., :2] + b[..., 2:]], axis=-1)


def edges_box(edges: np.ndarray) -> np.ndarray:
    """COCO boxes `[..., 4]` (x, y, w, h) of edges `[..., 4]` (x1, y1, x2, y2), float64; a box
    whose edges cross (x2 < x1) gets a negative width, kept as it is."""
    e = np.asarray(edges, dtype=np.float64)
    return np.concatenate([e[..., :2], e[..., 2:] - e[..., :2]], axis=-1)
