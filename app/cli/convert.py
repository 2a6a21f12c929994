"""`detcal convert`: a dump, or a detector's own files (`--from`), written as a Parquet
dataset folder or an NPZ validation dump (docs/formats.md). Heavy imports happen inside the
handler so `detcal --help` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from app.cli.main import CliError
from app.cli.offline import add_dump_input, load_input

CONVERT_DESCRIPTION = """\
Write an NPZ dump (or a nuScenes results JSON with --nuscenes-gt) as a Parquet dataset
folder (docs/formats.md): detections and ground truth in parts of whole frames, for streamed
and Dask fits. With --from, read a detector's own files (KITTI labels, OpenPCDet result.pkl,
MMDetection3D arrays, Argoverse 2 feather) into a dump: OUT_DIR ending in .npz writes it as
a validation dump."""

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `convert`."""
    conv = subparsers.add_parser(
        "convert", help="a dump or a detector's own files as a Parquet dataset or NPZ dump",
        description=CONVERT_DESCRIPTION)
    add_dump_input(conv)
    conv.add_argument("out_dir", metavar="OUT_DIR", help="dataset folder to create")
    conv.add_argument("--rows-per-part", type=int, default=None,
                      help="detections per part file (default: 1,000,000)")
    conv.add_argument("--float32", action="store_true",
                      help="store floats as float32 (half the size, rounded values)")
    conv.add_argument("--from", dest="source_format", metavar="FORMAT", default="npz",
                      help="format of DUMP: npz (default), parquet, nuscenes, kitti, openpcdet, "
                           "mmdet3d or av2 (docs/formats.md); OUT_DIR ending in .npz writes a "
                           "validation dump instead of a Parquet dataset")
    conv.add_argument("--gt", metavar="PATH", help="ground truth of --from kitti (label folder), "
                      "openpcdet (infos .pkl), mmdet3d (.npz), av2 (annotations .feather)")
    conv.add_argument("--calib", metavar="PATH",
                      help="--from kitti: calib file or folder (boxes to the lidar frame)")
    conv.add_argument("--classes", metavar="A,B,...",
                      help="class list, in order (--from openpcdet: the config's CLASS_NAMES)")
    conv.add_argument("--score", choices=("probability", "logit"),
                      help="--from kitti: the score column is a probability (default) or a "
                           "logit (PointRCNN / AB3DMOT detection files)")
    conv.add_argument("--difficulty", choices=("easy", "moderate", "hard"),
                      help="--from kitti: KITTI's difficulty rules (default: every box counts)")
    conv.set_defaults(func=run_convert)


def run_convert(args: argparse.Namespace) -> int:
    """`detcal convert`: write a dump as a Parquet dataset folder."""
    from calibrators.io import save_parquet

    dump, sha = _convert_input(args)
    if args.out_dir.lower().endswith(".npz"):
        from calibrators.io import save_dump

        save_dump(args.out_dir, dump)
        print(f"wrote {args.out_dir}: {dump.n_frames} frames, {dump.n_detections} detections, "
              f"{len(dump.gt_labels)} ground-truth boxes", file=sys.stderr)
        return 0
    rows = {} if args.rows_per_part is None else {"rows_per_part": args.rows_per_part}
    out = save_parquet(args.out_dir, dump, float_dtype="float32" if args.float32 else "float64",
                       source_sha256=sha, **rows)
    print(f"wrote {out}: {dump.n_frames} frames, {dump.n_detections} detections, "
          f"{len(dump.gt_labels)} ground-truth boxes", file=sys.stderr)
    return 0


def _convert_input(args: argparse.Namespace) -> tuple[Any, str]:
    """(Dump, sha256) of `detcal convert`'s DUMP read as `--from` (calibrators.io.load_dump),
    with its `--gt`, `--calib` and `--classes`; plain npz / nuScenes input as `load_input`."""
    if args.source_format == "npz" and not (args.gt or args.calib or args.classes
                                            or args.score or args.difficulty):
        return load_input(args.dump, args.nuscenes_gt)
    from calibrators.io.formats import inputs_sha256, load_dump

    options: dict[str, Any] = {}
    gt = args.gt or args.nuscenes_gt
    for key, value in (("ground_truth", gt), ("calib", args.calib), ("score", args.score),
                       ("difficulty", args.difficulty)):
        if value is not None:
            options[key] = value
    if args.classes:
        options["classes"] = [c.strip() for c in args.classes.split(",") if c.strip()]
    if not Path(args.dump).exists():
        raise CliError(f"{args.dump}: no such file or folder")
    try:
        dump = load_dump(args.dump, format=args.source_format, **options)
    except TypeError as exc:  # an option the format does not take
        raise CliError(f"--from {args.source_format}: {exc}") from None
    except ValueError as exc:
        raise CliError(f"{args.dump}: {exc}") from None
    return dump, inputs_sha256(args.dump, gt, args.calib)
