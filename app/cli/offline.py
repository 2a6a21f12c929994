"""`detcal fit`, `detcal evaluate` and `detcal calibrate`: the calibration library offline.

Inputs are a validation dump v1 (`.npz`) or a nuScenes results JSON with its ground-truth JSON
(`--nuscenes-gt`), or for a 2-D profile a COCO results JSON with its instances (`--gt`,
`app.cli.coco`). Heavy imports happen inside the handlers so `detcal --help` stays fast.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from app.cli.main import CliError
from app.fitting.options import fit_option_specs, options_of
from calibrators.core.defaults import DEFAULT_LEVELS, ELLIPSE_CONFIDENCE, MATCH_THRESHOLD
from calibrators.fit import FitOptions

#: Ellipse levels `detcal calibrate` writes when --levels is not given (as the service's).


FIT_DESCRIPTION = """\
Match detections to ground truth, choose and fit each stage of the profile (score
calibration, covariance scaling, regions: see the fit options), print the chosen method of
each stage with its held-out score and the before/after table, and write the profile JSON. A
Parquet dataset folder (detcal convert) is fit streamed, in bounded memory, with the thesis
methods (temperature, depth, gaussian: pass --calibration 0 or name them), optionally on
Dask (--dask). A COCO results JSON with --gt (its instances JSON) fits a 2-D profile."""

EVALUATE_DESCRIPTION = """\
nuScenes mAP / NDS, per-class AP, and calibration metrics (before, and after the profile if
one is given)."""

CALIBRATE_DESCRIPTION = """\
Apply a profile to an NPZ dump or a nuScenes results JSON and write a nuScenes results JSON
with the calibrated detection_score and, as extra keys, the raw score, the calibrated
covariance and the ellipses at --levels; with a 2-D profile, a COCO results JSON into
calibrated COCO results (score, score_raw, an inner and outer box per level)."""

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `fit`, `evaluate` and `calibrate` subcommands."""
    fit = subparsers.add_parser(
        "fit", help="fit a calibration profile on a validation dump",
        description=FIT_DESCRIPTION)
    add_dump_input(fit)
    fit.add_argument("--from", dest="source_format", metavar="FORMAT",
                     help="coco: DUMP is a COCO results JSON and --gt its instances JSON (a "
                          "2-D profile; a JSON list with --gt is read as COCO without it)")
    fit.add_argument("--gt", metavar="INSTANCES.json", help="COCO instances of --from coco")
    fit.add_argument("--out", default="profile.json", help="profile JSON to write "
                     "(default: %(default)s)")
    add_fit_options(fit)
    fit.add_argument("--dask", metavar="SPEC",
                     help="Parquet dataset only: run the per-part work on Dask: local[:N] "
                          "starts a LocalCluster of N worker processes (default 2), "
                          "tcp://host:port connects to a scheduler (needs detcal[dask])")
    fit.add_argument("--quiet", action="store_true", help="no progress on stderr")
    fit.set_defaults(func=run_fit)

    ev = subparsers.add_parser(
        "evaluate", help="mAP and calibration metrics of a dump",
        description=EVALUATE_DESCRIPTION)
    add_dump_input(ev)
    ev.add_argument("--profile", help="profile JSON to apply")
    ev.add_argument("--threshold", type=float, default=MATCH_THRESHOLD,
                    help="matching distance for the calibration metrics (default: %(default)s)")
    ev.add_argument("--json", action="store_true", help="print one JSON document")
    ev.set_defaults(func=run_evaluate)

    cal = subparsers.add_parser(
        "calibrate", help="calibrate detections offline into a nuScenes results JSON",
        description=CALIBRATE_DESCRIPTION)
    cal.add_argument("file", metavar="FILE", help="NPZ dump or nuScenes results JSON")
    cal.add_argument("--profile", required=True, help="profile JSON to apply")
    cal.add_argument("--levels", nargs="+", metavar="Q", default=list(DEFAULT_LEVELS),
                     help="coverage levels of the ellipses written per result, each in (0, 1), "
                          "at most 20 (default: %(default)s)")
    cal.add_argument("--nuscenes-gt", metavar="GT.json",
                     help="ground-truth JSON giving the frames' ego positions (results JSON)")
    cal.add_argument("--gt", metavar="INSTANCES.json",
                     help="2-D profile: the COCO instances of FILE's images (their sizes)")
    cal.add_argument("--out", default="-", help="output JSON (default: stdout)")
    cal.set_defaults(func=run_calibrate)


