"""The detector's outputs on a split as COCO files, and COCO AP per class (pycocotools).

`dump_coco(model, split, n, out_dir)` writes, for the first `n` scenes of `split`:

- `instances.json`: the COCO instances ground truth (`detectors.sim.coco_instances`, its
  image ids: one image per scene and camera);
- `results.json`: a COCO results list, one record per detection with `image_id`,
  `category_id`, `bbox` (x y w h pixels), `score` (sigmoid), and for calibration `logits
  [C]`, `layer_logits [L, C]`, `layer_boxes [L, 4]` (`decode.decode_image`), `query`.

`coco_ap(instances, results)` runs pycocotools' COCOeval (bbox) and returns AP, AP50 and
AP75 per class and over all classes (`"all"`: COCO's mean over the classes).
"""

from __future__ import annotations

import contextlib
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from detectors.boxer2d.data import frame_inputs
from detectors.boxer2d.decode import decode_image
from detectors.boxer2d.model import Boxer2D
from detectors.sim import coco_instances, make_image_frame, split_seeds


@dataclass(frozen=True)
class DumpFiles:
    """What `dump_coco` wrote, and the mean time per frame (render + forward + decode)."""

    instances: Path
    results: Path
    seconds_per_frame: float


@torch.no_grad()
def dump_coco(model: Boxer2D, split: str, n: int, out_dir: str | Path,
              max_dets: int = 100, instances: dict[str, Any] | None = None) -> DumpFiles:
    """Write `instances.json` and `results.json` of the first `n` scenes of `split` into
    `out_dir` (module docstring); returns their paths. `instances`: the COCO instances of
    the same scenes when already at hand (rendering them again costs as much as the
    detector's own pass)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if instances is None:
        instances = coco_instances(split, n)
    elif instances["info"]["split"] != split or instances["info"]["scenes"] != n:
        raise ValueError(f"instances are of {instances['info']['scenes']} "
                         f"{instances['info']['split']} scenes, not {n} {split} scenes")
    ids = {(img["scene_seed"], img["camera"]): img["id"] for img in instances["images"]}
    model.eval()
    results: list[dict[str, Any]] = []
    start = time.perf_counter()
    for seed in split_seeds(split, n):
        frame = make_image_frame(seed)
        outputs = model(frame_inputs(frame.images, model.config))
        for camera in range(outputs["pred_logits"].shape[1]):
            for det in decode_image(outputs, camera, model.config, max_dets):
                results.append({"image_id": ids[(seed, camera)], **det})
    per_frame = (time.perf_counter() - start) / max(1, n)
    paths = out / "instances.json", out / "results.json"
    paths[0].write_text(json.dumps(instances), encoding="utf-8")
    paths[1].write_text(json.dumps(results), encoding="utf-8")
    return DumpFiles(instances=paths[0], results=paths[1], seconds_per_frame=per_frame)


def coco_ap(instances: str | Path, results: str | Path) -> dict[str, dict[str, float]]:
    """`{class name or "all": {"AP", "AP50", "AP75", "n_gt"}}` by pycocotools (bbox, all
    areas, 100 detections per image); a class without ground truth gets NaN."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    # only the COCO fields: pycocotools copies every record, the calibration fields are
    # ~90 % of a record and made loading 500 scenes' results take minutes
    dets = [{k: r[k] for k in ("image_id", "category_id", "bbox", "score")}
            for r in json.loads(Path(results).read_text(encoding="utf-8"))]
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO(str(instances))
        if not dets:
            raise ValueError(f"{results} holds no detections")
        ev = COCOeval(gt, gt.loadRes(dets), "bbox")
        ev.evaluate()
        ev.accumulate()
    precision = ev.eval["precision"][:, :, :, 0, -1]            # [T, R, K] all areas, 100
    table = {}
    for k, cat in enumerate(ev.params.catIds):
        name = gt.cats[cat]["name"]
        table[name] = {**_ap(precision[:, :, k]),
                       "n_gt": len(gt.getAnnIds(catIds=[cat], iscrowd=False))}
    table["all"] = {key: float(np.nanmean([row[key] for row in table.values()]))
                    for key in ("AP", "AP50", "AP75")}
    table["all"]["n_gt"] = len(gt.getAnnIds())
    return table


def _ap(precision: np.ndarray) -> dict[str, float]:
    """AP (mean over IoU 0.50:0.95), AP50, AP75 of one class's `[T, R]` precision."""
    def mean(p: np.ndarray) -> float:
        valid = p[p > -1]
        return float(valid.mean()) if valid.size else float("nan")

    return {"AP": mean(precision), "AP50": mean(precision[0]), "AP75": mean(precision[5])}
