"""Beyond the thesis: per-class score calibrators, `s·Σ + k·d·I` and conformal ellipses.

Every profile is fit on val with `fit_profile` and measured on test exactly like the thesis
rows (`rows.measure`): the score rows keep the raw layer-spread covariance (like the TS row),
the covariance rows serve their calibrated Σ'. The region table measures the *served*
ellipses at 50 / 90 / 95 / 99 %: the fraction of test true positives whose true centre lies
inside, and the mean ellipse area (sharpness), for the thesis's depth scaling with Gaussian
χ²₂ radii, shrinkage with Gaussian radii, and detcal's default profile (every stage chosen on
a calibration part of val; conformal radii per class × distance bin).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibrators import CalibrationProfile, Dump, FitOptions, MatchResult, fit_profile, metrics
from calibrators import summarize as summarize_dump
from detectors.report.rows import Row, profile_row

LEVELS = (0.5, 0.9, 0.95, 0.99)
#: Score methods beyond the global temperature, with their row names.
SCORE_ROWS = {"class_temperature": "TS per class", "platt": "Platt per class",
              "platt_range": "Platt per class + range", "isotonic": "Isotonic per class",
              "histogram": "Histogram binning per class"}
_THESIS = {"cov_source": "layers", "score_method": "temperature", "cov_method": "depth",
           "region_method": "gaussian", "calibration": 0.0, "other_sources": False}


@dataclass(frozen=True)
class RegionRow:
    """Served ellipses of one profile on test: coverage and mean area (m²) per level."""

    name: str
    method: str
    coverage: tuple[float, ...]
    mean_area: tuple[float, ...]


@dataclass(frozen=True)
class HonestClassRow:
    """One class on test: TPs, ECE of global TS and of the default profile, served coverage."""

    name: str
    n_tp: int
    ece_ts: float | None
    ece_auto: float | None
    coverage: tuple[float | None, ...]


@dataclass
class HonestSection:
    """The rows, region rows and class rows of one sensor, and the default profile's
    choices (`chosen`: score, covariance and region methods)."""

    rows: list[Row] = field(default_factory=list)
    regions: list[RegionRow] = field(default_factory=list)
    classes: list[HonestClassRow] = field(default_factory=list)
    chosen: tuple[str, str, str] = ("", "", "")
    default_row: Row | None = None
    ts_row: Row | None = None


def honest_section(val: Dump, test: Dump, m: MatchResult, forward_ms: float,
                   thesis: CalibrationProfile) -> HonestSection:
    """Fit the profiles beyond the thesis on `val`, measure them on `test` (matched as `m`);
    `thesis` is the Depth Scaling row's profile."""
    out = HonestSection()
    ts = fit_profile(val, FitOptions(**_THESIS))
    out.ts_row = profile_row("TS", test, ts, forward_ms, False, m)
    for method, name in SCORE_ROWS.items():
        prof = fit_profile(val, FitOptions(**{**_THESIS, "score_method": method}))
        out.rows.append(profile_row(name, test, prof, forward_ms, False, m))
    shrink = fit_profile(val, FitOptions(**{**_THESIS, "cov_method": "shrinkage"}))
    out.rows.append(profile_row("Shrinkage (TS + s·Σ + k·d·I)", test, shrink, forward_ms, True,
                                m))
    auto = fit_profile(val, cov_source="layers", other_sources=False)
    out.chosen = (auto.score_method, auto.cov_method, auto.region_method)
    out.default_row = profile_row("detcal default (" + " + ".join(out.chosen) + ")", test, auto,
                                  forward_ms, True, m)
    out.rows.append(out.default_row)
    for name, prof in (("Depth Scaling, Gaussian χ²₂ radii (thesis)", thesis),
                       ("Shrinkage, Gaussian χ²₂ radii", shrink), ("detcal default", auto)):
        regions = summarize_dump(test, prof, match=m, levels=LEVELS).regions
        out.regions.append(RegionRow(name, regions["method"],
                                     tuple(regions["coverage"]["overall"]),
                                     tuple(regions["mean_area"])))
    out.classes = _class_rows(test, m, ts, auto)
    return out


def _class_rows(test: Dump, m: MatchResult, ts: CalibrationProfile, auto: CalibrationProfile
                ) -> list[HonestClassRow]:
    from calibrators import apply_profile, tp_residuals
    from calibrators.regions import xy_mahalanobis

    tp = np.asarray(m.tp, dtype=bool)
    s_ts = apply_profile(test, ts).scores
    served = apply_profile(test, auto, levels=LEVELS)
    md = xy_mahalanobis(tp_residuals(test, m), served.covariances[tp], tuple(auto.cov_dims))
    radii = np.stack([served.region_radii[q][tp] for q in LEVELS], axis=1)
    labels, tp_labels = test.det_labels, test.det_labels[tp]
    rows = []
    for c, name in enumerate(test.classes):
        det, mine = labels == c, tp_labels == c
        rows.append(HonestClassRow(
            name, int(mine.sum()),
            metrics.expected_calibration_error(s_ts[det], tp[det]) if det.any() else None,
            metrics.expected_calibration_error(served.scores[det], tp[det])
            if det.any() else None,
            tuple((md[mine, None] <= radii[mine]).mean(axis=0).tolist()) if mine.any()
            else (None,) * len(LEVELS)))
    return rows


def honest_markdown(section: HonestSection, number) -> str:  # noqa: ANN001 - tables.number
    """The sensor's "beyond the thesis" subsection (tables and how to read them)."""
    from detectors.report import tables

    levels = " / ".join(f"{q:.0%}" for q in LEVELS)
    region_lines = [f"| ellipses | method | coverage at {levels} | mean area at {levels} (m²) |",
                    "|---|---|---|---|"]
    for r in section.regions:
        region_lines.append(f"| {r.name} | {r.method} | "
                            + " / ".join(f"{c:.3f}" for c in r.coverage) + " | "
                            + " / ".join(number(a, 3) for a in r.mean_area) + " |")
    class_lines = [f"| class | test TPs | ECE TS → default | coverage at {levels} |",
                   "|---|---:|---|---|"]
    for c in section.classes:
        cover = " / ".join("-" if v is None else f"{v:.3f}" for v in c.coverage)
        class_lines.append(f"| {c.name} | {c.n_tp} | {number(c.ece_ts)} → "
                           f"{number(c.ece_auto)} | {cover} |")
    score, cov, region = section.chosen
    return "\n\n".join([
        "### Beyond the thesis: per-class scores, s·Σ + k·d·I, conformal ellipses",
        "Each profile fit on val with `fit_profile` and measured on test like the rows above "
        "(score rows keep the raw layer-spread Σ, like TS). The default profile chose "
        f"`{score}` scores, `{cov}` covariance scaling and `{region}` regions on a "
        "calibration half of the val frames (held-out NLL; conformal radii per class × "
        "distance bin 0-15 / 15-30 / 30+ m).",
        tables.main_table(([section.ts_row] if section.ts_row else []) + section.rows),
        "Served ellipses on test: the share of true centres inside the level-q ellipse, and "
        "its mean area (a method that covers with huge ellipses is not better):",
        "\n".join(region_lines),
        "Class-wise, default profile:",
        "\n".join(class_lines)])
