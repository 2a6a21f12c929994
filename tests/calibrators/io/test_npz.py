"""calibrators.io: validation dump v1 NPZ (the nuScenes JSON pair: test_nuscenes_*.py)."""

from __future__ import annotations

import hashlib
import io
import tracemalloc

import numpy as np
import pytest

from calibrators.core.errors import FieldError
from calibrators.io import (
    file_sha256,
    load_dump,
    save_dump,
)
from calibrators.io.npz import OPTIONAL_KEYS, REQUIRED_KEYS
from tests.calibrators.io.dump_cases import CLASSES, arrays, assert_same, hostile_npz, write


@pytest.mark.parametrize("optional", [True, False])
@pytest.mark.parametrize("mode", ["sigmoid", "softmax"])
def test_npz_round_trip(tmp_path, optional, mode):
    dump = load_dump(write(tmp_path / "a.npz", arrays(mode=mode, optional=optional)))
    target = tmp_path / "copy.dump"  # no .npz suffix appended
    save_dump(target, dump)
    assert target.exists() and not (tmp_path / "copy.dump.npz").exists()
    assert_same(load_dump(target), dump)
    assert (dump.det_cov is None) != optional


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_every_missing_key_is_refused(tmp_path, key):
    content = arrays()
    del content[key]
    with pytest.raises(ValueError, match=f"missing key '{key}'"):
        load_dump(write(tmp_path / "a.npz", content))


def test_optional_keys_may_be_absent(tmp_path):
    content = arrays()
    for key in OPTIONAL_KEYS:
        content.pop(key, None)
    dump = load_dump(write(tmp_path / "a.npz", content))
    assert dump.ego_translation is None and dump.det_cov is None and dump.cov_dims == ("x", "y")
    assert dump.det_label is None


def test_unknown_key_is_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown key 'det_covs'"):
        load_dump(write(tmp_path / "a.npz", {**arrays(), "det_covs": np.zeros(3)}))


@pytest.mark.parametrize("key, value, message", [
    ("det_boxes", lambda a: a["det_boxes"][..., :8], "det_boxes must have shape"),
    ("det_logits", lambda a: a["det_logits"][..., :2], "det_logits has 2 columns"),
    ("det_logits", lambda a: a["det_logits"][:, 0], "det_logits must have 3 dimensions"),
    ("gt_boxes", lambda a: a["gt_boxes"][:, :7], "gt_boxes must have shape"),
    ("gt_labels", lambda a: a["gt_labels"][:-1], "gt_labels has 4 rows"),
    ("det_frame", lambda a: a["det_frame"][:, None], "det_frame must have 1 dimensions"),
    ("ego_translation", lambda a: a["ego_translation"][:, :2], "ego_translation must have shape"),
    ("det_cov", lambda a: a["det_cov"][:, :1, :1], r"det_cov must have shape \[12, 2, 2\]"),
    ("det_frame", lambda a: a["det_frame"][:-2], "det_frame has 10 rows but det_logits has 12"),
    ("det_cov", lambda a: a["det_cov"][:-1], "det_cov has 11 rows but det_logits has 12"),
    ("frame_ids", lambda a: a["frame_ids"][:-1], "ego_translation has 3 rows but frame_ids"),
    ("det_logits", lambda a: a["det_logits"] + 1j, "key 'det_logits' is complex"),
    ("det_cov", lambda a: a["det_cov"].astype(np.complex64), "key 'det_cov' is complex"),
    ("gt_boxes", lambda a: a["gt_boxes"].astype("datetime64[s]"),
     "gt_boxes must be a real numeric array"),
    ("score_mode", lambda a: np.array(["sigmoid"]), "score_mode must be a scalar"),
    ("score_mode", lambda a: np.array("logistic"), "score_mode must be one of"),
    ("classes", lambda a: np.arange(3), "classes must be a string array"),
    ("cov_dims", lambda a: np.array(["x", "q"]), "cov_dims must be one of"),
])
def test_wrong_shapes_and_values_are_named(tmp_path, key, value, message):
    content = arrays()
    content[key] = value(content)
    with pytest.raises(ValueError, match=message):
        load_dump(write(tmp_path / "a.npz", content))


