"""The dashboard's bird's-eye view: panels stacked one above the other, zoomed to the objects
(ground truth, detections and their ellipses), points drawn as one raster layer, ellipses
filled so that small ones still show, and score labels placed so that none overlaps another.

Called by `plots.bev` under its figure lock and RC; matplotlib is imported by then.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from calibrators.regions import Ellipse
from detectors.panels import pyplot
from detectors.panels.bev import BevStyle, bev_panel

#: Grey points as one raster image (no marker per point), solid green ground truth, each
#: panel's detections and ellipses in the panel's colour; labels are placed here instead.
STYLE = BevStyle(point_color="0.6", point_size=(0.6, 0.6), gt_color="#2ca02c", gt_width=0.8,
                 gt_line="-", box_width=0.9, label_dy=0.0, label_colored=True,
                 ellipse_width=1.1, ellipse_alpha=0.9, ego_size=6, units="[m]",
                 rasterize_points=True)
#: Metres of margin around the objects; the smallest span of an axis.
MARGIN_M, MIN_SPAN_M = 4.0, 20.0
#: Width of the figure (inches) and the most height one panel takes.
WIDTH_IN, MAX_PANEL_IN = 13.0, 5.0
#: Dots per inch of the raster point layer.
POINT_DPI = 110
LABEL_SIZE = 6.5


def content_box(gt_boxes: np.ndarray, panels: Sequence[dict]) -> tuple[float, float, float,
                                                                       float]:
    """`(x0, x1, y0, y1)` metres holding the ego, the ground truth, every detection and its
    ellipse, with a margin; each span at least `MIN_SPAN_M`."""
    xs, ys = [0.0], [0.0]
    for boxes, reach in [(gt_boxes, None)] + [(p["boxes"], p.get("ellipses"))
                                               for p in panels]:
        if len(boxes) == 0:
            continue
        r = np.hypot(boxes[:, 3], boxes[:, 4]) / 2
        if reach is not None:
            r = np.maximum(r, np.asarray(reach[0], dtype=float))
        xs += [float(np.min(boxes[:, 0] - r)), float(np.max(boxes[:, 0] + r))]
        ys += [float(np.min(boxes[:, 1] - r)), float(np.max(boxes[:, 1] + r))]
    box = []
    for lo, hi in ((min(xs), max(xs)), (min(ys), max(ys))):
        lo, hi = lo - MARGIN_M, hi + MARGIN_M
        grow = max(0.0, MIN_SPAN_M - (hi - lo)) / 2
        box += [lo - grow, hi + grow]
    return box[0], box[1], box[2], box[3]


def _fit_aspect(box: tuple[float, float, float, float], width: float,
                height: float) -> tuple[float, float, float, float]:
    """`box` widened along one axis so that it fills a `width` x `height` panel at equal
    scale."""
    x0, x1, y0, y1 = box
    want = width / height
    if (x1 - x0) / (y1 - y0) < want:
        grow = ((y1 - y0) * want - (x1 - x0)) / 2
        return x0 - grow, x1 + grow, y0, y1
    grow = ((x1 - x0) / want - (y1 - y0)) / 2
    return x0, x1, y0 - grow, y1 + grow


#: Label offsets tried in turn (points from the box centre): above, below, right, left, then
#: further up and down; `ha`/`va` follow the side.
_OFFSETS = [(0, 7, "center", "bottom"), (0, -7, "center", "top"), (9, 0, "left", "center"),
            (-9, 0, "right", "center")] + [
    (0, s * (7 + 8 * k), "center", "bottom" if s > 0 else "top")
    for k in range(1, 30) for s in (1, -1)]


_HALO = {"boxstyle": "square,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.75}


def place_labels(ax: Any, renderer: Any, xy: np.ndarray, texts: Sequence[str], color: str,
                 panel: int) -> None:
    """Each text near its point at the first offset where it overlaps no label placed
    before it (a thin leader line when it had to move away); gid `score-<panel>-<i>`."""
    placed: list[Any] = []
    for i in np.argsort(xy[:, 0]):
        for dx, dy, ha, va in _OFFSETS:
            far = abs(dy) > 8
            t = ax.annotate(texts[i], tuple(xy[i]), xytext=(dx, dy), textcoords="offset points",
                            ha=ha, va=va, fontsize=LABEL_SIZE, color=color, bbox=_HALO,
                            arrowprops={"arrowstyle": "-", "lw": 0.4, "color": color}
                            if far else None, annotation_clip=False)
            bb = t.get_window_extent(renderer).expanded(1.2, 1.3)
            if not any(bb.overlaps(p) for p in placed):
                t.set_gid(f"score-{panel}-{i}")
                placed.append(bb)
                break
            t.remove()


def draw(points: np.ndarray, gt_boxes: np.ndarray, panels: Sequence[dict]) -> Any:
    """The figure: one row per panel (`{"title", "boxes" [N, 9], "scores" [N], "ellipses":
    (major, minor, angle) arrays or None, "color"}`), all at the same zoom."""
    box = content_box(gt_boxes, panels)
    aspect = (box[1] - box[0]) / (box[3] - box[2])
    height = min(MAX_PANEL_IN, max(2.4, WIDTH_IN / aspect))
    x0, x1, y0, y1 = _fit_aspect(box, WIDTH_IN, height)
    inside = ((points[:, 0] > x0) & (points[:, 0] < x1) & (points[:, 1] > y0)
              & (points[:, 1] < y1)) if len(points) else np.zeros(0, bool)
    fig, axes = pyplot().subplots(len(panels), 1, figsize=(WIDTH_IN, height * len(panels) + 0.6),
                                  squeeze=False)
    fig.dpi = POINT_DPI
    renderer = fig.canvas.get_renderer()
    for k, (ax, panel) in enumerate(zip(axes[:, 0], panels, strict=True)):
        el = panel.get("ellipses")
        ell = None if el is None else Ellipse(*el)
        bev_panel(ax, points[inside], gt_boxes, panel["boxes"], [""] * len(panel["boxes"]),
                  None, color=panel["color"], ellipse_color=panel["color"], half=1.0,
                  style=STYLE)
        if ell is not None:
            _ellipses(ax, panel["boxes"], ell, panel["color"], k)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_title(panel["title"])
    fig.tight_layout()
    for k, (ax, panel) in enumerate(zip(axes[:, 0], panels, strict=True)):
        place_labels(ax, renderer, np.asarray(panel["boxes"])[:, :2].reshape(-1, 2),
                     [f"{s:.2f}" for s in panel["scores"]], panel["color"], k)
    return fig


def _ellipses(ax: Any, boxes: np.ndarray, ell: Ellipse, color: str, panel: int) -> None:
    """Every ellipse filled (light) and outlined, so that one a few pixels wide still shows;
    gid `ellipse-<panel>-<i>`."""
    from matplotlib.colors import to_rgba
    from matplotlib.patches import Ellipse as EllipsePatch

    fill = (*to_rgba(color)[:3], 0.22)
    for j, box in enumerate(boxes):
        if not ell.semi_major[j] > 0:
            continue
        patch = EllipsePatch((box[0], box[1]), 2 * ell.semi_major[j], 2 * ell.semi_minor[j],
                             angle=math.degrees(ell.angle[j]), facecolor=fill,
                             edgecolor=color, lw=STYLE.ellipse_width, zorder=3)
        patch.set_gid(f"ellipse-{panel}-{j}")
        ax.add_patch(patch)
