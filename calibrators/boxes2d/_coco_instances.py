"""A COCO instances (ground-truth) document: its annotations as `GroundTruth2D`, with the
images (their sizes) and the categories, each field checked as the COCO format gives it
(https://cocodataset.org/#format-data; `_coco_records`).

    {"images": [{"id": int, "width": int, "height": int, ...}],
     "annotations": [{"id": int, "image_id": int, "category_id": int, "bbox": [x, y, w, h],
                      "area": number, "iscrowd": 0 | 1, ...}],
     "categories": [{"id": int, "name": str, ...}], ...}

Read here: image and category ids (distinct), image width and height (integers > 0), category
names, and per annotation its id (distinct), image and category (each one listed), box, area
(>= 0) and `iscrowd` (0 when absent). Segmentations, `info` and `licenses` are not read.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibrators.boxes2d._boxes import GroundTruth2D
from calibrators.boxes2d._coco_records import ints, records, strings
from calibrators.core.checks import as_int_array
from calibrators.core.errors import FieldError

__all__ = ["CocoInstances", "parse_instances"]


@dataclass(frozen=True, eq=False)
class CocoInstances:
    """A COCO instances document (module docstring); rows keep the document's order.

    ground_truth         GroundTruth2D [G]   the annotations; row g is `annotations[g]`
    annotation_id [G]    int64
    image_id [I]         int64               the images, with their size in pixels:
    width, height [I]    int64
    category_id [K]      int64               the categories, with their names
    category_name [K]    tuple of str
    """

    ground_truth: GroundTruth2D
    annotation_id: np.ndarray
    image_id: np.ndarray
    width: np.ndarray
    height: np.ndarray
    category_id: np.ndarray
    category_name: tuple[str, ...]

    def image_rows(self, image_id: np.ndarray, what: str = "image_id") -> np.ndarray:
        """`[N]` row in `image_id` of each of `image_id [N]`; FieldError naming the first that
        is not an image of this document (`what[i]`)."""
        return _rows(self.image_id, as_int_array(what, image_id), what, "images")

    def image_size(self, image_id: np.ndarray) -> np.ndarray:
        """`[N, 2]` float64 (width, height) of the images `image_id [N]`."""
        rows = self.image_rows(image_id)
        return np.stack([self.width[rows], self.height[rows]], axis=1).astype(np.float64)


def parse_instances(document: Mapping[str, Any]) -> CocoInstances:
    """The `CocoInstances` of a parsed instances document; FieldError naming the first bad
    field (`annotations[3].bbox must be 4 finite numbers with w, h >= 0`)."""
    if not isinstance(document, Mapping):
        raise FieldError("instances", "an instances document must be an object with images, "
                                      "annotations and categories")
    lists = {}
    for key in ("images", "annotations", "categories"):
        if key not in document:
            raise FieldError(key, f"the instances document has no {key!r}")
        lists[key] = records(document[key], key)
    images, categories = lists["images"], lists["categories"]
    image_id = _distinct(ints(images, "id", "images"), "images")
    width, height = (_positive(ints(images, key, "images"), key) for key in ("width", "height"))
    category_id = _distinct(ints(categories, "id", "categories"), "categories")
    names = tuple(strings(categories, "name", "categories"))
    annotations = lists["annotations"]
    annotation_id = _distinct(ints(annotations, "id", "annotations"), "annotations")
    truth = GroundTruth2D.from_coco(annotations)
    _rows(image_id, truth.image_id, "image_id", "images", "annotations")
    _rows(category_id, truth.category_id, "category_id", "categories", "annotations")
    return CocoInstances(truth, annotation_id, image_id, width, height, category_id, names)


def _distinct(ids: np.ndarray, what: str) -> np.ndarray:
    """`ids [N]`, or a FieldError naming the first that repeats an earlier one."""
    order = np.argsort(ids, kind="stable")
    repeats = order[1:][ids[order][1:] == ids[order][:-1]]
    if repeats.size:
        i = int(repeats.min())
        first = int(np.flatnonzero(ids == ids[i])[0])
        raise FieldError("id", f"{what}[{i}].id {int(ids[i])} repeats {what}[{first}].id",
                         row=i)
    return ids


def _positive(values: np.ndarray, key: str) -> np.ndarray:
    bad = values <= 0
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError(key, f"images[{i}].{key} must be an integer > 0, got {int(values[i])}",
                         row=i)
    return values


def _rows(known: np.ndarray, ids: np.ndarray, key: str, listed: str,
          what: str | None = None) -> np.ndarray:
    """`[N]` row in `known` of each of `ids`; a FieldError names the first not in it (as
    `what[i].key`, or `key[i]` when `what` is None)."""
    order = np.argsort(known, kind="stable")
    pos = np.clip(np.searchsorted(known[order], ids), 0, max(len(known) - 1, 0))
    bad = np.ones(len(ids), dtype=bool) if len(known) == 0 else known[order][pos] != ids
    if bad.any():
        i = int(np.argmax(bad))
        where = f"{key}[{i}]" if what is None else f"{what}[{i}].{key}"
        raise FieldError(key, f"{where} {int(ids[i])} is not the id of any of the {listed}",
                         row=i)
    return order[pos] if len(known) else np.zeros(0, dtype=np.int64)
