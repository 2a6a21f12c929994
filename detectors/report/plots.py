"""The report's figures (matplotlib, Agg backend), each written as PNG and SVG.

- `reliability_per_class`: reliability diagram per class, vanilla vs calibrated (Fig. 5-10);
- `calibration_curves`: average calibration curve of x and y per method (Fig. 5-8);
- `residual_plots`: |residual| vs predicted σ for x, y and combined per method (Fig. 5-9);
- `bev_before_after`: one test frame, boxes, scores and 95 % ellipses before / after
  (Figs. 5-11..5-14);
- `attention_plots`: seed 000's median attention spread vs IoU, distance, layer (Figs. 3-5).

Every function takes plain arrays and a path *stem* (no suffix) and returns the two files.
Point clouds and scatter points are rasterised inside the SVGs (lines and text stay vector),
which keeps each SVG under a megabyte. The reliability, calibration-curve and bird's-eye
panels are `detectors.panels`' (shared with `detcal show` and the dashboard).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from calibrators import ellipse, metrics
from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from detectors.panels import Curve, panel_grid, pyplot
from detectors.panels.bev import BevStyle, bev_panel
from detectors.panels.calibration_curve import calibration_curve_panel
from detectors.panels.reliability import reliability_panel
from detectors.report.attention import AttentionStats, Binned

#: The report's bird's-eye view: grey rasterised points, green dashed ground truth, blue
#: detections with black text, red ellipses.
REPORT_BEV = BevStyle(point_color="0.7", point_size=(0.5, 3), rasterize_points=True,
                      gt_color="tab:green", box_width=1.1, label_dy=1.2, label_colored=False)


def _save(fig: object, stem: Path) -> list[Path]:
    """Write `fig` as `stem.png` and `stem.svg`, close it, return both paths."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    fig.tight_layout()  # type: ignore[attr-defined]
    for p in paths:
        fig.savefig(p, dpi=110)  # type: ignore[attr-defined]
    pyplot().close(fig)
    return paths


def reliability_per_class(classes: Sequence[str], correct: np.ndarray, labels: np.ndarray,
                          scores: Mapping[str, np.ndarray], stem: Path) -> list[Path]:
    """One panel per class: accuracy vs confidence (10 bins) of each `scores[method] [N]`
    against `correct [N]` for the detections labelled with that class (`labels [N]`)."""
    cols = 5
    fig, axes = panel_grid(len(classes), cols, 3.2, 3.0)
    for c, name in enumerate(classes):
        ax = axes.flat[c]
        rows_c = labels == c
        curves = [_reliability_curve(method, s[rows_c], correct[rows_c])
                  for method, s in scores.items()] if rows_c.any() else []
        reliability_panel(ax, curves, f"{name} ({int(rows_c.sum())} det.)")
        if rows_c.any():
            ax.legend(fontsize=6, loc="upper left")
        if c % cols == 0:
            ax.set_ylabel("precision (TP fraction)")
        if c // cols == axes.shape[0] - 1:
            ax.set_xlabel("confidence")
    return _save(fig, stem)


def _reliability_curve(method: str, scores: np.ndarray, correct: np.ndarray) -> Curve:
    """The reliability curve of one method (10 bins, the empty ones left out), its ECE in
    the label."""
    d = metrics.reliability_diagram(scores, correct)
    ece = metrics.expected_calibration_error(scores, correct)
    ok = d.count > 0
    return Curve(d.confidence[ok], d.accuracy[ok], {"label": f"{method} (ECE {ece:.3f})"})


def calibration_curves(residuals: Mapping[str, np.ndarray], covariances: Mapping[str, np.ndarray],
                       stem: Path) -> list[Path]:
    """Average calibration curves of x and y: `residuals[m] [M, 2]`, `covariances[m]
    [M, 2, 2]` per method (TPs with a zero variance on an axis are left out of that axis)."""
    fig, axes = pyplot().subplots(1, 2, figsize=(10, 4.6))
    for j, axis in enumerate(("x", "y")):
        curves = []
        for method, res in residuals.items():
            std = np.sqrt(np.maximum(covariances[method][:, j, j], 0.0))
            ok = std > 0
            if not ok.any():
                continue
            curve = metrics.average_calibration_curve(res[ok, j], std[ok], n_bins=50)
            area = metrics.miscalibration_area(res[ok, j], std[ok], n_bins=50)
            curves.append(Curve(curve.expected, curve.observed,
                                {"label": f"{method} (area {area:.3f})"}))
        calibration_curve_panel(axes[j], curves, f"average calibration, {axis}",
                                diagonal_label="ideal")
        axes[j].legend(fontsize=8)
    return _save(fig, stem)


