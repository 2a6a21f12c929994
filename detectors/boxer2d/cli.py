"""Command line of the image-plane detector: train, evaluate on a split, dump COCO results.

    python -m detectors.boxer2d train [--steps N] [--run-dir runs/boxer2d] [--fresh]
    python -m detectors.boxer2d evaluate [--split test] [--scenes 500] [--out DIR]
                                          [--weights W] [--instances DIR/instances.json]
    python -m detectors.boxer2d dump --split val --scenes 200 --out DIR
"""

from __future__ import annotations

import argparse
import json
import shutil
from collections.abc import Sequence
from pathlib import Path


def main(argv: Sequence[str] | None = None) -> int:
    """Parse `argv` and run the command; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m detectors.boxer2d")
    sub = parser.add_subparsers(dest="command", required=True)
    tr = sub.add_parser("train", help="train (or resume) and write the shipped weights")
    tr.add_argument("--steps", type=int)
    tr.add_argument("--batch-size", type=int)
    tr.add_argument("--seed", type=int)
    tr.add_argument("--run-dir", default="runs/boxer2d")
    tr.add_argument("--weights-out", default=None)
    tr.add_argument("--fresh", action="store_true", help="delete the run directory first")
    for name, helptext in (("evaluate", "COCO AP per class on a split"),
                           ("dump", "COCO results + instances JSON of a split")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--split", default="test" if name == "evaluate" else "val")
        p.add_argument("--scenes", type=int, default=500)
        p.add_argument("--out", default=f"runs/boxer2d/{name}")
        p.add_argument("--weights", default=None)
        p.add_argument("--instances", default=None,
                       help="a COCO instances JSON of the same scenes, to reuse")
    args = parser.parse_args(argv)

    if args.command == "train":
        from detectors.boxer2d.train import Boxer2DTrainConfig, train_boxer2d
        from detectors.boxer2d.weights import WEIGHTS_FILE

        if args.fresh:
            shutil.rmtree(args.run_dir, ignore_errors=True)
        cfg = Boxer2DTrainConfig.recipe(steps=args.steps, batch_size=args.batch_size,
                                        seed=args.seed)
        out = train_boxer2d(cfg, args.run_dir, args.weights_out or WEIGHTS_FILE)
        print(f"weights: {out}")
        return 0

    from detectors.boxer2d.coco_results import coco_ap, dump_coco
    from detectors.boxer2d.weights import build_boxer2d

    model = build_boxer2d(weights=args.weights)
    known = None if args.instances is None else \
        json.loads(Path(args.instances).read_text(encoding="utf-8"))
    files = dump_coco(model, args.split, args.scenes, args.out, instances=known)
    print(f"wrote {files.results} and {files.instances} ({files.seconds_per_frame * 1e3:.1f} "
          "ms per frame, render included)")
    if args.command == "evaluate":
        table = coco_ap(files.instances, files.results)
        Path(args.out, "ap.json").write_text(json.dumps(table, indent=1), encoding="utf-8")
        for name, row in table.items():
            print(f"{name:22s} AP {row['AP']:.3f}  AP50 {row['AP50']:.3f}  "
                  f"AP75 {row['AP75']:.3f}")
    return 0
