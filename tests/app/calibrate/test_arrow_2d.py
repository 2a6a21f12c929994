"""POST /v1/calibrate with a 2-D Arrow batch (`calibrators.io.arrow_boxes2d`) to a 2-D profile:
the same answer as the JSON `images` request, in Arrow or (Accept: JSON) as its document; each
answer row keeps its identity under any order; a bad column is a 422 naming it (and the row);
a batch of the other kind is a 422 saying what the profile wants."""

from __future__ import annotations

import json
from collections.abc import Callable

import numpy as np
import pyarrow as pa
import pytest

from app.store import Store
from calibrators.boxes2d import Profile2D
from calibrators.io.arrow_batch import ARROW_STREAM, write_stream
from tests.arrow_mutator import request_batch, request_batch_2d

CAL = "/v1/calibrate"
ARROW = {"content-type": ARROW_STREAM}
LEVELS = "levels=0.5&levels=0.9"


@pytest.fixture(scope="module")
def records(coco_pair) -> list[dict]:
    """The detections of the first six images, in image order."""
    return [r for r in coco_pair[0] if r["image_id"] <= 6]


def _post(client, batch: pa.RecordBatch, query: str = "?profile=cam2d", **headers):
    return client.post(CAL + query, content=write_stream(batch), headers={**ARROW, **headers})


def _read(response) -> pa.Table:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == ARROW_STREAM
    return pa.ipc.open_stream(response.content).read_all()


def _loc(response) -> list:
    assert response.status_code == 422, response.text
    return response.json()["detail"][0]["loc"]


def _images(batch: pa.RecordBatch) -> list[dict]:
    """The rows of a 2-D request `batch` as the `images` of a JSON request (the same values)."""
    keys = [k for k in ("id", "category_id", "bbox", "score", "logits", "layer_boxes")
            if k in batch.schema.names]
    images: dict[int, dict] = {}
    for row in batch.to_pylist():
        image = images.setdefault(row["image_id"], {"image_id": row["image_id"],
                                                    "detections": []})
        if "width" in row:
            image.update(width=int(row["width"]), height=int(row["height"]))
        image["detections"].append({k: row[k] for k in keys})
    return list(images.values())


def _same(got: dict, want: dict) -> None:
    """Two answer rows agree: scores to 1e-12, every other value exactly."""
    assert got.keys() == want.keys()
    for key in got:
        if key in ("score", "score_raw"):
            assert abs(got[key] - want[key]) <= 1e-12, key
        else:
            assert got[key] == want[key], key


@pytest.mark.parametrize("variant", [0, 1, 2])
def test_arrow_and_json_requests_get_the_same_answer(client_2d, records, variant):
    batch = request_batch_2d(records, variant=variant)
    table = _read(_post(client_2d, batch, f"?profile=cam2d&{LEVELS}"))
    r = client_2d.post(CAL, json={"profile": "cam2d", "levels": [0.5, 0.9],
                                  "images": _images(batch)})
    assert r.status_code == 200, r.text
    doc = r.json()
    want = {d["id"]: d for image in doc["images"] for d in image["detections"]}
    rows = table.to_pylist()
    assert [g["row"] for g in rows] == list(range(len(records)))
    assert [g["id"] for g in rows] == [f"d{i}" for i in range(len(records))]
    for got in rows:
        w = want[got["id"]]
        _same({k: got[k] for k in got if k not in ("row", "id")},
              {k: w[k] for k in got if k not in ("row", "id")})
        assert got["region_0.9"]["outer"] is not None
    assert [c for c in table.column_names if c.startswith("region_")] == ["region_0.5",
                                                                         "region_0.9"]
    meta = json.loads(table.schema.metadata[b"detcal"])
    assert meta == {"profile": doc["profile"], "kind": "boxes2d",
                    "categories": doc["categories"], "levels": [0.5, 0.9]}
    # Accept: JSON -> the JSON request's document, `row` being the batch row
    r = _post(client_2d, batch, f"?profile=cam2d&{LEVELS}", accept="application/json")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json", r.text
    answer = r.json()
    for image in answer["images"]:
        for d in image["detections"]:
            assert d["row"] == int(d["id"][1:])
            d["row"] = want[d["id"]]["row"]
    assert answer == doc


