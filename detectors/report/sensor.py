"""Build one sensor's report: forward passes, rows, class-wise tables, seed-000 analysis, plots.

`build_sensor(sensor, options)` fits every calibration on the val split and measures every
row on the test split (`detectors.report.rows`), draws the figures into
`{out}/plots/{sensor}_*.{png,svg}` and returns a `SensorReport` whose `markdown` is the
sensor's section of `docs/report/README.md` (also written to `{out}/{sensor}.md`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibrators import (
    CalibratedDetections,
    Dump,
    MatchResult,
    apply_profile,
    fit_profile,
    layer_spread,
    match_dump,
    tp_residuals,
)
from detectors.report import plots
from detectors.report.attention import AttentionStats, attention_stats
from detectors.report.dumps import merged_sampling_dump, vanilla_dump
from detectors.report.honest import HonestSection, honest_section
from detectors.report.rows import (
    ClassRow,
    Row,
    class_rows,
    fit_profiles,
    measure,
    profile_row,
    sampling_row,
    vanilla_row,
)
from detectors.report.runner import MethodSpec, Passes, Truth, run_split

NOT_TRAINED = "not trained (see docs/report/README.md)"
DE_SIZES = (2, 4)
Log = Callable[[str], None]


@dataclass(frozen=True)
class ReportOptions:
    """Frame counts, MC-dropout sizes, detections kept per frame, folders, BEV frame."""

    out: Path
    cache: Path
    val_frames: int = 200
    test_frames: int = 200
    mcd: tuple[int, ...] = (2, 4, 6)
    max_detections: int = 100
    bev_frame: int = 0
    min_score: float = 0.3
    threads: int = 2


@dataclass
class SensorReport:
    """Everything measured for one sensor (rows in table order) and its markdown section."""

    sensor: str
    rows: list[Row] = field(default_factory=list)
    missing: list[tuple[str, str]] = field(default_factory=list)
    vanilla_classes: list[ClassRow] = field(default_factory=list)
    calibrated_classes: list[ClassRow] = field(default_factory=list)
    attention: AttentionStats | None = None
    honest: HonestSection | None = None
    covariance_rows: list[Row] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)
    best_profile: str = ""
    from_cache: list[str] = field(default_factory=list)
    temperature: float = 1.0
    seconds: float = 0.0
    markdown: str = ""


def report_base(sensor: str) -> Path:
    """The model the report measures (vanilla, MC dropout, DE member 0, the DSE heads'
    trunk): `{sensor}_de0.pt` where it exists, else the shipped `{sensor}.pt`.

    A sensor whose shipped model moved on while its deep ensemble did not (lidar: v2 group
    heads since issue 13, its DE members 1-3 and DSE heads are v1) keeps the model its
    ensemble was trained with as DE member 0, so that every sampling baseline measures the
    same detector; docs/report/detectors_v2.md compares the two models."""
    from detectors.registry import WEIGHTS_DIR, weights_path

    member0 = WEIGHTS_DIR / f"{sensor}_de0.pt"
    return member0 if member0.exists() else weights_path(sensor)


def weights_for(sensor: str, kind: str, n: int) -> tuple[Path, ...] | None:
    """Member weights of `kind` with `n` members, or None if one is missing.

    "de": the report's base model (`report_base`) then `{sensor}_de{i}.pt` (i = 1..n-1);
    "dse": the `n` heads trained on the base model's frozen trunk, `{sensor}_dse{i}.pt`
    (i = 1..n; the thesis's sub-ensemble is made of the new heads only)."""
    from detectors.registry import WEIGHTS_DIR

    if kind == "de":
        members = [report_base(sensor), *(WEIGHTS_DIR / f"{sensor}_de{i}.pt"
                                          for i in range(1, n))]
    else:
        members = [WEIGHTS_DIR / f"{sensor}_dse{i}.pt" for i in range(1, n + 1)]
    return tuple(members) if all(p.exists() for p in members) else None


def _check_sub_ensemble(sensor: str, heads: tuple[Path, ...]) -> None:
    """Sub-ensemble heads must sit on the report base's trunk (stale heads after a retrain
    of that model would measure another model)."""
    from detectors.registry import build_detector
    from detectors.subensemble import same_trunk

    base_path = report_base(sensor)
    base = build_detector(sensor, weights=base_path)
    for path in heads:
        if not same_trunk(base, build_detector(sensor, weights=path)):
            raise ValueError(f"{path} was not trained on the trunk of {base_path.name}; "
                             f"retrain it with `detcal train --sensor {sensor} "
                             f"--base-weights detectors/weights/{base_path.name} --out {path}`")


def build_sensor(sensor: str, options: ReportOptions, log: Log = print) -> SensorReport:
    """The whole report of `sensor` (module docstring)."""
    from detectors.sim import CLASSES, split_seeds

    start = time.perf_counter()
    report = SensorReport(sensor)
    shipped = report_base(sensor)   # the model every row measures
    if not shipped.exists():
        report.markdown = (f"## {sensor}\n\nNo shipped weights yet "
                           f"(`detectors/weights/{sensor}.pt`): train them with "
                           f"`detcal train --sensor {sensor}`, then re-run the report.\n")
        return report
    classes = tuple(CLASSES)
    test_specs = [MethodSpec("vanilla", (shipped,), 1)]
    if options.mcd:
        test_specs.append(MethodSpec("mcd", (shipped,), max(options.mcd)))
    de = next((w for n in sorted(DE_SIZES, reverse=True)
               if (w := weights_for(sensor, "de", n)) is not None), None)
    if de is not None:
        test_specs.append(MethodSpec("de", de, len(de)))
    dse = weights_for(sensor, "dse", 2)
    if dse is not None:
        _check_sub_ensemble(sensor, dse)
        test_specs.append(MethodSpec("dse", dse, 2))

    def progress(split: str, i: int, n: int) -> None:
        if i == n or i % 50 == 0:
            log(f"  {sensor} {split}: {i}/{n} frames")

    val_truth, val = run_split(sensor, split_seeds("val", options.val_frames),
                               [MethodSpec("vanilla", (shipped,), 1)], options.cache, "val",
                               options.max_detections, progress)
    test_truth, test = run_split(sensor, split_seeds("test", options.test_frames), test_specs,
                                 options.cache, "test", options.max_detections, progress)
    report.from_cache = sorted([f"val {k}" for k, p in val.items() if p.from_cache]
                               + [f"test {k}" for k, p in test.items() if p.from_cache])
    log(f"  {sensor}: passes from cache: {report.from_cache or 'none'}")

    val_dump = vanilla_dump(val["vanilla"], val_truth, classes)
    test_dump = vanilla_dump(test["vanilla"], test_truth, classes)
    _rows(report, options, val_dump, test_dump, test, test_truth, classes, log)
    _attention(report, val_dump, val["vanilla"], val_truth, test["vanilla"], test_truth,
               test_dump, classes, options)
    report.seconds = time.perf_counter() - start
    from detectors.report.markdown import sensor_section

    report.markdown = sensor_section(report, options)
    (options.out / f"{sensor}.md").write_text(report.markdown)
    return report


def _rows(report: SensorReport, options: ReportOptions, val_dump: Dump, test_dump: Dump,
          test: dict[str, Passes], truth: Truth, classes: tuple[str, ...], log: Log) -> None:
    """Main table, class-wise tables and the calibration figures."""
    m = match_dump(test_dump)
    vanilla_ms = test["vanilla"].forward_ms_per_frame()
    profiles = fit_profiles(val_dump)
    report.best_profile, report.temperature = profiles.best_name, profiles.best.temperature
    rows = [vanilla_row(test_dump, vanilla_ms, m)]
    sampling_rows, merged = _sampling_rows(report, options, test, truth, classes)
    rows += sampling_rows
    rows += [profile_row("TS", test_dump, profiles.ts, vanilla_ms, False, m),
             profile_row("Mod", test_dump, profiles.mod, vanilla_ms, False, m),
             profile_row("TS+Mod", test_dump, profiles.ts_mod, vanilla_ms, False, m),
             profile_row(f"Depth Scaling ({profiles.best_name} + DS)", test_dump,
                         profiles.best, vanilla_ms, True, m)]
    report.rows = rows
    log(f"  {report.sensor}: {len(rows)} rows measured")
    report.honest = honest_section(val_dump, test_dump, m, vanilla_ms, profiles.best)
    log(f"  {report.sensor}: beyond-the-thesis rows measured")

    calibrated = apply_profile(test_dump, profiles.best)
    raw_cov = layer_spread(test_dump.det_boxes, ("x", "y"))
    report.vanilla_classes = class_rows(test_dump, test_dump.det_scores, raw_cov, m)
    report.calibrated_classes = class_rows(test_dump, calibrated.scores,
                                           calibrated.covariances, m)
    report.figures += _figures(report.sensor, test_dump, m, raw_cov, calibrated, merged, truth,
                               classes, options)


def _sampling_rows(report: SensorReport, options: ReportOptions, test: dict[str, Passes],
                   truth: Truth, classes: tuple[str, ...]) -> tuple[list[Row], dict[str, Dump]]:
    """MCD (by query, and one N by DBSCAN), DE (DBSCAN) and DSE (by query) rows, plus the
    merged dumps by row name; absent DE / DSE weights go to `report.missing`."""
    rows: list[Row] = []
    merged: dict[str, Dump] = {}

    def add(name: str, passes: Passes, rule: str, keep: bool = True) -> None:
        md = merged_sampling_dump(passes, truth, classes, rule, options.max_detections)
        rows.append(sampling_row(name, md.dump, passes.forward_ms_per_frame(), md.merge_ms))
        if keep:
            merged[name] = md.dump

    for n in sorted(options.mcd):
        add(f"MCD N={n}", test["mcd"].first_members(n), "query")
    if options.mcd:
        n = 4 if 4 in options.mcd else max(options.mcd)
        add(f"MCD N={n} (DBSCAN merge)", test["mcd"].first_members(n), "dbscan", keep=False)
    for n in DE_SIZES:
        if "de" in test and test["de"].n_members >= n:
            add(f"DE N={n}", test["de"].first_members(n), "dbscan")
        else:
            report.missing.append((f"DE N={n}", NOT_TRAINED))
    if "dse" in test:
        add("DSE N=2", test["dse"], "query")
    else:
        report.missing.append(("DSE N=2", NOT_TRAINED))
    return rows, merged


def _figures(sensor: str, test_dump: Dump, m: MatchResult, raw_cov: np.ndarray,
             calibrated: CalibratedDetections, merged: dict[str, Dump], truth: Truth,
             classes: tuple[str, ...], options: ReportOptions) -> list[Path]:
    """Reliability per class, calibration curves and residuals (vanilla, the largest
    sampling method: DE N=4 if trained, else the largest MCD; Depth Scaling), BEV."""
    stem = options.out / "plots" / sensor
    tp = np.asarray(m.tp, dtype=bool)
    files = plots.reliability_per_class(
        classes, tp, test_dump.det_labels,
        {"vanilla": test_dump.det_scores, "calibrated": calibrated.scores},
        Path(f"{stem}_reliability"))
    res = {"Vanilla": tp_residuals(test_dump, m)}
    cov = {"Vanilla": raw_cov[tp]}
    sampling = next((k for k in ("DE N=4", "DE N=2") if k in merged),
                    max(merged, key=lambda k: int(k.split("=")[1])) if merged else None)
    if sampling is not None:
        sm = merged[sampling]
        ms = match_dump(sm)
        res[sampling], cov[sampling] = tp_residuals(sm, ms), sm.det_cov[ms.tp]
    res["Depth Scaling"], cov["Depth Scaling"] = res["Vanilla"], calibrated.covariances[tp]
    files += plots.calibration_curves(res, cov, Path(f"{stem}_calibration_xy"))
    files += plots.residual_plots(res, cov, Path(f"{stem}_residuals"))
    files += _bev(sensor, test_dump, truth, raw_cov, calibrated, classes, options,
                  Path(f"{stem}_bev"))
    return files


def _bev(sensor: str, dump: Dump, truth: Truth, raw_cov: np.ndarray,
         calibrated: CalibratedDetections,
         classes: tuple[str, ...], options: ReportOptions, stem: Path) -> list[Path]:
    """BEV of test frame `options.bev_frame`: raw vs calibrated scores and ellipses."""
    from detectors.sim import make_frame

    f = min(max(options.bev_frame, 0), dump.n_frames - 1)
    frame = make_frame(int(truth.seeds[f]), sensor)
    det = dump.det_frame == f
    return plots.bev_before_after(
        np.asarray(frame.sensor_frame.points), truth.gt_boxes[truth.gt_frame == f],
        dump.final_boxes[det], dump.det_labels[det], classes,
        {f"{sensor} scene {truth.seeds[f]}: vanilla (layer spread)":
            (dump.det_scores[det], raw_cov[det]),
         "Depth Scaling (calibrated scores, Σ + k·d·I)":
            (calibrated.scores[det], calibrated.covariances[det])},
        stem, min_score=options.min_score)


def _attention(report: SensorReport, val_dump: Dump, val: Passes, val_truth: Truth,
               test: Passes, truth: Truth, test_dump: Dump, classes: tuple[str, ...],
               options: ReportOptions) -> None:
    """Seed-000 statistics and the covariance-source comparison (each + DS, fit on val)."""
    if test.attn_cov is None:
        raise ValueError("the vanilla test passes carry no attention covariance")
    report.attention = attention_stats(test_dump, test.attn_cov, test.token_cell,
                                       options.min_score)
    report.figures += plots.attention_plots(
        report.attention, options.out / "plots" / f"{report.sensor}_attention_spread")
    val_attn = vanilla_dump(val, val_truth, classes, attention_cov=True)
    test_attn = vanilla_dump(test, truth, classes, attention_cov=True)
    m = match_dump(test_dump)
    ms = test.forward_ms_per_frame()
    by_name = {r.name.split(" (")[0]: r for r in report.rows}
    layers_raw, layers_ds = by_name["Vanilla"], by_name["Depth Scaling"]
    attn_profile = fit_profile(val_attn, cov_source="given")
    zero_profile = fit_profile(val_dump, cov_source="none")
    report.covariance_rows = [
        _renamed(layers_raw, "layer spread (raw)"),
        _renamed(layers_ds, "layer spread + DS"),
        measure("attention spread + cell²/12 (raw)", test_attn, test_attn.det_scores,
                test_attn.det_cov, ms, m=m),
        profile_row("attention spread + cell²/12 + DS", test_attn, attn_profile, ms, True, m),
        profile_row("Σ = 0 + DS (distance only)", test_dump, zero_profile, ms, True, m),
    ]


def _renamed(row: Row, name: str) -> Row:
    from dataclasses import replace

    return replace(row, name=name)
