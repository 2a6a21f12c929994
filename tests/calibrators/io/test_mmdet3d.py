"""calibrators.io.mmdet3d: MMDetection3D `pred_instances_3d` saved as NPZ arrays.

Fixtures are arrays in the layout of `LiDARInstance3DBoxes.tensor` (x y z dx dy dz yaw
[vx vy], z at the bottom centre), `scores_3d` and 0-based `labels_3d`, written by hand with
`np.savez` as a user saves them from `Det3DDataSample.pred_instances_3d`.
"""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibrators.core.errors import FieldError
from calibrators.io import load_dump
from calibrators.io.mmdet3d import load_mmdet3d
from tests.calibrators.io.reader_checks import (
    assert_reads_or_refuses,
    assert_same_content,
    npz_round_trip,
)

CLASSES = np.array(["car", "pedestrian", "cyclist"])


def predictions(**extra):
    arrays = dict(
        classes=CLASSES, sample_idx=np.array([7, 3, 7]),
        bboxes_3d=np.array([[10.0, 2.0, -1.8, 4.2, 1.8, 1.6, 0.5],
                            [4.0, -1.0, -1.6, 0.6, 0.7, 1.7, -1.0],
                            [25.0, 8.0, -1.7, 1.8, 0.6, 1.7, 3.0]], np.float32),
        scores_3d=np.array([0.8, 0.4, 0.6], np.float32), labels_3d=np.array([0, 1, 2]))
    arrays.update(extra)
    return arrays


def save(tmp_path, name, arrays):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def test_fields_and_bottom_centre(tmp_path):
    dump = load_mmdet3d(save(tmp_path, "pred.npz", predictions()))
    assert dump.classes == ("car", "pedestrian", "cyclist")
    assert dump.frame_ids.tolist() == ["3", "7"]
    # x y z dx dy dz yaw -> x y z+dz/2 w(=dy) l(=dx) h yaw 0 0
    np.testing.assert_allclose(dump.final_boxes[0], [10.0, 2.0, -1.0, 1.8, 4.2, 1.6, 0.5, 0, 0],
                               atol=1e-6)
    assert dump.det_labels.tolist() == [0, 1, 2]
    np.testing.assert_allclose(dump.det_scores, [0.8, 0.4, 0.6], atol=1e-6)
    assert_same_content(npz_round_trip(dump), dump)


def test_ground_truth_and_frames(tmp_path):
    gt = save(tmp_path, "gt.npz", dict(
        sample_idx=np.array([3, 7, 7]), gt_labels_3d=np.array([1, -1, 0]),
        gt_bboxes_3d=np.array([[4.1, -1.0, -1.6, 0.6, 0.7, 1.7, -1.0, 0.2, 0.0],
                               [9.0, 9.0, -1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0],
                               [10.2, 2.0, -1.8, 4.2, 1.8, 1.6, 0.5, 3.0, 0.1]])))
    pred = save(tmp_path, "pred.npz", predictions(frames=np.array([3, 7, 11])))
    dump = load_mmdet3d(pred, gt)
    assert dump.frame_ids.tolist() == ["11", "3", "7"]  # 11: evaluated, nothing in it
    assert dump.gt_labels.tolist() == [1, 0]  # the -1 row is no class
    np.testing.assert_allclose(dump.gt_boxes[1], [10.2, 2.0, -1.0, 1.8, 4.2, 1.6, 0.5, 3.0, 0.1])
    same = load_dump(pred, format="mmdet3d", ground_truth=gt)
    assert_same_content(same, dump)


def test_class_scores_and_logits(tmp_path):
    cls = np.array([[0.8, 0.1, 0.05], [0.3, 0.4, 0.2], [0.1, 0.7, 0.6]])
    dump = load_mmdet3d(save(tmp_path, "p.npz", predictions(cls_scores_3d=cls)))
    np.testing.assert_allclose(dump.det_logits[:, 0], np.log(cls / (1 - cls)))
    assert dump.det_labels.tolist() == [0, 1, 2]  # row 2's label is not its arg-max: kept
    logits = np.log(cls / (1 - cls))
    dump = load_mmdet3d(save(tmp_path, "q.npz", predictions(cls_logits_3d=logits)))
    np.testing.assert_allclose(dump.det_scores, [0.8, 0.4, 0.6], atol=1e-6)
    with pytest.raises(FieldError, match=r"p2.npz: scores_3d\[0\] = 0.8 but the per-class "
                                         r"arrays give its label 0.05"):
        load_mmdet3d(save(tmp_path, "p2.npz", predictions(cls_scores_3d=cls[:, ::-1])))


