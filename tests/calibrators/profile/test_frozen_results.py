"""Profiles and results are immutable: assigning to a `CalibrationProfile` or a
`CalibratedDetections` raises FrozenInstanceError, `dataclasses.replace` gives a new (validated)
copy, and a profile's parsed stages are read-only. `CalibratedDetections.to_dict()` is JSON,
column by column (an unbounded region is null)."""

from __future__ import annotations

import copy
import dataclasses
import json
import pickle

import numpy as np
import pytest

from calibrators.fit import CovarianceFit, RegionFit, ScoreFit
from calibrators.profile import CalibratedDetections, CalibrationProfile, Detections

CLASSES = ("car", "pedestrian")


def _profile(**changes: object) -> CalibrationProfile:
    fields = dict(classes=CLASSES, score_mode="sigmoid", temperature=1.5, cov_source="given",
                  depth_k={"car": 0.02, "pedestrian": 0.01}, pooled_k=0.015)
    return CalibrationProfile(**{**fields, **changes})


def _calibrated(levels: tuple[float, ...] | None = (0.5, 0.9)) -> CalibratedDetections:
    rng = np.random.default_rng(3)
    n = 6
    boxes = np.zeros((n, 9))
    boxes[:, :2] = rng.uniform(-30.0, 30.0, (n, 2))
    a = rng.normal(size=(n, 2, 2))
    return _profile().calibrate(logits=rng.normal(size=(n, 2)), boxes=boxes,
                                covariances=a @ a.transpose(0, 2, 1) + np.eye(2),
                                levels=levels)


def test_calibrated_to_dict_is_json_column_by_column():
    out = _calibrated()
    doc = json.loads(json.dumps(out.to_dict(), allow_nan=False))
    n = len(out)
    assert doc["labels"] == out.labels.tolist() and len(doc["scores"]) == n
    assert np.array(doc["covariances"]).shape == (n, 2, 2)
    assert set(doc["ellipses"]) == {"semi_major", "semi_minor", "angle"}
    assert doc["ellipses"]["semi_major"] == out.ellipses.semi_major.tolist()
    assert sorted(doc["regions"]) == ["0.5", "0.9"] == sorted(doc["region_radii"])
    assert doc["regions"]["0.9"]["angle"] == out.regions[0.9].angle.tolist()
    assert doc["classes"] == list(CLASSES) and doc["cov_source"] == "given"
    assert doc["detections"] is None


def test_calibrated_to_dict_without_regions_and_with_an_identity():
    bare = _calibrated(levels=None).to_dict()
    assert bare["regions"] == {} and bare["region_radii"] == {}
    batch = Detections(frame_ids=np.array(["f0", "f0", "f1"]), rows=np.array([4, 1, 0]),
                       boxes=np.zeros((3, 9)) + [[5.0] + [0.0] * 8],
                       ego_xy=np.zeros((3, 2)), logits=np.zeros((3, 2)),
                       covariances=np.tile(np.eye(2), (3, 1, 1)),
                       detection_ids=["a", "b", "c"])
    doc = json.loads(json.dumps(batch.calibrate(_profile()).to_dict(), allow_nan=False))
    assert doc["detections"] == {"frame_ids": ["f0", "f0", "f1"], "rows": [4, 1, 0],
                                 "ids": ["a", "b", "c"]}


@pytest.mark.parametrize("name, value", [("temperature", 2.0), ("classes", ("a", "b")),
                                         ("depth_k", {}), ("report", {"x": 1}),
                                         ("score_calibrator", ("temperature", None)),
                                         ("source_stages", {})])
def test_a_profile_is_frozen(name, value):
    profile = _profile()
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(profile, name, value)


def test_replace_gives_a_new_validated_profile():
    profile = _profile()
    hotter = dataclasses.replace(profile, temperature=3.0)
    assert (hotter.temperature, profile.temperature) == (3.0, 1.5)
    assert hotter.to_json() != profile.to_json()
    with pytest.raises(ValueError, match="temperature must be > 0"):
        dataclasses.replace(profile, temperature=-1.0)


def test_the_parsed_stages_are_read_only():
    profile = _profile()
    assert profile.score_calibrator == ("temperature", None)
    stages = profile.source_stages
    assert list(stages) == ["given"] == list(profile.served_sources)
    assert stages["given"].depth_k == {"car": 0.02, "pedestrian": 0.01}
    with pytest.raises(TypeError):
        stages["none"] = stages["given"]          # type: ignore[index]
    with pytest.raises(dataclasses.FrozenInstanceError):
        stages["given"].pooled_k = 1.0            # type: ignore[misc]


def test_a_frozen_profile_round_trips_pickles_and_copies():
    profile = _profile(min_score=0.1)
    back = CalibrationProfile.from_json(profile.to_json())
    assert back == profile and back.to_json() == profile.to_json()
    for again in (pickle.loads(pickle.dumps(profile)), copy.deepcopy(profile)):
        assert again == profile and again.served_sources == ("given",)
        assert type(again.source_stages) is type(profile.source_stages)
        with pytest.raises(TypeError):
            again.source_stages["none"] = None    # type: ignore[index]


def test_a_result_is_frozen():
    served = _calibrated()
    with pytest.raises(dataclasses.FrozenInstanceError):
        served.scores = served.scores * 0   # type: ignore[misc]


@pytest.mark.parametrize("result", [
    ScoreFit("temperature", 1.5, None, {"temperature": {"nll": 0.3, "ece": 0.01}}),
    CovarianceFit("depth", {"car": 0.01}, 0.02, {"car": 1.0}, 1.0, ("bus",)),
    RegionFit("gaussian", None, 12),
])
def test_fit_stage_results_are_frozen_and_json(result):
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.method = "other"   # type: ignore[misc]
    assert json.loads(json.dumps(result.to_dict(), allow_nan=False))["method"] == result.method
