"""Ellipses at requested levels: POST /v1/calibrate, /v1/calibrate/nuscenes and /v1/detect,
against real fitted profiles (conformal, and a version-1 thesis profile that must serve as
before plus `ellipses`); `detcal calibrate --levels`: tests/app/cli/test_calibrate_levels.py."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import TypeAdapter

from app.cli.main import main
from app.main import create_app
from app.schemas.calibrate import CalibrateResponse
from app.settings import Settings
from app.store import Store
from calibrators.fit import fit_profile
from calibrators.io import save_dump
from calibrators.profile import CalibrationProfile
from calibrators.regions import ellipse

CAL, NUS, DET = "/v1/calibrate", "/v1/calibrate/nuscenes", "/v1/detect"
JSON = {"content-type": "application/json"}
LEVEL_KEYS = {"semi_major", "semi_minor", "angle", "method", "group", "guarantee",
              "calibration_n"}
GROUP = re.compile(r"^(pooled classes|[a-z_]+) \d+(-\d+|\+) m$")
N = 40   # detections of the dump sent per request


@pytest.fixture
def client(seeded: Settings, conformal_json: str, thesis_json: str) -> Iterator[TestClient]:
    """The seeded store (`lidar`, `layers`) plus `conformal` and `thesis` (schema 1)."""
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("conformal", conformal_json)
    store.add_profile("thesis", thesis_json)
    store.close()
    with TestClient(create_app(seeded)) as c:
        yield c


def _frames(dump, detection, n: int = N) -> list[dict]:
    return [{"frame_id": "f0", "detections": [detection(dump, i) for i in range(n)]}]


def _reference(profile_json: str, dump, levels=None, n: int = N):
    prof = CalibrationProfile.from_json(profile_json)
    return prof.calibrate(logits=dump.det_logits[:n, -1], boxes=dump.det_boxes[:n, -1],
                          covariances=dump.det_cov[:n], levels=levels)


def _calibrate(client, dump, detection, **body) -> list[dict]:
    r = client.post(CAL, json={"frames": _frames(dump, detection), **body})
    assert r.status_code == 200, r.text
    TypeAdapter(CalibrateResponse).validate_json(r.content)
    return r.json()["frames"][0]["detections"]


def _nus_document(dump, n: int = 12) -> dict:
    boxes = []
    for i in range(n):
        logits = dump.det_logits[i, -1]
        b = dump.det_boxes[i, -1].tolist()
        boxes.append({
            "sample_token": "tok0", "translation": b[:3], "size": b[3:6],
            "rotation": [math.cos(b[6] / 2), 0.0, 0.0, math.sin(b[6] / 2)],
            "velocity": b[7:9], "detection_name": dump.classes[int(np.argmax(logits))],
            "detection_score": 0.5, "detection_logits": logits.tolist(),
            "covariance": dump.det_cov[i].tolist()})
    return {"meta": {"use_lidar": True}, "results": {"tok0": boxes}}


# -- the ellipses of a response ---------------------------------------------------------------
@pytest.mark.parametrize("profile", ["lidar", "conformal", "thesis"])
def test_default_levels_serve_one_ellipse_equal_to_ellipse(client, dump_given, detection,
                                                            profile):
    rows = _calibrate(client, dump_given, detection, profile=profile)
    for row in rows:
        assert list(row["ellipses"]) == ["0.95"]
        served = row["ellipses"]["0.95"]
        assert set(served) == LEVEL_KEYS
        assert {k: served[k] for k in ("semi_major", "semi_minor", "angle")} == {
            k: row["ellipse"][k] for k in ("semi_major", "semi_minor", "angle")}
        assert row["ellipse"]["confidence"] == 0.95


def test_levels_are_nested_and_match_the_library(client, dump_given, detection,
                                                 profile_json_given):
    levels = [0.5, 0.9, 0.95, 0.99]
    rows = _calibrate(client, dump_given, detection, levels=levels)
    ref = _reference(profile_json_given, dump_given, levels)
    keys = [str(float(q)) for q in levels]
    for j, row in enumerate(rows):
        assert list(row["ellipses"]) == keys == ["0.5", "0.9", "0.95", "0.99"]
        major = [row["ellipses"][k]["semi_major"] for k in keys]
        minor = [row["ellipses"][k]["semi_minor"] for k in keys]
        # nested: never shrinks with q (a small cell's tail floor may serve its largest score
        # at two levels)
        assert (np.diff(major) >= 0).all() and (np.diff(minor) >= 0).all()
        assert major[-1] > major[0] and minor[-1] > minor[0]
        assert len({row["ellipses"][k]["angle"] for k in keys}) == 1
        for q, k in zip(levels, keys, strict=True):
            assert row["ellipses"][k]["semi_major"] == pytest.approx(ref.regions[q].semi_major[j])
            assert row["ellipses"][k]["method"] == ref.region_method
            assert row["ellipses"][k]["group"] == ref.region_groups[j]


def test_a_conformal_profile_names_its_method_and_group(client, dump_given, detection,
                                                        conformal_json):
    rows = _calibrate(client, dump_given, detection, profile="conformal", levels=[0.5, 0.9])
    ref = _reference(conformal_json, dump_given, [0.5, 0.9])
    assert ref.region_method == "conformal"
    for j, row in enumerate(rows):
        for served in row["ellipses"].values():
            assert served["method"] == "conformal"
            assert GROUP.match(served["group"]), served["group"]
            assert served["group"] == ref.region_groups[j]
        assert row["ellipses"]["0.9"]["semi_major"] == pytest.approx(
            ref.regions[0.9].semi_major[j])


def test_each_served_ellipse_says_what_holds_for_it(client, dump_given, detection,
                                                     conformal_json):
    """`guarantee` and `calibration_n` of every ellipse are its conformal group's row of
    `ConformalRegions.guarantee_table` (the profile's record of what holds per cell)."""
    levels = [0.5, 0.9, 0.99]
    rows = _calibrate(client, dump_given, detection, profile="conformal", levels=levels)
    prof, ref = CalibrationProfile.from_json(conformal_json), _reference(conformal_json,
                                                                          dump_given, levels)
    conformal = prof.source_stages[prof.cov_source].conformal
    names, counts = conformal.guarantee_table(levels)
    index = conformal.group_index(ref.labels, ref.distances)
    for j, row in enumerate(rows):
        for k, q in enumerate(levels):
            served = row["ellipses"][str(q)]
            assert served["guarantee"] == names[index[j], k] == ref.region_guarantees[q][j]
            assert served["calibration_n"] == counts[index[j], k] > 0


def test_a_version_1_profile_serves_as_before_plus_gaussian_ellipses(client, dump_given,
                                                                     detection, thesis_json):
    before = {"id", "label", "label_index", "score", "score_raw", "class_scores", "box",
              "covariance", "ellipse", "distance"}
    rows = _calibrate(client, dump_given, detection, profile="thesis", levels=[0.5, 0.99])
    old = _reference(thesis_json, dump_given)        # what the service served before levels
    for j, row in enumerate(rows):
        assert set(row) == before | {"ellipses", "row"}   # row: its identity in the frame
        assert row["row"] == j
        assert row["score"] == old.scores[j] and row["score_raw"] == old.scores_raw[j]
        assert row["covariance"] == old.covariances[j].tolist()
        assert row["class_scores"] == old.class_scores[j].tolist()
        assert row["ellipse"] == {"semi_major": old.ellipses.semi_major[j],
                                  "semi_minor": old.ellipses.semi_minor[j],
                                  "angle": old.ellipses.angle[j], "confidence": 0.95}
        for q in (0.5, 0.99):
            served = row["ellipses"][str(q)]
            gauss = ellipse(old.covariances[j], q)     # χ²₂ radius on Σ' (cov_dims x, y)
            assert served["method"] == "gaussian" and served["group"] is None
            assert served["guarantee"] == "none" and served["calibration_n"] is None
            assert served["semi_major"] == pytest.approx(gauss.semi_major)
            assert served["semi_minor"] == pytest.approx(gauss.semi_minor)


@pytest.fixture(scope="module")
def height_json(dump_given) -> str:
    """A version-1 profile over cov_dims ["z"] (Σ = 0, depth k only): no x, y ellipse."""
    doc = json.loads(fit_profile(dump_given, cov_source="none", score_method="temperature",
                                 cov_method="depth", region_method="gaussian",
                                 other_sources=False).to_json())
    doc["cov_dims"] = ["z"]
    return json.dumps(doc)


def test_no_x_y_in_cov_dims_serves_null_ellipses(client, dump_given, detection, seeded,
                                                 height_json, tmp_path):
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("height", height_json)
    store.close()
    dets = [detection(dump_given, i, cov=False) for i in range(3)]
    r = client.post(CAL, json={"profile": "height", "levels": [0.5, 0.9],
                               "frames": [{"detections": dets}]})
    assert r.status_code == 200, r.text
    TypeAdapter(CalibrateResponse).validate_json(r.content)
    rows = r.json()["frames"][0]["detections"]
    assert all(row["ellipse"] is None and row["ellipses"] is None for row in rows)
    assert all(len(row["covariance"]) == 1 for row in rows)
    (tmp_path / "height.json").write_text(height_json)
    save_dump(tmp_path / "val.npz", dump_given)
    assert main(["calibrate", str(tmp_path / "val.npz"), "--profile",
                 str(tmp_path / "height.json"), "--levels", "0.5", "0.9",
                 "--out", str(tmp_path / "out.json")]) == 0
    doc = json.loads((tmp_path / "out.json").read_text())
    assert all(b["ellipses"] is None for frame in doc["results"].values() for b in frame)


# -- bad levels -------------------------------------------------------------------------------
@pytest.mark.parametrize(("levels", "loc"), [
    ("[0]", ["body", "levels", 0]),
    ("[0.5, 1]", ["body", "levels", 1]),
    ("[NaN]", ["body", "levels", 0]),
    ("[-0.1]", ["body", "levels", 0]),
    ("[1e999]", ["body", "levels", 0]),
    (json.dumps([round(0.04 * k, 2) for k in range(1, 22)]), ["body", "levels"]),
    ("[]", ["body", "levels"]),
    ('"0.95"', ["body", "levels"]),
    ('["abc"]', ["body", "levels", 0]),
    ("[0.9, 0.5, 0.9]", ["body", "levels", 2]),
])
def test_bad_levels_are_a_422_naming_levels(client, levels, loc):
    det = ('{"score": 0.5, "label": "car", "box": [10, 2, 1, 2, 4.5, 1.6, 0.1, 0, 0], '
           '"covariance": [[0.1, 0], [0, 0.1]]}')
    content = f'{{"levels": {levels}, "frames": [{{"detections": [{det}]}}]}}'.encode()
    r = client.post(CAL, content=content, headers=JSON)
    assert r.status_code == 422, r.text
    (item,) = r.json()["detail"]
    assert item["loc"] == loc, item


def test_bad_levels_are_a_422_without_detections(client):
    r = client.post(CAL, json={"levels": [0.5, 0.5], "frames": [{"detections": []}]})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "levels", 1]
    assert "repeats" in r.json()["detail"][0]["msg"]