def test_rows_keep_their_identity_in_any_order(client_2d, records):
    batch = request_batch_2d(records)
    base = _read(_post(client_2d, batch)).to_pylist()
    perm = np.random.default_rng(3).permutation(len(records))
    shuffled = batch.take(pa.array(perm))
    rows = _read(_post(client_2d, shuffled)).to_pylist()
    for k, got in enumerate(rows):
        assert got["row"] == k and got["id"] == f"d{perm[k]}"
        _same({**got, "row": int(perm[k])}, base[perm[k]])
    doc = _post(client_2d, shuffled, accept="application/json").json()
    first_seen = list(dict.fromkeys(records[i]["image_id"] for i in perm))
    assert [image["image_id"] for image in doc["images"]] == first_seen
    for image in doc["images"]:
        for d in image["detections"]:
            assert d["id"] == f"d{perm[d['row']]}" and d["image_id"] == image["image_id"]


def test_an_empty_batch_is_a_422_at_the_body(client_2d, records):
    empty = request_batch_2d(records).slice(0, 0)
    r = _post(client_2d, empty)
    assert _loc(r) == ["body"] and "no rows" in r.text


Change = Callable[[dict, int], None]


def _set(name: str, values) -> Change:
    def change(cols: dict, n: int) -> None:
        cols[name] = values(n) if callable(values) else values
    return change


def _drop(name: str) -> Change:
    return lambda cols, n: cols.pop(name)


def _bbox_at(row: int, value: list[float]) -> Change:
    def change(cols: dict, n: int) -> None:
        boxes = np.asarray(cols["bbox"].to_pylist(), dtype=np.float64)
        boxes[row] = value
        cols["bbox"] = pa.FixedSizeListArray.from_arrays(pa.array(boxes.ravel()), 4)
    return change


def _value_at(name: str, row: int, value, kind: pa.DataType) -> Change:
    def change(cols: dict, n: int) -> None:
        values = cols[name].to_pylist()
        values[row] = value
        cols[name] = pa.array(values, kind)
    return change


@pytest.mark.parametrize(("change", "loc"), [
    (_drop("image_id"), ["body", "image_id"]),
    (_drop("bbox"), ["body", "bbox"]),
    (_drop("score"), ["body", "score"]),
    (_drop("category_id"), ["body", "category_id"]),
    (_drop("layer_boxes"), ["body", "layer_boxes"]),               # the regions read them
    (_drop("height"), ["body", "height"]),
    (_set("bbox", lambda n: pa.array([["a"] * 4] * n)), ["body", "bbox"]),
    (_set("bbox", lambda n: pa.array([[1.0, 2.0, 3.0]] * n)), ["body", "bbox"]),
    (_set("score", lambda n: pa.array(["0.5"] * n)), ["body", "score"]),
    (_set("category_id", lambda n: pa.array([1.0] * n)), ["body", "category_id"]),
    (_set("image_id", lambda n: pa.array(["a"] * n)), ["body", "image_id"]),
    (_set("layer_boxes", lambda n: pa.array([[[1.0, 2.0, 3.0]]] * n)), ["body", "layer_boxes"]),
    (_set("box", lambda n: pa.array([1.0] * n)), ["body", "box"]),
    (_bbox_at(3, [np.nan, 10.0, 20.0, 20.0]), ["body", "bbox", 3]),
    (_bbox_at(2, [10.0, 10.0, -4.0, 20.0]), ["body", "bbox", 2]),
    (_value_at("score", 1, 1.5, pa.float64()), ["body", "score", 1]),
    (_value_at("score", 4, None, pa.float64()), ["body", "score", 4]),
    (_value_at("category_id", 4, 77, pa.int64()), ["body", "category_id", 4]),
    (_value_at("width", 5, 0, pa.int32()), ["body", "width", 5]),
    (_set("height", lambda n: pa.array([1e-310] * n)), ["body", "height", 0]),
    (_set("height", lambda n: pa.array([480.5] * n)), ["body", "height", 0]),
    (_value_at("image_id", 2, 2**63, pa.uint64()), ["body", "image_id", 2]),
])
def test_a_bad_column_is_a_422_naming_it(client_2d, records, change, loc):
    batch = request_batch_2d(records)
    cols = {name: batch.column(name) for name in batch.schema.names}
    change(cols, batch.num_rows)
    r = _post(client_2d, pa.RecordBatch.from_pydict(cols))
    assert _loc(r) == loc, r.json()


