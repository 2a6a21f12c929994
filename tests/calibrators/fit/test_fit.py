"""fit_profile on synthetic dumps with a known temperature and per-class k."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibrators.data import CLASSES10, DEFAULT_DEPTH_K, synthetic_dump
from calibrators.fit import fit_profile
from calibrators.profile import CalibrationProfile


def test_synthetic_dump_is_deterministic_and_plausible():
    a = synthetic_dump(n_frames=5, seed=11)
    b = synthetic_dump(n_frames=5, seed=11)
    assert a.classes == CLASSES10 and a.n_frames == 5 and a.n_layers == 3
    np.testing.assert_array_equal(a.det_logits, b.det_logits)
    np.testing.assert_array_equal(a.gt_boxes, b.gt_boxes)
    assert 2.0 <= a.gt_distance.min() and a.gt_distance.max() <= 60.0
    assert a.det_cov is not None and a.det_cov.shape == (a.n_detections, 2, 2)
    # per-layer boxes converge: the first layer is further from the final box than the middle
    gap = np.abs(a.det_boxes[:, :, :2] - a.det_boxes[:, -1:, :2]).mean(axis=(0, 2))
    assert gap[0] > gap[1] > gap[2] == 0.0
    assert synthetic_dump(n_frames=3, with_cov=False, n_layers=1).det_cov is None


@pytest.mark.parametrize("name", ["sigmoid_dump", "softmax_dump"])
def test_recovers_the_generating_temperature(name, request):
    dump = request.getfixturevalue(name)
    true_t = 2.0 if dump.score_mode == "sigmoid" else 1.5
    profile = fit_profile(dump, cov_source="none")
    assert profile.score_mode == dump.score_mode
    assert abs(profile.temperature - true_t) / true_t < 0.1


def test_recovers_depth_k_in_the_right_order(sigmoid_dump):
    profile = fit_profile(sigmoid_dump, cov_source="given")
    k = profile.depth_k
    assert set(k) == set(CLASSES10)
    assert all(v > 0 for v in k.values())
    assert k["truck"] > k["car"] > k["pedestrian"]
    for name in ("car", "pedestrian"):   # the most common classes: tight
        assert k[name] == pytest.approx(DEFAULT_DEPTH_K[name], rel=0.2)


def test_calibration_keeps_the_argmax_and_grows_covariance_with_distance(sigmoid_profile,
                                                                          sigmoid_dump):
    d = sigmoid_dump
    out = sigmoid_profile.calibrate(logits=d.det_logits[:, -1], boxes=d.final_boxes,
                                    covariances=d.det_cov)
    np.testing.assert_array_equal(out.labels, d.det_labels)
    assert not np.allclose(out.scores, d.det_scores)
    added = np.trace(out.covariances - d.det_cov, axis1=1, axis2=2)
    near, far = d.det_distance < 15, d.det_distance > 45
    assert added[far].mean() > 2 * added[near].mean()


def test_profile_report_has_fit_and_holdout_parts(sigmoid_profile, sigmoid_dump):
    rep = sigmoid_profile.report
    assert set(rep) == {"fit", "holdout", "min_score", "threshold", "selection"}
    assert set(rep["selection"]) == {"score", "covariance", "regions"}
    assert rep["min_score"] is None and rep["threshold"] == 2.0
    assert rep["fit"]["counts"]["frames"] + rep["holdout"]["counts"]["frames"] == \
        sigmoid_dump.n_frames
    assert rep["holdout"]["counts"]["frames"] == round(0.3 * sigmoid_dump.n_frames)
    held = rep["holdout"]["classification"]["ece"]
    assert held["after"] < held["before"]
    prov = sigmoid_profile.provenance
    assert prov["n_frames"] == sigmoid_dump.n_frames and len(prov["dump_sha256"]) == 64
    assert prov["n_matched"] == rep["fit"]["counts"]["tp"]
    assert prov["created_at"].endswith("Z")


def test_profile_round_trips_through_json(sigmoid_profile):
    again = CalibrationProfile.from_json(sigmoid_profile.to_json())
    assert again.to_json() == sigmoid_profile.to_json()
    assert again.temperature == sigmoid_profile.temperature


@pytest.mark.parametrize("source", ["auto", "given", "layers", "none"])
def test_covariance_sources(source, small_dump):
    profile = fit_profile(small_dump, cov_source=source, min_samples=20)
    assert profile.cov_source == ("given" if source == "auto" else source)
    assert profile.pooled_k >= 0
    regression = profile.report["fit"]["regression"]
    if source == "none":   # no raw covariance: before is undefined, after is not
        assert regression["nll"]["before"] is None and regression["note_before"]
    else:
        assert regression["nll"]["before"] is not None
    assert regression["nll"]["after"] is not None


def test_auto_source_without_det_cov_uses_layers_then_none():
    assert fit_profile(synthetic_dump(n_frames=10, with_cov=False),
                       min_samples=10).cov_source == "layers"
    one_layer = synthetic_dump(n_frames=10, with_cov=False, n_layers=1)
    assert fit_profile(one_layer, min_samples=10).cov_source == "none"
    with pytest.raises(ValueError, match="cov_source='layers'"):
        fit_profile(one_layer, cov_source="layers")


def test_rare_classes_fall_back_to_pooled_k(small_dump):
    profile = fit_profile(small_dump, min_samples=1000)
    assert set(profile.fallback_classes) == set(CLASSES10)
    assert all(k == profile.pooled_k for k in profile.depth_k.values())


def test_min_score_filter_is_applied_and_reported(small_dump):
    profile = fit_profile(small_dump, min_score=0.3)
    kept = int((small_dump.det_scores >= 0.3).sum())
    assert profile.min_score == 0.3 and profile.report["min_score"] == 0.3
    assert profile.report["fit"]["counts"]["detections"] == kept
    with pytest.raises(ValueError, match="min_score"):
        fit_profile(small_dump, min_score=1.0)


def test_progress_reports_every_stage(small_dump):
    calls: list[tuple[str, float]] = []
    fit_profile(small_dump, holdout=0.25, progress=lambda s, f: calls.append((s, f)))
    stages = [s for s, _ in calls]
    assert stages[0] == "prepare" and stages[-1] == "done"
    assert {"match", "scores", "covariance", "regions", "report", "holdout report"} <= set(stages)
    fractions = [f for _, f in calls]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


@pytest.mark.parametrize(("options", "message"), [
    ({"threshold": 0.0}, "threshold"),
    ({"holdout": 1.0}, "holdout"),
    ({"holdout": -0.1}, "holdout"),
    ({"dims": ("x", "speed")}, "dims"),
    ({"dims": ()}, "dims"),
    ({"cov_source": "attention"}, "cov_source"),
    ({"min_score": 1.5}, "min_score"),
    ({"min_samples": 0}, "min_samples"),
])
def test_bad_options_raise_naming_the_option(options, message, small_dump):
    with pytest.raises(ValueError, match=message):
        fit_profile(small_dump, **options)


def test_given_covariance_must_exist_and_match_dims(small_dump):
    with pytest.raises(ValueError, match="cov_source='given'.*no det_cov"):
        fit_profile(replace(small_dump, det_cov=None), cov_source="given")
    with pytest.raises(ValueError, match="cov_dims"):
        fit_profile(small_dump, cov_source="given", dims="x,y,z")


def test_no_match_raises(small_dump):
    far = small_dump.gt_boxes.copy()
    far[:, 0] += 500.0
    with pytest.raises(ValueError, match="no detection matched ground truth within 2.0 m"):
        fit_profile(replace(small_dump, gt_boxes=far))


def test_yaw_dimension_fits(small_dump):
    profile = fit_profile(small_dump, dims="x,y,yaw", cov_source="layers", min_samples=20)
    assert profile.cov_dims == ("x", "y", "yaw")
    assert profile.report["fit"]["regression"]["nll"]["after"] is not None