def add_fit_options(parser: argparse.ArgumentParser) -> None:
    """One flag per option of a 3-D or a COCO fit (`--min-score` for `min_score`;
    `app.fitting.options`), with its type, default, choices and help: the same options, names
    and defaults as POST /v1/fit's form."""
    for spec in fit_option_specs():
        flag = "--" + spec.name.replace("_", "-")
        if spec.type is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction,
                                default=spec.default, help=spec.help)
            continue
        text = spec.help if spec.default is None else f"{spec.help} (default: %(default)s)"
        parser.add_argument(flag, type=spec.type, default=spec.default, choices=spec.choices,
                            help=text)


def fit_options_of(args: argparse.Namespace, coco: bool = False) -> Any:
    """The `FitOptions` (or with `coco` the `FitOptions2D`) of parsed `add_fit_options` flags;
    ValueError naming a bad one, or one the other kind of fit takes (set to a non-default)."""
    specs = fit_option_specs()
    values = {spec.name: getattr(args, spec.name) for spec in specs}
    given = {spec.name for spec in specs if values[spec.name] != spec.default}
    return options_of(values, given, coco)


def add_dump_input(parser: argparse.ArgumentParser) -> None:
    """The DUMP argument and --nuscenes-gt (read by `load_input`)."""
    parser.add_argument("dump", metavar="DUMP",
                        help="validation dump (.npz), or a nuScenes results JSON with "
                             "--nuscenes-gt")
    parser.add_argument("--nuscenes-gt", metavar="GT.json",
                        help="ground-truth JSON (DetectionBox form) when DUMP is a results JSON")


# -- handlers --------------------------------------------------------------------------------
def run_fit(args: argparse.Namespace) -> int:
    """`detcal fit`: fit, print the table, write the profile."""
    from app.cli.coco import is_coco_fit, run_fit_coco
    from calibrators import ProfileReport, fit_profile, format_table

    if is_coco_fit(args):
        return run_fit_coco(args, fit_options_of(args, coco=True))
    options = fit_options_of(args)
    progress = None if args.quiet else _progress
    if Path(args.dump).is_dir():
        profile = _fit_dataset(args, options, progress)
    else:
        if args.dask:
            raise CliError("--dask needs a Parquet dataset folder (detcal convert DUMP OUT_DIR)")
        dump, sha = load_input(args.dump, args.nuscenes_gt)
        profile = fit_profile(dump, options, dump_sha256=sha, progress=progress)
    write_text(args.out, profile.to_json())
    print(format_table(ProfileReport.from_dict(profile.report)))
    print(stages_text(profile.report))
    print(f"wrote {args.out}: T = {profile.temperature:.4g}, pooled k = {profile.pooled_k:.4g}, "
          f"cov_source {profile.cov_source}", file=sys.stderr)
    return 0


#: A stage whose method was named, or that had no calibration part to choose on.
_NOT_CHOSEN = "(named, or no calibration part to choose on: no held-out score)"


def stages_text(report: dict[str, Any]) -> str:
    """One line per stage of a fit report: the chosen method and its held-out score (the
    selection split's NLL / ECE for scores and covariances; the held-out part's coverage of
    the served regions, when the fit kept one)."""
    sel = report.get("selection") or {}
    lines = ["stages (chosen method: held-out score on the selection split)"]
    score, cov = sel.get("score"), sel.get("covariance")
    if score:
        best = score["candidates"].get(score["chosen"])
        lines.append(f"  score calibrator    {score['chosen']:<18} " + (
            f"NLL {best.get('nll', 0):.4f}  ECE {best.get('ece', 0):.4f}  "
            f"({len(score['candidates'])} candidates)" if best else _NOT_CHOSEN))
    if cov:
        best = cov["candidates"].get(cov["chosen"])
        lines.append(f"  covariance scaling  {cov['chosen']:<18} " + (
            f"regression NLL {best.get('nll') or 0:.4f}  ({len(cov['candidates'])} candidates)"
            if best else _NOT_CHOSEN))
    regions = sel.get("regions")
    if regions:
        held = ((report.get("holdout") or {}).get("regions") or {}).get("coverage")
        where = ("held-out coverage " + " / ".join(
            f"{q:g}: {c:.3f}" for q, c in zip(held["levels"], held["overall"], strict=True))
                 if held else "no held-out part (--holdout) to measure coverage on")
        lines.append(f"  regions             {regions['chosen']:<18} {where}  "
                     f"({regions['calibration_tps']} calibration TPs)")
    return "\n".join(lines)


