"""POST /v1/calibrate with a profile fit on the `hypotheses` covariance source: detections
carry `hypothesis_boxes` / `hypothesis_scores` (JSON fields or Arrow columns), the numbers are
the library's, JSON and Arrow agree bit for bit, and a missing or malformed hypothesis array
is a 422 naming it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.store import Store
from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile
from calibrators.io.arrow_batch import ARROW_STREAM, write_stream
from calibrators.profile import CalibrationProfile
from tests.app.arrow_compare import assert_same_floats

CAL = "/v1/calibrate"
ARROW = {"content-type": ARROW_STREAM}
H = 4


@pytest.fixture(scope="module")
def dump():
    """A small synthetic dump with H box hypotheses per detection (no given covariances)."""
    return synthetic_dump(n_frames=30, seed=0, n_hypotheses=H, with_cov=False)


@pytest.fixture(scope="module")
def profiles(dump) -> dict[str, str]:
    """`hyp`: fit on the hypotheses only; `mixed`: on the layers, serving the hypotheses too."""
    # hyp: split-conformal regions without tail floors, so that its feedback coverage is near
    # each level (on this small dump every cell is small, and tail floors over-cover)
    return {"hyp": fit_profile(dump, cov_source="hypotheses", other_sources=False,
                               floor_delta=None).to_json(),
            "mixed": fit_profile(dump, cov_source="layers").to_json()}


@pytest.fixture
def client(tmp_path: Path, profiles: dict[str, str], profile_json_layers: str
           ) -> Iterator[TestClient]:
    """A TestClient over a SQLite store holding `hyp`, `mixed` and an old `layers` profile."""
    settings = Settings(data_dir=tmp_path / "data", admin_token="t" * 32)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    for name, text in profiles.items():
        store.add_profile(name, text)
    store.add_profile("layers", profile_json_layers)
    store.close()
    with TestClient(create_app(settings)) as c:
        yield c


def _detection(dump, i: int) -> dict:
    return {"id": i, "logits": dump.det_logits[i, -1].tolist(),
            "box": dump.det_boxes[i, -1].tolist(),
            "hypothesis_boxes": dump.det_hyp_boxes[i].tolist(),
            "hypothesis_scores": dump.det_hyp_scores[i].tolist()}


def _json(client, profile: str, dets: list[dict]):
    return client.post(CAL, json={"profile": profile, "levels": [0.5, 0.9],
                                  "frames": [{"frame_id": "f", "detections": dets}]})


def _fixed(values) -> pa.Array:
    flat = np.asarray(values, dtype=np.float64)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[-1])


def _batch(dump, n: int, *, nested: bool = True, **change) -> pa.RecordBatch:
    hyp = dump.det_hyp_boxes[:n]
    cols = {"frame_id": pa.array(["f"] * n), "id": pa.array(range(n)),
            "logits": _fixed(dump.det_logits[:n, -1]), "box": _fixed(dump.det_boxes[:n, -1]),
            "hypothesis_boxes": pa.FixedSizeListArray.from_arrays(_fixed(hyp.reshape(-1, 9)), H)
            if nested else _fixed(hyp.reshape(n, -1)),
            "hypothesis_scores": _fixed(dump.det_hyp_scores[:n])}
    cols.update(change)
    return pa.RecordBatch.from_pydict({k: v for k, v in cols.items() if v is not None})


def _arrow(client, batch: pa.RecordBatch, profile: str):
    return client.post(f"{CAL}?profile={profile}&levels=0.5&levels=0.9",
                       content=write_stream(batch), headers=ARROW)


def test_json_serves_the_library_numbers(client, dump, profiles):
    n = 12
    r = _json(client, "hyp", [_detection(dump, i) for i in range(n)])
    assert r.status_code == 200, r.text
    dets = r.json()["frames"][0]["detections"]
    prof = CalibrationProfile.from_json(profiles["hyp"])
    want = prof.calibrate(logits=dump.det_logits[:n, -1], boxes=dump.det_boxes[:n, -1],
                          hyp_boxes=dump.det_hyp_boxes[:n], hyp_scores=dump.det_hyp_scores[:n],
                          levels=[0.5, 0.9])
    assert [d["covariance"] for d in dets] == want.covariances.tolist()
    assert [d["score"] for d in dets] == want.scores.tolist()
    assert [d["ellipses"]["0.9"]["semi_major"] for d in dets] == \
        want.regions[0.9].semi_major.tolist()


@pytest.mark.parametrize("nested", [True, False])
def test_arrow_and_json_give_the_same_floats(client, dump, nested):
    n = 20
    r = _arrow(client, _batch(dump, n, nested=nested), "hyp")
    assert r.status_code == 200, r.text
    table = pa.ipc.open_stream(r.content).read_all()
    assert b'"cov_source": "hypotheses"' in table.schema.metadata[b"detcal"]
    body = _json(client, "hyp", [_detection(dump, i) for i in range(n)])
    assert body.status_code == 200, body.text
    dets = body.json()["frames"][0]["detections"]
    assert_same_floats(table, dets)


def _without(det: dict, *keys: str) -> dict:
    return {k: v for k, v in det.items() if k not in keys}


@pytest.mark.parametrize(("change", "loc_tail"), [
    (lambda d: _without(d, "hypothesis_boxes", "hypothesis_scores"), ["hypothesis_boxes"]),
    (lambda d: _without(d, "hypothesis_scores"), ["hypothesis_scores"]),
    (lambda d: _without(d, "hypothesis_boxes"), ["hypothesis_boxes"]),
    (lambda d: {**d, "hypothesis_boxes": [r[:7] for r in d["hypothesis_boxes"]]},
     ["hypothesis_boxes", 0]),
    (lambda d: {**d, "hypothesis_boxes": []}, ["hypothesis_boxes"]),
    (lambda d: {**d, "hypothesis_scores": d["hypothesis_scores"][:2]}, ["hypothesis_scores"]),
    (lambda d: {**d, "hypothesis_scores": [-1.0] * H}, ["hypothesis_scores", 0]),
])
def test_missing_or_malformed_hypotheses_are_a_422_naming_the_field(client, dump, change,
                                                                    loc_tail):
    dets = [_detection(dump, i) for i in range(3)]
    dets[1] = change(dets[1])
    r = _json(client, "hyp", dets)
    assert r.status_code == 422, r.text
    loc = r.json()["detail"][0]["loc"]
    assert loc[:5] == ["body", "frames", 0, "detections", 1], loc
    assert loc[5:5 + len(loc_tail)] == loc_tail, loc


def test_the_openapi_schema_states_the_shapes(client):
    schema = client.get("/openapi.json").json()["components"]["schemas"]["DetectionIn"]
    boxes = schema["properties"]["hypothesis_boxes"]["anyOf"][0]
    assert boxes["items"]["minItems"] == boxes["items"]["maxItems"] == 9
    scores = schema["properties"]["hypothesis_scores"]["anyOf"][0]
    assert scores["items"]["minimum"] == 0
    assert schema["dependentRequired"]["hypothesis_boxes"] == ["hypothesis_scores"]


@pytest.mark.parametrize(("change", "loc"), [
    ({"hypothesis_boxes": None, "hypothesis_scores": None}, ["body", "hypothesis_boxes"]),
    ({"hypothesis_scores": None}, ["body", "hypothesis_scores"]),
    ({"hypothesis_boxes": "text"}, ["body", "hypothesis_boxes"]),
    ({"hypothesis_boxes": "width"}, ["body", "hypothesis_boxes"]),
    ({"hypothesis_scores": "narrow"}, ["body", "hypothesis_scores"]),
    ({"hypothesis_scores": "negative"}, ["body", "hypothesis_scores", 2]),
])
def test_bad_hypothesis_columns_are_a_422_naming_the_column(client, dump, change, loc):
    n = 5
    bad = {"text": pa.array([["a"] * 9] * n), "width": _fixed(np.zeros((n, 10))),
           "narrow": _fixed(dump.det_hyp_scores[:n, :2]),
           "negative": _fixed(np.where(np.arange(n)[:, None] == 2, -1.0,
                                       dump.det_hyp_scores[:n]))}
    cols = {k: None if v is None else bad[v] for k, v in change.items()}
    r = _arrow(client, _batch(dump, n, **cols), "hyp")
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == loc, r.json()


def test_a_mixed_profile_serves_whatever_the_detection_carries(client, dump):
    with_hyp = _detection(dump, 0)
    plain = _without(with_hyp, "hypothesis_boxes", "hypothesis_scores")
    layers = {**plain, "layer_boxes": dump.det_boxes[0].tolist()}
    r = _json(client, "mixed", [with_hyp, plain, layers])
    assert r.status_code == 200, r.text
    got = [d["covariance"] for d in r.json()["frames"][0]["detections"]]
    assert len({str(c) for c in got}) == 3    # hypotheses, none and layers differ


def test_old_profiles_still_serve_and_ignore_hypotheses(client, dump):
    det = {**_detection(dump, 0), "layer_boxes": dump.det_boxes[0].tolist()}
    a = _json(client, "layers", [det])
    b = _json(client, "layers", [_without(det, "hypothesis_boxes", "hypothesis_scores")])
    assert a.status_code == b.status_code == 200, a.text
    assert a.json()["frames"][0]["detections"][0]["covariance"] == \
        b.json()["frames"][0]["detections"][0]["covariance"]


def test_feedback_with_hypotheses_scores_a_hypotheses_profile(client, dump):
    """JSON feedback carrying the box hypotheses is matched and scored for a profile whose
    only covariance source is `hypotheses` (coverage of its served levels measured)."""
    from tests.app.feedback_frames import feedback_frames

    admin = {"Authorization": "Bearer " + "t" * 32}
    frames = feedback_frames(dump, cov=False)
    r = client.post("/v1/feedback", headers=admin, json={"profile": "hyp", "frames": frames})
    assert r.status_code == 200, r.text
    health = client.get("/v1/profiles/hyp/health").json()
    assert health["window"]["frames"] == len(frames)
    overall = {c["level"]: c["coverage"] for c in health["window"]["coverage"]["overall"]}
    assert abs(overall[0.9] - 0.9) < 0.05 and abs(overall[0.5] - 0.5) < 0.07, overall
    bad = [dict(f, detections=[{k: v for k, v in d.items() if k != "hypothesis_scores"}
                               for d in f["detections"]]) for f in frames[:1]]
    r = client.post("/v1/feedback", headers=admin, json={"profile": "hyp", "frames": bad})
    assert r.status_code == 422
