"""Matching + mAP: `calibrators.evaluate` against the nuScenes devkit, same data, same run.

Synthetic validation set: 600 frames x 300 detections x 40 ground truth, 10 nuScenes classes,
seeded. Detections sit near ground truth with Gaussian noise (some duplicated, some with the
wrong class) plus uniform false positives; scores are rounded to 1e-3 so ties are common and
the tie order is exercised. Frames have a global ego position (boxes in global coordinates).

Reference: `nuscenes.eval.detection.algo.accumulate` + `calc_ap` (and `calc_tp` for the TP
errors) for every class and the 4 thresholds. Only those calls are timed; building the
devkit's `DetectionBox`/`EvalBoxes` objects and its range filter are not. Ours is timed end to
end (`evaluate(dump)`: range filter, matching, AP, TP errors, NDS).

Run: `.bench-venv/bin/python -m bench.bench_match` (the devkit lives only in `.bench-venv`,
see bench/requirements-reference-devkit.txt); without it the reference is skipped.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.special import logit

from calibrators.data import Dump
from calibrators.evaluation import DEFAULT_CLASS_RANGE, TP_METRICS, evaluate

CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
           "motorcycle", "bicycle", "traffic_cone", "barrier")
CLASS_WEIGHT = np.array([0.3, 0.08, 0.03, 0.03, 0.03, 0.2, 0.05, 0.05, 0.1, 0.13])
CLASS_SIZE = np.array([[1.9, 4.6, 1.7], [2.5, 7.0, 2.9], [2.9, 11.0, 3.5], [2.9, 12.0, 3.9],
                       [2.8, 6.5, 3.2], [0.7, 0.7, 1.8], [0.8, 2.1, 1.5], [0.6, 1.7, 1.3],
                       [0.4, 0.4, 1.1], [2.5, 0.5, 1.0]])
THRESHOLDS = (0.5, 1.0, 2.0, 4.0)


def synthetic_dump(n_frames: int = 600, n_det: int = 300, n_gt: int = 40, seed: int = 0) -> Dump:
    """A seeded dump: [F * n_det] detections (sigmoid logits, L = 1), [F * n_gt] ground truth."""
    rng = np.random.default_rng(seed)
    c = len(CLASSES)
    ego = np.column_stack([rng.uniform(-1000, 1000, (n_frames, 2)), np.zeros(n_frames)])
    gt_frame = np.repeat(np.arange(n_frames), n_gt)
    g = len(gt_frame)
    gt_labels = rng.choice(c, size=g, p=CLASS_WEIGHT)
    gt_xy = ego[gt_frame, :2] + rng.uniform(-60, 60, (g, 2))
    gt_size = CLASS_SIZE[gt_labels] * rng.uniform(0.85, 1.15, (g, 3))
    gt_boxes = np.column_stack([gt_xy, rng.normal(1.0, 0.3, g), gt_size,
                                rng.uniform(-np.pi, np.pi, g), rng.normal(0, 3, (g, 2))])

    det_frame, det_labels, det_boxes, det_scores = [], [], [], []
    for f in range(n_frames):
        rows = np.flatnonzero(gt_frame == f)
        hits = rows[rng.random(len(rows)) < 0.8]
        hits = np.concatenate([hits, rng.choice(hits, size=len(hits) // 4)])  # duplicates
        noise = rng.gamma(2.0, 0.35, len(hits))[:, None] * _unit(rng, len(hits))
        boxes = gt_boxes[hits].copy()
        boxes[:, :2] += noise
        boxes[:, 3:6] *= rng.uniform(0.8, 1.2, (len(hits), 3))
        boxes[:, 6] += rng.normal(0, 0.3, len(hits))
        boxes[:, 7:9] += rng.normal(0, 1.0, (len(hits), 2))
        labels = np.where(rng.random(len(hits)) < 0.9, gt_labels[hits], rng.integers(0, c,
                                                                                     len(hits)))
        scores = np.clip(rng.beta(5, 2, len(hits)), 0.01, 0.99)
        n_fp = n_det - len(hits)
        fp_labels = rng.choice(c, size=n_fp, p=CLASS_WEIGHT)
        fp = np.column_stack([ego[f, :2] + rng.uniform(-65, 65, (n_fp, 2)),
                              rng.normal(1.0, 0.3, n_fp),
                              CLASS_SIZE[fp_labels] * rng.uniform(0.8, 1.2, (n_fp, 3)),
                              rng.uniform(-np.pi, np.pi, n_fp), rng.normal(0, 3, (n_fp, 2))])
        det_frame.append(np.full(n_det, f))
        det_labels.append(np.concatenate([labels, fp_labels]))
        det_boxes.append(np.concatenate([boxes, fp]))
        det_scores.append(np.concatenate([scores, np.clip(rng.beta(1.2, 6, n_fp), 0.01, 0.99)]))
    labels = np.concatenate(det_labels)
    scores = np.round(np.concatenate(det_scores), 3)  # ties on purpose
    logits = np.full((len(labels), c), logit(1e-6))
    logits[np.arange(len(labels)), labels] = logit(scores)
    return Dump(classes=CLASSES, score_mode="sigmoid",
                frame_ids=np.array([f"sample-{i:04d}" for i in range(n_frames)]),
                ego_translation=ego, det_frame=np.concatenate(det_frame),
                det_logits=logits[:, None, :], det_boxes=np.concatenate(det_boxes)[:, None, :],
                gt_frame=gt_frame, gt_labels=gt_labels, gt_boxes=gt_boxes)


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    angle = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([np.cos(angle), np.sin(angle)])


def time_ours(dump: Dump, repeat: int) -> tuple[float, object]:
    """Best-of-`repeat` wall time of `evaluate(dump)` and its report."""
    best, report = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        report = evaluate(dump, thresholds=THRESHOLDS)
        best = min(best, time.perf_counter() - start)
    return best, report


def devkit_boxes(dump: Dump, scores: np.ndarray):
    """The devkit's GT and prediction EvalBoxes for `dump`, range-filtered as the devkit does."""
    from nuscenes.eval.common.data_classes import EvalBoxes
    from nuscenes.eval.detection.data_classes import DetectionBox

    ego = dump.ego_translation

    def box(row: np.ndarray, f: int, name: str, score: float) -> DetectionBox:
        yaw = float(row[6])
        return DetectionBox(
            sample_token=str(dump.frame_ids[f]), translation=tuple(float(v) for v in row[:3]),
            size=tuple(float(v) for v in row[3:6]),
            rotation=(float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))),
            velocity=(float(row[7]), float(row[8])),
            ego_translation=tuple(float(v) for v in row[:3] - ego[f]),
            detection_name=name, detection_score=float(score))

    gt, pred = EvalBoxes(), EvalBoxes()
    det_by_frame = np.argsort(dump.det_frame, kind="stable")
    gt_by_frame = np.argsort(dump.gt_frame, kind="stable")
    det_split = np.split(det_by_frame, np.cumsum(np.bincount(dump.det_frame,
                                                             minlength=dump.n_frames))[:-1])
    gt_split = np.split(gt_by_frame, np.cumsum(np.bincount(dump.gt_frame,
                                                           minlength=dump.n_frames))[:-1])
    for f, token in enumerate(dump.frame_ids):
        preds = [box(dump.final_boxes[i], f, dump.classes[dump.det_labels[i]], scores[i])
                 for i in det_split[f]]
        gts = [box(dump.gt_boxes[i], f, dump.classes[dump.gt_labels[i]], -1.0)
               for i in gt_split[f]]
        # filter_eval_boxes' distance and point filters (its bike-rack step needs the map DB).
        pred.add_boxes(str(token), [b for b in preds if b.ego_dist
                                    < DEFAULT_CLASS_RANGE[b.detection_name] and b.num_pts != 0])
        gt.add_boxes(str(token), [b for b in gts if b.ego_dist
                                  < DEFAULT_CLASS_RANGE[b.detection_name] and b.num_pts != 0])
    return gt, pred


