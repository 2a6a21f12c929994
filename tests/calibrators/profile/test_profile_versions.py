"""Profile versions: a version-1 profile (written by detcal before the version-2 stages) loads,
writes back byte for byte and serves exactly what it served; version-2 stages round-trip."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibrators import CalibrationProfile, fit_profile
from calibrators.data import synthetic_dump

DATA = Path(__file__).parent / "data"


def test_version_1_profile_loads_and_serves_identically():
    text = (DATA / "profile_v1.json").read_text()
    profile = CalibrationProfile.from_json(text)
    assert profile.schema_version == 1 and profile.score_method == "temperature"
    assert profile.cov_method == "depth" and profile.region_method == "gaussian"
    assert profile.to_json() == text                         # written back as version 1
    served = json.loads((DATA / "profile_v1_served.json").read_text())
    dump = synthetic_dump(n_frames=12, seed=3)   # the dump the fixture was fit and served on
    out = profile.calibrate(logits=dump.det_logits[:, -1], boxes=dump.final_boxes,
                            covariances=dump.det_cov, ego_xy=dump.ego_xy(dump.det_frame),
                            ellipse_confidence=0.9)
    assert out.scores.tolist() == served["scores"]           # bit for bit
    assert out.scores_raw.tolist() == served["scores_raw"]
    assert out.labels.tolist() == served["labels"]
    assert out.covariances.tolist() == served["covariances"]
    assert out.ellipses.semi_major.tolist() == served["semi_major"]
    assert out.ellipses.semi_minor.tolist() == served["semi_minor"]
    assert out.ellipses.angle.tolist() == served["angle"]
    levels = profile.calibrate(logits=dump.det_logits[:, -1], boxes=dump.final_boxes,
                               covariances=dump.det_cov, levels=[0.5, 0.9])
    assert levels.region_method == "gaussian" and levels.region_groups is None
    assert levels.regions[0.9].semi_major.tolist() == served["semi_major"]


def test_a_version_1_profile_cannot_carry_stages():
    data = json.loads((DATA / "profile_v1.json").read_text())
    data["regions"] = {"method": "gaussian", "conformal": None}
    with pytest.raises(ValueError, match="schema_version 1 profile has no"):
        CalibrationProfile.from_dict(data)


def test_version_2_stages_round_trip_and_serve_the_same():
    dump = synthetic_dump(n_frames=40, seed=5)
    profile = fit_profile(dump, cov_source="given", score_method="isotonic",
                          cov_method="shrinkage", region_method="conformal", min_group=30)
    assert profile.schema_version == 2
    assert (profile.score_method, profile.cov_method, profile.region_method) == (
        "isotonic", "shrinkage", "conformal")
    back = CalibrationProfile.from_json(profile.to_json())
    assert back == profile and back.to_json() == profile.to_json()
    kw = {"logits": dump.det_logits[:, -1], "boxes": dump.final_boxes,
          "covariances": dump.det_cov, "levels": [0.5, 0.95]}
    a, b = profile.calibrate(**kw), back.calibrate(**kw)
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.covariances, b.covariances)
    np.testing.assert_array_equal(a.regions[0.95].semi_major, b.regions[0.95].semi_major)
    assert a.region_method == "conformal" and len(a.region_groups) == dump.n_detections
    assert (a.regions[0.95].semi_major >= a.regions[0.5].semi_major).all()


@pytest.mark.parametrize("stage, value, match", [
    ("score_calibration", {"method": "magic"}, "score_calibration.method must be one of"),
    ("score_calibration", {"method": "isotonic", "params": {}}, "score_calibration.params"),
    ("covariance_scaling", {"method": "shrinkage", "scale": {"car": -1.0}},
     r"covariance_scaling.scale\['car'\] must be > 0"),
    ("regions", {"method": "conformal", "conformal": {}}, "regions.conformal is not valid"),
])
def test_bad_stages_name_the_key(stage, value, match):
    data = json.loads((DATA / "profile_v1.json").read_text())
    data.update(schema_version=2, **{stage: value})
    with pytest.raises(ValueError, match=match):
        CalibrationProfile.from_dict(data)
