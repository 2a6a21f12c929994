"""COCO files into the 2-D containers: a results JSON into `Detections2D`, an instances JSON
into `CocoInstances` (its annotations as `GroundTruth2D`, the images and categories).

A file larger than `max_bytes` (default `MAX_COCO_BYTES`) is refused from its size before
a byte of it is parsed; so is JSON that is not valid or not strict (`NaN`, `Infinity`), or
nested too deep for the parser. Every field is then checked as the COCO format gives it
(`_coco_records`); every error is a `FieldError` naming the file's role and, for a bad
field, the record and key (`results[3].score must be a number in [0, 1], got 1.5`).
Messages never show the file's path.
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from calibrators.boxes2d._boxes import Detections2D
from calibrators.boxes2d._coco_instances import CocoInstances, parse_instances
from calibrators.core.errors import FieldError
from calibrators.io.reader_files import ByteBudget

__all__ = ["MAX_COCO_BYTES", "read_coco_instances", "read_coco_results"]

#: Largest COCO file read by default (bytes); `max_bytes=` changes it.
MAX_COCO_BYTES = 512 * 2**20


def read_coco_results(path: str | os.PathLike[str], *, max_bytes: int | None = None,
                      instances: CocoInstances | None = None) -> Detections2D:
    """The detections of a COCO results file: a list of `{"image_id", "category_id", "bbox",
    "score"}` (score in [0, 1]), each optionally with `logits` (C' numbers) and `layer_boxes`
    (L boxes `[x, y, w, h]`), in every record or none. With `instances`, every image must be
    one of its images (as pycocotools' `loadRes` requires). Row i is record i."""
    document = load_json(path, "results", max_bytes)
    detections = Detections2D.from_coco(document)
    bad = (detections.score > 1.0) | (detections.score < 0.0)
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError("score", f"results[{i}].score must be a number in [0, 1], got "
                                  f"{detections.score[i]!r}", row=i)
    if instances is not None:
        try:
            instances.image_rows(detections.image_id)
        except FieldError as exc:
            raise FieldError("image_id", f"results[{exc.row}].image_id "
                             f"{int(detections.image_id[exc.row or 0])} is not the id of any "
                             "image of the instances", row=exc.row) from None
    return detections


def read_coco_instances(path: str | os.PathLike[str], *, max_bytes: int | None = None
                        ) -> CocoInstances:
    """The ground truth, images and categories of a COCO instances file (`parse_instances`)."""
    return parse_instances(load_json(path, "instances", max_bytes))


def load_json(path: str | os.PathLike[str], what: str, max_bytes: int | None) -> Any:
    """The parsed JSON of the file at `path` (the `what` file), bounded (module docstring)."""
    data = ByteBudget(MAX_COCO_BYTES if max_bytes is None else max_bytes).read(path, what)
    try:
        return json.loads(data, parse_constant=_no_constant)
    except (ValueError, RecursionError) as exc:  # bad JSON, bad UTF-8, NaN, too deep
        raise FieldError(what, f"{what}: not valid JSON: {_reason(exc)}") from None


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _reason(exc: BaseException) -> str:
    if isinstance(exc, RecursionError):
        return "nested too deep"
    return str(exc)[:200]
