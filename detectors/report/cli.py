"""`detcal report`: the thesis-style calibration report of the bundled detectors (and the
`report-v2` subcommand of `cli_unified_vs_group`, registered here).

    detcal report --sensor lidar [--sensor radar5 ...] [--val-frames N] [--test-frames N]
                  [--mcd 2 4 6] [--out docs/report/] [--cache runs/report_cache]

Heavy imports (torch, matplotlib) happen in the handler, so `detcal --help` stays fast.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from detectors.vocab import SENSORS

REPORT_DESCRIPTION = """\
Fit TS / modulation / depth scaling on the val split of each sensor, measure them and the
sampling baselines (MC dropout, deep ensembles when trained) on the test split; write
markdown tables, PNG + SVG figures and OUT/README.md. Forward passes are cached in CACHE."""

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `report` subcommand."""
    p = subparsers.add_parser(
        "report", help="thesis-style calibration report of the bundled detectors",
        description=REPORT_DESCRIPTION)
    p.add_argument("--sensor", action="append", choices=SENSORS, required=True,
                   help="sensor to report (repeat for several)")
    p.add_argument("--val-frames", type=_positive, default=200,
                   help="first N val scenes to fit on (default: %(default)s)")
    p.add_argument("--test-frames", type=_positive, default=200,
                   help="first N test scenes to measure on (default: %(default)s)")
    p.add_argument("--mcd", type=_positive, nargs="*", default=[2, 4, 6],
                   help="MC-dropout pass counts N (default: 2 4 6; none to skip)")
    p.add_argument("--max-detections", type=_positive, default=100,
                   help="detections kept per frame (default: %(default)s)")
    p.add_argument("--bev-frame", type=int, default=0,
                   help="index of the test frame drawn in bird's-eye view (default: 0)")
    p.add_argument("--out", type=Path, default=Path("docs/report"),
                   help="output folder (default: %(default)s)")
    p.add_argument("--cache", type=Path, default=Path("runs/report_cache"),
                   help="forward-pass cache folder (default: %(default)s)")
    p.add_argument("--threads", type=_positive, default=2,
                   help="torch CPU threads (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run_report)
    from detectors.report import cli_unified_vs_group

    cli_unified_vs_group.register(subparsers)


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text}")
    return value


def run_report(args: argparse.Namespace) -> int:
    """Handler of `detcal report`: every requested sensor, then OUT/README.md."""
    import torch

    from detectors.report.markdown import readme
    from detectors.report.sensor import ReportOptions, build_sensor

    torch.set_num_threads(args.threads)
    options = ReportOptions(out=args.out, cache=args.cache, val_frames=args.val_frames,
                            test_frames=args.test_frames, mcd=tuple(sorted(set(args.mcd))),
                            max_detections=args.max_detections, bev_frame=args.bev_frame,
                            threads=args.threads)
    args.out.mkdir(parents=True, exist_ok=True)

    def log(message: str) -> None:
        if not args.quiet:
            print(message, file=sys.stderr, flush=True)

    start = time.perf_counter()
    reports = []
    for sensor in dict.fromkeys(args.sensor):
        log(f"report: {sensor}")
        reports.append(build_sensor(sensor, options, log))
        log(f"report: {sensor} done in {reports[-1].seconds:.0f} s")
    seconds = time.perf_counter() - start
    command = "detcal report " + shlex.join(_argv_of(args))
    (args.out / "README.md").write_text(readme(reports, command, seconds, options))
    print(f"wrote {args.out / 'README.md'} ({len(reports)} sensor(s), {seconds:.0f} s)")
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """The options of `args` as command-line words (the command the README names)."""
    words: list[str] = []
    for s in dict.fromkeys(args.sensor):
        words += ["--sensor", s]
    words += ["--val-frames", str(args.val_frames), "--test-frames", str(args.test_frames),
              "--mcd", *[str(n) for n in args.mcd], "--out", str(args.out),
              "--cache", str(args.cache), "--threads", str(args.threads)]
    return words
