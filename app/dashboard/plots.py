"""Matplotlib figures (Agg backend) rendered to inline SVG strings for the dashboard.

Inputs are the plot data of a profile's summary (`report["fit"]["plots"]`, see
`calibrators.evaluation`) and, for the bird's-eye view, one frame's detections. The panels are
`detectors.panels`' (shared with the report and `detcal show`); matplotlib is imported
when a figure is drawn, never when this module is.
"""

from __future__ import annotations

import functools
import io
import re
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from app.dashboard.intervals import too_small
from detectors.panels import Curve, panel_grid, pyplot
from detectors.panels.calibration_curve import calibration_curve_panel
from detectors.panels.reliability import reliability_panel

BEFORE, AFTER = "#d62728", "#1f77b4"
#: Matplotlib settings of every dashboard figure: text stays text in the SVG, small fonts,
#: and element ids that do not change from one rendering to the next.
RC = {"svg.fonttype": "none", "font.size": 8, "axes.titlesize": 9, "svg.hashsalt": "detcal"}
_DRAWING = threading.Lock()


def _figure(draw: Callable[..., str]) -> Callable[..., str]:
    """Run `draw` (which creates, draws and `to_svg`s a figure) under the dashboard's RC,
    one figure at a time: pyplot and its settings are process-wide, requests are threads."""

    @functools.wraps(draw)
    def wrapper(*args: Any, **kwargs: Any) -> str:
        with _DRAWING, pyplot().rc_context(RC):
            return draw(*args, **kwargs)

    return wrapper


def to_svg(fig: Any, title: str) -> str:
    """The figure as an `<svg>` element (XML prolog dropped), closed afterwards."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Title": title, "Date": None})
    pyplot().close(fig)
    text = buf.getvalue()
    start = text.find("<svg")
    svg = re.sub(r"<metadata>.*?</metadata>\s*", "", text[start:], flags=re.S)
    return svg.replace("<svg ", f'<svg class="plot" role="img" aria-label="{title}" ', 1)


def _arr(values: Sequence[Any] | None) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in (values or [])], dtype=float)


def _before_after(pair: dict, x: str, y: str, lw: float) -> list[Curve]:
    """The `before` and `after` curves of `pair` that exist, in their colours."""
    return [Curve(_arr(data[x]), _arr(data[y]), {"color": color, "lw": lw, "label": key})
            for key, color in (("before", BEFORE), ("after", AFTER)) if (data := pair.get(key))]


@_figure
def reliability(plots: dict, title: str = "Reliability (all classes)") -> str:
    """Accuracy vs confidence per bin, before and after calibration."""
    fig, ax = pyplot().subplots(figsize=(3.4, 3.4))
    curves = _before_after(plots.get("reliability") or {}, "confidence", "accuracy", 1.2)
    reliability_panel(ax, curves, title, square=True)
    ax.set_xlabel("confidence")
    ax.set_ylabel("precision (TP fraction)")
    ax.legend(loc="upper left", frameon=False)
    return to_svg(fig, title)


@_figure
def reliability_per_class(plots: dict, tps_of: dict[str, int] | None = None) -> str:
    """Small-multiple reliability diagrams, one per class, titled with the class's true
    positives (`tps_of`) and greyed when they are too few to judge."""
    tps_of = tps_of or {}
    per = plots.get("reliability_per_class") or {}
    fig, axes = panel_grid(len(per), 5, 2.0, 2.15)
    for i, (ax, (name, pair)) in enumerate(zip(axes.flat, per.items(), strict=False)):
        tps = tps_of.get(name)
        reliability_panel(ax, _before_after(pair, "confidence", "accuracy", 1.2),
                          name if tps is None else f"{name} ({tps} TPs)", square=True)
        if tps is not None and too_small(tps):   # the tables' rule: too few true positives to judge
            ax.set_facecolor("#f3f4f6")
            ax.title.set_color("#9aa3ad")
            ax.text(0.97, 0.04, "too few to judge", ha="right", fontsize=6, color="#9aa3ad",
                    transform=ax.transAxes)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("confidence", fontsize=7)
        if i % axes.shape[1] == 0:
            ax.set_ylabel("precision", fontsize=7)
        if i == 0:
            ax.legend(loc="upper left", frameon=False, fontsize=6)
    fig.tight_layout()
    return to_svg(fig, "Reliability per class")


@_figure
def calibration_curves(plots: dict) -> str:
    """Average-calibration curves (observed vs expected interval proportion) for x and y."""
    curves = plots.get("calibration_curve") or {}
    fig, axes = pyplot().subplots(1, 2, figsize=(6.4, 3.2))
    for ax, axis in zip(axes, ("x", "y"), strict=True):
        calibration_curve_panel(ax, _before_after(curves.get(axis) or {}, "expected",
                                                  "observed", 1.4),
                                f"Average calibration, {axis}", ylabel="observed proportion",
                                square=True)
        ax.legend(loc="upper left", frameon=False)
    fig.tight_layout()
    return to_svg(fig, "Average calibration curves")


@_figure
def residual_plot(plots: dict) -> str:
    """Residual norm vs predicted sigma (sqrt trace Σ) of matched detections (the report's
    `residual_plots` draw each axis on log scales instead)."""
    res = plots.get("residuals") or {}
    fig, ax = pyplot().subplots(figsize=(3.6, 3.4))
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


@_figure
def bev(points: np.ndarray, gt_boxes: np.ndarray, panels: Sequence[dict], title: str) -> str:
    """Bird's-eye view panels of one frame, zoomed to its objects (see `app.dashboard.bev`).

    Each panel: `{"title", "boxes" [N, 9], "scores" [N], "ellipses": (major, minor, angle)
    arrays or None, "color"}`; points `[P, >=2]`, ground truth `[G, 9]`.
    """
    from app.dashboard import bev as bev_figure

    return to_svg(bev_figure.draw(points, gt_boxes, panels), title)
