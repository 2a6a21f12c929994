"""Parquet datasets: conversion round trip, parts of whole frames, and bad datasets refused
with the column (or key) and the file named."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from calibrators.core.errors import FieldError
from calibrators.data import concat_frames, synthetic_dump
from calibrators.io import ParquetWriter, load_parquet, open_parquet, save_parquet

ARRAYS = ("frame_ids", "det_frame", "det_logits", "det_boxes", "det_cov", "gt_frame",
          "gt_labels", "gt_boxes", "ego_translation")


def same_dump(a, b):
    assert (a.classes, a.score_mode, a.cov_dims) == (b.classes, b.score_mode, b.cov_dims)
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.array_equal(x, y), name


@pytest.mark.parametrize("mode, with_cov", [("sigmoid", True), ("softmax", False)])
def test_round_trip_is_exact_and_frames_never_span_parts(tmp_path, mode, with_cov):
    dump = synthetic_dump(n_frames=25, n_gt_per_frame=8, score_mode=mode, seed=1,
                          with_cov=with_cov)
    save_parquet(tmp_path / "ds", dump, rows_per_part=60)
    ds = open_parquet(tmp_path / "ds")
    assert len(ds.parts) > 3 and ds.n_detections == dump.n_detections
    assert ds.has_cov == with_cov and ds.source_sha256
    same_dump(load_parquet(tmp_path / "ds"), dump)
    seen = []
    for i, part in enumerate(ds.parts):
        frames = pq.read_table(tmp_path / "ds" / "detections" / f"{part.name}.parquet")
        got = np.unique(frames.column("frame").to_numpy())
        assert ((got >= part.first) & (got < part.stop)).all()
        seen.extend(range(part.first, part.stop))
        assert ds.read_part(i).n_frames == part.stop - part.first
    assert seen == list(range(dump.n_frames))


def test_unsorted_detections_are_stored_frame_by_frame_in_dump_order(tmp_path):
    dump = synthetic_dump(n_frames=6, n_gt_per_frame=4, seed=2)
    order = np.random.default_rng(0).permutation(dump.n_detections)
    shuffled = replace(dump, det_frame=dump.det_frame[order], det_logits=dump.det_logits[order],
                       det_boxes=dump.det_boxes[order], det_cov=dump.det_cov[order])
    save_parquet(tmp_path / "ds", shuffled)
    back = load_parquet(tmp_path / "ds")
    stable = np.argsort(shuffled.det_frame, kind="stable")
    assert np.array_equal(back.det_frame, shuffled.det_frame[stable])
    assert np.array_equal(back.det_logits, shuffled.det_logits[stable])


def test_writer_appends_chunks_as_new_frames(tmp_path):
    chunks = [synthetic_dump(n_frames=5, n_gt_per_frame=6, seed=s) for s in range(3)]
    writer = ParquetWriter(tmp_path / "ds", rows_per_part=40, float_dtype="float32")
    for chunk in chunks:
        writer.add(chunk)
    writer.close()
    back = load_parquet(tmp_path / "ds")
    whole = concat_frames(chunks)
    assert back.n_frames == 15 and np.array_equal(back.det_frame, whole.det_frame)
    assert np.array_equal(back.det_logits, whole.det_logits.astype(np.float32))
    with pytest.raises(ValueError, match="already holds a Parquet dataset"):
        ParquetWriter(tmp_path / "ds")
    other = ParquetWriter(tmp_path / "other")
    other.add(chunks[0])
    with pytest.raises(ValueError, match="score_mode"):
        other.add(synthetic_dump(n_frames=3, score_mode="softmax"))


@pytest.fixture
def dataset(tmp_path):
    save_parquet(tmp_path / "ds", synthetic_dump(n_frames=10, n_gt_per_frame=5, seed=3),
                 rows_per_part=50)
    return tmp_path / "ds"


def rewrite(path, column, array):
    table = pq.read_table(path)
    if array is None:
        table = table.drop_columns([column])
    else:
        table = table.set_column(table.schema.get_field_index(column), column, array)
    pq.write_table(table, path)


def test_missing_folder_or_metadata_is_refused(tmp_path, dataset):
    with pytest.raises(FieldError, match="is not a folder"):
        open_parquet(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FieldError, match="has no detcal.json"):
        open_parquet(tmp_path / "empty")
    meta = json.loads((dataset / "detcal.json").read_text())
    del meta["score_mode"]
    (dataset / "detcal.json").write_text(json.dumps(meta))
    with pytest.raises(FieldError, match="has no 'score_mode'") as err:
        open_parquet(dataset)
    assert err.value.field == "score_mode"


@pytest.mark.parametrize("column, array, match", [
    ("cov", None, "part-00000.parquet has no column 'cov'"),
    ("frame", pa.array(["a"] * 0, pa.string()), "column 'frame' must be integers"),
    ("logits", "ints", r"column 'logits' must be fixed_size_list<float32 or float64>\[30\]"),
    ("boxes", "short", r"column 'boxes' must be fixed_size_list.*\[27\]"),
])
def test_bad_columns_are_named_with_their_file(dataset, column, array, match):
    path = dataset / "detections" / "part-00000.parquet"
    n = pq.read_metadata(path).num_rows
    if array == "ints":
        array = pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(n * 30, np.int32)), 30)
    elif array == "short":
        array = pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(n * 26)), 26)
    elif array is not None:
        array = pa.array(["x"] * n, pa.string())
    rewrite(path, column, array)
    with pytest.raises(FieldError, match=match) as err:
        open_parquet(dataset)
    assert err.value.field == column


def test_bad_values_are_named_with_their_part(dataset):
    path = dataset / "detections" / "part-00000.parquet"
    table = pq.read_table(path)
    logits = table.column("logits").combine_chunks().flatten().to_numpy().copy()
    logits[31] = np.nan
    rewrite(path, "logits", pa.FixedSizeListArray.from_arrays(pa.array(logits), 30))
    ds = open_parquet(dataset)
    with pytest.raises(FieldError, match="part part-00000: det_logits has NaN") as err:
        ds.read_part(0)
    assert err.value.field == "det_logits"
    frames = table.column("frame").to_numpy().copy()
    frames[2] = 999
    rewrite(path, "frame", pa.array(frames))
    with pytest.raises(FieldError, match="frame 999 at row 2 is outside"):
        open_parquet(dataset).read_part(0)
    rewrite(path, "frame", pa.array([None] + frames[1:].tolist(), pa.int64()))
    with pytest.raises(FieldError, match="column 'frame' has a null at row 0"):
        open_parquet(dataset).read_part(0)


def test_missing_part_file_is_named(dataset):
    (dataset / "ground_truth" / "part-00001.parquet").unlink()
    with pytest.raises(FieldError, match="ground_truth/part-00001.parquet is missing"):
        open_parquet(dataset)


def test_box_hypotheses_round_trip_and_survive_a_min_score_fit(tmp_path):
    from calibrators.fit import fit_profile_stream

    dump = synthetic_dump(n_frames=12, n_gt_per_frame=6, seed=4)
    rng = np.random.default_rng(0)
    dump = replace(dump, det_hyp_boxes=dump.det_boxes[:, -1:, :] + rng.normal(
        0.0, 0.1, (dump.n_detections, 3, 9)), det_hyp_scores=rng.uniform(
        0.0, 1.0, (dump.n_detections, 3)))
    save_parquet(tmp_path / "ds", dump, rows_per_part=80)
    assert open_parquet(tmp_path / "ds").n_hypotheses == 3
    same_dump(load_parquet(tmp_path / "ds"), dump)
    back = load_parquet(tmp_path / "ds")
    assert np.array_equal(back.det_hyp_boxes, dump.det_hyp_boxes)
    assert np.array_equal(back.det_hyp_scores, dump.det_hyp_scores)
    profile = fit_profile_stream(tmp_path / "ds", min_score=0.1, calibration=0.0)
    assert profile.temperature > 0