def _fit_dataset(args: argparse.Namespace, options: FitOptions,
                 progress: Callable[[str, float], None] | None) -> Any:
    """The streamed fit of a Parquet dataset folder, here or on Dask (`--dask`)."""
    from calibrators.fit import fit_profile_stream

    if args.nuscenes_gt:
        raise CliError("--nuscenes-gt does not apply to a Parquet dataset folder")
    if not args.dask:
        return fit_profile_stream(args.dump, options, progress=progress)
    from calibrators.fit import dask_client

    try:
        with dask_client(args.dask) as client:
            return fit_profile_stream(args.dump, options, client=client, progress=progress)
    except ImportError as exc:
        raise CliError(f"--dask: {exc}") from None


def run_evaluate(args: argparse.Namespace) -> int:
    """`detcal evaluate`: mAP, per-class AP and calibration metrics."""
    from calibrators import apply_profile, evaluate, format_table, summarize

    profile = load_profile(args.profile) if args.profile else None
    dump, _ = load_input(args.dump, args.nuscenes_gt)
    summary = summarize(dump, profile, threshold=args.threshold)
    ev = evaluate(dump)
    ev_after = None
    if profile is not None and dump.n_detections:
        scores = apply_profile(dump, profile).scores
        ev_after = evaluate(dump, scores=scores)
    if args.json:
        doc = {"evaluation": ev.to_dict(),
               "evaluation_calibrated": None if ev_after is None else ev_after.to_dict(),
               "calibration": summary.to_dict()}
        print(json.dumps(doc, allow_nan=False))
        return 0
    print(_ap_table(ev.to_dict(), None if ev_after is None else ev_after.to_dict()))
    print()
    print(format_table(summary))
    return 0


def run_calibrate(args: argparse.Namespace) -> int:
    """`detcal calibrate`: write a calibrated nuScenes results JSON with ellipses per level."""
    from calibrators.io.nuscenes_batch import calibrated_document

    levels = _levels(args.levels)
    profile = load_profile(args.profile, kinds=("3d", "boxes2d"))
    if profile.kind == "boxes2d":
        from app.cli.coco import run_calibrate_coco

        return run_calibrate_coco(args, profile, levels)
    if args.gt:
        raise CliError("--gt names the COCO instances of a 2-D profile's input; a 3-D "
                       "profile's nuScenes results take --nuscenes-gt")
    path = Path(args.file)
    if path.is_dir():
        batches, meta = _dump_batches(path, profile), None
    elif _existing(args.file).suffix.lower() == ".json":
        batches, meta = _results_batches(path, profile, args.nuscenes_gt)
    else:
        batches, meta = _dump_batches(path, profile), None
    served = [_served(batch.calibrate, profile=profile, levels=levels) for batch in batches]
    doc = calibrated_document(served, {"profile": str(args.profile), "levels": levels,
                                       "ellipse_confidence": ELLIPSE_CONFIDENCE}, meta)
    write_text(args.out, json.dumps(doc, allow_nan=False))
    n = sum(map(len, served))
    print(f"detcal calibrate: {n} detections in {len(doc['results'])} frames calibrated with "
          f"{args.profile} ({profile.score_method}, {profile.cov_method}, "
          f"{profile.region_method}) -> {'stdout' if args.out == '-' else args.out}",
          file=sys.stderr)
    return 0


def _levels(values: list[str]) -> list[float]:
    """`--levels` as floats, checked by the library (at most 20, distinct, in (0, 1))."""
    from calibrators.core.errors import FieldError
    from calibrators.regions import check_levels

    try:
        return check_levels([float(v) for v in values], "--levels").tolist()
    except ValueError as exc:
        text = str(exc) if isinstance(exc, FieldError) else f"must be numbers in (0, 1): {exc}"
        raise CliError(text if text.startswith("--levels") else f"--levels {text}") from None


def _served(calibrate: Callable[..., Any], **arrays: Any) -> Any:
    """`calibrate(**arrays)` (`apply_profile` or `CalibrationProfile.calibrate`); a level the
    profile cannot serve (a conformal group with too few calibration points) is a CliError
    naming --levels."""
    from calibrators.core.errors import FieldError

    try:
        return calibrate(**arrays)
    except FieldError as exc:
        if exc.field == "levels":
            raise CliError(f"--levels: {exc}") from None
        raise CliError(f"{exc.field}: {exc}") from None


def _dump_batches(path: Path, profile: Any) -> list[Any]:
    """The detections of an NPZ dump or a Parquet dataset folder, each with its identity
    (frame token, dump row)."""
    from calibrators import check_profile_fits
    from calibrators.io.npz import load_dump
    from calibrators.io.parquet import load_parquet
    from calibrators.profile import Detections

    try:   # the library's messages name no file: here do
        dump = load_parquet(str(path)) if path.is_dir() else load_dump(str(path))
        check_profile_fits(dump, profile)
    except ValueError as exc:
        raise CliError(f"{path}: {exc}") from None
    return [Detections.from_dump(dump, profile.cov_source)]


