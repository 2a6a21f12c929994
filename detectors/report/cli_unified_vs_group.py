"""`detcal report-v2`: the unified-vs-group page of issue 13 (registered by
`detectors.report.cli.register`).

    detcal report-v2 --weights runs/lidar_v2/lidar.pt --baseline detectors/weights/lidar.pt \
        --test-frames 500 [--val-frames 200] [--out docs/report/detectors_v2.md] [--threads 2]

Heavy imports (torch) happen in the handler, so `detcal --help` stays fast.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPORT_V2_DESCRIPTION = """\
mAP / per-class AP, class switches per decoder layer, inter-group std, attention-spread
trends and the hypotheses vs layers covariance sources of a group-head model (WEIGHTS)
against a unified-head one (BASELINE), on the first N test scenes; writes one markdown page."""

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `report-v2` subcommand."""
    p = subparsers.add_parser(
        "report-v2", help="unified-vs-group detector page (docs/report/detectors_v2.md)",
        description=REPORT_V2_DESCRIPTION)
    p.add_argument("--weights", type=Path, required=True, help="group-head weights file")
    p.add_argument("--baseline", type=Path, required=True, help="unified-head weights file")
    p.add_argument("--test-frames", type=_count(1), required=True,
                   help="first N test scenes to measure on")
    p.add_argument("--val-frames", type=_count(0), default=200,
                   help="first N val scenes to fit section 5's profiles on (0: skip; "
                        "default: %(default)s)")
    p.add_argument("--max-detections", type=_count(1), default=100,
                   help="queries kept per frame for sections 2-4 (default: %(default)s)")
    p.add_argument("--min-score", type=float, default=0.3,
                   help="no-object threshold of the class switches and score floor of the "
                        "inter-group std (default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("docs/report/detectors_v2.md"),
                   help="markdown page to write (default: %(default)s)")
    p.add_argument("--cache", type=Path, default=Path("runs/report_v2_cache"),
                   help="attention-pass cache folder (default: %(default)s)")
    p.add_argument("--probe-windows", type=_count(1), nargs="+", default=[], metavar="W",
                   help="also run the group model (windowed attention) with each wider "
                        "window W x W at inference: mAP and the attention trend per window")
    p.add_argument("--threads", type=_count(1), default=2,
                   help="torch CPU threads (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_report_v2)


def _count(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= `minimum`."""
    def parse(text: str) -> int:
        value = int(text)
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text}")
        return value
    return parse


def run_report_v2(args: argparse.Namespace) -> int:
    """Handler of `detcal report-v2`: measure both models, write the page."""
    import torch

    from detectors.report.unified_vs_group import V2Options, measure_v2, v2_page

    torch.set_num_threads(args.threads)
    for path in (args.weights, args.baseline):
        if not path.exists():
            raise FileNotFoundError(f"weights file not found: {path}")
    options = V2Options(weights=args.weights, baseline=args.baseline,
                        test_frames=args.test_frames, val_frames=args.val_frames,
                        max_detections=args.max_detections, min_score=args.min_score,
                        cache=args.cache, probe_windows=tuple(args.probe_windows))

    def log(message: str) -> None:
        if not args.quiet:
            print(message, file=sys.stderr, flush=True)

    start = time.perf_counter()
    runs = measure_v2(options, log)
    seconds = time.perf_counter() - start
    page = v2_page(runs, options, "detcal report-v2 " + shlex.join(_argv_of(args)), seconds)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(page)
    print(f"wrote {args.out} ({seconds:.0f} s)")
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """The options of `args` as command-line words (the command the page names)."""
    return ["--weights", str(args.weights), "--baseline", str(args.baseline),
            "--test-frames", str(args.test_frames), "--val-frames", str(args.val_frames),
            "--max-detections", str(args.max_detections), "--min-score", f"{args.min_score:g}",
            *(["--probe-windows", *map(str, args.probe_windows)] if args.probe_windows else []),
            "--out", str(args.out), "--cache", str(args.cache), "--threads", str(args.threads)]
