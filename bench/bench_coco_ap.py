"""COCO box AP: `calibrators.boxes2d.evaluate_coco` against pycocotools' `COCOeval`, same data,
same run.

Synthetic COCO-format set: 5,000 images of 640 x 480, 10 categories, about 7 ground-truth boxes
per image (sizes log-uniform from 8 to 400 px so that small, medium and large all occur; the
`area` field 40-90 % of the box as a segmentation's would be; 1 % crowd) and about 100
detections per image (each ground truth found 0-3 times with jitter, some with the wrong
category, the rest false positives). Scores are rounded to 1e-3 so ties are common and the
tie order is exercised. Seeded.

Reference: pycocotools' `COCOeval(gt, dt, 'bbox')` `evaluate()` + `accumulate()` +
`summarize()`; building its `COCO` objects (`createIndex`, `loadRes`) is not timed. Ours:
`evaluate_coco(detections, ground_truth)` on `Detections2D` / `GroundTruth2D` already built
(`from_coco` on the same dicts is timed apart). Both single-threaded, in the same process.

Run: `.venv/bin/python -m bench.bench_coco_ap` (pycocotools is a dev dependency).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import time
from typing import Any

import numpy as np

from calibrators.boxes2d import STAT_NAMES, Detections2D, GroundTruth2D, evaluate_coco

WIDTH, HEIGHT = 640.0, 480.0


def synthetic_coco(n_images: int = 5000, n_categories: int = 10, gt_per_image: float = 7.0,
                   det_per_image: int = 100, seed: int = 0
                   ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A seeded COCO ground-truth dataset (`images`, `annotations`, `categories`) and a results
    list of about `det_per_image` detections per image."""
    rng = np.random.default_rng(seed)
    n_gt = rng.poisson(gt_per_image, n_images)
    gt_image = np.repeat(np.arange(1, n_images + 1), n_gt)
    g = len(gt_image)
    gt_cat = rng.integers(1, n_categories + 1, g)
    size = np.exp(rng.uniform(np.log(8), np.log(400), (g, 2)))
    xy = rng.uniform(0, 1, (g, 2)) * np.maximum([WIDTH, HEIGHT] - size, 1.0)
    gt_box = np.column_stack([xy, size])
    area = size[:, 0] * size[:, 1] * rng.uniform(0.4, 0.9, g)
    crowd = rng.random(g) < 0.01

    hits = np.repeat(np.arange(g), rng.choice(4, g, p=[0.2, 0.5, 0.2, 0.1]))
    jitter = rng.normal(0, 0.08, (len(hits), 4)) * np.tile(gt_box[hits, 2:], 2)
    tp_box = gt_box[hits] + jitter
    tp_box[:, 2:] = np.abs(tp_box[:, 2:])
    tp_cat = np.where(rng.random(len(hits)) < 0.9, gt_cat[hits],
                      rng.integers(1, n_categories + 1, len(hits)))
    n_fp = np.maximum(det_per_image - np.bincount(gt_image[hits] - 1, minlength=n_images), 0)
    fp_image = np.repeat(np.arange(1, n_images + 1), n_fp)
    fp_size = np.exp(rng.uniform(np.log(4), np.log(400), (len(fp_image), 2)))
    fp_box = np.column_stack([rng.uniform(0, 1, (len(fp_image), 2)) * [WIDTH, HEIGHT],
                              fp_size])
    det_image = np.concatenate([gt_image[hits], fp_image])
    det_cat = np.concatenate([tp_cat, rng.integers(1, n_categories + 1, len(fp_image))])
    det_box = np.concatenate([tp_box, fp_box])
    score = np.round(np.concatenate([rng.beta(5, 2, len(hits)), rng.beta(1, 5, len(fp_image))]),
                     3)
    order = np.lexsort((rng.random(len(det_image)), det_image))  # image by image, shuffled

    annotations = [{"id": i + 1, "image_id": int(gt_image[i]), "category_id": int(gt_cat[i]),
                    "bbox": gt_box[i].tolist(), "area": float(area[i]),
                    "iscrowd": int(crowd[i])} for i in range(g)]
    results = [{"image_id": int(det_image[i]), "category_id": int(det_cat[i]),
                "bbox": det_box[i].tolist(), "score": float(score[i])} for i in order]
    dataset = {"images": [{"id": i, "width": WIDTH, "height": HEIGHT}
                          for i in range(1, n_images + 1)],
               "annotations": annotations,
               "categories": [{"id": c, "name": f"class{c}"} for c in range(1, n_categories + 1)]}
    return dataset, results


