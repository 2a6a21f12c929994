"""fit_profile's stages: candidates chosen on a held-out calibration part, thesis methods kept
as version 1, and conformal ellipses that hold on exchangeable data (synthetic dumps)."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators import (
    CalibrationProfile,
    FitOptions,
    OptionError,
    apply_profile,
    fit_profile,
    match_dump,
    tp_residuals,
)
from calibrators.data import synthetic_dump
from calibrators.regions import xy_mahalanobis

LEVELS = (0.5, 0.9, 0.95, 0.99)


@pytest.fixture(scope="module")
def val_test():
    return synthetic_dump(n_frames=200, seed=11), synthetic_dump(n_frames=200, seed=12)


@pytest.fixture(scope="module")
def auto_profile(val_test):
    return fit_profile(val_test[0], cov_source="given")


def test_auto_picks_the_best_held_out_candidate(auto_profile):
    selection = auto_profile.report["selection"]
    scores = selection["score"]["candidates"]
    assert set(scores) == {"temperature", "class_temperature", "platt", "platt_range",
                           "isotonic", "histogram"}
    best = min(scores, key=lambda m: scores[m]["nll"])
    assert selection["score"]["chosen"] == best == auto_profile.score_method
    cov = selection["covariance"]["candidates"]
    assert selection["covariance"]["chosen"] == min(cov, key=lambda m: cov[m]["nll"])
    assert auto_profile.region_method == "conformal" and auto_profile.schema_version == 2
    assert selection["regions"]["calibration_tps"] >= 100


def test_thesis_methods_give_a_version_1_profile_equal_to_the_plain_fit(val_test):
    val = val_test[0]
    thesis = fit_profile(val, cov_source="given", score_method="temperature",
                         cov_method="depth", region_method="gaussian", other_sources=False)
    plain = fit_profile(val, cov_source="given", score_method="temperature",
                        cov_method="depth", region_method="gaussian", calibration=0.0,
                        other_sources=False)
    assert thesis.schema_version == 1 and thesis.score_calibration is None
    assert thesis.temperature == plain.temperature and thesis.depth_k == plain.depth_k


def test_scores_keep_labels_and_ranking_within_a_class(auto_profile, val_test):
    test = val_test[1]
    out = apply_profile(test, auto_profile)
    np.testing.assert_array_equal(out.labels, test.det_labels)
    if auto_profile.score_method == "platt_range":
        pytest.skip("the range term may reorder within a class")
    for c in range(len(test.classes)):
        rows = test.det_labels == c
        order = np.argsort(test.det_scores[rows], kind="stable")
        assert (np.diff(out.scores[rows][order]) >= 0).all()


def test_conformal_ellipses_cover_exchangeable_test_frames(auto_profile, val_test):
    test = val_test[1]
    m = match_dump(test)
    out = apply_profile(test, auto_profile, levels=LEVELS)
    md = xy_mahalanobis(tp_residuals(test, m), out.covariances[m.tp], ("x", "y"))
    for q in LEVELS:
        covered = float((md <= out.region_radii[q][m.tp]).mean())
        # calibration part ~1800 TPs in groups of >= 100, test ~3600: a few pp of noise
        assert q - 0.04 <= covered <= q + 0.04, (q, covered)
    assert len(set(out.region_groups)) > 1


def test_explicit_methods_are_used_and_conformal_needs_a_calibration_part(val_test):
    val = val_test[0]
    prof = fit_profile(val, cov_source="given", score_method="histogram",
                       cov_method="shrinkage", region_method="gaussian")
    assert (prof.score_method, prof.cov_method, prof.region_method) == (
        "histogram", "shrinkage", "gaussian")
    assert prof.report["selection"]["score"]["candidates"] == {}
    with pytest.raises(OptionError, match="calibration") as info:
        fit_profile(val, FitOptions(region_method="conformal", calibration=0.0))
    assert info.value.field == "calibration"


def test_a_profile_serves_every_covariance_source_the_dump_allowed(val_test):
    val, test = val_test
    profile = fit_profile(val, cov_source="layers", region_method="conformal")
    assert profile.served_sources == ("layers", "given", "none")
    assert CalibrationProfile.from_json(profile.to_json()) == profile
    base = {"logits": test.det_logits[:, -1], "boxes": test.final_boxes, "levels": [0.9]}
    m = match_dump(test)
    for extra, source in (({"covariances": test.det_cov}, "given"),
                          ({"layer_boxes": test.det_boxes}, "layers"), ({}, "none")):
        out = profile.calibrate(**base, **extra)
        assert out.cov_source == source and out.region_method == "conformal"
        md = xy_mahalanobis(tp_residuals(test, m), out.covariances[m.tp], ("x", "y"))
        covered = float((md <= out.region_radii[0.9][m.tp]).mean())
        assert 0.86 <= covered <= 0.94, (source, covered)   # each source calibrated on its own
    only = fit_profile(val, cov_source="layers", other_sources=False)
    with pytest.raises(ValueError, match="layer_boxes .* is required"):
        only.calibrate(logits=test.det_logits[:, -1], boxes=test.final_boxes)
