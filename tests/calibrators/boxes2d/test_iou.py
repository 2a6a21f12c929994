"""box_iou: pycocotools' maskUtils.iou for boxes, bit for bit, crowd rule included."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pycocotools import mask as mask_utils

from calibrators.boxes2d import box_iou
from calibrators.core.errors import FieldError


def test_hand_values():
    dt = [[0, 0, 10, 10], [5, 0, 10, 10], [20, 20, 1, 1]]
    gt = [[0, 0, 10, 10], [0, 0, 100, 100]]
    iou = box_iou(dt, gt, [False, True])
    # [5, 0, 10, 10] overlaps the first box on 5 x 10: 50 / (100 + 100 - 50)
    assert iou[:, 0].tolist() == [1.0, 50 / 150, 0.0]
    # a crowd region: the fraction of the detection inside it
    assert iou[:, 1].tolist() == [1.0, 1.0, 1.0]
    assert box_iou(dt, gt)[0, 1] == 100 / 10000


def test_touching_boxes_and_empty_boxes_do_not_overlap():
    iou = box_iou([[0, 0, 10, 10], [0, 0, 0, 10], [3, 3, 0, 0]], [[10, 0, 5, 5], [0, 0, 10, 10]],
                  [False, True])
    assert iou.tolist() == [[0.0, 1.0], [0.0, 0.0], [0.0, 0.0]]


def test_an_empty_side_gives_an_empty_matrix():
    assert box_iou(np.zeros((0, 4)), [[0, 0, 1, 1]]).shape == (0, 1)
    assert box_iou([[0, 0, 1, 1]], []).shape == (1, 0)


def test_bad_input_is_named():
    with pytest.raises(FieldError, match=r"gt\[0\] has a negative width"):
        box_iou([[0, 0, 1, 1]], [[0, 0, -1, 1]])
    with pytest.raises(FieldError, match=r"iscrowd has 2 rows but gt has 1") as info:
        box_iou([[0, 0, 1, 1]], [[0, 0, 1, 1]], [0, 1])
    assert info.value.field == "iscrowd"


coordinate = st.one_of(st.integers(-20, 60).map(float),
                       st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False))
# (a float size below ~1e-154 would make w·h underflow, which the containers refuse)
size = st.one_of(st.integers(0, 40).map(float), st.floats(1e-6, 1e4))
box = st.tuples(coordinate, coordinate, size, size).map(list)


@settings(max_examples=150, deadline=None)
@given(dt=st.lists(box, min_size=1, max_size=8), gt=st.lists(box, min_size=1, max_size=8),
       data=st.data())
def test_equals_mask_iou_bit_for_bit(dt, gt, data):
    crowd = data.draw(st.lists(st.booleans(), min_size=len(gt), max_size=len(gt)))
    expected = mask_utils.iou(dt, gt, [int(c) for c in crowd])
    ours = box_iou(dt, gt, crowd)
    assert ours.shape == expected.shape
    assert ours.tobytes() == np.asarray(expected, dtype=np.float64).tobytes()