def time_ours(dataset: dict[str, Any], results: list[dict[str, Any]], repeat: int
              ) -> tuple[float, float, Any]:
    """Best-of-`repeat` wall time of `evaluate_coco`, of `from_coco` for both sides, and the
    evaluation."""
    best, convert, evaluation = np.inf, np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        dt = Detections2D.from_coco(results)
        gt = GroundTruth2D.from_coco(dataset["annotations"])
        mid = time.perf_counter()
        evaluation = evaluate_coco(dt, gt)
        best = min(best, time.perf_counter() - mid)
        convert = min(convert, mid - start)
    return best, convert, evaluation


def time_pycocotools(dataset: dict[str, Any], results: list[dict[str, Any]]) -> tuple[float, Any]:
    """Wall time of evaluate + accumulate + summarize and the `COCOeval` (prints muted)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = copy.deepcopy(dataset)
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(copy.deepcopy(results))
        evaluator = COCOeval(coco_gt, coco_dt, "bbox")
        start = time.perf_counter()
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
        elapsed = time.perf_counter() - start
    return elapsed, evaluator


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=5000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-write", action="store_true", help="do not touch docs/benchmarks.md")
    args = parser.parse_args(argv)

    dataset, results = synthetic_coco(n_images=args.images)
    size = (f"{args.images:,} images, 10 categories, {len(dataset['annotations']):,} "
            f"ground-truth boxes, {len(results):,} detections")
    print(f"data: {size}")
    ours, convert, evaluation = time_ours(dataset, results, args.repeat)
    print(f"detcal evaluate_coco: {ours:.3f} s (best of {args.repeat}; from_coco {convert:.3f} s)"
          f"; AP {evaluation.stats[0]:.6f}")

    from importlib.metadata import version

    ref, evaluator = time_pycocotools(dataset, results)
    reference = f"pycocotools {version('pycocotools')}"
    stats_diff = float(np.max(np.abs(evaluation.stats - evaluator.stats)))
    prec_diff = float(np.max(np.abs(evaluation.precision - evaluator.eval["precision"])))
    rec_diff = float(np.max(np.abs(evaluation.recall - evaluator.eval["recall"])))
    ratio = ref / ours
    print(f"{reference} evaluate+accumulate+summarize: {ref:.2f} s; AP {evaluator.stats[0]:.6f}")
    print(f"max |stats diff| {stats_diff:.3g}, max |precision diff| {prec_diff:.3g}, "
          f"max |recall diff| {rec_diff:.3g}")
    print(f"speed-up: {ratio:.1f}x (with from_coco: {ref / (ours + convert):.1f}x)")
    if max(stats_diff, prec_diff, rec_diff) > 1e-9:
        raise SystemExit("COCO metrics differ from pycocotools")
    if args.no_write:
        return
    from bench._report import write_section

    stats = " ".join(f"{name} {value:.4f}" for name, value in zip(STAT_NAMES, evaluation.stats,
                                                                   strict=True))
    write_section("coco_ap", "\n".join([
        "## COCO box AP vs pycocotools",
        "",
        f"Synthetic COCO-format set: {size}; box sizes 8-400 px, 1 % crowd, scores rounded to "
        "1e-3 (many ties). `bench/bench_coco_ap.py`.",
        "",
        "| | time | AP |",
        "|---|---|---|",
        f"| detcal `evaluate_coco` (matching, precision/recall, 12 stats, per-class AP; best of "
        f"{args.repeat}) | {ours:.3f} s | {evaluation.stats[0]:.6f} |",
        f"| the same plus `from_coco` of both lists of dicts | {ours + convert:.3f} s | |",
        f"| {reference} `evaluate` + `accumulate` + `summarize` (building its `COCO` objects "
        f"not timed) | {ref:.2f} s | {evaluator.stats[0]:.6f} |",
        "",
        f"Speed-up **{ratio:.0f}x** ({ref / (ours + convert):.0f}x with `from_coco`). Max abs "
        f"difference of the 12 stats {stats_diff:.1g}, of the precision array "
        f"{prec_diff:.1g}, of the recall array {rec_diff:.1g}. Stats: {stats}.",
    ]))


if __name__ == "__main__":
    main()