def test_a_level_beyond_a_conformal_group_is_unbounded_with_null_axes(
        client, dump_given, detection):
    """Split-conformal regions at a level above n/(n + 1) of the group's n calibration
    points are the whole plane (MAPIE's infinite intervals): null semi-axes, never a 422 and
    never `Infinity`; the levels the group certifies are served as usual."""
    frames = _frames(dump_given, detection)
    r = client.post(CAL, json={"profile": "conformal", "levels": [0.5, 0.999],
                               "frames": frames})
    assert r.status_code == 200, r.text
    assert "Infinity" not in r.text
    dets = r.json()["frames"][0]["detections"]
    for det in dets:
        wide, usual = det["ellipses"]["0.999"], det["ellipses"]["0.5"]
        assert wide["semi_major"] is None and wide["semi_minor"] is None, wide
        assert wide["angle"] == usual["angle"] and wide["group"] == usual["group"]
        assert usual["semi_major"] >= usual["semi_minor"] > 0
    r = client.post(CAL, json={"profile": "conformal", "ellipse_confidence": 0.999,
                               "frames": frames})
    assert r.status_code == 200, r.text
    ellipse = r.json()["frames"][0]["detections"][0]["ellipse"]
    assert ellipse["semi_major"] is None and ellipse["confidence"] == 0.999
    r = client.post(f"{NUS}?profile=conformal&levels=0.999", json=_nus_document(dump_given))
    assert r.status_code == 200, r.text
    assert all(b["ellipses"]["0.999"]["semi_major"] is None
               for b in r.json()["results"]["tok0"])


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_an_overflowing_ellipse_is_a_422_never_infinity(client):
    huge = {"score": 0.5, "label": "car", "box": [1, 0, 0, 1, 1, 1, 0, 0, 0],
            "covariance": [[1.7e308, 0.0], [0.0, 1.7e308]]}
    far = {"score": 0.5, "label": "car", "box": [1e308, 0, 0, 1, 1, 1, 0, 0, 0],
           "covariance": [[1.0, 0.0], [0.0, 1.0]]}
    fine = {"score": 0.5, "label": "car", "box": [5, 0, 0, 1, 1, 1, 0, 0, 0],
            "covariance": [[1.0, 0.0], [0.0, 1.0]]}
    r = client.post(CAL, json={"levels": [0.5, 0.99],
                               "frames": [{"detections": [fine, huge]}]})
    assert r.status_code == 422, r.text
    assert "Infinity" not in r.text
    assert r.json()["detail"][0]["loc"] == ["body", "frames", 0, "detections", 1, "covariance"]
    assert "overflows" in r.json()["detail"][0]["msg"]
    r = client.post(CAL, json={"frames": [{"ego_translation": [-1e308, 0, 0],
                                           "detections": [fine, far]}]})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "frames", 0, "detections", 1, "box"]


