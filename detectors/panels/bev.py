"""Bird's-eye view of one frame: points, ground-truth boxes, detections with a text and a
confidence ellipse each, and the ego (`detcal show`, the report's BEV figure, the
dashboard). What differs between those pictures is data: a `BevStyle`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibrators.regions import Ellipse


@dataclass(frozen=True)
class BevStyle:
    """How one kind of picture draws a bird's-eye view (matplotlib colours and sizes).

    point_color: one colour for every point, or None to colour points by height (viridis).
    point_size: marker area of a dense cloud (over 5000 points) and of a sparse one.
    gt_line: line style of the ground-truth outlines.
    label_dy: metres between a detection's centre and its text.
    label_colored: the text in the detection's colour (else the default text colour).
    units: how the x and y axis labels write metres.
    """

    point_color: str | None
    point_size: tuple[float, float]
    gt_color: str
    box_width: float
    label_dy: float
    label_colored: bool
    point_alpha: float | None = None
    rasterize_points: bool = False
    gt_width: float = 1.0
    gt_line: str = "--"
    ellipse_width: float = 0.9
    ellipse_alpha: float | None = None
    ego_size: float = 8
    units: str = "(m)"


def bev_panel(ax: Any, points: np.ndarray, gt_boxes: np.ndarray, boxes: np.ndarray,
              texts: Sequence[str], ell: Ellipse | None, *, color: str, ellipse_color: str,
              half: float, style: BevStyle) -> None:
    """Draw one frame on `ax`, a square [-half, half]^2 metres around the ego.

    `points [P, >=2]` (a third column is the height), ground truth `gt_boxes [G, >=7]`,
    detections `boxes [N, >=7]` outlined in `color` with `texts[N]` above them, and `ell`,
    their ellipses (`[N]` arrays, centred on the boxes; zero-size ones are left out) or None.
    """
    from detectors.sim.geometry import bev_outline

    if len(points):
        size = style.point_size[0] if len(points) > 5000 else style.point_size[1]
        colour: dict[str, Any] = {"c": style.point_color}
        if style.point_color is None and points.shape[1] > 2:
            colour = {"c": points[:, 2], "cmap": "viridis"}
        ax.scatter(points[:, 0], points[:, 1], s=size, alpha=style.point_alpha, linewidths=0,
                   rasterized=style.rasterize_points, **colour)
    for box in gt_boxes:
        xy = bev_outline(box)
        ax.plot(xy[:, 0], xy[:, 1], color=style.gt_color, lw=style.gt_width, ls=style.gt_line)
    for j, (box, text) in enumerate(zip(boxes, texts, strict=True)):
        xy = bev_outline(box)
        ax.plot(xy[:, 0], xy[:, 1], color=color, lw=style.box_width)
        ax.text(box[0], box[1] + style.label_dy, text, fontsize=5, ha="center",
                color=color if style.label_colored else None)
        if ell is not None and ell.semi_major[j] > 0:
            _ellipse(ax, box[0], box[1], ell, j, ellipse_color, lw=style.ellipse_width,
                     alpha=style.ellipse_alpha)
    ax.plot([0], [0], marker="^", color="black", ms=style.ego_size)
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x {style.units}")
    ax.set_ylabel(f"y {style.units}")


def _ellipse(ax: Any, x: float, y: float, ell: Ellipse, j: int, color: str,
             **style: Any) -> None:
    """Draw ellipse `j` of `ell` centred at (x, y) metres (`style`: patch keywords)."""
    from matplotlib.patches import Ellipse as EllipsePatch

    ax.add_patch(EllipsePatch((x, y), 2 * ell.semi_major[j], 2 * ell.semi_minor[j],
                              angle=math.degrees(ell.angle[j]), fill=False, color=color,
                              **style))
