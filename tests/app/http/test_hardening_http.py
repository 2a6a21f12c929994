"""Issue 11, HTTP hardening: bounded metric labels, one version parser, the admin check before
the body, safe profile names, no empty form fields, strict numbers in, finite JSON in."""

from __future__ import annotations

import json
import random

import pytest
from prometheus_client.parser import text_string_to_metric_families
from pydantic import TypeAdapter

from app.http.deps import AdminBeforeBodyMiddleware
from app.http.metrics import METHODS
from app.routers import calibrate, dashboard, detect, fit, jobs, liveness, metrics, profiles
from app.schemas.calibrate import CalibrateRequest, DetectRequest
from app.schemas.nuscenes import NuScenesResults
from tests.app.conftest import ADMIN

JSON = {"Content-Type": "application/json"}
HUGE = "9223372036854775808"          # 2^63: beyond every integer column
ROUTERS = (liveness, metrics, calibrate, fit, jobs, profiles, detect, dashboard)


def _locs(r) -> list[list]:
    assert r.status_code == 422, r.text
    return [item["loc"] for item in r.json()["detail"]]


def _box(**extra) -> dict:
    return {"sample_token": "t", "translation": [12.0, -3.0, 0.9], "size": [1.9, 4.6, 1.7],
            "rotation": [1.0, 0.0, 0.0, 0.0], "detection_name": "car",
            "detection_score": 0.9, "covariance": [[0.04, 0.0], [0.0, 0.04]], **extra}


# -- 1. metric labels ---------------------------------------------------------------------


def test_random_methods_and_paths_leave_the_metric_label_sets_bounded(client):
    rng = random.Random(11)
    known = sorted(METHODS - {"HEAD"})
    for i in range(500):
        method = rng.choice([f"M{i}", f"X-{rng.randrange(10**9)}", rng.choice(known)])
        path = rng.choice(["/healthz", "/v1/profiles", f"/no/such/{i}", f"/v1/{i}x",
                           f"/v1/profiles/lidar/{i}/activate"])
        client.request(method, path)
    text = client.get("/metrics").text
    routes = {r.path for r in _api_routes()} | {"unmatched"}
    label_sets = set()
    for family in text_string_to_metric_families(text):
        if family.name in ("detcal_http_requests", "detcal_http_request_duration_seconds"):
            for sample in family.samples:
                assert sample.labels["method"] in METHODS | {"other"}, sample.labels
                assert sample.labels["route"] in routes, sample.labels
                label_sets.add((family.name, sample.labels["method"], sample.labels["route"],
                                sample.labels.get("status")))
    # every method x these 5 routes x a handful of statuses; 500 made-up ones would be > 500
    assert 5 < len(label_sets) < 120, sorted(label_sets)


# -- 2. one version parser ----------------------------------------------------------------


@pytest.mark.parametrize("version", [HUGE, "2147483648", "0", "-1", "1.5", "abc", "1e3"])
def test_a_bad_version_in_a_path_is_a_422_naming_it(client, version):
    assert _locs(client.get(f"/v1/profiles/lidar/{version}")) == [["path", "version"]]
    r = client.post(f"/v1/profiles/lidar/{version}/activate", headers=ADMIN)
    assert _locs(r) == [["path", "version"]]


@pytest.mark.parametrize("ref", [f"lidar@{HUGE}", "lidar@0", "lidar@-1", "lidar@x!", "lidar@",
                                 "lidar@1@2", "..", ".", "-lidar", ""])
def test_a_bad_profile_reference_is_a_422_naming_profile_everywhere(client, detection,
                                                                    dump_given, ref):
    body = {"profile": ref, "frames": [{"detections": [detection(dump_given, 0)]}]}
    assert _locs(client.post("/v1/calibrate", json=body)) == [["body", "profile"]]
    r = client.post("/v1/calibrate/nuscenes", params={"profile": ref},
                    json={"results": {"t": [_box()]}})
    assert _locs(r) == [["query", "profile"]]
    r = client.post("/v1/detect", json={"sensor": "lidar", "seed": 1, "profile": ref})
    assert _locs(r) == [["body", "profile"]]


def test_the_largest_storable_version_is_a_plain_404(client, detection, dump_given):
    assert client.get("/v1/profiles/lidar/2147483647").status_code == 404
    body = {"profile": "lidar@2147483647",
            "frames": [{"detections": [detection(dump_given, 0)]}]}
    r = client.post("/v1/calibrate", json=body)
    assert r.status_code == 404 and "no version 2147483647" in r.text
    assert client.post("/v1/calibrate", json={**body, "profile": "lidar@1"}).status_code == 200


