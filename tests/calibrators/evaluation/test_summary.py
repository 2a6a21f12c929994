"""summarize, Summary / ProfileReport and format_table: stable keys, typed round trips, null
handling, real improvements."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibrators import ProfileReport, Summary, format_table, summarize
from calibrators.metrics import expected_mahalanobis

TOP_KEYS = {"schema", "threshold", "score_mode", "cov_source", "dims", "temperature", "counts",
            "classification", "regression", "per_class", "plots"}
CLASS_KEYS = {"ece", "mce", "dece", "nll", "brier"}
REGRESSION_KEYS = {"n", "nll", "mean_md", "expected_md", "coverage", "miscalibration_area",
                   "note_before", "note_after"}
ROW_KEYS = {"class", "n", "tp", "k", "fallback", "ece_before", "ece_after", "nll_before",
            "nll_after"}
PLOT_KEYS = {"reliability", "reliability_per_class", "calibration_curve", "residuals"}


def _check_keys(report):
    assert set(report) - {"regions"} == TOP_KEYS
    assert set(report["classification"]) == CLASS_KEYS
    assert set(report["regression"]) == REGRESSION_KEYS
    assert all(set(row) == ROW_KEYS for row in report["per_class"])
    assert set(report["plots"]) == PLOT_KEYS
    json.dumps(report, allow_nan=False)   # JSON-able, no NaN


def test_expected_mahalanobis_is_the_chi_mean():
    assert expected_mahalanobis(1) == pytest.approx(math.sqrt(2 / math.pi))
    assert expected_mahalanobis(2) == pytest.approx(math.sqrt(math.pi / 2))
    rng = np.random.default_rng(0)
    sample = np.linalg.norm(rng.standard_normal((200_000, 3)), axis=1).mean()
    assert expected_mahalanobis(3) == pytest.approx(sample, rel=0.01)


def test_report_without_profile_has_null_after(small_dump):
    report = summarize(small_dump).to_dict()
    _check_keys(report)
    assert report["temperature"] is None and report["cov_source"] == "given"
    assert all(pair["after"] is None for pair in report["classification"].values())
    assert report["regression"]["nll"]["before"] is not None
    assert report["regression"]["nll"]["after"] is None
    assert report["plots"]["reliability"]["after"] is None
    counts = report["counts"]
    assert counts["tp"] + counts["fp"] == small_dump.n_detections
    assert counts["tp"] + counts["fn"] == len(small_dump.gt_labels)


def test_report_with_no_covariance_nulls_regression_before(small_dump):
    report = summarize(small_dump, cov_source="none").to_dict()
    _check_keys(report)
    reg = report["regression"]
    assert reg["nll"]["before"] is None and reg["mean_md"]["before"] is None
    assert reg["coverage"]["before"] is None
    assert "undefined" in reg["note_before"]
    assert report["plots"]["residuals"]["before"] is None
    assert "regression" in format_table(Summary.from_dict(report))


def test_calibration_improves_the_fit_part(sigmoid_profile):
    fit = sigmoid_profile.report["fit"]
    _check_keys(fit)
    cls, reg = fit["classification"], fit["regression"]
    for key in ("ece", "nll", "brier"):
        assert cls[key]["after"] < cls[key]["before"], key
    assert reg["nll"]["after"] < reg["nll"]["before"]
    # the detector's own covariance is far too small; after depth scaling MD is near E[MD]
    assert reg["mean_md"]["before"] > 2 * reg["expected_md"]
    assert reg["mean_md"]["after"] == pytest.approx(reg["expected_md"], rel=0.1)
    for observed, nominal in zip(reg["coverage"]["after"], reg["coverage"]["nominal"],
                                 strict=True):
        assert observed == pytest.approx(nominal, abs=0.05)
    for axis in ("x", "y"):
        area = reg["miscalibration_area"][axis]
        assert area["after"] < area["before"]


def test_per_class_rows_and_plot_data(sigmoid_profile, sigmoid_dump):
    fit = sigmoid_profile.report["fit"]
    rows = {row["class"]: row for row in fit["per_class"]}
    assert list(rows) == list(sigmoid_dump.classes)
    assert sum(row["tp"] for row in rows.values()) == fit["counts"]["tp"]
    assert rows["car"]["k"] == sigmoid_profile.depth_k["car"]
    assert rows["car"]["nll_after"] < rows["car"]["nll_before"]
    plots = fit["plots"]
    diagram = plots["reliability"]["after"]
    assert len(diagram["bin_edges"]) == len(diagram["accuracy"]) + 1
    assert sum(diagram["count"]) == fit["counts"]["detections"]
    assert set(plots["reliability_per_class"]) == set(sigmoid_dump.classes)
    curve = plots["calibration_curve"]["x"]["after"]
    assert len(curve["expected"]) == len(curve["observed"]) == 50
    residuals = plots["residuals"]
    assert residuals["n_total"] == fit["counts"]["tp"]
    assert len(residuals["after"]["residual_norm"]) == min(2000, residuals["n_total"])


def test_residual_sample_is_capped(small_dump):
    report = summarize(small_dump, max_points=100).to_dict()
    assert len(report["plots"]["residuals"]["before"]["sigma"]) == 100


def test_softmax_report_uses_categorical_nll(softmax_dump):
    report = summarize(softmax_dump, cov_source="layers").to_dict()
    _check_keys(report)
    assert report["score_mode"] == "softmax"
    assert report["classification"]["nll"]["before"] > 0


def test_format_table_lists_metrics_and_classes(sigmoid_profile):
    text = format_table(ProfileReport.from_dict(sigmoid_profile.report))
    assert "== fit part ==" in text and "== held-out part ==" in text
    assert "all queries" in text
    for label in ("ECE", "D-ECE", "Brier", "NLL", "mean MD", "coverage 1σ",
                  "miscalibration area x", "car", "traffic_cone"):
        assert label in text
    header = next(line for line in text.splitlines() if line.startswith("metric"))
    assert "before" in header and "after" in header


def test_summary_and_profile_report_round_trip_their_dict_form(sigmoid_profile, small_dump):
    stored = sigmoid_profile.report
    report = ProfileReport.from_dict(stored)
    assert report.to_dict() == stored
    assert json.dumps(report.to_dict()) == json.dumps(stored)      # same key order too
    assert report.fit.counts.tp == stored["fit"]["counts"]["tp"]
    assert report.fit.per_class[0].name == stored["fit"]["per_class"][0]["class"]
    summary = summarize(small_dump)
    assert Summary.from_dict(summary.to_dict()) == summary
    assert ProfileReport.from_dict({}) is None                     # a profile built by hand


def test_summary_from_dict_names_a_missing_key(sigmoid_profile):
    broken = json.loads(json.dumps(sigmoid_profile.report["fit"]))
    del broken["regression"]["mean_md"]
    with pytest.raises(ValueError, match="regression is missing key 'mean_md'"):
        Summary.from_dict(broken)


def test_served_region_coverage_is_measured(sigmoid_profile):
    regions = sigmoid_profile.report["fit"]["regions"]
    assert regions["levels"] == [0.5, 0.9, 0.95, 0.99]
    assert regions["method"] == sigmoid_profile.region_method
    overall = regions["coverage"]["overall"]
    assert overall == sorted(overall) and all(0.0 <= c <= 1.0 for c in overall)
    assert regions["mean_area"] == sorted(regions["mean_area"])
    rows = regions["coverage"]["rows"]
    assert sum(r["count"] for r in rows) == sigmoid_profile.report["fit"]["counts"]["tp"]
