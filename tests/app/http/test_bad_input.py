"""A table of malformed requests: each gets its 4xx with a located reason, never a 5xx."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from app.main import create_app

TOKEN = "test-admin-token-0123456789"
ADMIN = {"Authorization": f"Bearer {TOKEN}"}
JSON = {"content-type": "application/json"}
GOOD_COV = [[0.1, 0.0], [0.0, 0.1]]
BOX = [10.0, 2.0, 1.0, 2.0, 4.5, 1.6, 0.1, 0.0, 0.0]


def det(**kw) -> dict:
    base = {"logits": [0.5] + [-3.0] * 9, "box": BOX, "covariance": GOOD_COV}
    base.update(kw)
    return {k: v for k, v in base.items() if v is not None}


def body(*dets, **kw) -> bytes:
    return json.dumps({"frames": [{"detections": list(dets)}], **kw}).encode()


def raw(text: str) -> bytes:
    return text.encode()


# (id, method, path, content, headers, status, expected fragment of loc or message)
CASES = [
    ("nan-logit", "POST", "/v1/calibrate",
     raw('{"frames":[{"detections":[{"logits":[NaN,0,0,0,0,0,0,0,0,0],"box":[0,0,0,1,1,1,0,0,0],'
         '"covariance":[[1,0],[0,1]]}]}]}'), JSON, 422, "logits"),
    ("inf-box", "POST", "/v1/calibrate",
     raw('{"frames":[{"detections":[{"logits":[0,0,0,0,0,0,0,0,0,0],"box":[Infinity,0,0,1,1,1,0,'
         '0,0],"covariance":[[1,0],[0,1]]}]}]}'), JSON, 422, "box"),
    ("overflow-to-inf", "POST", "/v1/calibrate",
     raw('{"frames":[{"detections":[{"score":0.5,"label":"car","box":[1e999,0,0,1,1,1,0,0,0],'
         '"covariance":[[1,0],[0,1]]}]}]}'), JSON, 422, "box"),
    ("nan-covariance", "POST", "/v1/calibrate",
     raw('{"frames":[{"detections":[{"score":0.5,"label":"car","box":[1,0,0,1,1,1,0,0,0],'
         '"covariance":[[NaN,0],[0,1]]}]}]}'), JSON, 422, "covariance"),
    ("box-wrong-length", "POST", "/v1/calibrate", body(det(box=[1, 2, 3])), JSON, 422, "box"),
    ("logits-too-wide", "POST", "/v1/calibrate", body(det(logits=[0.0] * 11)), JSON, 422,
     "needs 10"),
    ("ragged-layer-logits", "POST", "/v1/calibrate",
     body(det(logits=None, layer_logits=[[0.0] * 10, [0.0] * 9])), JSON, 422, "layer_logits"),
    ("layer-boxes-not-9", "POST", "/v1/calibrate", body(det(layer_boxes=[[0.0] * 8] * 2)),
     JSON, 422, "layer_boxes"),
    ("non-psd-covariance", "POST", "/v1/calibrate", body(det(covariance=[[1, 2], [2, 1]])),
     JSON, 422, "positive semi-definite"),
    ("asymmetric-covariance", "POST", "/v1/calibrate", body(det(covariance=[[1, 0.5], [0, 1]])),
     JSON, 422, "symmetric"),
    ("covariance-wrong-dims", "POST", "/v1/calibrate",
     body(det(covariance=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])), JSON, 422, "cov_dims"),
    ("covariance-not-square", "POST", "/v1/calibrate", body(det(covariance=[[1, 0], [0]])),
     JSON, 422, "covariance"),
    ("missing-covariance-for-given", "POST", "/v1/calibrate", body(det(covariance=None)), JSON,
     422, "cov_source 'given'"),
    ("two-evidence-forms", "POST", "/v1/calibrate", body(det(score=0.5, label="car")), JSON,
     422, "exactly one"),
    ("no-evidence", "POST", "/v1/calibrate", body(det(logits=None)), JSON, 422, "exactly one"),
    ("score-without-label", "POST", "/v1/calibrate", body(det(logits=None, score=0.5)), JSON,
     422, "needs label"),
    ("score-above-one", "POST", "/v1/calibrate",
     body(det(logits=None, score=1.5, label="car")), JSON, 422, "score"),
    ("unknown-class", "POST", "/v1/calibrate", body(det(logits=None, score=0.5, label="tank")),
     JSON, 422, "unknown class"),
    ("class-index-out-of-range", "POST", "/v1/calibrate",
     body(det(logits=None, score=0.5, label=10)), JSON, 422, "out of range"),
    ("no-box", "POST", "/v1/calibrate", body(det(box=None)), JSON, 422, "box"),
    ("unknown-field", "POST", "/v1/calibrate", body(det(logit=[1.0])), JSON, 422, "logit"),
    ("unknown-profile", "POST", "/v1/calibrate", body(det(), profile="radar9"), JSON, 404,
     "radar9"),
    ("unknown-version", "POST", "/v1/calibrate", body(det(), profile="lidar@9"), JSON, 404,
     "no version 9"),
    ("malformed-profile-ref", "POST", "/v1/calibrate", body(det(), profile="a b"), JSON, 422,
     "profile"),
    ("confidence-out-of-range", "POST", "/v1/calibrate", body(det(), ellipse_confidence=1.0),
     JSON, 422, "ellipse_confidence"),
    ("no-frames", "POST", "/v1/calibrate", raw('{"frames": []}'), JSON, 422, "frames"),
    ("empty-body", "POST", "/v1/calibrate", b"", JSON, 422, "body"),
    ("not-json", "POST", "/v1/calibrate", raw("{frames: "), JSON, 422, "JSON"),
    ("json-array", "POST", "/v1/calibrate", raw("[1, 2]"), JSON, 422, "body"),
    ("wrong-content-type", "POST", "/v1/calibrate", body(det()), {"content-type": "text/plain"},
     415, "application/json"),
    ("no-content-type", "POST", "/v1/calibrate", body(det()), {}, 415, "application/json"),
    ("oversized-body", "POST", "/v1/calibrate", b"[" + b"0," * 40_000 + b"0]", JSON, 413,
     "exceeds"),
    ("nuscenes-nan-score", "POST", "/v1/calibrate/nuscenes",
     raw('{"results":{"t":[{"sample_token":"t","translation":[1,2,3],"size":[1,1,1],'
         '"rotation":[1,0,0,0],"detection_name":"car","detection_score":NaN}]}}'), JSON, 422,
     "detection_score"),
    ("nuscenes-unknown-class", "POST", "/v1/calibrate/nuscenes",
     raw('{"results":{"t":[{"sample_token":"t","translation":[1,2,3],"size":[1,1,1],'
         '"rotation":[1,0,0,0],"detection_name":"ufo","detection_score":0.5,'
         '"covariance":[[1,0],[0,1]]}]}}'), JSON, 422, "unknown class"),
    ("nuscenes-missing-results", "POST", "/v1/calibrate/nuscenes", raw('{"meta": {}}'), JSON,
     422, "results"),
    ("nuscenes-zero-rotation", "POST", "/v1/calibrate/nuscenes",
     raw('{"results":{"t":[{"sample_token":"t","translation":[1,2,0],"size":[2,4,1.5],'
         '"rotation":[0,0,0,0],"detection_name":"car","detection_score":0.5,'
         '"covariance":[[1,0],[0,1]]}]}}'), JSON, 422, '"loc":["body","results","t",0,"rotation"]'),
    ("detect-unknown-sensor", "POST", "/v1/detect", raw('{"sensor": "sonar", "seed": 1}'), JSON,
     None, None),
    ("detect-seed-and-points", "POST", "/v1/detect",
     raw('{"seed": 1, "points": [[0, 0, 0, 1]]}'), JSON, 422, "not both"),
    ("activate-no-token", "POST", "/v1/profiles/lidar/1/activate", b"", {}, 401, "token"),
    ("activate-wrong-token", "POST", "/v1/profiles/lidar/1/activate", b"",
     {"Authorization": "Bearer nope"}, 403, "wrong admin token"),
    ("activate-basic-auth", "POST", "/v1/profiles/lidar/1/activate", b"",
     {"Authorization": "Basic dXNlcjpwYXNz"}, 401, "token"),
    ("activate-unknown-version", "POST", "/v1/profiles/lidar/5/activate", b"", ADMIN, 404,
     "no version 5"),
    ("activate-version-zero", "POST", "/v1/profiles/lidar/0/activate", b"", ADMIN, 422,
     "version"),
    ("fit-no-token", "POST", "/v1/fit", b"", {}, 401, "token"),
    ("fit-nothing-uploaded", "POST", "/v1/fit", None, ADMIN, 422, "upload"),
    ("fit-garbage-npz", "POST", "/v1/fit", "garbage", ADMIN, 422, "dump"),
    ("fit-bad-dims", "POST", "/v1/fit", "dims", ADMIN, 422, "dims"),
    ("fit-bad-threshold", "POST", "/v1/fit", "threshold", ADMIN, 422, "threshold"),
    ("fit-oversized", "POST", "/v1/fit", "huge", ADMIN, 413, "exceeds"),
    ("job-unknown", "GET", "/v1/jobs/" + "0" * 32, None, ADMIN, 404, "does not exist"),
    ("job-malformed-id", "GET", "/v1/jobs/xyz", None, ADMIN, 422, "job_id"),
    ("job-no-token", "GET", "/v1/jobs/" + "0" * 32, None, {}, 401, "token"),
    ("jobs-wrong-token", "GET", "/v1/jobs", None, {"Authorization": "Bearer x"}, 403, "token"),
    ("profile-unknown", "GET", "/v1/profiles/radar9", None, {}, 404, "radar9"),
    ("profile-version-not-int", "GET", "/v1/profiles/lidar/abc", None, {}, 422, "version"),
]


@pytest.fixture(scope="module")
def bad_client(tmp_path_factory, profile_json_given):
    from app.settings import Settings
    from app.store import Store

    settings = Settings(data_dir=tmp_path_factory.mktemp("bad"), admin_token=TOKEN,
                        max_request_bytes=50_000, max_upload_bytes=200_000)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile("lidar", profile_json_given)
    store.close()
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


def _fit_upload(kind: str) -> dict:
    if kind == "garbage":
        return {"files": {"dump": ("x.npz", b"not an npz at all")}}
    if kind == "dims":
        return {"files": {"dump": ("x.npz", b"PK")}, "data": {"dims": "x,q"}}
    if kind == "threshold":
        return {"files": {"dump": ("x.npz", b"PK")}, "data": {"threshold": "-1"}}
    if kind == "huge":
        return {"files": {"dump": ("x.npz", b"0" * 300_000)}}
    return {"data": {"name": "lidar"}}


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_a_located_4xx(bad_client, case):
    _, method, path, content, headers, status, fragment = case
    if path == "/v1/fit" and content is not None and content != b"":
        r = bad_client.post(path, headers=headers, **_fit_upload(content))
    elif path == "/v1/fit" and content is None:
        r = bad_client.post(path, headers=headers, **_fit_upload("nothing"))
    else:
        r = bad_client.request(method, path, content=content, headers=headers)
    assert 400 <= r.status_code < 500, (r.status_code, r.text)
    if status is not None:
        assert r.status_code == status, r.text
        assert fragment in r.text, r.text
    detail = r.json()["detail"]
    if isinstance(detail, list):
        assert all(item["loc"] and item["msg"] for item in detail)
