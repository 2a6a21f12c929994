import numpy as np
import pytest

from calibrators.data import Dump

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


# -- optional multi-hypothesis arrays (group regression heads, seed 001) ------------------

def _hypotheses(n: int = 4, h: int = 3, seed: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    boxes = rng.normal(size=(n, h, 9)) + np.array([3.0, 4.0, 0, 2, 4, 1.5, 0, 0, 0])
    return {"det_hyp_boxes": boxes, "det_hyp_scores": rng.uniform(0, 1.5, size=(n, h))}


def test_hypotheses_are_optional_and_carried_by_selections():
    assert make().det_hyp_boxes is None and make().n_hypotheses == 0
    hyp = _hypotheses()
    d = make(**hyp)
    assert d.n_hypotheses == 3 and d.det_hyp_boxes.dtype == np.float64
    sub = d.select_frames(np.array([False, True, True]))
    np.testing.assert_array_equal(sub.det_hyp_boxes, hyp["det_hyp_boxes"][2:])
    np.testing.assert_array_equal(sub.det_hyp_scores, hyp["det_hyp_scores"][2:])
    keep = np.array([True, False, True, False])
    picked = d.select_detections(keep)
    assert picked.n_detections == 2 and picked.n_frames == 3
    np.testing.assert_array_equal(picked.det_hyp_boxes, hyp["det_hyp_boxes"][keep])
    np.testing.assert_array_equal(picked.det_logits, d.det_logits[keep])


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"det_hyp_boxes": _hypotheses()["det_hyp_boxes"]}, "without det_hyp_scores"),
        ({"det_hyp_scores": _hypotheses()["det_hyp_scores"]}, "without det_hyp_boxes"),
        ({**_hypotheses(), "det_hyp_boxes": np.zeros((4, 3, 7))},
         r"det_hyp_boxes must have shape \[4, H, 9\]"),
        ({**_hypotheses(), "det_hyp_boxes": np.zeros((3, 3, 9))},
         r"det_hyp_boxes must have shape \[4, H, 9\]"),
        ({**_hypotheses(), "det_hyp_scores": np.zeros((4, 2))},
         r"det_hyp_scores must have shape \[4, 3\]"),
        ({**_hypotheses(), "det_hyp_scores": -np.ones((4, 3))}, "negative group score"),
        ({**_hypotheses(), "det_hyp_scores": np.full((4, 3), np.nan)}, "det_hyp_scores has NaN"),
    ],
)
def test_bad_hypotheses_name_the_key(over, message):
    with pytest.raises(ValueError, match=message) as info:
        make(**over)
    assert info.value.field in ("det_hyp_boxes", "det_hyp_scores")


def test_hypotheses_round_trip_through_npz_and_old_dumps_still_load(tmp_path):
    from calibrators.io import load_dump, save_dump

    d = make(**_hypotheses())
    save_dump(tmp_path / "hyp.npz", d)
    back = load_dump(tmp_path / "hyp.npz")
    np.testing.assert_array_equal(back.det_hyp_boxes, d.det_hyp_boxes)
    np.testing.assert_array_equal(back.det_hyp_scores, d.det_hyp_scores)
    save_dump(tmp_path / "old.npz", make())
    with np.load(tmp_path / "old.npz") as z:
        assert "det_hyp_boxes" not in z.files
    assert load_dump(tmp_path / "old.npz").det_hyp_boxes is None


def test_npz_hypothesis_shapes_are_checked_before_reading(tmp_path):
    from calibrators.core.errors import FieldError
    from calibrators.io import load_dump, save_dump

    save_dump(tmp_path / "ok.npz", make(**_hypotheses()))
    with np.load(tmp_path / "ok.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["det_hyp_scores"] = arrays["det_hyp_scores"][:, :2]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FieldError, match=r"det_hyp_scores must have shape \[4, 3\]") as info:
        load_dump(tmp_path / "bad.npz")
    assert info.value.field == "det_hyp_scores"
    arrays["det_hyp_scores"] = arrays["det_hyp_scores"][:3]
    with pytest.raises(FieldError, match="det_hyp_scores has 3 rows but det_logits has 4"):
        np.savez(tmp_path / "bad.npz", **arrays)
        load_dump(tmp_path / "bad.npz")
