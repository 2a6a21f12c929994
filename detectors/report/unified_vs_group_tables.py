"""Markdown tables of the unified-vs-group page (sections 1-4 of `detcal report-v2`).

Each table is a function of the library's outputs, so a test can recompute every cell:

- `ap_table(evaluations)`: mAP, NDS and per-class AP (`EvaluationReport.class_ap`);
- `switch_stats(outputs, no_object_below)` -> `[L - 1, 4]` mean, median, p25, p75 per frame
  of `groups.class_switches`; `switch_table` prints them for several models;
- `group_std(outputs, min_score)` -> `[3]` `Binned` (x, y, z) of `groups.per_layer` over
  `groups.inter_group_std` of the queries with final-layer score >= `min_score`;
  `group_std_table` prints them;
- `trend_bins_table(trends, axis)`: median AS and counts per IoU or distance bin, one
  column per layer; `trend_summary_table(trends)`: rhos and rank-deficient share per layer;
- `trend_sentence(trend)`: the issue's three criteria checked on one layer's numbers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from calibrators import EvaluationReport
from detectors.report.attention import Binned
from detectors.report.groups import (
    GroupOutputs,
    LayerTrend,
    class_switches,
    inter_group_std,
    per_layer,
)
from detectors.report.tables import number

AXES = ("x", "y", "z")
RHO_IOU_MAX = -0.6
RHO_DISTANCE_MIN = 0.6
RANK_DEFICIENT_MAX = 0.2
MIN_BIN = 5   # bins with fewer detections are left out of rho (`groups.trend`'s min_n)


def ap_table(evaluations: Mapping[str, EvaluationReport]) -> str:
    """mAP, NDS and per-class AP (mean over the distance thresholds), one column per model."""
    names = list(evaluations)
    reports = list(evaluations.values())
    lines = ["| | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names),
             "| **mAP** | " + " | ".join(f"**{r.mean_ap:.3f}**" for r in reports) + " |",
             "| NDS | " + " | ".join(f"{r.nd_score:.3f}" for r in reports) + " |"]
    for c in reports[0].class_ap:
        lines.append(f"| {c} | " + " | ".join(f"{r.class_ap[c]:.3f}" for r in reports) + " |")
    lines.append("| detections / GT evaluated | " + " | ".join(
        f"{r.n_detections_evaluated} / {r.n_gt_evaluated}" for r in reports) + " |")
    return "\n".join(lines)


def switch_stats(outputs: GroupOutputs, no_object_below: float) -> np.ndarray:
    """`[L - 1, 4]` mean, median, p25, p75 over frames of the class switches per transition."""
    per_frame = class_switches(outputs.layer_logits, outputs.det_frame, outputs.n_frames,
                               no_object_below).astype(np.float64)    # [F, L - 1]
    q = np.percentile(per_frame, [50, 25, 75], axis=0)
    return np.stack([per_frame.mean(axis=0), q[0], q[1], q[2]], axis=1)


def switch_table(outputs: Mapping[str, GroupOutputs], no_object_below: float) -> str:
    """Class switches per frame and layer transition, mean / median [p25, p75] per model."""
    stats = {name: switch_stats(o, no_object_below) for name, o in outputs.items()}
    n_trans = max(len(s) for s in stats.values())
    lines = ["| transition | " + " | ".join(f"{n}: mean | {n}: median [p25, p75]"
                                             for n in stats) + " |",
             "|---|" + "---:|---:|" * len(stats)]
    for t in range(n_trans):
        cells = []
        for s in stats.values():
            if t < len(s):
                cells.append(f"{s[t, 0]:.2f} | {s[t, 1]:g} [{s[t, 2]:g}, {s[t, 3]:g}]")
            else:
                cells.append("- | -")
        lines.append(f"| layer {t + 1} → {t + 2} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def kept_queries(outputs: GroupOutputs, min_score: float) -> np.ndarray:
    """`[N]` bool: final-layer best sigmoid score >= `min_score`."""
    best = outputs.layer_logits[:, -1].astype(np.float64).max(axis=1)
    return 1.0 / (1.0 + np.exp(-best)) >= min_score


def group_std(outputs: GroupOutputs, min_score: float) -> list[Binned]:
    """Per axis x, y, z: `per_layer` of the inter-group std of the kept queries."""
    if outputs.group_boxes is None:
        raise ValueError("a unified-head model has no group boxes")
    std = inter_group_std(outputs.group_boxes[kept_queries(outputs, min_score)])  # [n, L, 3]
    return [per_layer(std[:, :, a]) for a in range(len(AXES))]


def group_std_table(stats: Sequence[Binned]) -> str:
    """Median [p25, p75] of the inter-group std (m) per layer and axis."""
    lines = ["| layer | queries | " + " | ".join(f"σ_{a} median [p25, p75] (m)" for a in AXES)
             + " |", "|---|---:|" + "---:|" * len(AXES)]
    for i, label in enumerate(stats[0].labels):
        cells = [f"{number(b.median[i], 3)} [{number(b.p25[i], 3)}, {number(b.p75[i], 3)}]"
                 for b in stats]
        lines.append(f"| {label} | {stats[0].n[i]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def trend_bins_table(trends: Sequence[LayerTrend], axis: str) -> str:
    """Median AS (m⁴) per bin of `axis` ("iou" or "distance"), one column per layer."""
    bins = [t.stats.vs_iou if axis == "iou" else t.stats.vs_distance for t in trends]
    what = "IoU" if axis == "iou" else "distance"
    lines = [f"| {what} | n | " + " | ".join(f"AS median, layer {t.layer}" for t in trends)
             + " |", "|---|---:|" + "---:|" * len(trends)]
    for i, label in enumerate(bins[0].labels):
        lines.append(f"| {label} | {bins[0].n[i]} | "
                     + " | ".join(number(b.median[i], 3) for b in bins) + " |")
    return "\n".join(lines)


def _interval(pair: tuple[float, float]) -> str:
    lo, hi = pair
    return "-" if not (np.isfinite(lo) and np.isfinite(hi)) else f"[{lo:.2f}, {hi:.2f}]"


def trend_summary_table(trends: Sequence[LayerTrend]) -> str:
    """Per layer: detections, ρ(AS, IoU bin), ρ(AS, distance bin), each with its bootstrap
    95 % interval over the detections, rank-deficient share, and the per-detection ρ of AS
    against IoU and against distance."""
    lines = ["| layer | detections | ρ vs IoU (≤ −0.6) | ρ vs IoU, bootstrap 95 % | "
             "ρ vs distance (≥ 0.6) | ρ vs distance, bootstrap 95 % | "
             "rank-deficient C_K (< 20 %) | per-detection ρ(AS, IoU) | "
             "per-detection ρ(AS, distance) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for t in trends:
        lines.append(f"| {t.layer} | {t.stats.n_detections} | {number(t.rho_iou, 3)} | "
                     f"{_interval(t.rho_iou_interval)} | {number(t.rho_distance, 3)} | "
                     f"{_interval(t.rho_distance_interval)} | "
                     f"{100 * t.rank_deficient:.1f} % | {number(t.sample_rho_iou, 3)} | "
                     f"{number(t.sample_rho_distance, 3)} |")
    return "\n".join(lines)


def _ends(b: Binned) -> tuple[str, float, str, float] | None:
    """(label, median) of the lowest and highest bin with >= MIN_BIN detections."""
    ok = np.flatnonzero((b.n >= MIN_BIN) & np.isfinite(b.median))
    if len(ok) < 2:
        return None
    lo, hi = int(ok[0]), int(ok[-1])
    return b.labels[lo], float(b.median[lo]), b.labels[hi], float(b.median[hi])


def _criterion(b: Binned, rho: float, what: str, falling: bool) -> tuple[bool, str]:
    ends = _ends(b)
    if ends is None or not np.isfinite(rho):
        return False, (f"no {what} trend measurable (fewer than 3 bins with >= {MIN_BIN} "
                       "detections, or equal medians)")
    lo_label, lo, hi_label, hi = ends
    moved = hi < lo if falling else hi > lo
    ok = moved and (rho <= RHO_IOU_MAX if falling else rho >= RHO_DISTANCE_MIN)
    verb = "falls" if hi < lo else ("rises" if hi > lo else "stays")
    bound = f"≤ {RHO_IOU_MAX}" if falling else f"≥ {RHO_DISTANCE_MIN}"
    return ok, (f"median AS {verb} with {what} from {number(lo, 3)} ({lo_label}) to "
                f"{number(hi, 3)} m⁴ ({hi_label}), ρ = {rho:.2f} (needs {bound}: "
                f"{'met' if ok else 'not met'})")


def trend_verdict(t: LayerTrend) -> tuple[bool, str]:
    """(all three criteria met, one sentence with the numbers) for one layer."""
    iou_ok, iou = _criterion(t.stats.vs_iou, t.rho_iou, "IoU", falling=True)
    dist_ok, dist = _criterion(t.stats.vs_distance, t.rho_distance, "distance", falling=False)
    rank_ok = t.rank_deficient < RANK_DEFICIENT_MAX
    rank = (f"{100 * t.rank_deficient:.1f} % rank-deficient C_K (needs < "
            f"{100 * RANK_DEFICIENT_MAX:.0f} %: {'met' if rank_ok else 'not met'})")
    ok = iou_ok and dist_ok and rank_ok
    return ok, (f"Layer {t.layer} ({t.stats.n_detections} detections): {iou}; {dist}; "
                f"{rank}. {'All three criteria met.' if ok else 'Criteria not all met.'}")

