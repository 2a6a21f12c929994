"""`calibrators.Detections`, the calibrate batch: every adapter gives each detection its
identity, a result is written back by that identity (never by position), and an error names
the record at fault."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from calibrators import Detections, apply_profile, fit_profile
from calibrators.core.errors import FieldError
from calibrators.data import synthetic_dump
from calibrators.io import calibrated_document


@pytest.fixture(scope="module")
def dump():
    return synthetic_dump(n_frames=6, seed=2)


@pytest.fixture(scope="module")
def profile(dump):
    return fit_profile(synthetic_dump(n_frames=30, seed=1), cov_source="given")


def _records(dump, rows):
    out = []
    for i in rows:
        rec = {"frame_id": str(dump.frame_ids[dump.det_frame[i]]), "id": f"det-{i}",
               "box": dump.det_boxes[i, -1, :7].tolist(), "covariance": dump.det_cov[i].tolist()}
        if i % 2:   # two evidence forms: one batch each
            rec.update(score=float(dump.det_scores[i]), label=dump.classes[dump.det_labels[i]])
        else:
            rec["logits"] = dump.det_logits[i, -1].tolist()
        out.append(rec)
    return out


def test_records_of_two_forms_come_back_by_identity(dump, profile):
    rows = list(range(12))
    batches = Detections.from_records(_records(dump, rows), profile.classes, profile.score_mode)
    assert sorted(len(b) for b in batches) == [6, 6]
    out = {}
    for b in batches:
        for rec in b.calibrate(profile, levels=[0.9]).to_records():
            out[rec["row"]] = rec
    assert sorted(out) == rows
    ref = apply_profile(dump, profile, levels=[0.9])
    for i in rows[::2]:     # logits: what the library serves the dump's detection
        assert out[i]["id"] == f"det-{i}" and out[i]["score"] == pytest.approx(ref.scores[i])
        assert out[i]["frame_id"] == str(dump.frame_ids[dump.det_frame[i]])
        assert out[i]["box"][7:] == [0.0, 0.0]                      # a 7-value box padded


def test_an_unknown_label_names_its_record(profile):
    records = [{"frame_id": "a", "score": 0.5, "label": "car", "box": [0.0] * 9},
               {"frame_id": "a", "score": 0.5, "label": "tram", "box": [0.0] * 9}]
    with pytest.raises(FieldError, match="unknown class 'tram'") as info:
        Detections.from_records(records, profile.classes, profile.score_mode)
    assert (info.value.field, info.value.row) == ("labels", 1)


def test_a_document_keeps_its_keys_tokens_and_ids(dump, profile):
    box = {"sample_token": "t1", "translation": [10.0, 0.0, 1.0], "size": [2.0, 4.0, 1.5],
           "rotation": [1.0, 0.0, 0.0, 0.0], "detection_name": "car", "detection_score": 0.7,
           "covariance": [[0.1, 0.0], [0.0, 0.1]], "num_pts": 5, "detection_id": "mine-1"}
    doc = {"meta": {"use_lidar": True}, "results": {"t0": [], "t1": [box, dict(box)]}}
    served = [b.calibrate(profile) for b in Detections.from_nuscenes(doc, profile.classes,
                                                                     profile.score_mode)]
    out = calibrated_document(served, {"profile": "p"}, doc["meta"])
    assert list(out["results"]) == ["t0", "t1"] and out["meta"] == {"use_lidar": True}
    first, second = out["results"]["t1"]
    assert (first["detection_row"], second["detection_row"]) == (0, 1)
    assert first["detection_id"] == "mine-1" and first["num_pts"] == 5
    assert first["detection_score_raw"] == 0.7 and first["detection_score"] != 0.7
    assert out["calibration"] == {"profile": "p", "cov_dims": list(profile.cov_dims)}


def test_an_arrow_batch_and_a_dump_carry_rows_and_frames(dump, profile):
    n = 5
    batch = pa.RecordBatch.from_pydict({
        "frame_id": pa.array([7, 7, 8, 8, 9]), "id": pa.array(list("abcde")),
        "logits": [r.tolist() for r in dump.det_logits[:n, -1]],
        "box": [r.tolist() for r in dump.det_boxes[:n, -1]],
        "covariance": [r.reshape(-1).tolist() for r in dump.det_cov[:n]]})
    out = Detections.from_arrow(batch, profile.classes).calibrate(profile).to_arrow()
    assert out["frame_id"].to_pylist() == [7, 7, 8, 8, 9]
    assert out["id"].to_pylist() == list("abcde") and out["row"].to_pylist() == list(range(n))
    det = Detections.from_dump(dump, "given")
    assert det.rows.tolist() == list(range(dump.n_detections))
    assert det.frame_ids.tolist() == dump.frame_ids[dump.det_frame].tolist()
    with pytest.raises(FieldError, match="rows"):
        Detections(frame_ids=np.zeros(2), rows=np.arange(3), boxes=np.zeros((3, 9)),
                   ego_xy=np.zeros((3, 2)))
