"""`detcal fit` and `detcal calibrate` on COCO files: a 2-D profile from a COCO results file
and its instances file, and calibrated COCO results from a 2-D profile.

    detcal fit results.json --from coco --gt instances.json --out profile2d.json
    detcal calibrate results.json --profile profile2d.json --levels 0.9 --out calibrated.json

A results file with `--gt` is read as COCO when it is a JSON list (a nuScenes results file is
an object and takes `--nuscenes-gt`); `--from coco` says so explicitly. `detcal calibrate`
knows a 2-D profile by its `kind`; `--gt` there gives the images' sizes (a `position` score
calibrator reads the box position in its image, adaptive regions where a box meets its
image's border) and checks every image id. Heavy imports
happen inside the handlers.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from app.cli.main import CliError

#: `--from` values `detcal fit` takes (the other inputs are recognised by their form).
FIT_FORMATS = ("coco",)


def is_coco_fit(args: argparse.Namespace) -> bool:
    """Whether `detcal fit`'s input is a COCO pair: `--from coco`, or `--gt` with a results
    file that is a JSON list; a CliError for a `--from` or `--gt` that does not fit."""
    if args.source_format is not None and args.source_format not in FIT_FORMATS:
        raise CliError(f"--from {args.source_format}: detcal fit reads --from coco; an NPZ "
                       f"dump, a Parquet folder or a nuScenes pair is recognised without it")
    if args.source_format is None and args.gt is None:
        return False
    if args.gt is None:
        raise CliError("--from coco needs --gt INSTANCES.json, the COCO instances file")
    if args.nuscenes_gt is not None:
        raise CliError("--gt (COCO instances) and --nuscenes-gt do not go together")
    if args.source_format is None and _first_byte(args.dump) != b"[":
        raise CliError(f"{args.dump} is not a COCO results list; --gt names the COCO "
                       f"instances of one (a nuScenes results JSON takes --nuscenes-gt)")
    return True


def run_fit_coco(args: argparse.Namespace, options: Any) -> int:
    """`detcal fit --from coco`: fit, print the chosen calibrator and the held-out figures,
    write the 2-D profile."""
    from calibrators.boxes2d import fit_profile_2d
    from calibrators.io import file_sha256

    detections, instances = read_pair(args.dump, args.gt)
    progress = None if args.quiet else _progress
    try:
        profile = fit_profile_2d(detections, instances, options,
                                 results_sha256=file_sha256(args.dump),
                                 instances_sha256=file_sha256(args.gt), progress=progress)
    except ValueError as exc:
        raise CliError(f"{args.dump}: {exc}") from None
    from app.cli.offline import write_text

    write_text(args.out, profile.to_json())
    print(report_text(profile.report))
    print(f"wrote {args.out}: 2-D profile of {len(profile.category_ids)} categories, scores "
          f"{profile.score_method}, regions {profile.region_score or 'none'}", file=sys.stderr)
    return 0


def run_calibrate_coco(args: argparse.Namespace, profile: Any, levels: list[float]) -> int:
    """`detcal calibrate` with a 2-D profile: a COCO results file in, calibrated COCO results
    out (`score`, `score_raw`, `region_<q>` per level)."""
    from calibrators.boxes2d import calibrate_2d, coco_results, read_coco_results
    from calibrators.core.errors import FieldError

    if args.nuscenes_gt:
        raise CliError("--nuscenes-gt does not apply to a 2-D profile (--gt: COCO instances)")
    instances = None if args.gt is None else _read(args.gt)
    try:
        detections = read_coco_results(_existing(args.file), instances=instances)
    except ValueError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    size = None if instances is None else instances.image_size(detections.image_id)
    try:
        served = calibrate_2d(profile, detections, levels, size)
    except FieldError as exc:
        flag = {"levels": "--levels", "image_size": "--gt"}.get(exc.field, exc.field)
        raise CliError(f"{flag}: {exc}") from None
    from app.cli.offline import write_text

    if args.out == "-":
        import json

        write_text("-", json.dumps(coco_results(detections, served.score, served.regions),
                                   allow_nan=False))
    else:
        served.write(args.out)
    print(f"detcal calibrate: {len(served)} detections calibrated with {args.profile} "
          f"(2-D: scores {profile.score_method}, regions {profile.region_score or 'none'}) -> "
          f"{'stdout' if args.out == '-' else args.out}", file=sys.stderr)
    return 0


def read_pair(results: str, gt: str) -> tuple[Any, Any]:
    """The detections and instances of a COCO pair, every field checked (CliError naming
    the file)."""
    from calibrators.boxes2d import read_coco_results

    instances = _read(gt)
    try:
        return read_coco_results(_existing(results), instances=instances), instances
    except ValueError as exc:
        raise CliError(f"{results}: {exc}") from None


def report_text(report: dict[str, Any]) -> str:
    """The fit report in a few lines: each score candidate's held-out NLL / ECE / D-ECE, then
    (with a held-out part) raw and calibrated ECE, D-ECE and LaECE and the regions' coverage."""
    score = (report.get("selection") or {}).get("score") or {}
    lines = [f"score calibrator: {score.get('chosen')}"]
    for name, c in (score.get("candidates") or {}).items():
        mark = "*" if name == score.get("chosen") else " "
        lines.append(f" {mark} {name:<18} NLL {c['nll']:.4f}  ECE {c['ece']:.4f}  "
                     f"D-ECE {c['d_ece']:.4f}")
    held = report.get("holdout")
    if not held:
        lines.append("no held-out images (--holdout) to measure on")
        return "\n".join(lines)
    lines.append(f"held-out images: {held['n_images']}, {held['n_detections']} detections, "
                 f"{held['n_true_positives']} true positives")
    for key, label in (("ece", "ECE"), ("d_ece", "D-ECE"), ("laece", "LaECE_0")):
        raw, cal = held[key]["raw"], held[key]["calibrated"]
        if raw is not None and cal is not None:
            lines.append(f"  {label:<8} raw {raw:.4f}  calibrated {cal:.4f}")
    regions = held.get("regions")
    if regions:
        lines.append("  regions coverage " + " / ".join(
            f"{q:g}: {c:.3f}" for q, c in zip(regions["levels"], regions["overall"],
                                               strict=True)) + f"  ({regions['n']} TPs)")
    return "\n".join(lines)


def _read(path: str) -> Any:
    from calibrators.boxes2d import read_coco_instances

    try:
        return read_coco_instances(_existing(path))
    except ValueError as exc:
        raise CliError(f"{path}: {exc}") from None


def _existing(path: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise CliError(f"{path}: no such file")
    return p


def _first_byte(path: str) -> bytes:
    """The first byte of `path` that is not JSON whitespace (b"" for none)."""
    with open(_existing(path), "rb") as fh:
        while chunk := fh.read(4096):
            text = chunk.lstrip(b" \t\r\n")
            if text:
                return text[:1]
    return b""


def _progress(stage: str, fraction: float) -> None:
    print(f"detcal fit: {stage} ({fraction:.0%})", file=sys.stderr, flush=True)
