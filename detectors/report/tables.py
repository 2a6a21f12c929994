"""Markdown tables of the report (rows from `detectors.report.rows`, attention statistics)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from detectors.report.attention import AttentionStats, Binned
from detectors.report.rows import EXPECTED_MD, ClassRow, Row


def number(value: float | None, digits: int = 4) -> str:
    """A table cell: `-` for None/NaN, scientific notation for very large or small values."""
    if value is None or not np.isfinite(value):
        return "-"
    if value != 0 and (abs(value) >= 1e5 or abs(value) < 1e-3):
        return f"{value:.3g}"
    return f"{value:.{digits}g}"


def main_table(rows: Sequence[Row], missing: Sequence[tuple[str, str]] = ()) -> str:
    """The per-sensor table (thesis Figs. 5-2/5-5/5-7 plus coverage); `missing` rows are
    (name, reason) pairs printed with the reason in place of numbers."""
    head = (f"| | reg. NLL ↓ | MD ↓ (E[χ₂] = {EXPECTED_MD:.3f}) | cls. NLL ↓ | ECE ↓ | D-ECE ↓ "
            "| mAP ↑ | forward ms/frame | post ms/frame | cov. 1σ / 2σ / 3σ | notes |")
    lines = [head, "|" + "---|" * 11]
    for row in rows:
        cover = " / ".join(number(c, 3) for c in row.coverage)
        lines.append(
            f"| {row.name} | {number(row.reg_nll)} | {number(row.mean_md)} | "
            f"{number(row.cls_nll)} | {number(row.ece)} | {number(row.dece)} | "
            f"{number(row.mean_ap, 3)} | {row.forward_ms:.1f} | {row.post_ms:.2f} | {cover} | "
            f"{row.note} |")
    for name, reason in missing:
        lines.append(f"| {name} | {reason} |" + " |" * 9)
    return "\n".join(lines)


def nominal_coverage_line() -> str:
    """The Gaussian coverage of the 1/2/3σ Mahalanobis balls in 2-D."""
    from scipy import stats

    nominal = stats.chi2(2).cdf(np.square([1.0, 2.0, 3.0]))
    return ("Nominal coverage of a calibrated 2-D Gaussian at 1σ / 2σ / 3σ: "
            + " / ".join(f"{v:.3f}" for v in nominal) + ".")


def class_table(rows: Sequence[ClassRow]) -> str:
    """Class-wise regression NLL / MD and classification NLL / ECE (thesis Figs. 5-3/5-4)."""
    lines = ["| class | detections | TP | reg. NLL ↓ | MD ↓ | cls. NLL ↓ | ECE ↓ |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.name} | {r.n} | {r.n_tp} | {number(r.reg_nll)} | "
                     f"{number(r.mean_md)} | {number(r.cls_nll)} | {number(r.ece)} |")
    return "\n".join(lines)


def binned_table(b: Binned, what: str) -> str:
    """Median attention spread (m⁴) with quartiles and the rank-deficient share per group."""
    lines = [f"| {what} | n | AS p25 | AS median | AS p75 | rank-deficient C_K |",
             "|---|---:|---:|---:|---:|---:|"]
    for i, label in enumerate(b.labels):
        lines.append(f"| {label} | {b.n[i]} | {number(b.p25[i], 3)} | {number(b.median[i], 3)} "
                     f"| {number(b.p75[i], 3)} | {number(b.collapsed[i], 2)} |")
    return "\n".join(lines)


def attention_tables(stats: AttentionStats) -> str:
    """The three seed-000 tables in one markdown block."""
    return "\n\n".join([
        f"Detections with raw score >= {stats.min_score:g}: {stats.n_detections}. "
        "AS = det(C_K + cell²/12·I) in m⁴ (C_K: top-6 attention cells of the 3.2 m token "
        "grid; floor (cell²/12)² = 0.728 m⁴ for a query attending to one cell); "
        "rank-deficient C_K: share of queries whose raw det C_K is ~0 (top-6 attention on "
        "one cell or on cells along one line).",
        "AS vs IoU with the closest ground truth (final layer, IoU > 0):\n\n"
        + binned_table(stats.vs_iou, "IoU"),
        "AS vs distance from the ego (final layer):\n\n"
        + binned_table(stats.vs_distance, "distance"),
        "AS per decoder layer:\n\n" + binned_table(stats.per_layer, "layer")])


def regression_table(rows: Sequence[Row]) -> str:
    """Regression-only comparison of covariance sources (attention spread vs layer spread)."""
    lines = [f"| covariance | reg. NLL ↓ | MD ↓ (E = {EXPECTED_MD:.3f}) | cov. 1σ / 2σ / 3σ | "
             "notes |", "|---|---:|---:|---|---|"]
    for r in rows:
        cover = " / ".join(number(c, 3) for c in r.coverage)
        lines.append(f"| {r.name} | {number(r.reg_nll)} | {number(r.mean_md)} | {cover} | "
                     f"{r.note} |")
    return "\n".join(lines)
