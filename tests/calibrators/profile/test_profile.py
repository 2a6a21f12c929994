"""CalibrationProfile: exact JSON round-trip, from_json validation, calibrate()."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators.covariance import layer_spread
from calibrators.profile import CalibratedDetections, CalibrationProfile, make_provenance
from calibrators.regions import ellipse
from calibrators.scores import class_probabilities

CLASSES = ("car", "pedestrian", "barrier")


def random_profile(seed: int = 0, **overrides) -> CalibrationProfile:
    """A profile whose every float is an arbitrary double (round-trip must keep all bits)."""
    rng = np.random.default_rng(seed)
    fields = dict(
        classes=CLASSES, score_mode="softmax", temperature=float(rng.uniform(0.2, 5.0)),
        cov_dims=("x", "y"), cov_source="given",
        depth_k={"car": float(rng.random()), "pedestrian": float(rng.random() / 3)},
        pooled_k=float(rng.random()), fallback_classes=("barrier",),
        matching={"rule": "center_distance", "threshold": 2.0},
        min_score=float(rng.random()),
        report={"fit": {"ece": {"before": float(rng.random()), "after": float(rng.random())},
                        "n": 1234, "per_class": [float(x) for x in rng.random(3)]},
                "holdout": None},
        provenance={"dump_sha256": "ab" * 32, "n_frames": 10, "n_detections": 3000,
                    "n_matched": 800, "created_at": "2026-01-02T03:04:05Z",
                    "detcal_version": "0.1.0"})
    fields.update(overrides)
    return CalibrationProfile(**fields)


@pytest.mark.parametrize("seed", range(5))
def test_json_round_trip_is_exact(seed):
    profile = random_profile(seed)
    text = profile.to_json()
    back = CalibrationProfile.from_json(text)
    assert back == profile
    for name in ("temperature", "pooled_k", "min_score"):
        assert getattr(back, name).hex() == getattr(profile, name).hex()
    assert back.depth_k == profile.depth_k and back.report == profile.report
    assert back.to_json() == text
    data = json.loads(text)
    for key in ("temperature", "depth_k", "pooled_k", "classes", "score_mode", "cov_dims",
                "report", "provenance", "schema_version"):
        assert key in data


def test_numpy_values_and_tuples_are_normalised():
    profile = random_profile(temperature=np.float32(1.5), classes=list(CLASSES),
                             report={"n": np.int64(3), "curve": np.arange(3.0),
                                     "pair": (1, 2)})
    assert profile.temperature == 1.5 and isinstance(profile.temperature, float)
    assert profile.classes == CLASSES
    assert profile.report == {"n": 3, "curve": [0.0, 1.0, 2.0], "pair": [1, 2]}
    assert CalibrationProfile.from_json(profile.to_json()) == profile


def _json_with(**changes) -> str:
    data = json.loads(random_profile().to_json())
    for key, value in changes.items():
        if value is _DELETE:
            del data[key]
        else:
            data[key] = value
    return json.dumps(data)


_DELETE = object()


@pytest.mark.parametrize("changes, match", [
    ({"temperature": _DELETE}, "missing key 'temperature'"),
    ({"schema_version": _DELETE}, "missing key 'schema_version'"),
    ({"schema_version": 3}, "schema_version 3 is not supported"),
    ({"schema_version": "1"}, "schema_version '1' is not supported"),
    ({"temperature": "1.0"}, "key 'temperature' has the wrong type str"),
    ({"temperature": True}, "key 'temperature' has the wrong type bool"),
    ({"temperature": 0.0}, "temperature must be > 0"),
    ({"temperature": -1.5}, "temperature must be > 0"),
    ({"pooled_k": -0.1}, "pooled_k must be >= 0"),
    ({"depth_k": {"car": -0.5}}, r"depth_k\['car'\] must be >= 0"),
    ({"depth_k": {"car": "x"}}, r"depth_k\['car'\] must be a number"),
    ({"depth_k": {"truck": 0.5}}, "depth_k names 'truck', which is not in classes"),
    ({"classes": "car"}, "key 'classes' has the wrong type str"),
    ({"classes": ["car", "car"]}, "classes has duplicate names"),
    ({"classes": []}, "classes must name at least one class"),
    ({"score_mode": "tanh"}, "score_mode must be one of"),
    ({"cov_source": "mc"}, "cov_source must be one of"),
    ({"cov_dims": ["x", "q"]}, "dims has unknown box field 'q'"),
    ({"fallback_classes": ["bus"]}, "fallback_classes names 'bus'"),
    ({"matching": {"rule": "iou", "threshold": 0.5}}, "matching.rule must be one of"),
    ({"matching": {"rule": "center_distance"}}, "matching.threshold must be a number"),
    ({"min_score": 1.5}, r"min_score must be in \[0, 1\]"),
    ({"report": []}, "key 'report' has the wrong type list"),
    ({"extra": 1}, "unknown key 'extra'"),
])
def test_from_json_validation_names_the_key(changes, match):
    with pytest.raises(ValueError, match=match):
        CalibrationProfile.from_json(_json_with(**changes))


def test_from_json_rejects_non_json_and_non_objects():
    with pytest.raises(ValueError, match="not valid JSON"):
        CalibrationProfile.from_json("{temperature: 1")
    with pytest.raises(ValueError, match="must be a JSON object"):
        CalibrationProfile.from_json("[1, 2]")
    with pytest.raises(ValueError, match="finite numbers"):
        random_profile(report={"ece": float("nan")})


def test_summary_and_provenance():
    profile = random_profile(provenance=make_provenance(dump_sha256="00", n_frames=3))
    summary = profile.summary()
    assert summary["classes"] == list(CLASSES)
    assert summary["temperature"] == profile.temperature
    assert summary["depth_k"] == profile.depth_k and summary["pooled_k"] == profile.pooled_k
    assert summary["cov_source"] == "given"
    assert summary["created_at"].endswith("Z") and summary["created_at"].startswith("20")
    assert profile.provenance["n_frames"] == 3 and "detcal_version" in profile.provenance
    json.dumps(summary)


# -- calibrate ---------------------------------------------------------------------------------

def detections(n: int = 200, seed: int = 1, width: int = 4):
    rng = np.random.default_rng(seed)
    logits = rng.normal(0.0, 3.0, size=(n, width))
    boxes = np.zeros((n, 9))
    boxes[:, :2] = rng.uniform(-50.0, 50.0, size=(n, 2))
    boxes[:, 3:6] = 1.0
    a = rng.normal(size=(n, 2, 2)) * 0.3
    return logits, boxes, a @ np.swapaxes(a, 1, 2)


def test_calibrate_softmax_logits_with_given_covariance():
    profile = random_profile(temperature=2.0, depth_k={"car": 0.1, "pedestrian": 0.02},
                             pooled_k=0.05)
    logits, boxes, cov = detections()
    ego = np.tile([3.0, -4.0], (len(boxes), 1))
    out = profile.calibrate(logits=logits, boxes=boxes, covariances=cov, ego_xy=ego)
    assert isinstance(out, CalibratedDetections) and len(out) == 200
    np.testing.assert_array_equal(out.labels, logits[:, :3].argmax(axis=1))
    np.testing.assert_array_equal(out.class_scores.argmax(axis=1), out.labels)
    np.testing.assert_allclose(out.class_scores, class_probabilities(logits, "softmax", 2.0))
    assert not np.allclose(out.scores, out.scores_raw)
    np.testing.assert_allclose(out.distances, np.hypot(boxes[:, 0] - 3.0, boxes[:, 1] + 4.0))
    k = np.array([0.1, 0.02, 0.05])[out.labels]  # barrier is not in depth_k -> pooled_k
    np.testing.assert_allclose(out.covariances, cov + (k * out.distances)[:, None, None]
                               * np.eye(2))
    expected = ellipse(out.covariances, 0.95)
    np.testing.assert_allclose(out.ellipses.semi_major, expected.semi_major)
    np.testing.assert_allclose(out.ellipses.angle, expected.angle)


def test_covariance_grows_with_distance():
    profile = random_profile(score_mode="sigmoid", cov_source="none",
                             depth_k={"car": 0.1, "pedestrian": 0.1}, pooled_k=0.1)
    boxes = np.zeros((4, 9))
    boxes[:, 0] = [1.0, 5.0, 20.0, 50.0]
    out = profile.calibrate(scores=np.full(4, 0.8), labels=np.zeros(4, dtype=int), boxes=boxes)
    traces = np.trace(out.covariances, axis1=1, axis2=2)
    assert np.all(np.diff(traces) > 0)
    np.testing.assert_allclose(traces, 2 * 0.1 * boxes[:, 0])
    assert np.all(np.diff(out.ellipses.semi_major) > 0)
    assert out.class_scores is None


def test_scores_only_input_uses_the_temperature_on_the_logit():
    profile = random_profile(score_mode="sigmoid", temperature=2.0, cov_source="none")
    p = np.array([0.5, 0.9, 0.1, 0.0, 1.0])
    out = profile.calibrate(scores=p, labels=np.zeros(5, dtype=int), boxes=np.ones((5, 9)))
    np.testing.assert_allclose(out.scores, [0.5, 0.75, 0.25, 0.0, 1.0])
    np.testing.assert_array_equal(out.scores_raw, p)


def test_sigmoid_logits_argmax_unchanged_and_layers_source():
    profile = random_profile(score_mode="sigmoid", temperature=0.5, cov_source="layers",
                             cov_dims=("y", "x", "z"))
    logits, boxes, _ = detections(width=3)
    rng = np.random.default_rng(2)
    layers = boxes[:, None, :] + rng.normal(0.0, 0.2, size=(len(boxes), 6, 9))
    out = profile.calibrate(logits=logits.astype(np.float32), boxes=boxes, layer_boxes=layers)
    np.testing.assert_array_equal(out.labels, logits.argmax(axis=1))
    assert out.covariances.shape == (200, 3, 3)
    spread = layer_spread(layers, ("y", "x", "z"))
    np.testing.assert_allclose(np.diagonal(out.covariances - spread, axis1=1, axis2=2)[:, 0],
                               np.diagonal(out.covariances - spread, axis1=1, axis2=2)[:, 2])
    xy = out.covariances[:, [1, 0]][:, :, [1, 0]]  # x, y block out of (y, x, z)
    np.testing.assert_allclose(out.ellipses.semi_major, ellipse(xy).semi_major)


def test_no_ellipses_without_x_and_y():
    profile = random_profile(cov_source="none", cov_dims=("z", "yaw"))
    logits, boxes, _ = detections()
    assert profile.calibrate(logits=logits, boxes=boxes).ellipses is None


@pytest.mark.parametrize("kwargs, match", [
    ({"logits": np.zeros((3, 3))}, "logits has 3 columns but the profile's softmax mode with "
                                   "3 classes needs 4"),
    ({"logits": np.zeros((3, 4)), "covariances": np.tile(np.eye(3), (3, 1, 1))},
     r"covariances are 3x3 but the profile's cov_dims \['x', 'y'\] need 2x2"),
    ({"logits": np.zeros((3, 4))}, r"covariances are required: the profile was fit on given "
                                   r"covariances \(cov_source 'given'\)"),
    ({"logits": np.zeros((3, 4)), "scores": np.zeros(3)}, "either logits or scores"),
    ({}, "either logits or scores"),
    ({"scores": np.full(3, 0.5)}, r"labels \(with scores\) is required"),
    ({"scores": np.full(3, 1.5), "labels": np.zeros(3, int)}, r"scores must .*probabilities"),
    ({"scores": np.full(3, 0.5), "labels": np.array([0, 3, 1])}, r"labels\[1\] = 3 is out"),
    ({"logits": np.zeros((3, 4)), "covariances": np.tile(np.eye(2), (3, 1, 1)),
      "ego_xy": np.zeros((3, 3))}, r"ego_xy must have shape \[3, 2\]"),
    ({"logits": np.zeros((3, 4)), "covariances": np.tile(np.eye(2), (2, 1, 1))},
     "covariances has 2 matrices but 3 were expected"),
])
def test_calibrate_mismatches(kwargs, match):
    profile = random_profile()
    boxes = kwargs.pop("boxes", np.ones((3, 9)))
    with pytest.raises(ValueError, match=match):
        profile.calibrate(boxes=boxes, **kwargs)


def test_calibrate_layers_and_none_sources_refuse_wrong_inputs():
    layers = random_profile(cov_source="layers")
    with pytest.raises(ValueError, match=r"layer_boxes \(the profile's cov_source is 'layers'\)"):
        layers.calibrate(logits=np.zeros((3, 4)), boxes=np.ones((3, 9)))
    with pytest.raises(ValueError, match="covariances were given but the profile's cov_source"):
        random_profile(cov_source="none").calibrate(
            logits=np.zeros((3, 4)), boxes=np.ones((3, 9)),
            covariances=np.tile(np.eye(2), (3, 1, 1)))
    with pytest.raises(ValueError, match=r"boxes must have shape \[N, 9\]"):
        random_profile(cov_source="none").calibrate(logits=np.zeros((3, 4)),
                                                    boxes=np.ones((3, 7)))
    with pytest.raises(ValueError, match="boxes is required"):
        random_profile(cov_source="none").calibrate(logits=np.zeros((3, 4)))


def test_no_detections_calibrate_to_empty_arrays():
    from calibrators.data import synthetic_dump
    from calibrators.fit import fit_profile

    profile = fit_profile(synthetic_dump(n_frames=10, seed=1), cov_source="given")
    res = profile.calibrate(logits=np.zeros((0, 10)), boxes=np.zeros((0, 9)),
                            covariances=np.zeros((0, 2, 2)), levels=[0.5, 0.9])
    assert len(res) == 0 and res.covariances.shape == (0, 2, 2)
    assert res.regions[0.9].semi_major.shape == (0,)


def test_twenty_levels_and_another_ellipse_confidence_are_served():
    from calibrators.data import synthetic_dump
    from calibrators.fit import fit_profile

    dump = synthetic_dump(n_frames=20, seed=1)
    profile = fit_profile(dump, cov_source="given", region_method="conformal", min_group=30)
    levels = [round(0.04 * k, 2) for k in range(1, 21)]              # 20 levels, not 0.95
    res = profile.calibrate(logits=dump.det_logits[:5, -1], boxes=dump.det_boxes[:5, -1],
                            covariances=dump.det_cov[:5], levels=levels,
                            ellipse_confidence=0.95)
    assert list(res.regions) == levels and res.ellipses is not None
    assert (res.ellipses.semi_major >= res.regions[0.8].semi_major).all()
