"""POST /v1/calibrate with an Arrow IPC stream: the same calibrated floats as the JSON path
(bit for bit), one row per detection in request order, and the same 4xx with the column named
for a bad batch."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from calibrators.io.arrow_batch import ARROW_STREAM, write_stream
from tests.app.arrow_compare import assert_same_floats

CAL = "/v1/calibrate"
ARROW = {"content-type": ARROW_STREAM}


def _fixed(values) -> pa.Array:
    flat = np.asarray(values, dtype=np.float64)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[-1])


def _rows(dump, n: int, *, cov: bool = True, layers: bool = False) -> pa.RecordBatch:
    cols = {"frame_id": pa.array([f"f{i % 3}" for i in range(n)]), "id": pa.array(range(n)),
            "logits": _fixed(dump.det_logits[:n, -1])}
    if layers:
        cols["layer_boxes"] = pa.FixedSizeListArray.from_arrays(
            _fixed(dump.det_boxes[:n].reshape(-1, 9)), dump.det_boxes.shape[1])
    else:
        cols["box"] = _fixed(dump.det_boxes[:n, -1])
    if cov:
        cols["covariance"] = _fixed(dump.det_cov[:n].reshape(n, -1))
    return pa.RecordBatch.from_pydict(cols)


def _post(client, batch: pa.RecordBatch, query: str = "", **headers):
    return client.post(CAL + query, content=write_stream(batch), headers={**ARROW, **headers})


def _read(response) -> pa.Table:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == ARROW_STREAM
    return pa.ipc.open_stream(response.content).read_all()


@pytest.mark.parametrize(("profile", "layers"), [("lidar", False), ("layers", True)])
def test_arrow_and_json_give_the_same_floats(client, dump_given, detection, profile, layers):
    n = 25
    table = _read(_post(client, _rows(dump_given, n, cov=not layers, layers=layers),
                        f"?profile={profile}&levels=0.5&levels=0.9"))
    frame = {"frame_id": "x", "detections": [detection(dump_given, i, cov=not layers,
                                                       layers=layers) for i in range(n)]}
    if layers:
        for det in frame["detections"]:
            del det["box"]
    body = client.post(CAL, json={"profile": profile, "levels": [0.5, 0.9],
                                  "frames": [frame]})
    assert body.status_code == 200, body.text
    dets = body.json()["frames"][0]["detections"]
    assert table["id"].to_pylist() == list(range(n))
    assert table["label"].to_pylist() == [d["label"] for d in dets]
    assert_same_floats(table, dets)
    for q in ("0.5", "0.9"):   # what holds for each ellipse, as in JSON
        served = table[f"ellipse_{q}"].to_pylist()
        assert [r["guarantee"] for r in served] == [d["ellipses"][q]["guarantee"] for d in dets]
        assert [r["calibration_n"] for r in served] == [d["ellipses"][q]["calibration_n"]
                                                         for d in dets]


@pytest.mark.parametrize(("change", "status", "loc"), [
    ({"covariance": None}, 422, ["body", "covariance"]),                # lidar needs Σ
    ({"box": "short"}, 422, ["body", "box"]),
    ({"logits": "nan"}, 422, ["body", "logits", 3]),
    ({"logits": "wide"}, 422, ["body", "logits"]),
    ({"frame_id": None}, 422, ["body", "frame_id"]),
    ({"logits": "text"}, 422, ["body", "logits"]),
])
def test_bad_batches_are_4xx_naming_the_column(client, dump_given, change, status, loc):
    batch = _rows(dump_given, 6)
    cols = {name: batch.column(name) for name in batch.schema.names}
    for name, how in change.items():
        if how is None:
            del cols[name]
        elif how == "short":
            cols[name] = _fixed(np.zeros((6, 5)))
        elif how == "nan":
            bad = dump_given.det_logits[:6, -1].astype(np.float64)
            bad[3, 1] = np.nan
            cols[name] = _fixed(bad)
        elif how == "wide":
            cols[name] = _fixed(np.zeros((6, 4)))
        elif how == "text":
            cols[name] = pa.array([["a"]] * 6)
    r = _post(client, pa.RecordBatch.from_pydict(cols))
    assert r.status_code == status, r.text
    assert r.json()["detail"][0]["loc"] == loc, r.json()


def test_options_limits_and_negotiation(client, dump_given):
    batch = _rows(dump_given, 4)
    r = _post(client, batch, "?levels=0.5&levels=1.5")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "levels", 1]
    assert _post(client, batch, "?profile=nope").status_code == 404
    r = client.post(CAL, content=b"not arrow", headers=ARROW)
    assert r.status_code == 422 and "not an Arrow IPC stream" in r.text
    assert _post(client, batch, accept="application/json").status_code == 406
    r = client.post(CAL, json={"frames": []}, headers={"accept": ARROW_STREAM})
    assert r.status_code == 406
    r = client.post(CAL, content=b"x", headers={"content-type": "text/csv"})
    assert r.status_code == 415 and ARROW_STREAM in r.text
    table = _read(_post(client, batch, "?ellipse_confidence=0.5", accept=f"{ARROW_STREAM}, */*"))
    assert table.num_rows == 4 and b'"confidence": 0.5' in table.schema.metadata[b"detcal"]


def test_too_many_rows_is_a_413(tmp_path, profile_json_given, dump_given):
    from fastapi.testclient import TestClient

    from app.main import create_app
    from app.settings import Settings
    from app.store import Store

    settings = Settings(data_dir=tmp_path / "d", admin_token="t" * 32, max_detections=5)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile("lidar", profile_json_given)
    store.close()
    with TestClient(create_app(settings)) as c:
        r = _post(c, _rows(dump_given, 6))
        assert r.status_code == 413 and "6 rows" in r.text
        assert _post(c, _rows(dump_given, 5)).status_code == 200
