"""The dashboard's tables from a real profile report (the browser test checks the page)."""

from __future__ import annotations

import re

from app.dashboard.page import COVERAGE_MIN_TPS, before_after_table, region_table
from calibrators import ProfileReport, fit_profile
from calibrators.data import synthetic_dump


def test_region_table_shows_every_cell_and_marks_only_judgeable_misses():
    profile = fit_profile(synthetic_dump(n_frames=60, seed=4), cov_source="given",
                          holdout=0.3)
    report = ProfileReport.from_dict(profile.report)
    html = region_table(report.holdout, "held-out part")
    rows = report.holdout.regions["coverage"]["rows"]
    assert html.count("<tr>") == len(rows) + 2          # header, all, one per cell
    assert "held-out part" in html and "conformal" in html
    for row in rows:                                    # a small cell is never marked red
        if row["count"] < COVERAGE_MIN_TPS:
            cell = re.search(rf"<td>{row['count']}</td>((?:<td[^>]*>.*?</td>){{4}})</tr>",
                             html)
            assert cell is not None and "worse" not in cell.group(1)
        if row["count"] < 30:                           # ... and one too small to judge is grey
            assert cell is not None and cell.group(1).count("<td class='small'>") == 4
    assert "Clopper-Pearson" in html and "<span class='ci'>[" in html
    assert "ECE" in before_after_table(report.fit)


def test_a_report_without_regions_says_so():
    profile = fit_profile(synthetic_dump(n_frames=20, seed=5), cov_source="layers",
                          dims=("z",))
    report = ProfileReport.from_dict(profile.report)
    assert "no served-region coverage" in region_table(report.fit, "fit part")