def residual_plots(residuals: Mapping[str, np.ndarray], covariances: Mapping[str, np.ndarray],
                   stem: Path, max_points: int = 2000, seed: int = 0) -> list[Path]:
    """Per method (rows) and x / y / combined (columns): |residual| against predicted σ on
    log axes, with the lines |r| = σ and |r| = 3σ and the fraction of points under each."""
    methods = list(residuals)
    fig, axes = pyplot().subplots(len(methods), 3, figsize=(12, 3.4 * len(methods)), squeeze=False)
    rng = np.random.default_rng(seed)
    for i, method in enumerate(methods):
        res, cov = residuals[method], covariances[method]
        pick = np.sort(rng.permutation(len(res))[:max_points])
        parts = [(np.abs(res[:, 0]), np.sqrt(np.maximum(cov[:, 0, 0], 0)), "x"),
                 (np.abs(res[:, 1]), np.sqrt(np.maximum(cov[:, 1, 1], 0)), "y"),
                 (np.hypot(res[:, 0], res[:, 1]),
                  np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0)), "x, y")]
        for j, (r, s, what) in enumerate(parts):
            ax = axes[i][j]
            positive = np.concatenate([r[r > 0], s[s > 0]])
            floor = 0.5 * float(positive.min()) if len(positive) else 1e-6
            ax.scatter(np.maximum(s[pick], floor), np.maximum(r[pick], floor), s=2, alpha=0.4,
                       rasterized=True)
            hi = float(positive.max()) if len(positive) else 1.0
            grid = np.geomspace(floor, hi * 2, 50)
            w1, w3 = float(np.mean(r <= s)), float(np.mean(r <= 3 * s))
            ax.plot(grid, grid, color="tab:orange", label=f"|r| = σ ({w1:.2f} below)")
            ax.plot(grid, 3 * grid, color="tab:blue", label=f"|r| = 3σ ({w3:.2f} below)")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("predicted σ (m)")
            ax.set_ylabel("|residual| (m)")
            ax.set_title(f"{method}: {what}", fontsize=9)
            ax.legend(fontsize=7)
    return _save(fig, stem)


def bev_before_after(points: np.ndarray, gt_boxes: np.ndarray, boxes: np.ndarray,
                     labels: np.ndarray, classes: Sequence[str],
                     sides: Mapping[str, tuple[np.ndarray, np.ndarray]], stem: Path,
                     min_score: float = 0.3, confidence: float = ELLIPSE_CONFIDENCE,
                     extent: float = 51.2) -> list[Path]:
    """One panel per side: `points [P, >=2]`, GT `gt_boxes [G, 9]` (dashed), detections
    `boxes [N, 9]` with `labels [N]` whose side's `scores [N] >= min_score`, and the
    `confidence` ellipse of that side's `cov [N, 2, 2]`; `sides[name] = (scores, cov)`."""
    fig, axes = pyplot().subplots(1, len(sides), figsize=(8 * len(sides), 8), squeeze=False)
    for ax, (name, (scores, cov)) in zip(axes[0], sides.items(), strict=True):
        keep = np.flatnonzero(scores >= min_score)
        ell = ellipse(cov[keep], confidence=confidence) if len(keep) else None
        bev_panel(ax, points, gt_boxes, boxes[keep],
                  [f"{classes[labels[i]]} {scores[i]:.2f}" for i in keep], ell,
                  color="tab:blue", ellipse_color="tab:red", half=extent, style=REPORT_BEV)
        ax.set_title(f"{name}: score >= {min_score:g} (blue), ground truth (green dashed), "
                     f"{confidence:.0%} ellipse (red)", fontsize=8)
    return _save(fig, stem)


def attention_plots(stats: AttentionStats, stem: Path) -> list[Path]:
    """Median attention spread with 25th-75th percentile bars vs IoU, distance and layer."""
    fig, axes = pyplot().subplots(1, 3, figsize=(15, 4.2))
    parts: list[tuple[Binned, str]] = [(stats.vs_iou, "IoU with closest ground truth"),
                                       (stats.vs_distance, "distance from ego"),
                                       (stats.per_layer, "decoder layer")]
    for ax, (b, what) in zip(axes, parts, strict=True):
        x = np.arange(len(b.labels))
        ok = b.n > 0
        ax.errorbar(x[ok], b.median[ok], yerr=[b.median[ok] - b.p25[ok], b.p75[ok] - b.median[ok]],
                    fmt="o", capsize=3)
        ax.set_xticks(x)
        ax.set_xticklabels(b.labels, rotation=45, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_xlabel(what)
        ax.set_ylabel("attention spread det(C_K + cell²/12·I) (m⁴)")
        ax.set_title(f"median AS vs {what}", fontsize=9)
    return _save(fig, stem)
