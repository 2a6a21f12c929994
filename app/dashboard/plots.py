"""Matplotlib figures (Agg backend) rendered to inline SVG strings for the dashboard.

Inputs are the plot data of a profile's report (`report["fit"]["plots"]`, see
calibrators.report) and, for the bird's-eye view, one frame's detections.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Ellipse as EllipsePatch  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from detectors.sim.geometry import bev_outline  # noqa: E402

BEFORE, AFTER = "#d62728", "#1f77b4"
plt.rcParams.update({"svg.fonttype": "none", "font.size": 8, "axes.titlesize": 9,
                     "svg.hashsalt": "detcal"})


def to_svg(fig: Figure, title: str) -> str:
    """The figure as an `<svg>` element (XML prolog dropped), closed afterwards."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Title": title, "Date": None})
    plt.close(fig)
    text = buf.getvalue()
    start = text.find("<svg")
    svg = re.sub(r"<metadata>.*?</metadata>\s*", "", text[start:], flags=re.S)
    return svg.replace("<svg ", f'<svg class="plot" role="img" aria-label="{title}" ', 1)


def _arr(values: Sequence[Any] | None) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in (values or [])], dtype=float)


def _reliability_axes(ax: Any, before: dict | None, after: dict | None, title: str) -> None:
    ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--")
    for data, color, label in ((before, BEFORE, "before"), (after, AFTER, "after")):
        if not data:
            continue
        conf, acc = _arr(data["confidence"]), _arr(data["accuracy"])
        ok = np.isfinite(conf) & np.isfinite(acc)
        ax.plot(conf[ok], acc[ok], "o-", color=color, ms=3, lw=1.2, label=label)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title(title)
    ax.set_aspect("equal")


def reliability(plots: dict, title: str = "Reliability (all classes)") -> str:
    """Accuracy vs confidence per bin, before and after calibration."""
    fig, ax = plt.subplots(figsize=(3.4, 3.4))
    rel = plots.get("reliability") or {}
    _reliability_axes(ax, rel.get("before"), rel.get("after"), title)
    ax.set_xlabel("confidence")
    ax.set_ylabel("precision (TP fraction)")
    ax.legend(loc="upper left", frameon=False)
    return to_svg(fig, title)


def reliability_per_class(plots: dict) -> str:
    """Small-multiple reliability diagrams, one per class."""
    per = plots.get("reliability_per_class") or {}
    names = list(per)
    cols = 5
    rows = max(1, math.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(1.9 * cols, 2.0 * rows), squeeze=False)
    for ax in axes.flat:
        ax.set_visible(False)
    for ax, name in zip(axes.flat, names, strict=False):
        ax.set_visible(True)
        _reliability_axes(ax, per[name].get("before"), per[name].get("after"), name)
        ax.tick_params(labelsize=6)
    fig.tight_layout()
    return to_svg(fig, "Reliability per class")


def calibration_curves(plots: dict) -> str:
    """Average-calibration curves (observed vs expected interval proportion) for x and y."""
    curves = plots.get("calibration_curve") or {}
    fig, axes = plt.subplots(1, 2, figsize=(6.4, 3.2))
    for ax, axis in zip(axes, ("x", "y"), strict=True):
        ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--")
        data = curves.get(axis) or {}
        for key, color in (("before", BEFORE), ("after", AFTER)):
            c = data.get(key)
            if c:
                ax.plot(_arr(c["expected"]), _arr(c["observed"]), color=color, lw=1.4, label=key)
        if not any(data.get(k) for k in ("before", "after")):
            ax.text(0.5, 0.5, "no covariance", ha="center", va="center")
        ax.set_title(f"Average calibration, {axis}")
        ax.set_xlabel("expected proportion in interval")
        ax.set_ylabel("observed proportion")
        ax.set_aspect("equal")
        ax.legend(loc="upper left", frameon=False)
    fig.tight_layout()
    return to_svg(fig, "Average calibration curves")


def residual_plot(plots: dict) -> str:
    """Residual norm vs predicted sigma (sqrt trace Σ) of matched detections."""
    res = plots.get("residuals") or {}
    fig, ax = plt.subplots(figsize=(3.6, 3.4))
    top = 0.0
    for key, color in (("before", BEFORE), ("after", AFTER)):
        r = res.get(key)
        if r:
            sigma, norm = _arr(r["sigma"]), _arr(r["residual_norm"])
            ax.scatter(sigma, norm, s=4, alpha=0.45, color=color, label=key, linewidths=0)
            top = max(top, float(np.nanmax(sigma)) if sigma.size else 0.0)
    if top > 0:
        ax.plot([0, top], [0, top], color="0.4", lw=0.8, ls="--", label="|r| = σ")
    else:
        ax.text(0.5, 0.5, "no covariance", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("predicted σ = sqrt(trace Σ)  [m]")
    ax.set_ylabel("residual |r|  [m]")
    ax.set_title("Residuals vs uncertainty")
    ax.legend(loc="upper left", frameon=False, markerscale=3)
    return to_svg(fig, "Residual plot")


def bev(points: np.ndarray, gt_boxes: np.ndarray, panels: Sequence[dict], extent: float,
        title: str) -> str:
    """Bird's-eye view panels of one frame.

    Each panel: `{"title", "boxes" [N, 9], "scores" [N], "ellipses": (major, minor, angle)
    arrays or None, "color"}`; points `[P, >=2]`, ground truth `[G, 9]`.
    """
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.4), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        if len(points):
            ax.scatter(points[:, 0], points[:, 1], s=0.3, color="0.55", linewidths=0,
                       rasterized=False)
        for box in gt_boxes:
            ax.add_patch(Polygon(bev_outline(box), closed=True, fill=False, ec="#2ca02c", lw=0.8))
        color = panel["color"]
        el = panel.get("ellipses")
        for i, (box, score) in enumerate(zip(panel["boxes"], panel["scores"], strict=True)):
            ax.add_patch(Polygon(bev_outline(box), closed=True, fill=False, ec=color, lw=0.9))
            ax.text(box[0], box[1] + 1.5, f"{score:.2f}", fontsize=5, color=color,
                    ha="center")
            if el is not None and el[0][i] > 0:
                ax.add_patch(EllipsePatch((box[0], box[1]), 2 * el[0][i], 2 * el[1][i],
                                          angle=math.degrees(el[2][i]), fill=False, ec=color,
                                          lw=0.7, ls="-", alpha=0.8))
        ax.plot([0], [0], marker="^", color="k", ms=5)
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        ax.set_title(panel["title"])
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.tight_layout()
    return to_svg(fig, title)
