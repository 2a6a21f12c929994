"""Held-out calibration of the 2-D camera detector: fit a 2-D profile (`fit_profile_2d`,
default options) on a COCO results + instances pair of val scenes, serve the test scenes'
results, and print per the issue's criteria: ECE of the raw, one-temperature and calibrated
scores (overall, and the largest class ECE over classes with >= `--min-class` true
positives), D-ECE over (confidence, cx, cy) for the same three, and the joint four-edge
coverage of the served box regions at 90 / 95 % overall and per class, with the mean outer
box area. True positives: COCO matching at IoU 0.5.

    .venv/bin/python -m detectors.boxer2d dump --split val --scenes 500 --out val
    .venv/bin/python -m detectors.boxer2d dump --split test --scenes 500 --out test
    .venv/bin/python -m bench.bench_2d_heldout --val val --test test --label boxer2d

With `--label`, the table is written to docs/benchmarks.md as section `2d held-out <label>`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.special import expit

from bench._report import write_section
from calibrators import metrics
from calibrators.boxes2d import (
    box_edges,
    calibrate_2d,
    detection_ece_2d,
    fit_profile_2d,
    match_labels,
    read_coco_instances,
    read_coco_results,
    score_inputs,
)

LEVELS = (0.9, 0.95)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--val", required=True, help="folder with results.json, instances.json")
    ap.add_argument("--test", required=True, help="the same for the held-out scenes")
    ap.add_argument("--min-class", type=int, default=500)
    ap.add_argument("--label", help="write the table to docs/benchmarks.md under this name")
    args = ap.parse_args(argv)
    read = {}
    for name in ("val", "test"):
        folder = Path(getattr(args, name))
        inst = read_coco_instances(folder / "instances.json", max_bytes=1 << 31)
        read[name] = (read_coco_results(folder / "results.json", max_bytes=1 << 31,
                                        instances=inst), inst)
    (val, val_inst), (test, test_inst) = read["val"], read["test"]
    start = time.perf_counter()
    profile = fit_profile_2d(val, val_inst, score_mode="sigmoid")
    fit_s = time.perf_counter() - start
    size = test_inst.image_size(test.image_id)
    served = calibrate_2d(profile, test, LEVELS, image_size=size)
    labels = match_labels(test, test_inst.ground_truth, 0.5)
    keep = ~labels.ignored
    hit = labels.true_positive
    z = score_inputs(test, profile.category_ids, "sigmoid").z
    temperature = expit(z / profile.score_stage.temperature)
    scores = {"raw": test.score, "temperature": temperature, "calibrated": served.score}
    cats = np.asarray(test.category_id)
    rows = []
    for name, s in scores.items():
        ece = metrics.expected_calibration_error(s[keep], hit[keep])
        by_class = [metrics.expected_calibration_error(s[keep & (cats == c)],
                                                       hit[keep & (cats == c)])
                    for c in np.unique(cats) if (hit & (cats == c)).sum() >= args.min_class]
        dece = detection_ece_2d(test, labels, size, scores=s, features=("cx", "cy"))
        rows.append(f"| {name} | {ece:.4f} | {max(by_class):.4f} | {dece:.4f} |")
    tp = np.flatnonzero(hit)
    names = dict(zip(profile.category_ids, profile.category_names, strict=True))
    truth = box_edges(test_inst.ground_truth.bbox[labels.gt_row[tp]])
    inside, outer_area, region_area = [], [], []
    for j in range(len(LEVELS)):
        inner = box_edges(served.regions.inner[tp, j])
        outer = box_edges(served.regions.outer[tp, j])
        inside.append(((truth[:, :2] >= outer[:, :2]) & (truth[:, :2] <= inner[:, :2])).all(1)
                      & ((truth[:, 2:] <= outer[:, 2:]) & (truth[:, 2:] >= inner[:, 2:])).all(1))
        box = served.regions.outer[tp, j, 2] * served.regions.outer[tp, j, 3]
        hole = np.clip(served.regions.inner[tp, j, 2], 0, None) * np.clip(
            served.regions.inner[tp, j, 3], 0, None)
        outer_area.append(float(np.mean(box)))
        region_area.append(float(np.mean(box - hole)))

    def row(name: str, mask: np.ndarray) -> str:
        cells = []
        for j, q in enumerate(LEVELS):
            got = inside[j][mask]
            lo, hi = metrics.proportion_bounds(int(got.sum()), len(got))
            flag = "" if abs(got.mean() - q) <= 0.04 else (
                " ✗" if (q < lo - 0.04 or q > hi + 0.04) else " ✗ (within sampling)")
            cells.append(f"{got.mean():.3f} [{float(lo):.3f}, {float(hi):.3f}]{flag}")
        return f"| {name} | {int(mask.sum()):,} | " + " | ".join(cells) + " |"

    cover = [row("all", np.ones(len(tp), dtype=bool))]
    cover += [row(names[int(c)], cats[tp] == c) for c in np.unique(cats[tp])]
    areas = ", ".join(f"{q:.0%}: outer {o:,.0f} px², region {r:,.0f} px²"
                      for q, o, r in zip(LEVELS, outer_area, region_area, strict=True))
    text = (f"2-D profile fit on `{args.val}` ({len(val):,} detections, "
            f"{len(val_inst.image_id)} images) in {fit_s:.1f} s with the default options "
            f"(score method `{profile.score_method}`, region score "
            f"`{profile.region_score}`), served on "
            f"`{args.test}` ({len(test):,} detections, {len(test_inst.image_id)} images, "
            f"{len(tp):,} true positives at IoU 0.5).\n\n"
            "| scores | ECE | max class ECE (>= "
            f"{args.min_class} TPs) | D-ECE (conf × cx × cy) |\n|---|---|---|---|\n"
            + "\n".join(rows) + "\n\nJoint four-edge coverage of the box regions per "
            "category, with its 95 % Clopper-Pearson interval; ✗: more than 4 pp from the "
            "level, '(within sampling)' when the level lies within 4 pp of the interval.\n\n"
            "| category | test TPs | " + " | ".join(f"{q:.0%}" for q in LEVELS) + " |\n"
            "|---|---|" + "---|" * len(LEVELS) + "\n" + "\n".join(cover)
            + f"\n\nMean areas over the test true positives ({areas}; region: between the "
            "inner and the outer box).")
    print(text)
    if args.label:
        write_section(f"2d held-out {args.label}", text)
    return 0


def _half(inside: np.ndarray) -> float:
    lo, hi = metrics.proportion_bounds(int(inside.sum()), len(inside))
    return (float(hi) - float(lo)) / 2


if __name__ == "__main__":
    raise SystemExit(main())