# -- 3. the admin check runs before the body is read (the real-server test is in e2e) ----


def _api_routes() -> list:
    return [r for module in ROUTERS for r in module.router.routes]


def test_exactly_the_admin_routes_are_checked_before_their_body(client):
    admin = {(r.path, *sorted(r.methods)) for r in _api_routes()
             if AdminBeforeBodyMiddleware.needs_admin(r)}
    assert admin == {("/v1/fit", "POST"), ("/v1/profiles/{name}/{version}/activate", "POST")}


@pytest.mark.parametrize(("headers", "status"), [({}, 401),
                                                 ({"Authorization": "Bearer nope"}, 403),
                                                 ({"Authorization": "Basic dXNlcjpwYXNz"}, 401)])
def test_an_unauthenticated_upload_is_refused_and_stores_nothing(client, npz_bytes, headers,
                                                                 status):
    r = client.post("/v1/fit", headers=headers, files={"dump": ("val.npz", npz_bytes)})
    assert r.status_code == status, r.text
    assert "token" in r.json()["detail"]
    dumps = client.app.state.settings.dumps_dir
    # the store's own lock files (dot-names) may exist; no uploaded dump may
    assert not dumps.exists() or not [p for p in dumps.iterdir() if not p.name.startswith(".")]
    assert f'route="/v1/fit",status="{status}"' in client.get("/metrics").text


# -- 4. profile names, empty form fields --------------------------------------------------


@pytest.mark.parametrize("name", [".", "..", "...", ".hidden", "-rf", "a/b", "a b", "x" * 65])
def test_a_path_like_profile_name_is_refused_naming_name(client, npz_bytes, name):
    r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz_bytes)},
                    data={"name": name})
    assert _locs(r) == [["body", "name"]]


def test_an_empty_form_field_is_refused_not_defaulted(client, npz_bytes):
    for field in ("name", "holdout"):
        r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("val.npz", npz_bytes)},
                        data={field: ""})
        assert _locs(r) == [["body", field]]
        assert "empty" in r.json()["detail"][0]["msg"]
    assert client.get("/v1/jobs", headers=ADMIN).json() == []


def test_a_path_like_name_in_a_path_is_refused(client):
    assert _locs(client.get("/v1/profiles/.lidar")) == [["path", "name"]]
    assert _locs(client.post("/v1/profiles/.lidar/1/activate", headers=ADMIN)) == [
        ["path", "name"]]


# -- 5. strict numbers in -----------------------------------------------------------------


@pytest.mark.parametrize(("change", "loc"), [
    ({"ego_translation": [False, 0, 0]}, ["frames", 0, "ego_translation", 0]),
    ({"ego_translation": ["1", 0, 0]}, ["frames", 0, "ego_translation", 0]),
    ({"det": {"logits": ["1.5", -3.0]}}, ["frames", 0, "detections", 0, "logits", 0]),
    ({"det": {"box": [True, 0, 0, 1, 1, 1, 0]}}, ["frames", 0, "detections", 0, "box", 0]),
    ({"det": {"covariance": [["0.04", 0], [0, 0.04]]}},
     ["frames", 0, "detections", 0, "covariance", 0, 0]),
    ({"det": {"logits": None, "score": "0.9", "label": "car"}},
     ["frames", 0, "detections", 0, "score"]),
    ({"det": {"logits": None, "score": 0.9, "label": 1.0}},
     ["frames", 0, "detections", 0, "label"]),
    ({"det": {"logits": None, "score": 0.9, "label": True}},
     ["frames", 0, "detections", 0, "label"]),
    ({"ellipse_confidence": "0.9"}, ["ellipse_confidence"]),
    ({"levels": [True]}, ["levels", 0]),
])
def test_numbers_as_strings_or_booleans_are_refused_naming_the_field(client, detection,
                                                                     dump_given, change, loc):
    det = {**detection(dump_given, 0), **change.pop("det", {})}
    det = {k: v for k, v in det.items() if v is not None}
    frame = {"frame_id": "f0", "detections": [det]}
    if "ego_translation" in change:
        frame["ego_translation"] = change.pop("ego_translation")
    r = client.post("/v1/calibrate", json={"profile": "lidar", "frames": [frame], **change})
    assert all(got[1:1 + len(loc)] == loc for got in _locs(r)), r.text
    assert _locs(r)[0][0] == "body"