@pytest.mark.parametrize("edit, match", [
    (dict(classes=None), r"missing key 'classes'"),
    (dict(scores_3d=None), r"missing key 'scores_3d'"),
    (dict(labels_3d=np.array([0, 1, 3])), r"labels_3d\[2\] = 3 is not an index into the 3"),
    (dict(labels_3d=np.array([0, -1, 2])), r"labels_3d\[1\] = -1 is not an index"),
    (dict(bboxes_3d=np.zeros((3, 8))), r"bboxes_3d must have 7 or 9 columns"),
    (dict(bboxes_3d=np.ones((2, 7))), r"bboxes_3d must have shape \[3, N\]"),
    (dict(scores_3d=np.array([0.5, np.nan, 0.1])), r"scores_3d has NaN or Inf at \[1\]"),
    (dict(scores_3d=np.array([0.5, 1.5, 0.1])), r"pred.npz: scores_3d\[1\] = 1.5 is not a "
                                                r"probability"),
    (dict(sample_idx=np.array([0.5, 1.0, 2.0])), r"sample_idx must be a 1-d array of strings"),
    (dict(box_type_3d=np.array("Camera")), r"box_type_3d is 'Camera'; only LiDAR"),
    (dict(extra=np.zeros(3)), r"unknown key 'extra'"),
    (dict(cls_scores_3d=np.full((3, 3), 0.5), cls_logits_3d=np.zeros((3, 3))), "not both"),
])
def test_malformed_arrays_name_file_and_key(tmp_path, edit, match):
    arrays = {k: v for k, v in predictions(**edit).items() if v is not None}
    with pytest.raises(FieldError, match=match):
        load_mmdet3d(save(tmp_path, "pred.npz", arrays))


def test_malformed_files(tmp_path):
    (tmp_path / "x.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(FieldError, match=r"x.npz: not an NPZ archive"):
        load_mmdet3d(tmp_path / "x.npz")
    obj = predictions(classes=np.array(["car", None, "cyclist"], dtype=object))
    with pytest.raises(FieldError, match=r"o.npz: an array cannot be read"):
        load_mmdet3d(save(tmp_path, "o.npz", obj))
    with pytest.raises(FieldError, match="limit of 100 bytes"):
        load_mmdet3d(save(tmp_path, "p.npz", predictions()), max_bytes=100)
    gt = save(tmp_path, "gt.npz", dict(classes=np.array(["car"]), sample_idx=np.array([3]),
                                       gt_bboxes_3d=np.ones((1, 7)), gt_labels_3d=[0]))
    with pytest.raises(FieldError, match=r"gt.npz: classes differ"):
        load_mmdet3d(save(tmp_path, "p.npz", predictions()), gt)
    with pytest.raises(FieldError, match="format must be one of"):
        load_dump(tmp_path / "p.npz", format="mmdet")


def test_a_header_declaring_terabytes_is_refused_before_allocating(tmp_path):
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)})
    with zipfile.ZipFile(tmp_path / "bomb.npz", "w") as archive:
        archive.writestr("bboxes_3d.npy", header.getvalue() + bytes(64))
    with pytest.raises(FieldError, match=r"bomb.npz: inflates to 8000000000000 bytes"):
        load_mmdet3d(tmp_path / "bomb.npz")


@settings(max_examples=25, deadline=None)
@given(st.permutations(list(range(8))))
def test_order_does_not_change_content(tmp_path_factory, order):
    base = tmp_path_factory.mktemp("mm")
    rng = np.random.default_rng(3)
    arrays = dict(classes=CLASSES, sample_idx=rng.integers(0, 3, 8),
                  bboxes_3d=np.column_stack([rng.uniform(-30, 30, (8, 3)),
                                             rng.uniform(0.5, 4, (8, 3)),
                                             rng.uniform(-3, 3, 8)]),
                  scores_3d=rng.uniform(0.05, 0.95, 8), labels_3d=rng.integers(0, 3, 8))
    shuffled = {k: (v if k == "classes" else v[list(order)]) for k, v in arrays.items()}
    assert_same_content(load_mmdet3d(save(base, "a.npz", shuffled)),
                        load_mmdet3d(save(base, "b.npz", arrays)))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10**6), st.integers(0, 10**6))
def test_damaged_file_is_read_or_refused(tmp_path_factory, cut, flip):
    buf = io.BytesIO()
    np.savez_compressed(buf, **predictions())
    path = tmp_path_factory.mktemp("dmg") / "pred.npz"
    assert_reads_or_refuses(path, buf.getvalue(), cut, flip, load_mmdet3d)
