"""`detcal train | dump | show`: the detectors' subcommands (registered by app.cli.main).

Heavy imports (torch, the simulator, matplotlib) happen inside the handlers, so listing the
commands stays fast and works without the detectors extra installed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from detectors.vocab import (
    DECODINGS,
    DETECTOR_COV_SOURCES,
    DUMP_COV_SOURCES,
    DUMP_FORMATS,
    GT_FILTERS,
    SENSORS,
    SPLIT_NAMES,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `train`, `dump` and `show` subcommands."""
    _train_options(_sensor_command(
        subparsers, "train", run_train,
        "train a bundled detector on simulated frames (CPU, resumable)",
        "Train SENSOR's detector from its seed; checkpoints go to runs/SENSOR/ and an "
        "interrupted run resumes from there; the final weights are written to "
        "detectors/weights/SENSOR.pt."))
    _dump_options(_sensor_command(
        subparsers, "dump", run_dump, "write a validation dump of a bundled detector",
        "Run SENSOR's detector over simulated scenes of a split and write validation dump "
        "v1 (NPZ) or a nuScenes results + ground-truth JSON pair."))
    _show_options(_sensor_command(
        subparsers, "show", run_show,
        "draw a bird's-eye view of one simulated frame with detections",
        "Points, ground-truth boxes, detections above a score and their covariance "
        "ellipses, optionally after applying a calibration profile."))


def _sensor_command(subparsers: argparse._SubParsersAction, name: str,
                    func: Callable[[argparse.Namespace], int], summary: str,
                    description: str) -> argparse.ArgumentParser:
    """Subcommand `name` about one bundled detector: a required `--sensor`, handled by
    `func`."""
    parser = subparsers.add_parser(name, help=summary, description=description)
    parser.add_argument("--sensor", choices=SENSORS, required=True)
    parser.set_defaults(func=func)
    return parser


def _train_options(tr: argparse.ArgumentParser) -> None:
    """`detcal train`'s options besides `--sensor`."""
    tr.add_argument("--steps", type=int, default=None,
                    help="optimiser steps (default: the sensor's recipe)")
    tr.add_argument("--batch-size", type=int, default=None, help="frames per step")
    tr.add_argument("--seed", type=int, default=None, help="training seed (default: recipe)")
    tr.add_argument("--run-dir", default=None, help="checkpoint/log folder "
                    "(default: runs/SENSOR)")
    tr.add_argument("--out", default=None, help="weights file to write "
                    "(default: detectors/weights/SENSOR.pt)")
    group = tr.add_mutually_exclusive_group()
    group.add_argument("--resume", action="store_true",
                       help="require a checkpoint to resume from (resuming is automatic)")
    group.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint")
    tr.add_argument("--workers", type=int, default=None, help="frame-generating workers")
    tr.add_argument("--threads", type=int, default=None,
                    help="torch threads (default 2; 1 when two runs share two cores)")
    tr.add_argument("--device", default=None,
                    help="torch device for the model (default cpu, the recipes' budget; "
                         "e.g. cuda: frames are still simulated on the CPU)")
    tr.add_argument("--snapshot-every", type=int, default=None, metavar="N",
                    help="also keep the weights of every N-th step as RUN_DIR/step_N.pt")
    tr.add_argument("--base-weights", default=None,
                    help="train a deep sub-ensemble head: freeze the trunk of this weights "
                         "file and train a fresh decoder head on it (recipe: "
                         "SUB_ENSEMBLE_RECIPE, e.g. --out detectors/weights/lidar_dse1.pt)")
    tr.add_argument("--model", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scalar field of the sensor's architecture (e.g. "
                         "d_model=96); repeatable; a resumed run must pass the same")
    tr.add_argument("--quiet", action="store_true", help="no progress bar")


