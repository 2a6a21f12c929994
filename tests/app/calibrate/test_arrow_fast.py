"""The Arrow fast path (`app.calibrate.arrow_route`) answers like the documented FastAPI route:
the same query validation (same 422 bodies as a JSON request with that query), the same negotiation,
the same size limit, and the same metrics (route label, detection counter)."""

from __future__ import annotations

import pyarrow as pa
import pytest

from calibrators.io.arrow_batch import ARROW_STREAM, write_stream

CAL = "/v1/calibrate"


def _batch(dump, n: int = 3) -> bytes:
    def fixed(a):
        return pa.FixedSizeListArray.from_arrays(pa.array(a.reshape(-1)), a.shape[-1])

    return write_stream(pa.RecordBatch.from_pydict({
        "frame_id": pa.array(["f"] * n), "id": pa.array(range(n)),
        "logits": fixed(dump.det_logits[:n, -1]), "box": fixed(dump.det_boxes[:n, -1]),
        "covariance": fixed(dump.det_cov[:n].reshape(n, -1))}))


@pytest.fixture
def routed(seeded):
    """A client of the same app without the fast path: Arrow bodies go through the route."""
    from fastapi.testclient import TestClient

    from app.calibrate.arrow_route import ArrowCalibrateMiddleware
    from app.main import create_app

    app = create_app(seeded)
    app.user_middleware = [m for m in app.user_middleware if m.cls is not ArrowCalibrateMiddleware]
    with TestClient(app) as c:
        yield c


@pytest.mark.parametrize("query", [
    "?ellipse_confidence=1.5", "?ellipse_confidence=abc", "?ellipse_confidence=",
    "?levels=0.5&levels=x", "?levels=0.5&levels=1.0", "?profile=bad@@ref", "?profile=",
    "?profile=" + "a" * 200, "?ellipse_confidence=0.5&ellipse_confidence=0",
    "?profile=nope", "?levels=0.5&levels=0.5"])
def test_answers_match_the_route(client, routed, dump_given, query):
    body, headers = _batch(dump_given), {"content-type": ARROW_STREAM}
    fast = client.post(CAL + query, content=body, headers=headers)
    slow = routed.post(CAL + query, content=body, headers=headers)
    assert fast.status_code == slow.status_code and fast.status_code in (404, 422), fast.text
    assert fast.json() == slow.json()
    ok = client.post(CAL + "?levels=0.5&levels=0.9", content=body, headers=headers)
    assert ok.content == routed.post(CAL + "?levels=0.5&levels=0.9", content=body,
                                     headers=headers).content
    for accept in ("application/json", "text/*"):
        r = client.post(CAL, content=body, headers={**headers, "accept": accept})
        assert r.status_code == 406 and r.json() == routed.post(
            CAL, content=body, headers={**headers, "accept": accept}).json()


def test_valid_queries_and_unknown_keys(client, dump_given):
    r = client.post(CAL + "?levels=0.5&levels=0.9&other=1&ellipse_confidence=0.9&"
                          "ellipse_confidence=0.5", content=_batch(dump_given),
                    headers={"content-type": f"{ARROW_STREAM}; charset=binary"})
    assert r.status_code == 200, r.text
    table = pa.ipc.open_stream(r.content).read_all()
    assert {"ellipse_0.5", "ellipse_0.9"} <= set(table.column_names) and table.num_rows == 3
    assert b'"confidence": 0.5' in table.schema.metadata[b"detcal"]   # the last value wins


def test_other_methods_and_paths_go_to_the_router(client, dump_given):
    body = _batch(dump_given)
    r = client.put(CAL, content=body, headers={"content-type": ARROW_STREAM})
    assert r.status_code == 405 and "POST" in r.headers["allow"]
    r = client.post(CAL + "/nuscenes", content=body, headers={"content-type": ARROW_STREAM})
    assert r.status_code == 415


def test_size_limit_applies(tmp_path, profile_json_given, dump_given):
    from fastapi.testclient import TestClient

    from app.main import create_app
    from app.settings import Settings
    from app.store import Store

    body = _batch(dump_given)
    settings = Settings(data_dir=tmp_path / "d", max_request_bytes=len(body) - 1)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile("lidar", profile_json_given)
    store.close()
    with TestClient(create_app(settings)) as c:
        r = c.post(CAL, content=body, headers={"content-type": ARROW_STREAM})
        assert r.status_code == 413 and "exceeds" in r.json()["detail"]


def test_metrics_label_the_route_and_count_detections(client, dump_given):
    def sample(text: str, prefix: str) -> float:
        return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
                   if line.startswith(prefix))

    before = client.get("/metrics").text
    for _ in range(2):
        r = client.post(CAL, content=_batch(dump_given, 4), headers={"content-type": ARROW_STREAM})
        assert r.status_code == 200 and "server-timing" in r.headers
    after = client.get("/metrics").text
    req = 'detcal_http_requests_total{method="POST",route="/v1/calibrate",status="200"}'
    assert sample(after, req) - sample(before, req) == 2
    det = 'detcal_detections_calibrated_total{profile="lidar"}'
    assert sample(after, det) - sample(before, det) == 8


@pytest.mark.parametrize(("query", "loc"), [("?levels=0.5&levels=1.0", ["query", "levels", 1]),
                                            ("?profile=nope@9", None)])
def test_json_bodies_locate_a_bad_query_option_in_the_query(client, dump_given, detection,
                                                             query, loc):
    frame = {"frame_id": "f", "detections": [detection(dump_given, 0)]}
    r = client.post(CAL + query, json={"frames": [frame]})
    assert r.status_code in (404, 422), r.text
    if loc is not None:
        assert r.json()["detail"][0]["loc"] == loc
    body = client.post(CAL, json={"frames": [frame], "levels": [0.5, 1.0]})
    assert body.json()["detail"][0]["loc"] == ["body", "levels", 1]