# -- nuScenes results -------------------------------------------------------------------------
def test_nuscenes_boxes_gain_ellipses_per_level(client, dump_given, profile_json_given):
    r = client.post(f"{NUS}?levels=0.5&levels=0.9&levels=0.99", json=_nus_document(dump_given))
    assert r.status_code == 200, r.text
    boxes = r.json()["results"]["tok0"]
    ref = _reference(profile_json_given, dump_given, [0.5, 0.9, 0.99], n=len(boxes))
    for j, box in enumerate(boxes):
        assert list(box["ellipses"]) == ["0.5", "0.9", "0.99"]
        assert all(set(v) == LEVEL_KEYS for v in box["ellipses"].values())
        assert box["ellipses"]["0.99"]["semi_major"] == pytest.approx(
            ref.regions[0.99].semi_major[j])
        assert box["ellipses"]["0.5"]["group"] == ref.region_groups[j]
        assert {"detection_score", "detection_score_raw", "covariance", "ellipse"} <= set(box)
    r = client.post(NUS, json=_nus_document(dump_given))        # default: 0.95
    assert r.status_code == 200, r.text
    assert all(list(b["ellipses"]) == ["0.95"] for b in r.json()["results"]["tok0"])


@pytest.mark.parametrize(("query", "loc"), [
    ("levels=0", ["query", "levels", 0]),
    ("levels=0.5&levels=nan", ["query", "levels", 1]),
    ("levels=abc", ["query", "levels", 0]),
    ("levels=0.5&levels=0.5", ["query", "levels", 1]),
])
def test_nuscenes_bad_levels_are_a_422_at_the_query(client, dump_given, query, loc):
    r = client.post(f"{NUS}?{query}", json=_nus_document(dump_given))
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == loc


# -- /v1/detect -------------------------------------------------------------------------------
def test_detect_serves_ellipses_at_levels(client):
    pytest.importorskip("detectors")
    import torch

    from detectors import build_detector
    from detectors.registry import weights_path

    torch.set_num_threads(1)
    if not weights_path("lidar").exists():
        client.app.state.detectors._models["lidar"] = build_detector(
            "lidar", pretrained=False).eval()
    r = client.post(DET, json={"seed": 7, "min_score": 0.0, "profile": "layers",
                               "levels": [0.5, 0.99]})
    assert r.status_code == 200, r.text
    dets = r.json()["frames"][0]["detections"]
    assert dets and all(list(d["ellipses"]) == ["0.5", "0.99"] for d in dets)
    assert all(d["ellipses"]["0.5"]["semi_major"] < d["ellipses"]["0.99"]["semi_major"]
               for d in dets)
    r = client.post(DET, json={"seed": 7, "levels": [1.5]})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "levels", 0]