def _dump_options(du: argparse.ArgumentParser) -> None:
    """`detcal dump`'s options besides `--sensor`."""
    du.add_argument("--split", choices=SPLIT_NAMES, default="val")
    du.add_argument("--frames", type=int, default=None, help="first N scenes of the split")
    du.add_argument("--cov-source", choices=DUMP_COV_SOURCES, default="layers",
                    help="det_cov source (default: %(default)s)")
    du.add_argument("--format", choices=DUMP_FORMATS, default="npz")
    du.add_argument("--gt-filter", choices=GT_FILTERS, default="lidar_radar",
                    help="ground truth kept: boxes with a lidar or radar point (nuScenes, "
                         "default), with a point of this sensor, or all")
    du.add_argument("--max-detections", type=int, default=None,
                    help="detections kept per frame, by score (default: as many as the "
                         "model has queries)")
    du.add_argument("--decode", choices=DECODINGS, default=DECODINGS[0],
                    help="topk_nms (default): topk, then class-wise circle NMS on the "
                         "box centres (CenterPoint's radii); topk: the best (query, class) "
                         "pairs, a query may give several classes (DETR3D/PETR); query: one "
                         "detection per query, its arg-max class")
    du.add_argument("--weights", default=None, help="weights file (default: shipped)")
    du.add_argument("--out", required=True, help="NPZ path, or results JSON for nuscenes "
                    "(the ground truth goes next to it as *_gt.json)")
    du.add_argument("--quiet", action="store_true", help="no progress bar")


def _show_options(sh: argparse.ArgumentParser) -> None:
    """`detcal show`'s options besides `--sensor`."""
    sh.add_argument("--seed", type=int, required=True, help="scene seed")
    sh.add_argument("--out", required=True, help="PNG to write")
    sh.add_argument("--profile", default=None, help="calibration profile JSON to apply")
    sh.add_argument("--min-score", type=float, default=0.3,
                    help="draw detections with at least this score (default: %(default)s)")
    sh.add_argument("--cov-source", choices=DETECTOR_COV_SOURCES, default="layers")
    sh.add_argument("--weights", default=None, help="weights file (default: shipped)")


def run_train(args: argparse.Namespace) -> int:
    from pathlib import Path

    from detectors.train import TrainConfig, train

    if args.base_weights and args.out is None:
        raise ValueError("--base-weights needs --out (never overwrite the shipped weights "
                         "with a sub-ensemble head)")
    cfg = TrainConfig.for_sensor(args.sensor, steps=args.steps, batch_size=args.batch_size,
                                 seed=args.seed, workers=args.workers, threads=args.threads,
                                 base_weights=args.base_weights, device=args.device,
                                 snapshot_every=args.snapshot_every)
    run = Path(args.run_dir) if args.run_dir else Path("runs") / args.sensor
    if args.resume and not (run / "ckpt.pt").exists():
        raise ValueError(f"--resume given but there is no checkpoint at {run / 'ckpt.pt'}")
    model = None
    if args.model:
        from detectors.registry import config_with

        model = config_with(args.sensor, args.model)
    result = train(cfg, run_dir=run, resume=not args.fresh, weights_out=args.out,
                   progress=not args.quiet, model_config=model)
    losses = ", ".join(f"{k} {v:.4f}" for k, v in result.final_losses.items())
    print(f"trained {args.sensor}: {result.steps} steps in {result.wall_s / 60:.1f} min; "
          f"final losses (mean of last 100 steps): {losses}")
    print(f"weights: {result.weights}; log: {result.log}")
    return 0


def run_dump(args: argparse.Namespace) -> int:
    from detectors.dumpwriter import build_dump, write_dump
    from detectors.registry import build_detector
    from detectors.sim import SPLITS

    seeds = list(SPLITS[args.split])
    if args.frames is not None:
        if args.frames < 1:
            raise ValueError(f"--frames must be >= 1, got {args.frames}")
        seeds = seeds[:args.frames]
    model = build_detector(args.sensor, weights=args.weights)
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(seeds), desc=f"dump {args.sensor} {args.split}", unit="frame",
                   file=sys.stderr)
    dump = build_dump(model, seeds, cov_source=args.cov_source,
                      max_detections=args.max_detections, gt_filter=args.gt_filter,
                      decode=args.decode,
                      progress=(lambda i, n: bar.update(1)) if bar is not None else None)
    if bar is not None:
        bar.close()
    paths = write_dump(dump, args.out, args.format)
    print(f"wrote {', '.join(str(p) for p in paths)}: {dump.n_frames} frames, "
          f"{dump.n_detections} detections, {len(dump.gt_labels)} ground-truth boxes")
    return 0


def run_show(args: argparse.Namespace) -> int:
    from pathlib import Path

    from detectors.registry import build_detector
    from detectors.show import render_frame

    profile = None
    if args.profile:
        from calibrators import CalibrationProfile

        profile = CalibrationProfile.from_json(Path(args.profile).read_text())
    model = build_detector(args.sensor, weights=args.weights)
    out = render_frame(model, args.seed, args.out, min_score=args.min_score,
                       cov_source=args.cov_source, profile=profile)
    print(f"wrote {out}")
    return 0