def test_detect_and_nuscenes_are_strict_too(client):
    assert _locs(client.post("/v1/detect", json={"seed": True})) == [["body", "seed"]]
    assert _locs(client.post("/v1/detect", json={"seed": 1.0})) == [["body", "seed"]]
    r = client.post("/v1/calibrate/nuscenes",
                    json={"results": {"t": [_box(translation=["12", 0, 0])]}})
    assert _locs(r) == [["body", "results", "t", 0, "translation", 0]]
    r = client.post("/v1/calibrate/nuscenes",
                    json={"results": {"t": [_box(detection_score=True)]}})
    assert _locs(r) == [["body", "results", "t", 0, "detection_score"]]


def test_the_openapi_examples_validate_strictly(client):
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    for model in (CalibrateRequest, DetectRequest, NuScenesResults):
        examples = schemas[model.__name__]["examples"]
        assert examples
        for example in examples:
            model.model_validate_json(json.dumps(example), strict=True)
    for example in schemas["DetectionIn"]["examples"]:
        TypeAdapter(CalibrateRequest).validate_json(json.dumps(
            {"frames": [{"detections": [example]}]}), strict=True)


# -- 6. finite JSON in, strict JSON out ---------------------------------------------------


def _strict_json(text: str):
    def refuse(constant: str):
        raise AssertionError(f"response holds {constant}")
    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize(("doc", "loc", "shown"), [
    ('{"meta": {"use_lidar": true, "x": NaN}, "results": {}}', ["meta", "x"], "NaN"),
    ('{"meta": {"a": {"b": [1, -Infinity]}}, "results": {}}', ["meta", "a"],
     "at ['b'][1]: -Infinity"),
    ('{"meta": {"big": 1e400}, "results": {}}', ["meta", "big"], "Infinity"),
    ('{"results": {}, "extra": [Infinity]}', ["extra"], "at [0]: Infinity"),
    ('{"results": {"t": [BOX]}}', ["results", "t", 0, "note"], "at ['z']: NaN"),
])
def test_non_finite_numbers_anywhere_in_a_results_document_are_a_422(client, doc, loc, shown):
    box = json.dumps(_box())[:-1] + ', "note": {"z": NaN}}'
    r = client.post("/v1/calibrate/nuscenes", content=doc.replace("BOX", box), headers=JSON)
    assert _locs(r) == [["body", *loc]]
    assert shown in r.json()["detail"][0]["msg"]


def test_meta_and_unknown_keys_are_echoed_as_strict_json(client):
    doc = {"meta": {"use_lidar": True, "eps": 1e-300, "big": 1.7e308, "n": 10**30,
                    "s": "NaN"},
           "results": {"t": [_box(note={"z": [1.5]})]}, "extra": {"k": -0.0}}
    r = client.post("/v1/calibrate/nuscenes", json=doc)
    assert r.status_code == 200, r.text
    body = _strict_json(r.text)
    assert body["meta"] == doc["meta"] and body["extra"] == doc["extra"]
    assert body["results"]["t"][0]["note"] == {"z": [1.5]}


def test_too_many_detections_is_a_413_naming_the_limit(seeded, detection, dump_given):
    from fastapi.testclient import TestClient

    from app.main import create_app

    limited = seeded.model_copy(update={"max_detections": 3})
    with TestClient(create_app(limited)) as client:
        frames = [{"frame_id": "f", "detections": [detection(dump_given, i) for i in range(4)]}]
        r = client.post("/v1/calibrate", json={"frames": frames})
        assert r.status_code == 413, r.text
        detail = r.json()["detail"][0]
        assert detail["loc"] == ["body", "frames"] and "at most 3" in detail["msg"]
        three = [detection(dump_given, i) for i in range(3)]
        ok = client.post("/v1/calibrate",
                         json={"frames": [{"frame_id": "f", "detections": three}]})
        assert ok.status_code == 200, ok.text


def test_a_405_allows_every_method_of_the_path(client):
    r = client.options("/v1/profiles/lidar/aliases/x")
    assert r.status_code == 405 and r.headers["allow"] == "DELETE, PUT"
    r = client.get("/v1/calibrate")
    assert r.status_code == 405 and r.headers["allow"] == "POST"


def test_one_decoder_layer_of_boxes_is_a_422_not_a_500(client):
    """Found by schemathesis: `layer_boxes` with L = 1 cannot give a spread across layers."""
    det = {"score": 0.0, "label": 1, "layer_boxes": [[0.0] * 9]}
    for profile in ("lidar", "layers"):
        r = client.post("/v1/calibrate", json={"profile": profile, "frames": [
            {"frame_id": "f", "detections": [det]}]})
        assert r.status_code == 422, r.text
        loc = r.json()["detail"][0]["loc"]   # the field the profile's source needs
        assert loc[:5] == ["body", "frames", 0, "detections", 0], loc
        assert loc[5] in ("layer_boxes", "covariance"), loc
