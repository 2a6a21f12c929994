"""POST /v1/calibrate with a 2-D profile (`images`), and a 2-D profile in the store: served
as the library serves it, the other kind of body refused at the field that does not fit, bad
detections refused at their field, the 3-D routes and the dashboard unharmed. The 2-D profile
`cam2d` (`client_2d`, `profile_2d`, `coco_pair`) comes from tests/app/calibrate/conftest.py."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.store import Store
from calibrators.boxes2d import (
    Detections2D,
    Profile2D,
    calibrate_2d,
    fit_profile_2d,
    parse_instances,
    synthetic_coco,
)
from tests.app.calibrate.conftest import serving


def _images(results: list[dict], n_images: int = 3) -> list[dict]:
    images: dict[int, list[dict]] = {}
    for r in results:
        if r["image_id"] <= n_images:
            images.setdefault(r["image_id"], []).append(
                {"id": f"d{len(images.get(r['image_id'], []))}", **{
                    k: r[k] for k in ("category_id", "bbox", "score", "layer_boxes")}})
    return [{"image_id": i, "width": 640, "height": 480, "detections": d}
            for i, d in images.items()]


def test_images_are_served_as_the_library_serves_them(client_2d, coco_pair, profile_2d):
    images = _images(coco_pair[0])
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "levels": [0.5, 0.9],
                                              "images": images})
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["kind"] == "boxes2d" and doc["profile"]["id"] == "cam2d@1"
    assert doc["levels"] == [0.5, 0.9]
    assert doc["categories"] == [{"id": 1, "name": "car"}, {"id": 2, "name": "person"}]
    flat = [d for image in images for d in image["detections"]]
    found = Detections2D.from_coco([{"image_id": image["image_id"], **{
        k: v for k, v in d.items() if k != "id"}} for image in images
        for d in image["detections"]])
    expected = calibrate_2d(profile_2d, found, [0.5, 0.9]).records()
    served = [d for image in doc["images"] for d in image["detections"]]
    assert len(served) == len(flat) == len(expected)
    for got, want, sent in zip(served, expected, flat, strict=True):
        assert got["id"] == sent["id"] and got["row"] == int(sent["id"][1:])
        assert got == {"row": got["row"], "id": sent["id"], **want}   # bit for bit
        assert got["score_raw"] == sent["score"]
    assert [i["image_id"] for i in doc["images"]] == [i["image_id"] for i in images]


def test_levels_from_the_query_and_the_default(client_2d, coco_pair):
    body = {"profile": "cam2d", "images": _images(coco_pair[0], 1)}
    plain = client_2d.post("/v1/calibrate", json=body).json()
    assert plain["levels"] == [0.95]
    det = plain["images"][0]["detections"][0]
    assert "region_0.95" in det and det["region_0.95"]["guarantee"] in ("cell", "pooled",
                                                                        "marginal")
    queried = client_2d.post("/v1/calibrate?levels=0.8", json=body).json()
    assert queried["levels"] == [0.8]
    r = client_2d.post("/v1/calibrate?levels=1.5", json=body)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:2] == ["query", "levels"]


def _loc(r) -> list:
    assert r.status_code == 422, r.text
    return r.json()["detail"][0]["loc"]


def test_a_body_of_the_other_kind_is_refused_at_its_field(client_2d, coco_pair, detection,
                                                          dump_given):
    frames = [{"frame_id": "f0", "detections": [detection(dump_given, 0)]}]
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "frames": frames})
    assert _loc(r) == ["body", "frames"] and "2-D (boxes2d) profile" in r.text
    images = _images(coco_pair[0], 1)
    r = client_2d.post("/v1/calibrate", json={"profile": "lidar", "images": images})
    assert _loc(r) == ["body", "images"] and "3-D profile" in r.text
    r = client_2d.post("/v1/calibrate", json={"images": images})   # the default: lidar
    assert _loc(r) == ["body", "images"]
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "images": images,
                                              "frames": frames})
    assert _loc(r) == ["body"] and "exactly one of" in r.text
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "images": images,
                                              "ellipse_confidence": 0.9})
    assert _loc(r) == ["body", "ellipse_confidence"]
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "images": images,
                                              "classes": ["car", "person"]})
    assert _loc(r) == ["body", "classes"]
    # the 3-D routes name the profile (Arrow bodies: tests/app/calibrate/test_arrow_2d.py)
    r = client_2d.post("/v1/calibrate/nuscenes?profile=cam2d", json={"results": {}})
    assert _loc(r) == ["query", "profile"]
    r = client_2d.get("/v1/profiles/cam2d/health")
    assert r.status_code == 422 and "2-D" in r.text


@pytest.mark.parametrize(("change", "field"), [
    (lambda d: d.update(bbox=[10.0, 10.0, -4.0, 20.0]), "bbox"),
    (lambda d: d.update(category_id=77), "category_id"),
    (lambda d: d.pop("layer_boxes"), "layer_boxes"),
    (lambda d: d.update(layer_boxes=[[10.0, 10.0, 5.0, 5.0]]), "layer_boxes"),
    (lambda d: d.update(bbox=[10.0, 10.0, 5.0]), "bbox"),
    (lambda d: d.update(score=1.5), "score"),
    (lambda d: d.update(category_id=1.0), "category_id"),
])
def test_a_bad_detection_is_refused_at_its_field(client_2d, coco_pair, change, field):
    images = _images(coco_pair[0], 2)
    target = images[1]["detections"][1]
    change(target)
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "images": images})
    assert _loc(r) == ["body", "images", 1, "detections", 1, field], r.text


def test_missing_layer_boxes_are_refused_at_the_first_detection(client_2d, coco_pair):
    images = _images(coco_pair[0], 2)
    for image in images:
        for d in image["detections"]:
            d.pop("layer_boxes")
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d", "images": images})
    assert _loc(r) == ["body", "images", 0, "detections", 0, "layer_boxes"]
    assert "read the spread" in r.text and "cam2d@1" in r.text


def test_a_position_profile_needs_an_image_size(client_2d, coco_pair, profile_2d, seeded):
    assert profile_2d.score_method == "position"
    unsized = Profile2D.from_dict({**json.loads(profile_2d.to_json()), "image_size": None})
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("cam2d", unsized.to_json())
    store.close()
    images = _images(coco_pair[0], 2)
    for image in images:
        image.pop("width")
        image.pop("height")
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d@2", "images": images})
    assert _loc(r) == ["body", "images", 0, "width"]
    images[1]["width"] = 640
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d@2", "images": images})
    assert _loc(r) == ["body", "images", 0, "width"]
    images[0].update(width=640, height=480)
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d@2", "images": images})
    assert _loc(r) == ["body", "images", 1, "height"]
    images[1]["height"] = 480
    r = client_2d.post("/v1/calibrate", json={"profile": "cam2d@2", "images": images})
    assert r.status_code == 200, r.text


def test_the_store_lists_both_kinds_and_3d_requests_still_serve(client_2d, detection,
                                                                dump_given):
    names = {p["name"] for p in client_2d.get("/v1/profiles").json()}
    assert {"lidar", "layers", "cam2d"} <= names
    detail = client_2d.get("/v1/profiles/cam2d/1").json()
    assert detail["profile"]["kind"] == "boxes2d" and detail["profile"]["report"]["holdout"]
    frames = [{"frame_id": "f0", "detections": [detection(dump_given, i) for i in range(3)]}]
    r = client_2d.post("/v1/calibrate", json={"frames": frames})
    assert r.status_code == 200 and len(r.json()["frames"][0]["detections"]) == 3


@pytest.fixture
def default_2d(settings: Settings, profile_2d: Profile2D) -> Iterator[TestClient]:
    """A store whose default profile name (`lidar`) holds a 2-D profile."""
    yield from serving(settings, "lidar", profile_2d)


def test_a_2d_default_profile_starts_the_service_and_the_dashboard(default_2d, coco_pair):
    r = default_2d.get("/")
    assert r.status_code == 200
    assert "2-D boxes" in r.text and "Box regions: coverage" in r.text and "lidar@1" in r.text
    ready = default_2d.get("/readyz")
    assert ready.status_code == 200 and ready.json()["checks"]["profile"] == "lidar@1"
    r = default_2d.post("/v1/calibrate", json={"images": _images(coco_pair[0], 1)})
    assert r.status_code == 200 and r.json()["profile"]["id"] == "lidar@1"
    r = default_2d.post("/v1/detect", json={"sensor": "lidar", "seed": 1})
    assert r.status_code == 422 and "2-D" in r.text


def test_a_logits_profile_reads_logits_and_names_their_errors(seeded):
    results, instances = synthetic_coco(300, seed=1, logits=True)
    profile = fit_profile_2d(Detections2D.from_coco(results), parse_instances(instances),
                             score_mode="sigmoid")
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("logits2d", profile.to_json())
    store.close()
    det = {k: results[0][k] for k in ("category_id", "bbox", "score", "layer_boxes", "logits")}

    def post(c: TestClient, *dets: dict):
        return c.post("/v1/calibrate", json={"profile": "logits2d", "images": [
            {"image_id": 1, "detections": list(dets)}, {"image_id": 2, "detections": []}]})

    with TestClient(create_app(seeded)) as c:
        ok = post(c, det).json()
        assert ok["images"][0]["detections"][0]["logits"] == det["logits"]
        assert ok["images"][1] == {"image_id": 2, "detections": []}
        assert post(c).json()["images"][0]["detections"] == []
        plain = {k: v for k, v in det.items() if k != "logits"}
        assert _loc(post(c, plain)) == ["body", "images", 0, "detections", 0, "logits"]
        assert _loc(post(c, det, plain)) == ["body", "images", 0, "detections", 1, "logits"]
        r = post(c, {**det, "logits": [0.5]})
        assert _loc(r) == ["body", "images", 0, "detections", 0, "logits"]
        assert "needs 2" in r.text
        r = post(c, det, {**det, "layer_boxes": det["layer_boxes"][:2]})
        assert _loc(r) == ["body", "images", 0, "detections", 1, "layer_boxes"]
