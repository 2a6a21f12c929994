"""The Arrow batch format of calibrators.io.arrow_batch: a batch's arrays are the library's,
calibrated rows come back in the same order, and every bad column is a FieldError naming it."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from calibrators.core.errors import FieldError
from calibrators.io.arrow_batch import (
    batch_request,
    calibrated_batch,
    read_stream,
    write_stream,
)

CLASSES = ["car", "pedestrian"]


def _fixed(values: np.ndarray) -> pa.Array:
    flat = np.asarray(values, dtype=np.float64)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[-1])


def _batch(n: int = 4, **columns) -> pa.RecordBatch:
    rng = np.random.default_rng(0)
    base = {"frame_id": pa.array([f"f{i // 2}" for i in range(n)]),
            "logits": _fixed(rng.normal(size=(n, 2))),
            "box": _fixed(rng.normal(size=(n, 9)) * 10),
            "covariance": _fixed(np.tile(np.eye(2).reshape(1, 4), (n, 1)))}
    base.update(columns)
    return pa.RecordBatch.from_pydict({k: v for k, v in base.items() if v is not None})


def test_a_batch_becomes_the_library_arrays():
    batch = _batch(ego_translation=pa.array([[1.0, 2.0, 3.0]] * 4), id=pa.array([7, 8, 9, 10]))
    req = batch_request(read_stream(write_stream(batch)), CLASSES)
    kw = req.calibrate_arguments()
    assert kw["logits"].shape == (4, 2) and kw["boxes"].shape == (4, 9)
    assert kw["covariances"].shape == (4, 2, 2) and kw["ego_xy"].tolist() == [[1.0, 2.0]] * 4
    np.testing.assert_array_equal(kw["logits"], np.stack(batch["logits"].to_numpy(
        zero_copy_only=False)))
    assert req.detection_ids.to_pylist() == [7, 8, 9, 10] and len(req) == 4
    assert req.rows.tolist() == [0, 1, 2, 3] and req.frame_ids.to_pylist() == ["f0", "f0", "f1",
                                                                                "f1"]


def test_variable_lists_seven_value_boxes_and_label_names_are_accepted():
    batch = pa.RecordBatch.from_pydict({
        "frame_id": pa.array([1, 1]), "score": pa.array([0.2, 0.9], pa.float32()),
        "label": pa.array(["pedestrian", "car"]),
        "box": pa.array([[1.0, 2, 0, 1, 1, 1, 0], [3.0, 4, 0, 1, 1, 1, 0]])})
    kw = batch_request(batch, CLASSES).calibrate_arguments()
    assert kw["labels"].tolist() == [1, 0] and kw["boxes"].shape == (2, 9)
    assert kw["boxes"][:, 7:].tolist() == [[0, 0], [0, 0]]
    assert kw["scores"].dtype == np.float64


@pytest.mark.parametrize(("columns", "field", "words"), [
    ({"frame_id": None}, "frame_id", "needs a frame_id"),
    ({"logits": None}, "logits", "exactly one of"),
    ({"score": pa.array([0.5] * 4)}, "logits", "exactly one of"),
    ({"box": None}, "box", "needs a box"),
    ({"box": _fixed(np.zeros((4, 8)))}, "box", "9 values"),
    ({"covariance": _fixed(np.zeros((4, 3)))}, "covariance", "D·D"),
    ({"logits": pa.array([["a", "b"]] * 4)}, "logits", "numbers"),
    ({"logits": pa.array([1.0] * 4)}, "logits", "list column"),
    ({"logits": pa.array([[1.0, 2.0], [1.0], [1.0, 2.0], [1.0, 2.0]])}, "logits",
     "same length"),
    ({"logits": pa.array([[1.0, None]] * 4)}, "logits", "null"),
    ({"box": pa.array([[0.0] * 9, None, [0.0] * 9, [0.0] * 9])}, "box", "null at row 1"),
    ({"colour": pa.array(["red"] * 4)}, "colour", "unknown column"),
    ({"label": pa.array(["lorry"] * 4)}, "label", "unknown class .lorry."),
    ({"frame_id": pa.array([1.5] * 4)}, "frame_id", "strings or integers"),
])
def test_bad_columns_are_field_errors_naming_them(columns, field, words):
    with pytest.raises(FieldError, match=words) as info:
        batch_request(_batch(**columns), CLASSES)
    assert info.value.field == field


def test_an_unknown_label_names_its_row():
    batch = pa.RecordBatch.from_pydict({"frame_id": pa.array(["a", "a"]),
                                        "score": pa.array([0.5, 0.5]),
                                        "label": pa.array(["car", "tram"]),
                                        "box": _fixed(np.zeros((2, 9)))})
    with pytest.raises(FieldError, match="'tram' at row 1") as info:
        batch_request(batch, CLASSES)
    assert (info.value.field, info.value.row) == ("label", 1)


def test_streams_that_are_not_arrow_or_too_long_are_refused_before_reading_columns():
    with pytest.raises(FieldError, match="not an Arrow IPC stream"):
        read_stream(b"\x00" * 64)
    two = write_stream(_batch(6))
    with pytest.raises(FieldError, match="6 rows") as info:
        read_stream(two, max_rows=5)
    assert info.value.field == "rows"
    assert read_stream(two, max_rows=6).num_rows == 6


def test_a_calibrated_batch_keeps_row_order_and_marks_unbounded_axes_null():
    from calibrators.data import synthetic_dump
    from calibrators.fit import fit_profile

    dump = synthetic_dump(n_frames=20, seed=1)
    profile = fit_profile(dump, cov_source="given", region_method="conformal", min_group=30)
    n = 50
    batch = pa.RecordBatch.from_pydict({
        "frame_id": pa.array(np.arange(n) // 10), "id": pa.array(np.arange(n)[::-1]),
        "logits": _fixed(dump.det_logits[:n, -1]), "box": _fixed(dump.det_boxes[:n, -1]),
        "covariance": _fixed(dump.det_cov[:n].reshape(n, -1))})
    req = batch_request(batch, profile.classes)
    res = req.calibrate(profile, levels=[0.5, 0.999])
    out = read_stream(write_stream(calibrated_batch(res, {"profile": "p@1"})))
    assert out["id"].to_pylist() == list(range(n))[::-1]
    assert out["row"].to_pylist() == list(range(n))
    assert out["frame_id"].to_pylist() == (np.arange(n) // 10).tolist()
    np.testing.assert_array_equal(out["score"].to_numpy(), res.scores)
    wide = out["ellipse_0.999"].field("semi_major")
    assert wide.null_count == n                      # 30-point groups cannot bound 0.999
    np.testing.assert_array_equal(out["ellipse_0.5"].field("semi_major").to_numpy(),
                                  res.regions[0.5].semi_major)
    assert out.schema.metadata[b"detcal"].startswith(b"{")
