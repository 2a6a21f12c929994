"""The 2-D Arrow batch format of calibrators.io.arrow_boxes2d: a batch's columns become the
library's `Detections2D` whatever their Arrow types, and calibrated rows come back with their
identity, an unbounded level's boxes null."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from calibrators.boxes2d import BoxRegions, Calibrated2D, synthetic_coco
from calibrators.core.errors import FieldError
from calibrators.io.arrow_boxes2d import boxes2d_request, calibrated_boxes2d_batch
from tests.arrow_mutator import request_batch_2d


@pytest.fixture(scope="module")
def records() -> list[dict]:
    return synthetic_coco(3, seed=1)[0]


@pytest.mark.parametrize("variant", [0, 1, 2])
def test_columns_of_any_type_read_as_the_records(records, variant):
    request = boxes2d_request(request_batch_2d(records, variant=variant))
    det = request.detections
    n = len(records)
    assert len(request) == n and request.rows.tolist() == list(range(n))
    assert det.image_id.tolist() == [r["image_id"] for r in records]
    assert det.category_id.tolist() == [r["category_id"] for r in records]
    tol = 1e-4 if variant == 1 else 0.0   # float32 columns
    np.testing.assert_allclose(det.bbox, [r["bbox"] for r in records], rtol=tol)
    np.testing.assert_allclose(det.layer_boxes, [r["layer_boxes"] for r in records])
    assert request.ids.to_pylist() == [f"d{i}" for i in range(n)]
    if variant == 1:
        assert request.image_size is None
    else:
        assert request.image_size.tolist() == [[640.0, 480.0]] * n
    assert (det.logits is not None) == (variant == 2)


def test_calibrated_rows_keep_their_identity_and_null_unbounded_boxes(records):
    request = boxes2d_request(request_batch_2d(records))
    n = len(request)
    level_boxes = [[10.0, 10.0, 5.0, 5.0], [np.inf, np.inf, -np.inf, -np.inf]]   # q=0.99: unbounded
    inner = np.repeat(np.array([level_boxes]), n, axis=0)
    outer = inner.copy()
    regions = BoxRegions(np.array([0.5, 0.99]), inner, outer,
                         np.array([["cell", "marginal"]] * n), np.full((n, 2), 40))
    served = Calibrated2D(request.detections, np.full(n, 0.25), regions)
    out = calibrated_boxes2d_batch(request, served, {"kind": "boxes2d"})
    out.validate(full=True)
    assert out.schema.names == ["image_id", "row", "id", "category_id", "bbox", "score",
                                "score_raw", "region_0.5", "region_0.99"]
    rows = out.to_pylist()
    assert rows[1]["row"] == 1 and rows[1]["id"] == "d1"
    assert rows[0]["region_0.5"] == {"inner": [10.0, 10.0, 5.0, 5.0],
                                     "outer": [10.0, 10.0, 5.0, 5.0], "guarantee": "cell",
                                     "calibration_n": 40}
    assert rows[0]["region_0.99"]["inner"] is None and rows[0]["region_0.99"]["outer"] is None
    assert out.schema.metadata[b"detcal"] == b'{"kind": "boxes2d", "levels": [0.5, 0.99]}'
    other = boxes2d_request(request_batch_2d(records))
    with pytest.raises(ValueError, match="calibrate_2d of request"):
        calibrated_boxes2d_batch(other, served, {})


def test_a_bad_column_names_itself(records):
    batch = request_batch_2d(records)
    with pytest.raises(FieldError) as err:
        boxes2d_request(batch.drop_columns(["width"]))
    assert err.value.field == "width" and "together" in str(err.value)
    big = pa.array([2**63 + 5] * batch.num_rows, pa.uint64())
    with pytest.raises(FieldError) as err:
        boxes2d_request(batch.set_column(0, "image_id", big))
    assert (err.value.field, err.value.row) == ("image_id", 0)
