"""calibrators.io.openpcdet and pickle_safe: OpenPCDet result.pkl through a restricted
unpickler.

Fixtures are the dicts OpenPCDet's `generate_prediction_dicts` builds (KITTI: name, truncated,
occluded, alpha, bbox, dimensions, location, rotation_y, score, boxes_lidar, frame_id;
nuScenes: name, score, boxes_lidar [N, 9], pred_labels, frame_id, metadata.token), and the
infos pickles of its data preparation, written with synthetic values and `pickle.dumps` as
OpenPCDet's `tools/test.py` does.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.core.errors import FieldError
from calibrators.io import load_dump
from calibrators.io.openpcdet import load_openpcdet
from calibrators.io.pickle_safe import load_restricted
from tests.calibrators.io.reader_checks import (
    assert_reads_or_refuses,
    assert_same_content,
    npz_round_trip,
)

NUSC = ("car", "truck", "pedestrian")
KITTI = ("Car", "Pedestrian", "Cyclist")


def nusc_result():
    return [
        {"name": np.array(["car", "pedestrian"]), "score": np.array([0.9, 0.3], np.float32),
         "boxes_lidar": np.array([[10.0, 2.0, -1.0, 4.5, 1.9, 1.6, 0.3, 1.0, -0.5],
                                  [5.0, -3.0, -0.8, 0.7, 0.6, 1.8, -2.0, 0.0, 0.2]]),
         "pred_labels": np.array([1, 3]), "frame_id": "n015-a",
         "metadata": {"token": "tok-a"}},
        {"name": np.array([], dtype="<U1"), "score": np.zeros(0, np.float32),
         "boxes_lidar": np.zeros((0, 9)), "pred_labels": np.zeros(0, np.int64),
         "frame_id": "n015-b", "metadata": {"token": "tok-b"}},
    ]


def kitti_entry(frame, rows):
    """A KITTI pred dict: rows of (name, score, boxes_lidar[7], bbox[4])."""
    return {"name": np.array([r[0] for r in rows]), "truncated": np.zeros(len(rows)),
            "occluded": np.zeros(len(rows)), "alpha": np.zeros(len(rows)),
            "bbox": np.array([r[3] for r in rows]).reshape(-1, 4),
            "dimensions": np.ones((len(rows), 3)), "location": np.ones((len(rows), 3)),
            "rotation_y": np.zeros(len(rows)), "score": np.array([r[1] for r in rows]),
            "boxes_lidar": np.array([r[2] for r in rows]).reshape(-1, 7), "frame_id": frame}


def dump_pickle(tmp_path: Path, name: str, obj, protocol=pickle.DEFAULT_PROTOCOL) -> Path:
    path = tmp_path / name
    path.write_bytes(pickle.dumps(obj, protocol=protocol))
    return path


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_nuscenes_style_fields(tmp_path, protocol):
    dump = load_openpcdet(dump_pickle(tmp_path, "result.pkl", nusc_result(), protocol),
                          classes=NUSC)
    assert dump.frame_ids.tolist() == ["tok-a", "tok-b"]  # metadata.token, empty frame kept
    # x y z dx dy dz heading vx vy -> x y z w(=dy) l(=dx) h yaw vx vy
    np.testing.assert_allclose(dump.final_boxes,
                               [[10.0, 2.0, -1.0, 1.9, 4.5, 1.6, 0.3, 1.0, -0.5],
                                [5.0, -3.0, -0.8, 0.6, 0.7, 1.8, -2.0, 0.0, 0.2]])
    assert dump.det_labels.tolist() == [0, 2]
    np.testing.assert_allclose(dump.det_scores, [0.9, 0.3], atol=1e-6)
    assert_same_content(npz_round_trip(dump), dump)
    same = load_dump(tmp_path / "result.pkl", format="openpcdet", classes=NUSC)
    assert_same_content(same, dump)


def test_kitti_infos_ground_truth_and_ignore_rules(tmp_path):
    car = [10.0, 1.0, -0.9, 3.9, 1.6, 1.5, 0.1]
    van = [20.0, -4.0, -0.9, 4.5, 1.9, 2.0, 0.0]
    result = [kitti_entry("000003", [
        ("Car", 0.9, car, [100, 150, 200, 250]),                         # on the Car: TP
        ("Car", 0.8, van, [300, 150, 380, 250]),                         # on the Van: ignored
        ("Car", 0.7, [30.0, 5.0, -0.9, 3.9, 1.6, 1.5, 0.0], [510, 160, 590, 240]),  # DontCare
        ("Car", 0.6, [40.0, -9.0, -0.9, 3.9, 1.6, 1.5, 0.0], [700, 160, 790, 240]),  # an FP
    ])]
    infos = [{"point_cloud": {"num_features": 4, "lidar_idx": "000003"},
              "image": {"image_idx": "000003"},
              "annos": {"name": np.array(["Car", "Van", "DontCare"]),
                        "bbox": np.array([[100, 150, 200, 250], [300, 150, 380, 250],
                                          [500, 150, 600, 250]], float),
                        "gt_boxes_lidar": np.array([car, van])}},
             {"point_cloud": {"lidar_idx": "000004"}, "annos": {
                 "name": np.array(["Car"]), "gt_boxes_lidar": np.array([car])}}]
    dump = load_openpcdet(dump_pickle(tmp_path, "result.pkl", result),
                          dump_pickle(tmp_path, "kitti_infos_val.pkl", infos), classes=KITTI)
    assert dump.frame_ids.tolist() == ["000003"]  # only the results' frames
    np.testing.assert_allclose(sorted(dump.det_scores), [0.6, 0.9])
    assert dump.gt_labels.tolist() == [0]
    np.testing.assert_allclose(dump.gt_boxes[0, :7], [10.0, 1.0, -0.9, 1.6, 3.9, 1.5, 0.1])


def test_nuscenes_infos_ground_truth(tmp_path):
    infos = [{"token": t, "gt_names": np.array(["car", "ignore", "pedestrian"]),
              "gt_boxes": np.array([[10.0, 2.0, -1.0, 4.5, 1.9, 1.6, 0.3, np.nan, np.nan],
                                    [1.0, 1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0],
                                    [5.0, -3.0, -0.8, 0.7, 0.6, 1.8, -2.0, 0.0, 0.1]]),
              "num_lidar_pts": np.array([30, 5, 0])} for t in ("tok-a", "tok-b")]
    dump = load_openpcdet(dump_pickle(tmp_path, "result.pkl", nusc_result()),
                          dump_pickle(tmp_path, "infos.pkl", infos), classes=NUSC)
    # 'ignore' is no class, the pedestrian has no lidar point; unknown velocity -> 0.
    assert dump.gt_labels.tolist() == [0, 0] and dump.frame_ids[dump.gt_frame].tolist() == \
        ["tok-a", "tok-b"]
    np.testing.assert_array_equal(dump.gt_boxes[:, 7:], 0.0)


class Evil:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


class EvalEvil:
    def __reduce__(self):
        return (eval, ("1 + 1",))


@pytest.mark.parametrize("make", [
    lambda t: Evil(t), lambda t: [{"score": Evil(t)}], lambda t: np.array([Evil(t)], object),
    lambda t: EvalEvil()])
def test_code_in_a_pickle_is_refused(tmp_path, make):
    target = tmp_path / "pwned"
    path = dump_pickle(tmp_path, "result.pkl", make(target))
    with pytest.raises(FieldError, match=r"result.pkl: not read: it names \w+\.(system|eval), "
                                         r"which is not allowed"):
        load_openpcdet(path, classes=NUSC)
    assert not target.exists()


def test_restricted_unpickler_refuses_other_globals():
    for obj in (Path("/etc"), {1: Evil("/nonexistent")}.keys, np.random.default_rng(0)):
        try:
            data = pickle.dumps(obj)
        except (TypeError, pickle.PicklingError):
            continue
        with pytest.raises(FieldError, match="which is not allowed"):
            load_restricted(data, "x.pkl")


@pytest.mark.parametrize("edit, match", [
    (lambda r: r[0].pop("score"), r"result.pkl\[0\]: missing 'score'"),
    (lambda r: r[0].update(boxes_lidar=np.zeros((2, 8))), r"\[0\].boxes_lidar must have 7 or 9"),
    (lambda r: r[0].update(boxes_lidar=np.zeros((3, 9))), r"\[0\].boxes_lidar must have shape "
                                                          r"\[2, N\]"),
    (lambda r: r[0]["score"].__setitem__(1, np.nan), r"\[0\].score has NaN or Inf at \[1\]"),
    (lambda r: r[0]["score"].__setitem__(0, 1.5), r"\[0\].score\[0\] = 1.5 is not a probability"),
    (lambda r: r[0].update(pred_labels=np.array([0, 3])), r"pred_labels\[0\] = 0 is not a "
                                                          r"1-based index"),
    (lambda r: r[0].update(pred_labels=np.array([2, 3])), r"pred_labels\[0\] = 2 names 'truck' "
                                                          r"but name is 'car'"),
    (lambda r: r[0].update(name=np.array(["car", "dog"])), r"name\[1\] = 'dog' is not one of"),
    (lambda r: r[0].update(name=np.array([1, 2])), r"\[0\].name must be strings"),
    (lambda r: r[0].update(score=[0.5, [0.1, 0.2]]), r"\[0\].score is not an array"),
    (lambda r: [r[0].pop("frame_id"), r[0].pop("metadata")], r"\[0\]: has no frame_id"),
    (lambda r: r[0]["boxes_lidar"].__setitem__((0, 3), -1.0), r"boxes_lidar\[0\] has a size"),
])
def test_malformed_results_name_entry_and_key(tmp_path, edit, match):
    result = nusc_result()
    edit(result)
    with pytest.raises(FieldError, match=match):
        load_openpcdet(dump_pickle(tmp_path, "result.pkl", result), classes=NUSC)


def test_malformed_files(tmp_path):
    data = pickle.dumps(nusc_result())
    (tmp_path / "cut.pkl").write_bytes(data[: len(data) // 2])
    with pytest.raises(FieldError, match=r"cut.pkl: not read: .*truncated"):
        load_openpcdet(tmp_path / "cut.pkl", classes=NUSC)
    (tmp_path / "junk.pkl").write_bytes(b"\x00\x01 not a pickle")
    with pytest.raises(FieldError, match=r"junk.pkl: not read"):
        load_openpcdet(tmp_path / "junk.pkl", classes=NUSC)
    with pytest.raises(FieldError, match=r"d.pkl: must be a list of dicts"):
        load_openpcdet(dump_pickle(tmp_path, "d.pkl", {"name": []}), classes=NUSC)
    path = dump_pickle(tmp_path, "result.pkl", nusc_result())
    with pytest.raises(FieldError, match="limit of 100 bytes"):
        load_openpcdet(path, classes=NUSC, max_bytes=100)
    infos = [{"token": "tok-a", "gt_names": np.array(["car"]), "gt_boxes": np.ones((1, 9))}]
    with pytest.raises(FieldError, match=r"i.pkl: has no entry for frame 'tok-b'"):
        load_openpcdet(path, dump_pickle(tmp_path, "i.pkl", infos), classes=NUSC)


def test_the_service_never_reads_pickles():
    root = Path(__file__).resolve().parents[3]
    for source in (root / "app").rglob("*.py"):
        text = source.read_text()
        assert "pickle" not in text or source.parent.name == "cli", source
    for source in (root / "calibrators").rglob("*.py"):
        text = source.read_text()
        assert "pickle.load(" not in text and "pickle.loads(" not in text, source


@settings(max_examples=25, deadline=None)
@given(st.permutations(list(range(6))), st.lists(st.integers(0, 1), min_size=6, max_size=6))
def test_order_and_frame_splits_do_not_change_content(tmp_path_factory, order, split):
    """Rows permuted, and each frame's rows split over two dicts placed anywhere in the
    list, give the same content per detection."""
    base = tmp_path_factory.mktemp("pcdet")
    rng = np.random.default_rng(7)
    boxes = np.column_stack([rng.uniform(-40, 40, (6, 3)), rng.uniform(0.5, 5, (6, 3)),
                             rng.uniform(-3, 3, (6, 3))])
    names = np.array(["car", "truck", "pedestrian", "car", "car", "truck"])
    scores = rng.uniform(0.05, 0.95, 6)
    frames = ["a", "b", "a", "c", "b", "a"]

    def entry(rows, frame):
        rows = np.asarray(rows, dtype=np.int64)
        return {"name": names[rows], "score": scores[rows], "boxes_lidar": boxes[rows],
                "frame_id": frame}

    ref = [entry([k for k in range(6) if frames[k] == f], f) for f in "abc"]
    parts = [entry([k for k in order if frames[k] == f and split[k] == s], f)
             for s in (1, 0) for f in "cab"]
    a = load_openpcdet(dump_pickle(base, "a.pkl", ref), classes=NUSC)
    b = load_openpcdet(dump_pickle(base, "b.pkl", parts), classes=NUSC)
    assert_same_content(a, b)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10**6), st.integers(0, 10**6))
def test_damaged_file_is_read_or_refused(tmp_path_factory, cut, flip):
    path = tmp_path_factory.mktemp("dmg") / "result.pkl"
    assert_reads_or_refuses(path, pickle.dumps(nusc_result()), cut, flip,
                            lambda p: load_openpcdet(p, classes=NUSC))
