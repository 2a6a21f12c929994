"""Detections that assert a class other than the arg-max of their logits (a top-K (query,
class) decoder gives one query a detection per class): `label` beside `logits` in JSON, a
`label` column beside `logits` in Arrow, and in feedback frames. The label is served as
given, its score is the library's, JSON and Arrow agree bit for bit, and a bad label is a
422 naming it."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from calibrators import CalibrationProfile, Dump, summarize
from calibrators.data import synthetic_dump
from calibrators.io.arrow_batch import ARROW_STREAM, write_stream
from tests.app.arrow_compare import assert_same_floats
from tests.app.conftest import ADMIN
from tests.app.feedback_frames import feedback_frames

CAL = "/v1/calibrate"


@pytest.fixture(scope="module")
def top2() -> Dump:
    """Every detection of a synthetic dump twice: its arg-max class and its second class."""
    d = synthetic_dump(n_frames=24, seed=11)
    second = np.argsort(-d.det_logits[:, -1], axis=1)[:, 1]
    rows = np.repeat(np.arange(d.n_detections), 2)
    return Dump(classes=d.classes, score_mode=d.score_mode, frame_ids=d.frame_ids,
                det_frame=d.det_frame[rows], det_logits=d.det_logits[rows],
                det_boxes=d.det_boxes[rows], det_cov=d.det_cov[rows], gt_frame=d.gt_frame,
                gt_labels=d.gt_labels, gt_boxes=d.gt_boxes,
                det_label=np.stack([d.det_labels, second], axis=1).reshape(-1))


def _detection(dump: Dump, i: int, label: bool = True) -> dict:
    det = {"id": i, "logits": dump.det_logits[i, -1].tolist(),
           "box": dump.det_boxes[i, -1].tolist(), "covariance": dump.det_cov[i].tolist()}
    if label:
        det["label"] = dump.classes[int(dump.det_labels[i])]
    return det


def _json(client, dets: list[dict]):
    return client.post(CAL, json={"profile": "lidar", "levels": [0.5, 0.9],
                                  "frames": [{"frame_id": "f", "detections": dets}]})


def test_json_serves_the_given_label_with_the_librarys_score(client, top2,
                                                             profile_json_given):
    n = 16
    dets = [_detection(top2, i) for i in range(n)] + [_detection(top2, 1, label=False)]
    r = _json(client, dets)
    assert r.status_code == 200, r.text
    out = r.json()["frames"][0]["detections"]
    prof = CalibrationProfile.from_json(profile_json_given)
    want = prof.calibrate(logits=top2.det_logits[:n, -1], labels=top2.det_labels[:n],
                          boxes=top2.final_boxes[:n], covariances=top2.det_cov[:n],
                          levels=[0.5, 0.9])
    assert [d["label_index"] for d in out[:n]] == top2.det_labels[:n].tolist()
    assert [d["score"] for d in out[:n]] == want.scores.tolist()
    assert len(set(top2.det_labels[:n:2].tolist()) ^ set(top2.det_labels[1:n:2].tolist())) > 0
    # Without a label, the arg-max: detection 1's query's first class, not its second.
    assert out[n]["label_index"] == int(top2.det_labels[0]) != int(top2.det_labels[1])


def test_arrow_label_column_gives_the_json_floats(client, top2):
    n = 20
    flat = lambda a: pa.FixedSizeListArray.from_arrays(  # noqa: E731
        pa.array(np.asarray(a, dtype=np.float64).reshape(-1)), int(np.prod(a.shape[1:])))
    batch = pa.RecordBatch.from_pydict({
        "frame_id": pa.array(["f"] * n), "id": pa.array(range(n)),
        "logits": flat(top2.det_logits[:n, -1]), "box": flat(top2.final_boxes[:n]),
        "covariance": flat(top2.det_cov[:n]),
        "label": pa.array([top2.classes[int(c)] for c in top2.det_labels[:n]])})
    r = client.post(f"{CAL}?profile=lidar&levels=0.5&levels=0.9", content=write_stream(batch),
                    headers={"content-type": ARROW_STREAM})
    assert r.status_code == 200, r.text
    table = pa.ipc.open_stream(r.content).read_all()
    assert table.column("label_index").to_pylist() == top2.det_labels[:n].tolist()
    body = _json(client, [_detection(top2, i) for i in range(n)])
    assert_same_floats(table, body.json()["frames"][0]["detections"])


@pytest.mark.parametrize("label", ["lorry", 10])
def test_a_bad_label_beside_logits_is_a_422_naming_it(client, top2, label):
    det = {**_detection(top2, 0), "label": label}
    r = _json(client, [_detection(top2, 1), det])
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "frames", 0, "detections", 1, "label"]


def test_feedback_scores_the_given_labels(client, top2, profile_json_given):
    r = client.post("/v1/feedback", headers=ADMIN,
                    json={"profile": "lidar", "frames": feedback_frames(top2)})
    assert r.status_code == 200, r.text
    offline = summarize(top2, CalibrationProfile.from_json(profile_json_given)).to_dict()
    # Read as arg-max labels, every second detection would be a duplicate (a false positive
    # of the same class) and the true positives would differ.
    assert r.json()["tp"] == offline["counts"]["tp"]
    win = client.get("/v1/profiles/lidar/health").json()["window"]
    assert win["ece"]["value"] == pytest.approx(offline["classification"]["ece"]["after"])
