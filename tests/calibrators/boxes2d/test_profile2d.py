"""A 2-D profile: fit on a synthetic COCO pair (`synthetic_coco`, exchangeable images), its
score calibration and box regions measured on held-out images, its JSON, serving, and the
errors that name the field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators.boxes2d import (
    Detections2D,
    FitOptions2D,
    Profile2D,
    calibrate_2d,
    fit_profile_2d,
    parse_instances,
    read_coco_results,
    synthetic_coco,
)
from calibrators.core.errors import FieldError, OptionError
from calibrators.profile import CalibrationProfile, read_profile


def pair(n_images: int = 400, seed: int = 0, **kw):
    results, instances = synthetic_coco(n_images, seed, **kw)
    return Detections2D.from_coco(results), parse_instances(instances)


@pytest.fixture(scope="module")
def fitted():
    found, instances = pair(600, seed=1)
    return found, instances, fit_profile_2d(found, instances, holdout=0.3)


def test_calibrated_scores_beat_raw_ones_on_held_out_images(fitted):
    _, _, profile = fitted
    held = profile.report["holdout"]
    assert held["n_images"] == 180 and held["n_true_positives"] > 100
    assert held["ece"]["calibrated"] < 0.5 * held["ece"]["raw"]
    assert held["d_ece"]["calibrated"] < held["d_ece"]["raw"]
    assert held["laece"]["calibrated"] < held["laece"]["raw"]
    for row in held["per_class"].values():
        assert row["ece_calibrated"] < row["ece_raw"]
    # the detector ignores the right half of its images: the position terms are chosen
    selection = profile.report["selection"]["score"]
    assert set(selection["candidates"]) == {"temperature", "class_temperature", "platt",
                                            "isotonic", "histogram", "position"}
    best = min(selection["candidates"], key=lambda n: selection["candidates"][n]["nll"])
    assert selection["chosen"] == best == profile.score_method == "position"
    assert all({"nll", "ece", "d_ece"} == set(c) for c in selection["candidates"].values())


@pytest.mark.parametrize(("layers", "region_score"), [
    (True, "scaled"), (False, "additive"), (True, "adaptive"), (False, "adaptive")])
def test_each_category_is_covered_near_its_level_over_many_draws(layers, region_score):
    """12 seeded draws, half the images held out: each category's joint four-edge coverage
    averaged over the draws is within 3 standard errors of q (scaled regions with layer
    boxes, additive without, adaptive with and without)."""
    levels = (0.8, 0.9)
    hits = {1: [], 2: []}
    for seed in range(12):
        found, instances = pair(500, seed=100 + seed)
        if not layers:
            found = Detections2D(found.image_id, found.category_id, found.bbox, found.score)
        profile = fit_profile_2d(found, instances, holdout=0.5, calibration=0.6, seed=seed,
                                 score_method="temperature", min_group=50,
                                 region_score=region_score)
        assert profile.region_score == region_score
        per_class = profile.report["holdout"]["regions"]["per_class"]
        for cid, name in zip(profile.category_ids, profile.category_names, strict=True):
            hits[cid].append(per_class[name]["coverage"])
    for cid, draws in hits.items():
        mean = np.mean(draws, axis=0)
        se = np.std(draws, axis=0, ddof=1) / np.sqrt(len(draws))
        for q, m, s in zip(levels, mean[1:3], se[1:3], strict=True):
            assert abs(m - q) < 3 * s + 0.01, (layers, cid, q, m, s)


def test_json_round_trip_serves_the_same_detections(fitted):
    found, _, profile = fitted
    text = profile.to_json()
    back = Profile2D.from_json(text)
    assert back == profile and back.to_json() == text
    assert json.loads(text)["kind"] == "boxes2d"
    assert isinstance(read_profile(text), Profile2D)
    a, b = calibrate_2d(profile, found, [0.5, 0.9]), calibrate_2d(back, found, [0.5, 0.9])
    assert np.array_equal(a.score, b.score)
    assert np.array_equal(a.regions.outer, b.regions.outer)
    assert a.records() == b.records()


def test_read_profile_tells_the_kinds_apart():
    three_d = CalibrationProfile(classes=("car",), score_mode="sigmoid")
    assert read_profile(three_d.to_json()) == three_d and three_d.kind == "3d"
    with pytest.raises(ValueError, match="kind must be one of"):
        read_profile(json.dumps({"kind": "boxes3d"}))
    with pytest.raises(ValueError, match="kind must be 'boxes2d'"):
        Profile2D.from_json(three_d.to_json())


@pytest.mark.parametrize(("change", "key"), [
    (lambda d: d.pop("regions"), "missing key 'regions'"),
    (lambda d: d.update(extra=1), "unknown key 'extra'"),
    (lambda d: d.update(schema_version=9), "schema_version 9"),
    (lambda d: d.update(categories=[{"id": 1, "name": "car"}]), "serves 2 classes"),
    (lambda d: d["matching"].update(iou_threshold=2), "matching.iou_threshold"),
    (lambda d: d["score_calibration"].update(method="magic"), "score_calibration.method"),
    (lambda d: d.update(image_size=[640]), "image_size"),
    (lambda d: d["regions"].pop("scale"), "and scale, for adaptive"),
    (lambda d: d["regions"].update(score="scaled"), "and scale, for adaptive"),
    (lambda d: d["regions"]["scale"].update(coef=[]), "scale.coef"),
    (lambda d: d["regions"]["conformal"]["hyper"].update(score="additive"),
     "conformal's score differ"),
])
def test_a_bad_profile_key_is_named(fitted, change, key):
    doc = json.loads(fitted[2].to_json())
    change(doc)
    with pytest.raises(ValueError, match=key):
        Profile2D.from_dict(doc)


def test_calibrated_records_keep_the_rows_and_read_back(fitted, tmp_path):
    found, _, profile = fitted
    served = calibrate_2d(profile, found, [0.9])
    served.write(tmp_path / "out.json")
    back = read_coco_results(tmp_path / "out.json")
    assert np.array_equal(back.bbox, found.bbox)
    assert np.array_equal(back.score, served.score)
    record = json.loads((tmp_path / "out.json").read_text())[0]
    assert record["score_raw"] == found.score[0]
    assert set(record["region_0.9"]) == {"inner", "outer", "guarantee", "calibration_n"}
    # a permutation of the input permutes the output, nothing else
    order = np.random.default_rng(0).permutation(len(found))
    again = calibrate_2d(profile, found.take(order), [0.9])
    assert np.array_equal(again.score, served.score[order])
    assert np.array_equal(again.regions.inner, served.regions.inner[order])


def test_the_fit_does_not_depend_on_the_order_of_the_records():
    found, instances = pair(300, seed=5)
    order = np.random.default_rng(1).permutation(len(found))
    a = fit_profile_2d(found, instances, score_method="isotonic")
    b = fit_profile_2d(found.take(order), instances, score_method="isotonic")
    assert a.provenance["n_calibration_images"] == b.provenance["n_calibration_images"]
    assert np.allclose(calibrate_2d(a, found).score, calibrate_2d(b, found).score)


def test_named_method_logits_and_no_calibration_part():
    found, instances = pair(300, seed=2, logits=True)
    with pytest.raises(OptionError, match="score_mode") as err:
        fit_profile_2d(found, instances)
    assert err.value.field == "score_mode"
    profile = fit_profile_2d(found, instances, score_mode="sigmoid", score_method="platt")
    assert profile.score_method == "platt" and profile.score_mode == "sigmoid"
    assert profile.report["selection"]["score"]["candidates"] == {}
    no_logits = Detections2D(found.image_id, found.category_id, found.bbox, found.score,
                             layer_boxes=found.layer_boxes)
    with pytest.raises(FieldError, match="logits") as err:
        calibrate_2d(profile, no_logits)
    assert err.value.field == "logits"
    bare = fit_profile_2d(no_logits, instances, calibration=0.0)
    assert bare.score_method == "temperature" and bare.regions is None
    assert calibrate_2d(bare, no_logits).regions is None
    with pytest.raises(FieldError, match="no box regions") as err:
        calibrate_2d(bare, no_logits, [0.9])
    assert err.value.field == "levels"


def test_serving_errors_name_the_field(fitted):
    found, _, profile = fitted
    unknown = Detections2D(found.image_id[:3], np.array([1, 7, 2]), found.bbox[:3],
                           found.score[:3], layer_boxes=found.layer_boxes[:3])
    with pytest.raises(FieldError, match="category_id") as err:
        calibrate_2d(profile, unknown)
    assert (err.value.field, err.value.row) == ("category_id", 1)
    flat = Detections2D(found.image_id, found.category_id, found.bbox, found.score)
    with pytest.raises(FieldError, match="layer_boxes") as err:
        calibrate_2d(profile, flat)
    assert err.value.field == "layer_boxes"
    with pytest.raises(FieldError) as err:
        calibrate_2d(profile, found, [1.5])
    assert err.value.field == "levels"
    sized = Profile2D.from_dict({**json.loads(profile.to_json()), "image_size": None})
    with pytest.raises(FieldError, match="width and height") as err:
        calibrate_2d(sized, found)
    assert err.value.field == "image_size"
    empty = calibrate_2d(profile, found.take(np.zeros(0, dtype=np.int64)), [0.9])
    assert len(empty) == 0 and empty.regions.inner.shape == (0, 1, 4)
    size = np.tile([640.0, 480.0], (len(found), 1))
    assert np.array_equal(calibrate_2d(sized, found, image_size=size).score,
                          calibrate_2d(profile, found).score)


def test_adaptive_regions_are_the_default_and_fall_back_on_few_fitting_boxes(fitted):
    found, instances, profile = fitted
    assert profile.region_score == "adaptive" and profile.error_scale is not None
    assert profile.error_scale.features_[-2:] == ["log_layer_sigma", "at_border"]
    assert profile.reads_image_size and profile.report["holdout"]["regions"] is not None
    # a narrower image: the border term reads the size the request gives, not the profile's
    narrow = np.tile([320.0, 480.0], (len(found), 1))
    wide = calibrate_2d(profile, found, [0.9]).regions.outer
    other = calibrate_2d(profile, found, [0.9], image_size=narrow).regions.outer
    assert not np.array_equal(wide, other)
    # too few fitting true positives: auto falls back, a named adaptive is refused
    small, small_inst = pair(60, seed=4)
    fallback = fit_profile_2d(small, small_inst, calibration=0.5)
    assert fallback.region_score == "scaled" and fallback.error_scale is None
    assert fallback.reads_image_size == fallback.score_stage.uses_position
    with pytest.raises(OptionError, match="fitting part's true positives") as err:
        fit_profile_2d(small, small_inst, calibration=0.5, region_score="adaptive")
    assert err.value.field == "region_score"


def test_fit_input_errors_name_the_field():
    found, instances = pair(100, seed=3)
    stray = Detections2D(found.image_id, np.where(np.arange(len(found)) == 4, 9,
                                                  found.category_id), found.bbox, found.score)
    with pytest.raises(FieldError) as err:
        fit_profile_2d(stray, instances)
    assert (err.value.field, err.value.row) == ("category_id", 4)
    flat = Detections2D(found.image_id, found.category_id, found.bbox, found.score)
    with pytest.raises(OptionError) as err:
        fit_profile_2d(flat, instances, region_score="scaled")
    assert err.value.field == "region_score"
    with pytest.raises(OptionError) as err:
        FitOptions2D(score_method="platt_range")
    assert err.value.field == "score_method"
    with pytest.raises(OptionError) as err:
        FitOptions2D.from_dict({"cov_source": "none"})
    assert err.value.field == "cov_source"
