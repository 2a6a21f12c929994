"""Every service path keeps each detection's identity (issue 27): POST /v1/calibrate with JSON
and with Arrow, POST /v1/calibrate/nuscenes, POST /v1/detect, and feedback (JSON and dump)
serve every detection the same values whatever the order of the request's detections and
frames: detections moved within and across frames, frames interleaved (one frame's
detections split around another's), duplicate boxes, frames without detections and frames
without ground truth."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.main import create_app
from calibrators.io import save_nuscenes
from calibrators.io.arrow_batch import ARROW_STREAM, read_stream, write_stream
from tests import identity_cases as ic
from tests.app.conftest import ADMIN
from tests.app.feedback_frames import feedback_frames, npz_bytes

SETTINGS = settings(max_examples=5, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])
LEVELS = [0.5, 0.9]


@pytest.fixture(scope="module")
def base(dump_given):
    keep = np.zeros(dump_given.n_frames, dtype=bool)
    keep[:6] = True
    return dump_given.select_frames(keep)


def _records(dump) -> list[dict]:
    """(frame_id, detection) of every detection of `dump`, id = its row, in dump order."""
    out = []
    for frame in feedback_frames(dump):
        out.extend((frame["frame_id"], det) for det in frame["detections"])
    order = np.argsort([det["id"] for _, det in out])
    return [out[i] for i in order]


def _frames(records: list, empty: int) -> list[dict]:
    """Request frames of `records` in their order: a new frame whenever the frame changes (a
    frame whose detections are not together comes as several interleaved frames), plus
    `empty` frames without detections."""
    frames: list[dict] = []
    for frame_id, det in records:
        if not frames or frames[-1]["frame_id"] != frame_id:
            frames.append({"frame_id": frame_id, "detections": []})
        frames[-1]["detections"].append(det)
    return frames + [{"frame_id": f"empty-{i}", "detections": []} for i in range(empty)]


def _by_id(body: dict) -> dict:
    out = {}
    for frame in body["frames"]:
        for j, det in enumerate(frame["detections"]):
            assert det["row"] == j
            out[det["id"]] = (frame["frame_id"], ic.served(det, *ic.RECORD_KEYS))
    return out


@SETTINGS
@given(case=ic.CASES)
def test_json_calibrate_serves_every_detection_the_same(client, base, case):
    dump = ic.awkward(base, case)
    records = _records(dump)
    rng = np.random.default_rng(case["seed"])
    moved = [records[i] for i in rng.permutation(len(records))]
    got = []
    for recs in (records, moved):
        r = client.post("/v1/calibrate", json={"levels": LEVELS,
                                               "frames": _frames(recs, case["empty_frames"])})
        assert r.status_code == 200, r.text
        got.append(_by_id(r.json()))
    assert len(got[1]) == dump.n_detections and got[0] == got[1]


def _arrow(records: list) -> bytes:
    batch = pa.RecordBatch.from_pydict({
        "frame_id": [f for f, _ in records], "id": [d["id"] for _, d in records],
        "logits": [d["logits"] for _, d in records], "box": [d["box"] for _, d in records],
        "covariance": [sum(d["covariance"], []) for _, d in records]})
    return write_stream(batch)


@SETTINGS
@given(case=ic.CASES)
def test_arrow_calibrate_serves_every_row_the_same(client, base, case):
    records = _records(ic.awkward(base, case))
    rng = np.random.default_rng(case["seed"])
    moved = [records[i] for i in rng.permutation(len(records))]
    got = []
    for recs in (records, moved):
        r = client.post("/v1/calibrate", params={"levels": LEVELS}, content=_arrow(recs),
                        headers={"content-type": ARROW_STREAM, "accept": ARROW_STREAM})
        assert r.status_code == 200, r.text
        table = read_stream(r.content).to_pylist()
        assert [row["row"] for row in table] == list(range(len(recs)))
        assert [row["id"] for row in table] == [d["id"] for _, d in recs]
        got.append({row.pop("id"): json.dumps({k: v for k, v in row.items() if k != "row"},
                                              sort_keys=True) for row in table})
    assert got[0] == got[1]


@SETTINGS
@given(case=ic.CASES)
def test_nuscenes_calibrate_serves_every_box_the_same(client, base, case, tmp_path):
    save_nuscenes(ic.awkward(base, case), tmp_path / "r.json")
    doc = json.loads((tmp_path / "r.json").read_text())
    moved, order = ic.permuted_document(doc, case["seed"])
    out = []
    for d in (doc, moved):
        r = client.post("/v1/calibrate/nuscenes", params={"levels": LEVELS}, json=d)
        assert r.status_code == 200, r.text
        out.append(r.json())
    assert list(out[1]["results"]) == list(moved["results"])
    ic.assert_same_boxes(out[0], out[1], order)
    assert out[0]["calibration"]["levels"] == LEVELS


def _window(settings_, body: dict | None = None, files: dict | None = None) -> dict:
    """The version's evidence since activation after one feedback request on a fresh store
    (its drift series follows the frames' order by design and is left out)."""
    with TestClient(create_app(settings_)) as c:
        r = c.post("/v1/feedback", headers=ADMIN, json=body, files=files,
                   data=None if files is None else {"profile": "lidar"})
        assert r.status_code == 200, r.text
        win = c.get("/v1/profiles/lidar/health").json()["since_activation"]
    return {k: v for k, v in win.items() if k not in ("series",)}


@pytest.fixture
def fresh(tmp_path, profile_json_given):
    """`fresh()`: settings of a new store holding `lidar` v1."""
    from app.settings import Settings
    from app.store import Store
    from tests.app.conftest import TOKEN

    count = [0]

    def make():
        count[0] += 1
        s = Settings(data_dir=tmp_path / f"data{count[0]}", admin_token=TOKEN)
        store = Store(s.sqlalchemy_url, s.dumps_dir)
        store.add_profile("lidar", profile_json_given)
        store.close()
        return s
    return make


@settings(max_examples=3, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=ic.CASES, upload=st.booleans())
def test_feedback_records_the_same_evidence_whatever_the_order(fresh, case, upload,
                                                               base):
    dump = ic.awkward(base, case)
    moved, _ = ic.shuffled(dump, case["seed"])
    wins = []
    for d in (dump, moved):
        if upload:
            wins.append(_window(fresh(), files={"dump": ("fb.npz", npz_bytes(d))}))
        else:
            wins.append(_window(fresh(), body={"profile": "lidar",
                                                "frames": feedback_frames(d)}))
    assert wins[0]["frames"] == dump.n_frames
    _close(wins[0], wins[1])


def _close(a: object, b: object) -> None:
    """Equal, floats to 1e-12 relative (sums over frames add in the frames' order)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys()
        for k in a:
            _close(a[k], b[k])
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _close(x, y)
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-12, abs=1e-15)
    else:
        assert a == b


@pytest.fixture(scope="module")
def detected(tmp_path_factory, profile_json_given):
    """(`/v1/detect`'s served detections by id, the same raw detections as request dicts)
    for one simulated lidar frame, on a module-scoped app."""
    pytest.importorskip("detectors")
    import torch

    from app.bundled_detectors import detections_of
    from app.settings import Settings
    from app.store import Store
    from detectors import build_detector
    from detectors.registry import weights_path
    from tests.app.conftest import TOKEN

    torch.set_num_threads(1)
    s = Settings(data_dir=tmp_path_factory.mktemp("detect") / "data", admin_token=TOKEN)
    store = Store(s.sqlalchemy_url, s.dumps_dir)
    store.add_profile("lidar", profile_json_given)
    store.close()
    app = create_app(s)
    if not weights_path("lidar").exists():
        app.state.detectors._models["lidar"] = build_detector("lidar", pretrained=False).eval()
    with TestClient(app) as c:
        r = c.post("/v1/detect", json={"seed": 7, "min_score": 0.0, "levels": LEVELS})
        assert r.status_code == 200, r.text
        served_ = _by_id(r.json())
        out = app.state.detectors.run("lidar", 7, None, 0.0)
        raw = [d.model_dump(exclude_none=True) for d in
               detections_of(out, app.state.cache.resolve("lidar", "lidar"))]
        yield c, served_, raw


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), split=st.integers(1, 4))
def test_detect_serves_each_detection_what_calibrating_it_in_any_order_serves(detected, seed,
                                                                             split):
    c, by_id, raw = detected
    order = np.random.default_rng(seed).permutation(len(raw))
    chunks = np.array_split(order, split)              # the frame's detections, interleaved
    frames = [{"frame_id": "lidar-7", "detections": [raw[i] for i in chunk]}
              for chunk in chunks]
    r = c.post("/v1/calibrate", json={"levels": LEVELS, "frames": frames})
    assert r.status_code == 200, r.text
    assert _by_id(r.json()) == by_id and len(by_id) == len(raw)