def time_devkit(gt, pred, classes: tuple[str, ...]) -> tuple[float, dict, dict]:
    """Wall time of the devkit's accumulate + calc_ap over classes x thresholds, its APs and
    (untimed) TP errors at 2 m."""
    from nuscenes.eval.common.utils import center_distance
    from nuscenes.eval.detection.algo import accumulate, calc_ap, calc_tp

    ap: dict[str, dict[str, float]] = {c: {} for c in classes}
    data = {}
    start = time.perf_counter()
    for name in classes:
        for th in THRESHOLDS:
            md = accumulate(gt, pred, name, center_distance, th)
            ap[name][str(th)] = calc_ap(md, 0.1, 0.1)
            data[name, th] = md
    elapsed = time.perf_counter() - start
    tp = {name: {m: calc_tp(data[name, 2.0], 0.1, m) for m in TP_METRICS} for name in classes}
    return elapsed, ap, tp


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-write", action="store_true", help="do not touch docs/benchmarks.md")
    args = parser.parse_args(argv)

    dump = synthetic_dump(n_frames=args.frames)
    size = f"{dump.n_frames} frames x 300 detections x 40 GT ({dump.n_detections} detections)"
    print(f"data: {size}")
    ours, report = time_ours(dump, args.repeat)
    print(f"detcal evaluate: {ours:.3f} s (best of {args.repeat}); mAP {report.mean_ap:.6f}, "
          f"NDS {report.nd_score:.6f}")

    try:
        import nuscenes.eval.detection.algo  # noqa: F401
    except ImportError as exc:
        print(f"reference skipped: nuScenes devkit not importable ({exc}); install it into "
              f".bench-venv (bench/requirements-reference-devkit.txt)")
        return
    gt, pred = devkit_boxes(dump, dump.det_scores)
    ref, ref_ap, ref_tp = time_devkit(gt, pred, dump.classes)
    from importlib.metadata import version

    devkit = f"nuscenes-devkit {version('nuscenes-devkit')}"
    ap_diff = max(abs(report.ap[c][t] - ref_ap[c][t]) for c in dump.classes for t in ref_ap[c])
    ref_map = float(np.mean([np.mean(list(ref_ap[c].values())) for c in dump.classes]))
    tp_diff = max(abs(report.tp_errors[c][m] - ref_tp[c][m]) for c in dump.classes
                  for m in TP_METRICS if not np.isnan(report.tp_errors[c][m]))
    ratio = ref / ours
    print(f"{devkit} accumulate+calc_ap: {ref:.3f} s; mAP {ref_map:.6f}")
    print(f"max |AP diff| {ap_diff:.3g}, |mAP diff| {abs(ref_map - report.mean_ap):.3g}, "
          f"max |TP error diff| {tp_diff:.3g}")
    print(f"speed-up: {ratio:.1f}x")
    if ap_diff != 0.0:
        raise SystemExit("AP differs from the devkit")
    if args.no_write:
        return
    from bench._report import write_section

    write_section("match", "\n".join([
        "## Matching + mAP vs the nuScenes devkit",
        "",
        f"Synthetic {size}, 10 classes, scores rounded to 1e-3 (many ties), thresholds "
        "0.5/1/2/4 m. `bench/bench_match.py`.",
        "",
        "| | time | mAP |",
        "|---|---|---|",
        f"| detcal `evaluate` (range filter, matching, AP, TP errors, NDS; best of "
        f"{args.repeat}) | {ours:.3f} s | "
        f"{report.mean_ap:.6f} |",
        f"| {devkit} `accumulate` + `calc_ap`, 10 classes x 4 thresholds (building its "
        f"box objects not timed) | "
        f"{ref:.2f} s | {ref_map:.6f} |",
        "",
        f"Speed-up **{ratio:.0f}x**. AP identical for every class and threshold (max abs diff "
        f"{ap_diff:.1g}); TP errors agree to {tp_diff:.1g} (yaw goes through quaternions in "
        "the devkit).",
    ]))


if __name__ == "__main__":
    main()
