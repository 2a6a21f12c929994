"""The `hypotheses` covariance source end to end in the library: a fit on a dump's box
hypotheses, regions that cover at their level on held-out data, serving from per-detection
hypotheses, and the errors naming what is missing."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibrators import (
    CalibrationProfile,
    OptionError,
    apply_profile,
    fit_profile,
    match_dump,
    resolve_cov_source,
    tp_residuals,
)
from calibrators.core.errors import FieldError
from calibrators.covariance import hypotheses_covariance
from calibrators.data import synthetic_dump
from calibrators.regions import xy_mahalanobis

LEVELS = (0.5, 0.9, 0.95)
H = 6


@pytest.fixture(scope="module")
def val_test():
    """Val and test dumps whose box hypotheses spread with the true position noise."""
    return (synthetic_dump(n_frames=200, seed=11, n_hypotheses=H, with_cov=False),
            synthetic_dump(n_frames=200, seed=12, n_hypotheses=H, with_cov=False))


@pytest.fixture(scope="module")
def profile(val_test):
    return fit_profile(val_test[0], cov_source="hypotheses", region_method="conformal",
                       other_sources=False)


def _served(profile, dump, **extra):
    return profile.calibrate(logits=dump.det_logits[:, -1], boxes=dump.final_boxes,
                             levels=list(LEVELS), **extra)


def _coverage(dump, out) -> dict[float, float]:
    m = match_dump(dump)
    md = xy_mahalanobis(tp_residuals(dump, m), out.covariances[m.tp], ("x", "y"))
    return {q: float((md <= out.region_radii[q][m.tp]).mean()) for q in LEVELS}


def test_synthetic_hypotheses_leave_the_other_arrays_unchanged():
    plain, with_h = synthetic_dump(n_frames=10, seed=5), synthetic_dump(n_frames=10, seed=5,
                                                                        n_hypotheses=3)
    for key in ("det_frame", "det_logits", "det_boxes", "det_cov", "gt_boxes", "gt_labels"):
        assert np.array_equal(getattr(plain, key), getattr(with_h, key)), key
    assert plain.det_hyp_boxes is None and with_h.det_hyp_boxes.shape == (
        with_h.n_detections, 3, 9)
    # the top-scoring hypothesis is the detection's own box
    top = with_h.det_hyp_scores.argmax(axis=1)
    rows = np.arange(with_h.n_detections)
    assert np.array_equal(with_h.det_hyp_boxes[rows, top], with_h.final_boxes)


def test_a_hypotheses_fit_covers_at_its_levels_on_held_out_data(profile, val_test):
    test = val_test[1]
    assert profile.cov_source == "hypotheses" and profile.served_sources == ("hypotheses",)
    assert profile.region_method == "conformal"
    assert profile.report["fit"]["cov_source"] == "hypotheses"
    assert profile.report["fit"]["regression"]["nll"]["before"] is not None
    out = _served(profile, test, hyp_boxes=test.det_hyp_boxes, hyp_scores=test.det_hyp_scores)
    assert out.cov_source == "hypotheses"
    for q, covered in _coverage(test, out).items():
        assert abs(covered - q) <= 0.04, (q, covered)   # about 1200 held-out TPs


def test_serving_the_hypotheses_is_their_spread_plus_the_depth_term(profile, val_test):
    test = val_test[1]
    out = _served(profile, test, hyp_boxes=test.det_hyp_boxes, hyp_scores=test.det_hyp_scores)
    raw = hypotheses_covariance(test.det_hyp_boxes, test.det_hyp_scores)
    k = np.array([profile.depth_k[c] for c in profile.classes])[out.labels]
    scale = np.ones(len(k))
    if profile.cov_method == "shrinkage":
        pooled = profile.covariance_scaling["pooled_scale"]
        table = profile.covariance_scaling["scale"]
        scale = np.array([table.get(c, pooled) for c in profile.classes])[out.labels]
    want = scale[:, None, None] * raw + (k * out.distances)[:, None, None] * np.eye(2)
    np.testing.assert_allclose(out.covariances, want, rtol=1e-12, atol=1e-15)
    # the dump path serves the same numbers
    via_dump = apply_profile(test, profile, levels=list(LEVELS))
    np.testing.assert_array_equal(via_dump.covariances, out.covariances)


def test_the_profile_round_trips_and_still_serves(profile, val_test):
    test = val_test[1]
    again = CalibrationProfile.from_json(profile.to_json())
    assert again == profile and again.cov_source == "hypotheses"
    kw = {"hyp_boxes": test.det_hyp_boxes[:20], "hyp_scores": test.det_hyp_scores[:20]}
    a = profile.calibrate(logits=test.det_logits[:20, -1], boxes=test.final_boxes[:20], **kw)
    b = again.calibrate(logits=test.det_logits[:20, -1], boxes=test.final_boxes[:20], **kw)
    np.testing.assert_array_equal(a.covariances, b.covariances)


def test_a_dump_without_hypotheses_cannot_be_fit_on_them():
    dump = synthetic_dump(n_frames=10, seed=5)
    with pytest.raises(OptionError, match="det_hyp_boxes") as info:
        fit_profile(dump, cov_source="hypotheses")
    assert info.value.field == "cov_source"
    assert "hypotheses" in str(info.value) and "det_hyp_scores" in str(info.value)


def test_auto_never_picks_the_hypotheses_but_other_sources_serve_them():
    dump = synthetic_dump(n_frames=40, seed=5, n_hypotheses=3)
    assert resolve_cov_source(dump, "auto", ("x", "y")) == "given"
    no_cov = replace(dump, det_cov=None)
    assert resolve_cov_source(no_cov, "auto", ("x", "y")) == "layers"
    prof = fit_profile(dump, min_samples=20)
    assert prof.cov_source == "given"
    assert prof.served_sources == ("given", "layers", "none", "hypotheses")
    n = 30
    base = {"logits": dump.det_logits[:n, -1], "boxes": dump.final_boxes[:n]}
    hyp = {"hyp_boxes": dump.det_hyp_boxes[:n], "hyp_scores": dump.det_hyp_scores[:n]}
    layers = {"layer_boxes": dump.det_boxes[:n]}
    assert prof.calibrate(**base, **hyp).cov_source == "hypotheses"
    assert prof.calibrate(**base, **hyp, **layers).cov_source == "hypotheses"
    assert prof.calibrate(**base, **layers).cov_source == "layers"
    assert prof.calibrate(**base, **hyp, covariances=dump.det_cov[:n]).cov_source == "given"
    assert prof.calibrate(**base).cov_source == "none"


@pytest.mark.parametrize(("extra", "field", "message", "row"), [
    ({}, "hyp_boxes",
     r"hyp_boxes with hyp_scores \(the profile's cov_source is 'hypotheses'\) is required", None),
    ({"hyp_boxes": "ok"}, "hyp_scores", "hyp_boxes is given without hyp_scores", None),
    ({"hyp_scores": "ok"}, "hyp_boxes", "hyp_scores is given without hyp_boxes", None),
    ({"hyp_boxes": "short", "hyp_scores": "ok"}, "hyp_boxes", r"shape \[8, H, 9\]", None),
    ({"hyp_boxes": "ok", "hyp_scores": "narrow"}, "hyp_scores", r"shape \[8, 6\]", None),
    ({"hyp_boxes": "nan", "hyp_scores": "ok"}, "hyp_boxes", "hyp_boxes has NaN", 3),
    ({"hyp_boxes": "ok", "hyp_scores": "negative"}, "hyp_scores", "negative score at row 5",
     5),
])
def test_missing_or_malformed_hypotheses_name_the_argument(profile, val_test, extra, field,
                                                           message, row):
    test = val_test[1]
    n = 8
    boxes, scores = test.det_hyp_boxes[:n].copy(), test.det_hyp_scores[:n].copy()
    nan = boxes.copy()
    nan[3, 1, 0] = np.nan
    negative = scores.copy()
    negative[5, 2] = -0.1
    values = {"ok": None, "short": boxes[:, :, :7], "narrow": scores[:, :4], "nan": nan,
              "negative": negative}
    kw = {name: (boxes if name == "hyp_boxes" else scores) if values[v] is None else values[v]
          for name, v in extra.items()}
    with pytest.raises(FieldError, match=message) as info:
        profile.calibrate(logits=test.det_logits[:n, -1], boxes=test.final_boxes[:n], **kw)
    assert info.value.field == field and info.value.row == row


def test_old_profiles_ignore_hypotheses_they_were_not_fit_on(val_test):
    val, test = val_test
    layers = fit_profile(val, cov_source="layers", other_sources=False)
    n = 10
    base = {"logits": test.det_logits[:n, -1], "boxes": test.final_boxes[:n],
            "layer_boxes": test.det_boxes[:n]}
    out = layers.calibrate(**base, hyp_boxes=test.det_hyp_boxes[:n],
                           hyp_scores=test.det_hyp_scores[:n])
    np.testing.assert_array_equal(out.covariances, layers.calibrate(**base).covariances)
    assert out.cov_source == "layers"
