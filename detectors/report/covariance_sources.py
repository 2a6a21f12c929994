"""Section 5 of `detcal report-v2`: covariance sources of a group model, raw vs depth-scaled.

For each source ("layers": spread of the box across decoder layers; "hypotheses": the
group-score-weighted spread of the six group heads' final boxes, `det_hyp_boxes [N, G, 9]`)
a profile is fit on the val dump with the report's thesis options (temperature, depth
scaling `Σ + k_c·d·I`, Gaussian regions) and measured on the test dump with
`detectors.report.rows`: the raw Σ of the source (`rows.raw_covariance`) and the profile's
calibrated Σ' (`rows.profile_row(regression=True)`). A source that cannot be fit (e.g.
`cov_source="hypotheses"` not available in `calibrators.fit_profile`, or a dump without
hypotheses) gives a `SourceSkip` with the reason instead of rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibrators import CalibrationProfile, Dump, fit_profile, match_dump
from detectors.report.rows import EXPECTED_MD, Row, measure, profile_row, raw_covariance
from detectors.report.tables import number

SOURCES = ("layers", "hypotheses")
THESIS_OPTIONS = {"score_method": "temperature", "cov_method": "depth",
                  "region_method": "gaussian", "calibration": 0.0, "other_sources": False}
NOMINAL_2SIGMA = 1.0 - float(np.exp(-2.0))   # chi2(2).cdf(4) = 0.8647


@dataclass(frozen=True)
class SourceRows:
    """One source's profile and its two test rows (raw Σ, depth-scaled Σ')."""

    source: str
    profile: CalibrationProfile
    raw: Row
    scaled: Row


@dataclass(frozen=True)
class SourceSkip:
    """A source that could not be fit, and why."""

    source: str
    reason: str


def source_rows(val: Dump, test: Dump, sources: Sequence[str] = SOURCES
                ) -> list[SourceRows | SourceSkip]:
    """Fit each source on `val`, measure raw and depth-scaled Σ on `test` (module docstring)."""
    m = match_dump(test)
    out: list[SourceRows | SourceSkip] = []
    for source in sources:
        try:
            profile = fit_profile(val, cov_source=source, **THESIS_OPTIONS)
        except (ValueError, TypeError, KeyError) as exc:
            out.append(SourceSkip(source, f"{type(exc).__name__}: {exc}"))
            continue
        raw = measure(f"{source}, raw Σ", test, test.det_scores,
                      raw_covariance(test, profile), 0.0, m=m)
        scaled = profile_row(f"{source}, depth-scaled Σ + k·d·I", test, profile, 0.0,
                             regression=True, m=m)
        out.append(SourceRows(source, profile, raw, scaled))
    return out


def source_table(results: Sequence[SourceRows | SourceSkip]) -> str:
    """Regression NLL, mean Mahalanobis distance and 2σ coverage per source and Σ."""
    lines = [f"| covariance | reg. NLL ↓ | mean MD (E = {EXPECTED_MD:.3f}) | 2σ coverage "
             f"(nominal {NOMINAL_2SIGMA:.3f}) | TPs used |", "|---|---:|---:|---:|---:|"]
    for r in results:
        if isinstance(r, SourceSkip):
            lines.append(f"| {r.source} | skipped: {r.reason} | | | |")
            continue
        for row in (r.raw, r.scaled):
            lines.append(f"| {row.name} | {number(row.reg_nll)} | {number(row.mean_md)} | "
                         f"{number(row.coverage[1], 3)} | {row.n_used} / {row.n_tp} |")
    return "\n".join(lines)


def depth_k_line(results: Sequence[SourceRows | SourceSkip]) -> str:
    """The fitted depth k per class (m² per m of distance) of each source's profile; classes
    with too few val matches share the pooled k."""
    parts = []
    for r in results:
        if isinstance(r, SourceRows):
            p = r.profile
            own = ", ".join(f"{c} {number(k, 3)}" for c, k in p.depth_k.items()
                            if c not in p.fallback_classes)
            pooled = f"pooled {number(p.pooled_k, 3)} ({len(p.fallback_classes)} classes)"
            parts.append(f"{r.source}: {own + '; ' if own else ''}{pooled}")
    return "Fitted k (val): " + " — ".join(parts) + "." if parts else ""