def test_a_batch_of_the_other_kind_is_refused_at_its_column(client_2d, records, dump_given):
    r = _post(client_2d, request_batch(dump_given, 4))
    assert _loc(r) == ["body", "frame_id"]
    msg = r.json()["detail"][0]["msg"]
    assert "cam2d@1 is a 2-D (boxes2d) profile" in msg and "`image_id`" in msg
    for profile in ("lidar", "layers"):
        r = _post(client_2d, request_batch_2d(records), f"?profile={profile}")
        assert _loc(r) == ["body", "image_id"]
        msg = r.json()["detail"][0]["msg"]
        assert f"{profile}@1 is a 3-D profile" in msg and "`frame_id`" in msg
    r = _post(client_2d, request_batch_2d(records), "")   # the default profile: lidar
    assert _loc(r) == ["body", "image_id"]


def test_options_and_negotiation(client_2d, records):
    batch = request_batch_2d(records)
    r = _post(client_2d, batch, "?profile=cam2d&ellipse_confidence=0.9")
    assert _loc(r) == ["query", "ellipse_confidence"] and "3-D profiles" in r.text
    assert _loc(_post(client_2d, batch, "?profile=cam2d&levels=1.5")) == ["query", "levels", 0]
    table = _read(_post(client_2d, batch, "?profile=cam2d&levels=0.8"))
    assert [c for c in table.column_names if c.startswith("region_")] == ["region_0.8"]
    assert "region_0.95" in _read(_post(client_2d, batch)).column_names   # the default
    for accept in (f"{ARROW_STREAM}, application/json", "*/*", "application/*"):
        _read(_post(client_2d, batch, accept=accept))
    assert _post(client_2d, batch, accept="text/csv").status_code == 406
    # a 3-D profile answers an Arrow body in Arrow only
    r = _post(client_2d, batch, "?profile=lidar", accept="application/json")
    assert r.status_code == 406 and ARROW_STREAM in r.text


def test_a_profile_without_an_image_size_needs_the_size_columns(client_2d, records,
                                                                profile_2d, seeded):
    assert profile_2d.score_method == "position"
    unsized = Profile2D.from_dict({**json.loads(profile_2d.to_json()), "image_size": None})
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("cam2d", unsized.to_json())
    store.close()
    sized = request_batch_2d(records)
    bare = sized.drop_columns(["width", "height"])
    r = _post(client_2d, bare, "?profile=cam2d@2")
    assert _loc(r) == ["body", "width"] and "width and height" in r.text
    assert _read(_post(client_2d, sized, "?profile=cam2d@2")).num_rows == len(records)
    assert _read(_post(client_2d, bare, "?profile=cam2d@1")).num_rows == len(records)


def test_metrics_count_the_2d_detections(client_2d, records):
    def sample(text: str, prefix: str) -> float:
        return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                   if line.startswith(prefix))

    det = 'detcal_detections_calibrated_total{profile="cam2d"}'
    before = sample(client_2d.get("/metrics").text, det)
    _read(_post(client_2d, request_batch_2d(records)))
    assert sample(client_2d.get("/metrics").text, det) - before == len(records)


def test_the_documented_route_answers_as_the_fast_path(client_2d, seeded, records, dump_given):
    from fastapi.testclient import TestClient

    from app.calibrate.arrow_route import ArrowCalibrateMiddleware
    from app.main import create_app

    app = create_app(seeded)   # the same store (with cam2d), without the fast path
    app.user_middleware = [m for m in app.user_middleware if m.cls is not ArrowCalibrateMiddleware]
    batch = request_batch_2d(records)
    with TestClient(app) as routed:
        for accept in ("", "application/json", "text/csv", ARROW_STREAM):
            for body, query in ((batch, f"?profile=cam2d&{LEVELS}"),
                                (request_batch(dump_given, 3), "?profile=cam2d"),
                                (batch, "?profile=lidar")):
                fast = _post(client_2d, body, query, accept=accept)
                slow = _post(routed, body, query, accept=accept)
                assert fast.status_code == slow.status_code, (accept, query, fast.text)
                if fast.status_code == 200:
                    assert fast.content == slow.content
                else:   # the same error (the middleware's JSON spacing differs)
                    assert fast.json() == slow.json()
