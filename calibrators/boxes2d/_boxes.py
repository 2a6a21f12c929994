"""`Detections2D` and `GroundTruth2D`: image-plane boxes in COCO form, validated once.

Shapes (N detections, G ground-truth boxes):

    Detections2D
        image_id     [N] int64     the image of each detection
        category_id  [N] int64     its category
        bbox         [N, 4] float  COCO `x, y, w, h` in pixels: top-left corner, width, height
        score        [N] float     confidence; higher ranks first
        logits       [N, C'] float the detector's class logits (None: not given); their columns
                                   follow a class list the caller states (`score_inputs`)
        layer_boxes  [N, L, 4]     the box `x, y, w, h` of every decoder layer (None: not
                     float         given), each obeying the box rules

    GroundTruth2D
        image_id     [G] int64
        category_id  [G] int64
        bbox         [G, 4] float  COCO `x, y, w, h` in pixels
        area         [G] float     the object's area (px²) that the area ranges test; in COCO
                                   the segmentation's area, not `w·h` (None: `w·h`)
        iscrowd      [G] bool      a crowd region: matches any number of detections, by the
                                   fraction of the detection inside it, and is never counted
        ignore       [G] bool      ignored like a crowd, but matched as an ordinary box (None:
                                   all False). pycocotools overwrites a COCO `ignore` key with
                                   `iscrowd`, so `from_coco` does not read it

Rules: every number finite; `w, h >= 0`; a box's right and bottom edges `x + w`, `y + h` and
its area `w·h` representable (finite, and not 0 unless `w` or `h` is): without that, an IoU
would be NaN where pycocotools' C code silently compares NaN. Ground-truth `area >= 0`.
A bad field raises `FieldError` naming it, with the row when one row is at fault.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from calibrators.boxes2d._coco_records import (
    at_record,
    boxes,
    flags,
    ints,
    layer_boxes,
    numbers_of,
    records,
    vectors,
)
from calibrators.core.checks import as_float_array, as_int_array, check_index, check_length
from calibrators.core.errors import FieldError

__all__ = ["Detections2D", "GroundTruth2D"]


@dataclass(frozen=True, eq=False)
class Detections2D:
    """N detected boxes (module docstring: shapes and rules)."""

    image_id: np.ndarray
    category_id: np.ndarray
    bbox: np.ndarray
    score: np.ndarray
    logits: np.ndarray | None = None
    layer_boxes: np.ndarray | None = None

    def __post_init__(self) -> None:
        image_id = as_int_array("image_id", self.image_id)
        n = len(image_id)
        _set(self, "image_id", image_id)
        _set(self, "category_id", _ids("category_id", self.category_id, n))
        _set(self, "bbox", check_bbox("bbox", self.bbox, n))
        score = as_float_array("score", self.score, ndim=1)
        check_length("score", score, n, "image_id")
        _set(self, "score", score)
        if self.logits is not None:
            logits = as_float_array("logits", self.logits, ndim=2)
            check_length("logits", logits, n, "image_id")
            if logits.shape[1] == 0:
                raise FieldError("logits", "logits must have at least one column")
            _set(self, "logits", logits)
        if self.layer_boxes is not None:
            _set(self, "layer_boxes", check_layer_boxes(self.layer_boxes, n))

    def __len__(self) -> int:
        return len(self.image_id)

    def take(self, rows: object) -> Detections2D:
        """The detections at `rows` (int indices `[M]` or a bool mask `[N]`), in that order."""
        return _take(self, rows)

    @classmethod
    def from_coco(cls, results: Sequence[Mapping[str, Any]]) -> Detections2D:
        """Detections from a COCO results list: `image_id`, `category_id`, `bbox`, `score`
        per detection, and optionally `logits` (C' numbers) and `layer_boxes` (L boxes) in
        every record or none; other keys are ignored. Each value is checked as the COCO format
        types it (`_coco_records`); a bad one raises FieldError naming the record and key."""
        rows = records(results, "results")
        what = "results"
        try:
            return cls(ints(rows, "image_id", what), ints(rows, "category_id", what),
                       boxes(rows, "bbox", what), numbers_of(rows, "score", what),
                       vectors(rows, "logits", what), layer_boxes(rows, "layer_boxes", what))
        except FieldError as exc:
            raise at_record(exc, what) from None


@dataclass(frozen=True, eq=False)
class GroundTruth2D:
    """G ground-truth boxes (module docstring: shapes and rules)."""

    image_id: np.ndarray
    category_id: np.ndarray
    bbox: np.ndarray
    area: np.ndarray | None = None
    iscrowd: np.ndarray | None = None
    ignore: np.ndarray | None = None

    def __post_init__(self) -> None:
        image_id = as_int_array("image_id", self.image_id)
        n = len(image_id)
        _set(self, "image_id", image_id)
        _set(self, "category_id", _ids("category_id", self.category_id, n))
        bbox = check_bbox("bbox", self.bbox, n)
        _set(self, "bbox", bbox)
        if self.area is None:
            area = bbox[:, 2] * bbox[:, 3]
        else:
            area = as_float_array("area", self.area, ndim=1)
            check_length("area", area, n, "image_id")
            _nonnegative("area", area)
        _set(self, "area", area)
        _set(self, "iscrowd", check_flags("iscrowd", self.iscrowd, n))
        _set(self, "ignore", check_flags("ignore", self.ignore, n))

    def __len__(self) -> int:
        return len(self.image_id)

    def take(self, rows: object) -> GroundTruth2D:
        """The boxes at `rows` (int indices `[M]` or a bool mask `[G]`), in that order."""
        return _take(self, rows)

    @classmethod
    def from_coco(cls, annotations: Sequence[Mapping[str, Any]]) -> GroundTruth2D:
        """Ground truth from a COCO `annotations` list: `image_id`, `category_id`, `bbox`,
        `area` (>= 0) and `iscrowd` (0 or 1; 0 when absent) per box, the fields pycocotools
        reads, each checked as `Detections2D.from_coco` checks its fields."""
        rows = records(annotations, "annotations")
        what = "annotations"
        try:
            return cls(ints(rows, "image_id", what), ints(rows, "category_id", what),
                       boxes(rows, "bbox", what), numbers_of(rows, "area", what, low=0.0),
                       flags(rows, "iscrowd", what, default=0))
        except FieldError as exc:
            raise at_record(exc, what) from None


def check_bbox(name: str, value: object, n: int | None, other: str = "image_id") -> np.ndarray:
    """`value` as `[n, 4]` float64 COCO boxes obeying the module's rules (`n` rows, the row
    count of `other`; any number if None), or a FieldError."""
    arr = as_float_array(name, value)
    if arr.size == 0 and arr.ndim <= 2 and n in (0, None):
        return np.zeros((0, 4))
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise FieldError(name, f"{name} must have shape [N, 4] (x, y, w, h), got {arr.shape}")
    if n is not None:
        check_length(name, arr, n, other)
    x, y, w, h = arr.T
    for label, bad in (("a negative width", w < 0), ("a negative height", h < 0)):
        _raise_first(name, bad, label)
    with np.errstate(over="ignore", under="ignore"):
        right, bottom, area = x + w, y + h, w * h
    _raise_first(name, ~(np.isfinite(right) & np.isfinite(bottom)),
                 "an edge x + w or y + h beyond the float range")
    _raise_first(name, ~np.isfinite(area) | ((area == 0) & (w > 0) & (h > 0)),
                 "an area w·h that over- or underflows")
    return arr


def check_layer_boxes(value: object, n: int) -> np.ndarray:
    """`value` as `[n, L, 4]` float64 boxes (L >= 1) each obeying the module's rules, or a
    FieldError naming `layer_boxes[i][l]`."""
    arr = as_float_array("layer_boxes", value, ndim=3)
    if arr.shape[2] != 4 or arr.shape[1] == 0:
        raise FieldError("layer_boxes", f"layer_boxes must have shape [N, L, 4] with L >= 1, "
                                        f"got {arr.shape}")
    check_length("layer_boxes", arr, n, "image_id")
    try:
        check_bbox("layer_boxes", arr.reshape(-1, 4), None)
    except FieldError as exc:
        if exc.row is None:
            raise
        i, layer = divmod(exc.row, arr.shape[1])
        text = str(exc).replace(f"layer_boxes[{exc.row}]", f"layer_boxes[{i}][{layer}]", 1)
        raise FieldError("layer_boxes", text, row=i) from None
    return arr


def _ids(name: str, value: object, n: int) -> np.ndarray:
    arr = as_int_array(name, value)
    check_length(name, arr, n, "image_id")
    return arr


def check_flags(name: str, value: object, n: int, other: str = "image_id") -> np.ndarray:
    """`[n]` bool from bools or 0/1 numbers, `n` the row count of `other` (None: all False)."""
    if value is None:
        return np.zeros(n, dtype=bool)
    arr = np.asarray(value)
    if arr.ndim != 1:
        raise FieldError(name, f"{name} must have 1 dimension, got shape {arr.shape}")
    check_length(name, arr, n, other)
    if arr.dtype == bool:
        return arr
    num = as_float_array(name, arr, ndim=1)
    _raise_first(name, (num != 0) & (num != 1), "a value other than 0, 1, True or False")
    return num == 1


def _nonnegative(name: str, arr: np.ndarray) -> None:
    _raise_first(name, arr < 0, "a negative value")


def _raise_first(name: str, bad: np.ndarray, what: str) -> None:
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError(name, f"{name}[{i}] has {what}", row=i)


def _take(boxes: Any, rows: object) -> Any:
    """A container of the same type holding `boxes`' rows `rows` (indices or a bool mask)."""
    index = np.asarray(rows)
    if index.dtype == bool:
        if index.shape != (len(boxes),):
            raise FieldError("rows", f"a row mask must have shape [{len(boxes)}], got "
                                     f"{index.shape}")
        index = np.flatnonzero(index)
    index = as_int_array("rows", index)
    check_index("rows", index, len(boxes), "rows")
    return type(boxes)(**{f.name: None if getattr(boxes, f.name) is None
                          else getattr(boxes, f.name)[index] for f in fields(boxes)})


def _set(obj: object, name: str, value: np.ndarray) -> None:
    object.__setattr__(obj, name, value)