def _results_batches(path: Path, profile: Any, gt_path: str | None
                     ) -> tuple[list[Any], dict | None]:
    """The boxes of a results document (checked by `load_nuscenes`), one batch per evidence
    form, and its meta.

    Boxes without `detection_logits` are calibrated from their score and `detection_name`
    (`sigmoid(logit(p) / T)`, or the profile's per-class calibrator). With `--nuscenes-gt`
    the frames' ego positions come from both files; without it, distances are measured from
    each box's `ego_translation` if it has one, else from the origin (ego-frame results).
    """
    from calibrators.io import load_nuscenes
    from calibrators.io.nuscenes_batch import detections_from_nuscenes

    gt = None if gt_path is None else str(_existing(gt_path))
    try:
        dump = load_nuscenes(str(path), gt, classes=profile.classes)
        doc = json.loads(path.read_bytes())
        ego = None if gt is None or dump.ego_translation is None else {
            str(t): e for t, e in zip(dump.frame_ids.tolist(), dump.ego_translation.tolist(),
                                      strict=True)}
        batches = detections_from_nuscenes(doc, profile.classes, profile.score_mode, ego)
    except ValueError as exc:
        raise CliError(f"{path}: {exc}") from None
    return batches, doc.get("meta") if isinstance(doc.get("meta"), dict) else None


# -- helpers ---------------------------------------------------------------------------------
def load_input(path: str, nuscenes_gt: str | None) -> tuple[Any, str]:
    """(Dump, sha256) from an NPZ dump or a nuScenes results + ground-truth JSON pair.

    The pair's sha256 is that of the two files' hex digests joined by a newline.
    """
    from calibrators.io import file_sha256, load_dump, load_nuscenes

    p = _existing(path)
    if p.suffix.lower() == ".json" and nuscenes_gt is None:
        raise CliError(f"{path} is a JSON file: a nuScenes results JSON needs --nuscenes-gt "
                       f"GT.json")
    try:   # the library's messages name no file (a service must not show its paths): here do
        if nuscenes_gt is None:
            return load_dump(str(p)), file_sha256(str(p))
        gt = _existing(nuscenes_gt)
        dump = load_nuscenes(str(p), str(gt))
    except ValueError as exc:
        raise CliError(f"{path}: {exc}") from None
    pair = f"{file_sha256(str(p))}\n{file_sha256(str(gt))}"
    return dump, hashlib.sha256(pair.encode()).hexdigest()


def load_profile(path: str, kinds: tuple[str, ...] = ("3d",)) -> Any:
    """A profile of one of `kinds` from a JSON file (`read_profile`: a CalibrationProfile, or
    a 2-D `Profile2D`); a CliError naming the bad key or the kind this command lacks."""
    from calibrators.profile import read_profile

    try:
        profile = read_profile(_existing(path).read_bytes())
    except ValueError as exc:
        raise CliError(f"{path} is not a valid profile: {exc}") from None
    if profile.kind not in kinds:
        raise CliError(f"{path} is a {'2-D' if profile.kind == 'boxes2d' else '3-D'} profile; "
                       f"this command reads {' and '.join(kinds)} profiles")
    return profile


def _existing(path: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise CliError(f"{path}: no such file")
    return p


def write_text(path: str, text: str) -> None:
    """Write `text` to `path` atomically (`-` = stdout)."""
    if path == "-":
        sys.stdout.write(text + "\n")
        return
    from calibrators.io import atomic_write

    with atomic_write(path, "w") as fh:
        fh.write(text + "\n")


def _progress(stage: str, fraction: float) -> None:
    print(f"detcal fit: {stage} ({fraction:.0%})", file=sys.stderr, flush=True)


def _ap_table(ev: dict, ev_after: dict | None) -> str:
    thresholds = [str(t) for t in ev["thresholds"]]
    head = f"mAP {ev['mean_ap']:.4f}  NDS {ev['nd_score']:.4f}"
    if ev_after is not None:
        head += f"  (calibrated scores: mAP {ev_after['mean_ap']:.4f})"
    lines = [head, f"{'class':<22}" + "".join(f"{'AP@' + t:>10}" for t in thresholds)
             + f"{'mean':>10}"]
    for name, by_t in ev["ap"].items():
        cells = "".join(_num(by_t.get(t)) for t in thresholds)
        lines.append(f"{name:<22}{cells}{_num(ev['class_ap'].get(name))}")
    return "\n".join(lines)


def _num(value: float | None) -> str:
    return f"{'-':>10}" if value is None else f"{value:>10.4f}"
