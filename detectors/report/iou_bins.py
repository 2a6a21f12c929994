"""What separates the IoU bins of seed 000's trend, beside the attention spread (issue 13).

Seed 000 reads the fall of AS with IoU as attention that spreads where the detector is
unsure of the object. Whether a detector can show it depends on what separates its IoU
bins: if confident boxes differ in IoU by centre errors well under one token cell, an
attention over those cells has little room to tell them apart. So, for one layer's
`AttentionStats` (the final layer in the report; the box errors are the final box's):

- `error_bins_table(stats, cell)`: per populated IoU bin, the median box errors against the
  closest ground truth (`attention.box_errors`: centre in metres and in token cells,
  absolute yaw and length errors), the median distance from the ego and the median AS;
- `error_rhos(stats)` -> `{name: (ρ(AS, x), ρ(IoU, x))}` over the detections with IoU > 0,
  x in `ERROR_NAMES` (Spearman, `groups.sample_rho`), and `error_rho_table` to print them;
- `why_sentence(stats, cell)`: the reading of those numbers, stated from them, with the
  median centre error after each decoder layer (how much localising the later layers' attention
  still does) (over the
  bins with >= `unified_vs_group_tables.MIN_BIN` detections, those the trend's ρ reads).

Needs `stats.errors` (set by `attention.attention_stats`); ValueError without it.
"""

from __future__ import annotations

import numpy as np

from detectors.report.attention import AttentionStats
from detectors.report.groups import sample_rho
from detectors.report.tables import number
from detectors.report.unified_vs_group_tables import MIN_BIN

#: The per-detection quantities set against AS and IoU, with their table labels.
ERROR_NAMES: dict[str, str] = {
    "iou": "IoU", "centre": "centre error (m)", "yaw": "yaw error (rad, absolute)",
    "length": "length error (m, absolute)", "width": "width error (m, absolute)",
    "distance": "distance from the ego (m)"}
#: Below this per-detection |ρ| AS is said to carry next to nothing of a quantity.
WEAK_RHO = 0.1


def _columns(stats: AttentionStats) -> dict[str, np.ndarray]:
    """The detections with IoU > 0: AS and every quantity of ERROR_NAMES, `[n]` each."""
    e = stats.errors
    if e is None or stats.iou is None or stats.final_as is None or stats.distance is None:
        raise ValueError("stats carry no per-detection box errors (attention_stats sets them)")
    keep = stats.iou > 0
    return {"as": stats.final_as[keep], "iou": stats.iou[keep], "centre": e.centre[keep],
            "yaw": e.yaw[keep], "length": e.length[keep], "width": e.width[keep],
            "distance": stats.distance[keep]}


def error_rhos(stats: AttentionStats) -> dict[str, tuple[float, float]]:
    """`{name: (ρ(AS, x), ρ(IoU, x))}` for x in ERROR_NAMES (ρ(IoU, IoU) is 1)."""
    c = _columns(stats)
    return {name: (sample_rho(c["as"], c[name]), sample_rho(c["iou"], c[name]))
            for name in ERROR_NAMES}


def error_rho_table(rhos: dict[str, tuple[float, float]]) -> str:
    """One row per quantity: per-detection ρ with AS and with IoU."""
    lines = ["| per detection, Spearman's ρ with | AS | IoU |", "|---|---:|---:|"]
    for name, (with_as, with_iou) in rhos.items():
        lines.append(f"| {ERROR_NAMES[name]} | {number(with_as, 3)} | "
                     f"{'-' if name == 'iou' else number(with_iou, 3)} |")
    return "\n".join(lines)


def _bins(stats: AttentionStats, c: dict[str, np.ndarray], min_n: int = 1
          ) -> list[tuple[str, np.ndarray]]:
    """(label, row mask over `c = _columns(stats)`) of every IoU bin with >= `min_n`
    detections, low to high."""
    labels = stats.vs_iou.labels
    bins = np.minimum((c["iou"] * len(labels)).astype(int), len(labels) - 1)
    return [(label, bins == b) for b, label in enumerate(labels)
            if np.sum(bins == b) >= min_n]


def error_bins_table(stats: AttentionStats, cell: float) -> str:
    """Per populated IoU bin: n and the medians of the box errors, distance and AS."""
    c = _columns(stats)
    lines = [f"| IoU | n | centre error (m) | centre error / cell ({cell:g} m) | "
             "yaw error (deg) | length error (m) | distance (m) | AS (m⁴) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, rows in _bins(stats, c):
        m = {k: float(np.median(v[rows])) for k, v in c.items()}
        lines.append(f"| {label} | {int(rows.sum())} | {m['centre']:.3f} | "
                     f"{m['centre'] / cell:.2f} | {np.degrees(m['yaw']):.1f} | "
                     f"{m['length']:.2f} | {m['distance']:.1f} | {number(m['as'], 3)} |")
    return "\n".join(lines)


def why_sentence(stats: AttentionStats, cell: float) -> str:
    """What the box errors and the per-detection ρs say about the IoU trend."""
    c = _columns(stats)
    bins = _bins(stats, c, MIN_BIN)     # the bins the trend's rho reads
    if len(bins) < 2:
        return (f"Fewer than two IoU bins hold {MIN_BIN} detections or more: nothing to "
                "compare.")
    rhos = error_rhos(stats)
    (lo_label, lo), (hi_label, hi) = bins[0], bins[-1]
    ce_lo, ce_hi = float(np.median(c["centre"][lo])), float(np.median(c["centre"][hi]))
    drivers = sorted(("centre", "yaw", "length", "width"), key=lambda k: rhos[k][1])
    iou_by = ", ".join(f"{ERROR_NAMES[k].split(' (')[0]} ρ = {rhos[k][1]:.2f}"
                       for k in drivers[:2])
    as_by = {k: rhos[k][0] for k in ("iou", "centre", "yaw", "length", "width")}
    weight = {k: abs(v) if np.isfinite(v) else -1.0 for k, v in as_by.items()}
    strongest = max(weight, key=weight.__getitem__)
    error = max(("centre", "yaw", "length", "width"), key=weight.__getitem__)
    as_med = float(np.median(c["as"]))
    layers = np.median(stats.errors.layer_centre[stats.iou > 0], axis=0)   # [L]
    per_layer = " / ".join(f"{v:.3f}" for v in layers)
    text = (f"{len(c['as'])} detections with IoU > 0; the lowest IoU bin with "
            f"{MIN_BIN} or more is {lo_label}. "
            f"From bin {lo_label} to bin {hi_label} the median centre error falls from "
            f"{ce_lo:.2f} m to {ce_hi:.2f} m, {ce_lo / cell:.2f} to {ce_hi / cell:.2f} of a "
            f"{cell:g} m token cell; per detection the IoU follows the box errors "
            f"({iou_by}). Median centre error after each decoder layer: {per_layer} m. "
            f"The median AS, {number(as_med, 3)} m⁴, is an attention spread of "
            f"{as_med ** 0.25:.2f} m (AS^¼, the geometric mean of C_K's two standard "
            f"deviations). ")
    if weight[strongest] < WEAK_RHO:
        return text + (f"AS carries next to nothing of the errors that set IoU (per-detection "
                       f"|ρ| ≤ {weight[strongest]:.2f} against IoU and every error), so "
                       f"the order of the IoU bins' AS medians is not set by how well the "
                       f"box is placed.")
    return text + (f"AS follows the IoU with per-detection ρ = {as_by['iou']:.2f} and, of the "
                   f"box errors, the {ERROR_NAMES[error].split(' (')[0]} most "
                   f"(ρ = {as_by[error]:.2f}).")
