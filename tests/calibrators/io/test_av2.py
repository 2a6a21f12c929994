"""calibrators.io.argoverse2: Argoverse 2 detections and annotations as Feather files.

Fixtures are tables with the columns of `av2.evaluation.detection` and a sensor log's
`annotations.feather` (log_id, timestamp_ns, category, tx_m .. qz, score / num_interior_pts),
synthetic values, written with `pyarrow.feather.write_feather` as pandas' `to_feather` does.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.core.errors import FieldError
from calibrators.io import load_dump
from calibrators.io.argoverse2 import AV2_CATEGORIES, load_av2
from tests.calibrators.io.reader_checks import (
    assert_reads_or_refuses,
    assert_same_content,
    npz_round_trip,
)

LOG = "0c6e62d7-bdfa-3061-8d3d-03b13aa21f68"


def table(rows, scored=True, **extra):
    """rows: (log, timestamp, category, tx, ty, tz, l, w, h, yaw, score-or-points)."""
    cols = {"log_id": [r[0] for r in rows],
            "timestamp_ns": pa.array([r[1] for r in rows], pa.int64()),
            "category": [r[2] for r in rows]}
    for k, name in enumerate(("tx_m", "ty_m", "tz_m", "length_m", "width_m", "height_m")):
        cols[name] = pa.array([float(r[3 + k]) for r in rows], pa.float32())
    yaw = np.array([r[9] for r in rows], dtype=float)
    cols.update(qw=np.cos(yaw / 2), qx=np.zeros(len(rows)), qy=np.zeros(len(rows)),
                qz=np.sin(yaw / 2))
    if scored:
        cols["score"] = pa.array([float(r[10]) for r in rows], pa.float32())
    else:
        cols["track_uuid"] = [f"t{k}" for k in range(len(rows))]
        cols["num_interior_pts"] = pa.array([r[10] for r in rows], pa.int64())
    cols.update(extra)
    return pa.table(cols)


def write(tmp_path, name, tab, compression="lz4"):
    path = tmp_path / name
    feather.write_feather(tab, path, compression=compression)
    return path


DETS = [(LOG, 315968867659956000, "REGULAR_VEHICLE", 12.5, -3.0, 0.8, 4.6, 1.9, 1.5, 2.0, 0.91),
        (LOG, 315968867659956000, "PEDESTRIAN", 6.0, 4.0, 0.9, 0.6, 0.7, 1.8, -0.5, 0.35),
        ("log-b", 315968867759956000, "BOLLARD", -8.0, 1.0, 0.5, 0.3, 0.3, 1.0, 0.0, 0.6)]


@pytest.mark.parametrize("compression", ["lz4", "zstd", "uncompressed"])
def test_detection_columns(tmp_path, compression):
    dump = load_av2(write(tmp_path, "detections.feather", table(DETS), compression))
    assert dump.classes == AV2_CATEGORIES and len(AV2_CATEGORIES) == 26
    assert dump.frame_ids.tolist() == [f"{LOG}/315968867659956000", "log-b/315968867759956000"]
    # x y z = tx ty tz (centre, ego frame), w = width_m, l = length_m, yaw of the quaternion
    np.testing.assert_allclose(dump.final_boxes[0], [12.5, -3.0, 0.8, 1.9, 4.6, 1.5, 2.0, 0, 0],
                               atol=1e-6)
    assert dump.det_labels.tolist() == [0, 1, 5]
    np.testing.assert_allclose(dump.det_scores, [0.91, 0.35, 0.6], atol=1e-6)
    assert dump.ego_translation is None
    assert_same_content(npz_round_trip(dump), dump)


def test_dictionary_encoded_columns_are_decoded(tmp_path):
    """pandas writes a `category` dtype as a dictionary column; the values are read."""
    tab = table(DETS)
    at = tab.schema.get_field_index("category")
    tab = tab.set_column(at, "category", tab.column("category").dictionary_encode())
    assert pa.types.is_dictionary(tab.schema.field("category").type)
    dump = load_av2(write(tmp_path, "detections.feather", tab))
    assert dump.det_labels.tolist() == [0, 1, 5]


def test_annotations_as_ground_truth(tmp_path):
    gt = [(LOG, 315968867659956000, "REGULAR_VEHICLE", 12.7, -3.1, 0.8, 4.5, 1.9, 1.5, 2.1, 120),
          (LOG, 315968867659956000, "PEDESTRIAN", 6.0, 4.0, 0.9, 0.6, 0.7, 1.8, -0.5, 0),
          (LOG, 315968867759956000, "OFFICIAL_SIGNALER", 1.0, 1.0, 1.0, 1, 1, 1, 0.0, 40),
          (LOG, 315968867859956000, "BUS", 30.0, 2.0, 1.6, 12.0, 2.6, 3.2, math.pi, 400),
          ("other-log", 1, "BUS", 30.0, 2.0, 1.6, 12.0, 2.6, 3.2, 0.0, 400)]
    det = write(tmp_path, "detections.feather", table(DETS))
    ann = write(tmp_path, "annotations.feather", table(gt, scored=False))
    dump = load_av2(det, ann)
    # no interior point, no competition category, another log: not read; frames kept
    assert [AV2_CATEGORIES[k] for k in dump.gt_labels] == ["REGULAR_VEHICLE", "BUS"]
    assert f"{LOG}/315968867759956000" in dump.frame_ids.tolist()
    assert "other-log/1" not in dump.frame_ids.tolist()
    assert math.cos(dump.gt_boxes[1, 6] - math.pi) == pytest.approx(1.0)
    assert_same_content(load_dump(det, format="av2", ground_truth=ann), dump)


def test_annotations_of_a_split_folder(tmp_path):
    gt = [(LOG, 315968867659956000, "REGULAR_VEHICLE", 12.7, -3.1, 0.8, 4.5, 1.9, 1.5, 2.1, 120),
          ("log-b", 315968867759956000, "BOLLARD", -8.0, 1.0, 0.5, 0.3, 0.3, 1.0, 0.0, 9)]
    for log in (LOG, "log-b", "log-c"):
        (tmp_path / "val" / log).mkdir(parents=True)
        write(tmp_path / "val" / log, "annotations.feather",
              table([r for r in gt if r[0] == log] or gt[:1], scored=False))
    det = write(tmp_path, "detections.feather", table(DETS))
    dump = load_av2(det, tmp_path / "val")
    assert [AV2_CATEGORIES[k] for k in dump.gt_labels] == ["REGULAR_VEHICLE", "BOLLARD"]
    write(tmp_path, "d2.feather", table(DETS + [("log-z", 1, "DOG", 1, 1, 1, 1, 1, 1, 0, 0.5)]))
    with pytest.raises(FieldError, match=r"val/log-z/annotations.feather is missing"):
        load_av2(tmp_path / "d2.feather", tmp_path / "val")


def test_explicit_classes_and_map(tmp_path):
    det = write(tmp_path, "d.feather", table(DETS))
    dump = load_av2(det, classes=("car", "pedestrian", "barrier"),
                    class_map={"REGULAR_VEHICLE": "car", "PEDESTRIAN": "pedestrian",
                               "BOLLARD": "barrier"})
    assert dump.det_labels.tolist() == [0, 1, 2]
    with pytest.raises(FieldError, match=r"d.feather: category 'BOLLARD' at row 2 is not one "
                                         r"of the classes"):
        load_av2(det, classes=("REGULAR_VEHICLE", "PEDESTRIAN"))


@pytest.mark.parametrize("tab, match", [
    (table(DETS).drop_columns(["qz"]), r"missing column 'qz'"),
    (table(DETS).drop_columns(["score"]), r"missing column 'score'"),
    (table(DETS).set_column(0, "log_id", pa.array([1, 2, 3])), r"'log_id' must be string"),
    (table(DETS).set_column(3, "tx_m", pa.array([1.0, None, 2.0])), r"'tx_m' is null at row 1"),
    (table(DETS).set_column(3, "tx_m", pa.array([1.0, np.nan, 2.0])), r"'tx_m' is nan at row 1"),
    (table(DETS).set_column(6, "length_m", pa.array([1.0, 0.0, 2.0])), r"must be > 0, row 1"),
    (table([r[:10] + (1.4,) for r in DETS]), r"score\[0\] = 1.4 is not a probability"),
    (table([r[:10] + (float("nan"),) for r in DETS]), r"column 'score' is nan at row 0"),
])
def test_malformed_tables_name_file_column_and_row(tmp_path, tab, match):
    with pytest.raises(FieldError, match=f"d.feather: .*{match}"):
        load_av2(write(tmp_path, "d.feather", tab))


def test_malformed_files(tmp_path):
    data = (tmp_path / "x.feather")
    data.write_bytes(b"not arrow at all")
    with pytest.raises(FieldError, match=r"x.feather: not a Feather v2"):
        load_av2(data)
    good = write(tmp_path, "d.feather", table(DETS)).read_bytes()
    (tmp_path / "cut.feather").write_bytes(good[:len(good) // 2] + b"ARROW1")
    with pytest.raises(FieldError, match=r"cut.feather: "):
        load_av2(tmp_path / "cut.feather")
    with pytest.raises(FieldError, match="limit of 200 bytes"):
        load_av2(tmp_path / "d.feather", max_bytes=200)
    zero = table(DETS, qw=np.zeros(3), qz=np.zeros(3))
    with pytest.raises(FieldError, match=r"row 0 has the zero quaternion"):
        load_av2(write(tmp_path, "z.feather", zero))


@settings(max_examples=20, deadline=None)
@given(st.permutations(list(range(6))))
def test_order_does_not_change_content(tmp_path_factory, order):
    base = tmp_path_factory.mktemp("av2")
    rng = np.random.default_rng(5)
    rows = [(f"log{k % 2}", 1000 + k % 3, AV2_CATEGORIES[k % 4], *rng.uniform(-20, 20, 3),
             *rng.uniform(0.5, 5, 3), float(rng.uniform(-3, 3)), float(rng.uniform(0.05, 0.95)))
            for k in range(6)]
    a = load_av2(write(base, "a.feather", table(rows)))
    b = load_av2(write(base, "b.feather", table([rows[k] for k in order])))
    assert_same_content(a, b)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10**6), st.integers(0, 10**6))
def test_damaged_file_is_read_or_refused(tmp_path_factory, cut, flip):
    folder = tmp_path_factory.mktemp("dmg")
    data = write(folder, "good.feather", table(DETS)).read_bytes()
    assert_reads_or_refuses(folder / "d.feather", data, cut, flip, load_av2)