@pytest.mark.parametrize("key", ["det_logits", "det_boxes", "gt_boxes", "ego_translation",
                                 "det_cov"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_and_inf_are_named(tmp_path, key, bad):
    content = arrays()
    content[key] = content[key].copy()
    content[key].reshape(-1)[3] = bad
    with pytest.raises(ValueError, match=f"{key} has (NaN|Inf)"):
        load_dump(write(tmp_path / "a.npz", content))


@pytest.mark.parametrize("key, value", [("det_frame", 3), ("gt_frame", -1), ("gt_labels", 3)])
def test_index_out_of_range_is_named(tmp_path, key, value):
    content = arrays()
    content[key] = content[key].copy()
    content[key][1] = value
    with pytest.raises(ValueError, match=rf"{key}\[1\] = {value} is out of range"):
        load_dump(write(tmp_path / "a.npz", content))


def test_pickled_arrays_are_never_loaded(tmp_path):
    content = arrays()
    content["classes"] = np.array(list(CLASSES), dtype=object)  # needs pickle
    with pytest.raises(ValueError, match="key 'classes' cannot be read without unpickling"):
        load_dump(write(tmp_path / "a.npz", content))


def test_not_an_archive(tmp_path):
    (tmp_path / "x.npz").write_text("hello")
    with pytest.raises(ValueError, match="not an NPZ archive: not a zip file") as err:
        load_dump(tmp_path / "x.npz")
    assert str(tmp_path) not in str(err.value) and "pickle" not in str(err.value)
    np.save(tmp_path / "y.npy", np.zeros(3))
    with pytest.raises(ValueError, match="single array"):
        load_dump(tmp_path / "y.npy")


def test_bytes_strings_are_accepted(tmp_path):
    content = arrays()
    content["classes"] = np.array([c.encode() for c in CLASSES])
    assert load_dump(write(tmp_path / "a.npz", content)).classes == CLASSES


def load_traced(data: bytes, **kw) -> tuple[BaseException, int]:
    """The error `load_dump` raises on `data` and the peak bytes it allocated meanwhile."""
    tracemalloc.start()
    try:
        load_dump(io.BytesIO(data), **kw)
    except ValueError as exc:
        return exc, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    raise AssertionError("load_dump accepted a hostile file")


def test_huge_declared_shape_is_refused_before_allocating():
    data = hostile_npz(arrays(), {"det_logits": ((10**12, 3, 10), "<f8", 0)})
    exc, peak = load_traced(data)
    assert isinstance(exc, FieldError) and exc.field == "det_logits"
    assert "(1000000000000, 3, 10)" in str(exc) and "limit" in str(exc)
    assert peak < 2**20


def test_deflated_zeros_over_the_limit_are_not_inflated():
    """The bomb of the issue, scaled down: 9.6 MB of zeros in det_logits (9 kB deflated)
    against max_bytes = 1 MiB, by its .npy header and by the zip's declared size alone."""
    by_header = hostile_npz(arrays(), {"det_logits": ((40_000, 3, 10), "<f8", 9_600_000)})
    assert len(by_header) < 100_000
    exc, peak = load_traced(by_header, max_bytes=2**20)
    assert exc.field == "det_logits" and "more than the limit of 1048576 bytes" in str(exc)
    assert peak < 2**19
    # an honest header followed by 9.6 MB of trailing zeros: the zip declares the size
    trailing = hostile_npz(arrays(), {"det_logits": ((12, 2, 3), "<f8", 9_600_000)})
    exc, peak = load_traced(trailing, max_bytes=2**20)
    assert exc.field == "det_logits" and "inflates to" in str(exc)
    assert peak < 2**19


def test_total_size_and_truncated_members():
    exc, _ = load_traced(hostile_npz(arrays()), max_bytes=3000)  # each key fits, not all
    assert "inflates to" in str(exc) and "limit of 3000 bytes" in str(exc)
    exc, _ = load_traced(hostile_npz(arrays(), {"det_boxes": ((12, 2, 9), "<f8", 10)}))
    assert exc.field == "det_boxes" and "declares shape (12, 2, 9)" in str(exc)
    with pytest.raises(ValueError, match="max_bytes must be a positive integer"):
        load_dump(io.BytesIO(hostile_npz(arrays())), max_bytes=0)


def test_fortran_order_and_big_endian_arrays_are_read(tmp_path):
    content = arrays()
    expected = load_dump(write(tmp_path / "a.npz", content))
    content["det_logits"] = np.asfortranarray(content["det_logits"])
    content["det_boxes"] = content["det_boxes"].astype(">f8")
    assert_same(load_dump(io.BytesIO(hostile_npz(content))), expected)


def test_npz_through_a_file_object(tmp_path):
    dump = load_dump(write(tmp_path / "a.npz", arrays()))
    buf = io.BytesIO()
    save_dump(buf, dump)
    assert_same(load_dump(io.BytesIO(buf.getvalue())), dump)
    with pytest.raises(ValueError, match="not an NPZ archive: not a zip file"):
        load_dump(io.BytesIO(b"garbage"))


def test_file_sha256(tmp_path):
    path = tmp_path / "blob"
    data = np.random.default_rng(0).bytes(3_000_000)
    path.write_bytes(data)
    assert file_sha256(path) == hashlib.sha256(data).hexdigest()
