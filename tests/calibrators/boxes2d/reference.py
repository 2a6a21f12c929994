"""pycocotools as the reference of the boxes2d tests: COCO objects built in memory from dicts,
`COCOeval(iouType='bbox')` run with its prints muted, and the same data as our containers."""

from __future__ import annotations

import contextlib
import copy
import io
from collections.abc import Sequence
from typing import Any

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from calibrators.boxes2d import Detections2D, GroundTruth2D, evaluate_coco


class KeepIgnoreCOCOeval(COCOeval):
    """COCOeval that honours a ground truth's `ignore` key (pycocotools' `_prepare` overwrites
    it with `iscrowd`): the rule `GroundTruth2D.ignore` follows."""

    def _prepare(self) -> None:
        super()._prepare()
        for anns in self._gts.values():
            for g in anns:
                g["ignore"] = int(bool(g["iscrowd"]) or bool(g.get("keep_ignore", 0)))


def coco_dataset(annotations: Sequence[dict[str, Any]], image_ids: Sequence[int],
                 category_ids: Sequence[int]) -> dict[str, Any]:
    """A COCO ground-truth dataset dict; annotations get ids 1, 2, ... (pycocotools counts a
    match to id 0 as none)."""
    anns = [{**a, "id": i + 1} for i, a in enumerate(annotations)]
    return {"images": [{"id": int(i)} for i in image_ids], "annotations": anns,
            "categories": [{"id": int(c)} for c in category_ids]}


def run_pycocotools(dataset: dict[str, Any], results: Sequence[dict[str, Any]],
                    keep_ignore: bool = False) -> COCOeval:
    """evaluate + accumulate + summarize on deep copies (pycocotools edits its input)."""
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = copy.deepcopy(dataset)
        gt.createIndex()
        dt = gt.loadRes(copy.deepcopy(list(results)))
        evaluator = (KeepIgnoreCOCOeval if keep_ignore else COCOeval)(gt, dt, "bbox")
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return evaluator


def run_ours(dataset: dict[str, Any], results: Sequence[dict[str, Any]], **kwargs: Any):
    """`evaluate_coco` on the same dicts, over the dataset's images and categories."""
    gt = GroundTruth2D.from_coco(dataset["annotations"])
    if any("keep_ignore" in a for a in dataset["annotations"]):
        gt = GroundTruth2D(gt.image_id, gt.category_id, gt.bbox, gt.area, gt.iscrowd,
                           [bool(a.get("keep_ignore", 0)) for a in dataset["annotations"]])
    kwargs.setdefault("image_ids", [i["id"] for i in dataset["images"]])
    kwargs.setdefault("category_ids", [c["id"] for c in dataset["categories"]])
    return evaluate_coco(Detections2D.from_coco(results), gt, **kwargs)


def assert_same(ours, evaluator: COCOeval, tol: float = 1e-9) -> None:
    """Stats, precision and recall within `tol` of pycocotools' (same shapes)."""
    np.testing.assert_allclose(ours.stats, evaluator.stats, rtol=0, atol=tol)
    np.testing.assert_allclose(ours.precision, evaluator.eval["precision"], rtol=0, atol=tol)
    np.testing.assert_allclose(ours.recall, evaluator.eval["recall"], rtol=0, atol=tol)
