"""Checks the format-reader tests share (test_kitti, test_openpcdet, test_mmdet3d, test_av2)."""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import numpy as np

from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.io import load_dump, save_dump


def per_detection(dump: Dump) -> list[tuple]:
    """Every detection as (frame token, label, final box, final logits), sorted: a dump's
    content per detection, whatever its order."""
    return sorted(
        (str(dump.frame_ids[f]), int(lab), tuple(np.round(box, 9)), tuple(np.round(z, 9)))
        for f, lab, box, z in zip(dump.det_frame, dump.det_labels, dump.final_boxes,
                                  dump.det_logits[:, -1], strict=True))


def per_truth(dump: Dump) -> list[tuple]:
    """Every ground-truth box as (frame token, label, box), sorted."""
    return sorted((str(dump.frame_ids[f]), int(lab), tuple(np.round(box, 9)))
                  for f, lab, box in zip(dump.gt_frame, dump.gt_labels, dump.gt_boxes,
                                         strict=True))


def assert_same_content(a: Dump, b: Dump) -> None:
    """Same classes, frames, detections and ground truth, in any order."""
    assert a.classes == b.classes and a.score_mode == b.score_mode
    np.testing.assert_array_equal(a.frame_ids, b.frame_ids)
    assert per_detection(a) == per_detection(b)
    assert per_truth(a) == per_truth(b)


def npz_round_trip(dump: Dump) -> Dump:
    """The dump written as validation dump v1 and read back."""
    buf = io.BytesIO()
    save_dump(buf, dump)
    buf.seek(0)
    return load_dump(buf)


def assert_reads_or_refuses(path: Path, data: bytes, cut: int, flip: int,
                            load: Callable[[Path], Dump]) -> None:
    """`data` cut after `cut` bytes with the byte at `flip` changed, written to `path`: the
    reader gives a Dump or a FieldError naming the file, never another exception."""
    damaged = bytearray(data[:cut % (len(data) + 1)])
    if damaged:
        damaged[flip % len(damaged)] ^= 0x5A
    path.write_bytes(bytes(damaged))
    try:
        assert isinstance(load(path), Dump)
    except FieldError as exc:
        assert path.name in str(exc), str(exc)
