import numpy as np
import pytest

from calibrators.dump import Dump

CLASSES = ("car", "pedestrian")


def make(**over):
    rng = np.random.default_rng(1)
    fields = dict(
        classes=CLASSES,
        score_mode="sigmoid",
        frame_ids=np.array(["a", "b", "c"]),
        det_frame=np.array([0, 0, 1, 2]),
        det_logits=rng.normal(size=(4, 2, 2)),
        det_boxes=rng.normal(size=(4, 2, 9)) + np.array([3.0, 4.0, 0, 2, 4, 1.5, 0, 0, 0]),
        gt_frame=np.array([0, 2]),
        gt_labels=np.array([0, 1]),
        gt_boxes=rng.normal(size=(2, 9)),
    )
    fields.update(over)
    return Dump(**fields)


def test_derived_views():
    d = make(ego_translation=np.array([[1.0, 1.0, 0.0], [0, 0, 0], [0, 0, 0]]))
    assert d.n_detections == 4 and d.n_layers == 2 and d.n_frames == 3
    xy = d.final_boxes[:, :2] - np.array([[1, 1], [1, 1], [0, 0], [0, 0]])
    np.testing.assert_allclose(d.det_distance, np.hypot(xy[:, 0], xy[:, 1]))
    assert d.det_labels.tolist() == np.argmax(d.det_logits[:, -1], axis=1).tolist()


def test_select_frames_reindexes():
    d = make()
    sub = d.select_frames(np.array([False, True, True]))
    assert sub.frame_ids.tolist() == ["b", "c"]
    assert sub.det_frame.tolist() == [0, 1]
    assert sub.gt_frame.tolist() == [1]
    np.testing.assert_array_equal(sub.det_logits, d.det_logits[2:])


def test_covariance_dims_and_psd():
    cov = np.tile(np.eye(2), (4, 1, 1))
    assert make(det_cov=cov).cov_dims == ("x", "y")
    bad = cov.copy()
    bad[2] = [[1.0, 2.0], [2.0, 1.0]]
    with pytest.raises(ValueError, match=r"det_cov\[2\] is not positive semi-definite"):
        make(det_cov=bad)


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"det_logits": np.zeros((4, 2, 3))}, "det_logits has 3 columns"),
        ({"score_mode": "softmax"}, "softmax mode with 2 classes needs 3"),
        ({"det_boxes": np.zeros((4, 2, 7))}, "det_boxes must have shape"),
        ({"det_frame": np.array([0, 0, 1, 3])}, r"det_frame\[3\] = 3 is out of range"),
        ({"gt_labels": np.array([0, 2])}, r"gt_labels\[1\] = 2 is out of range for 2 classes"),
        ({"gt_frame": np.array([0])}, "gt_frame has 1 rows but gt_boxes has 2"),
        ({"gt_boxes": np.full((2, 9), np.inf)}, "gt_boxes has Inf"),
        ({"frame_ids": np.array(["a", "a", "c"])}, "frame_ids has duplicate"),
        ({"classes": ("car", "car")}, "classes has duplicate"),
        ({"ego_translation": np.zeros((3, 2))}, "ego_translation must have shape"),
        ({"cov_dims": ("x", "q")}, "cov_dims must be one of"),
    ],
)
def test_bad_dumps_name_the_key(over, message):
    with pytest.raises(ValueError, match=message):
        make(**over)


def test_nan_logit_is_located():
    logits = np.zeros((4, 2, 2))
    logits[3, 1, 0] = np.nan
    with pytest.raises(ValueError, match=r"det_logits has NaN at index \[3, 1, 0\]"):
        make(det_logits=logits)
