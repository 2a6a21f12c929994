"""Markdown of the report: one section per sensor and `docs/report/README.md` around them.

The text around the tables is generated from the measured numbers (which row is best, by
how much), never written to match the thesis.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from detectors.report import tables
from detectors.report.honest import LEVELS, honest_markdown
from detectors.report.rows import EXPECTED_MD, Row

if TYPE_CHECKING:
    from detectors.report.sensor import ReportOptions, SensorReport

DE_COMMANDS = """\
Deep ensembles (DE N = 2/4): member 0 is the report's lidar model, `lidar_de0.pt` (the v1
lidar detector, training seed 0; the shipped `lidar.pt` is v2 (group heads), compared with
it in [detectors_v2.md](detectors_v2.md)), the others are the same v1 recipe with seeds 1-3;
the deep sub-ensemble (DSE N = 2) is two new decoder heads trained on the frozen trunk of
member 0 (thesis 4.3.3; merged by query index like MC dropout, since both heads decode the
same heatmap queries; the trunk runs once per frame). Every lidar row of this report (vanilla
and MC dropout too) measures that v1 model, so all baselines measure one detector. The
weights ship in `detectors/weights/`; they were trained with the v1 recipe (the commands ran
when it was the registry's, before v2):

```
detcal train --sensor lidar --seed 1 --run-dir runs/lidar_de1 --out detectors/weights/lidar_de1.pt
detcal train --sensor lidar --seed 2 --run-dir runs/lidar_de2 --out detectors/weights/lidar_de2.pt
detcal train --sensor lidar --seed 3 --run-dir runs/lidar_de3 --out detectors/weights/lidar_de3.pt
detcal train --sensor lidar --seed 1 --base-weights detectors/weights/lidar_de0.pt \\
    --run-dir runs/lidar_dse1 --out detectors/weights/lidar_dse1.pt
detcal train --sensor lidar --seed 2 --base-weights detectors/weights/lidar_de0.pt \\
    --run-dir runs/lidar_dse2 --out detectors/weights/lidar_dse2.pt
```

The report picks up `{sensor}_de{i}.pt` and `{sensor}_dse{1,2}.pt` for any sensor where they
exist; only lidar has them (the CPU budget of 2 cores: a member takes about 22 min alone,
37-43 min when two train side by side).
Rows without weights read "not trained"; they are never estimated or copied from elsewhere."""


def sensor_section(r: SensorReport, options: ReportOptions) -> str:
    """The markdown section of one sensor."""
    s = r.sensor
    parts = [f"## {s}", _summary(r),
             f"Fit on the first {options.val_frames} val scenes, measured on the first "
             f"{options.test_frames} test scenes; {options.max_detections} detections per frame "
             f"(best final-layer scores; merged sampling outputs are cut to the same number); "
             f"TP = same class within 2 m (nuScenes rule). Time: model forward per frame "
             f"(all passes) and post-processing per frame (merging or calibration), on this "
             f"machine during the report run. Built in {r.seconds:.0f} s.",
             tables.main_table(r.rows, r.missing), tables.nominal_coverage_line(),
             f"Depth Scaling row: the {r.best_profile} profile (lower val class NLL of TS and "
             f"TS+Mod; T = {r.temperature:.3f}) with Σ' = Σ_layers + k_c·d·I.",
             "### Class-wise, vanilla", tables.class_table(r.vanilla_classes),
             "### Class-wise, Depth Scaling", tables.class_table(r.calibrated_classes),
             "" if r.honest is None else honest_markdown(r.honest, tables.number),
             "### Attention spread (seed 000)"]
    if r.attention is not None:
        parts.append(tables.attention_tables(r.attention))
    parts += ["Covariance sources, each depth-scaled with its own k fit on val "
              "(regression only; classification is the same TS for all):",
              tables.regression_table(r.covariance_rows), _attention_verdict(r.covariance_rows),
              "### Figures", _figures(s)]
    return "\n\n".join(p for p in parts if p) + "\n"


def _figures(sensor: str) -> str:
    names = [("reliability", "reliability per class, vanilla vs calibrated"),
             ("calibration_xy", "average calibration x / y"),
             ("residuals", "residual vs predicted σ"),
             ("bev", "one test frame before / after"),
             ("attention_spread", "attention spread vs IoU, distance, layer")]
    return "\n".join(f"- {text}: ![{sensor} {text}](plots/{sensor}_{stem}.png) "
                     f"([SVG](plots/{sensor}_{stem}.svg))" for stem, text in names)


def _find(rows: Sequence[Row], prefix: str) -> Row | None:
    return next((r for r in rows if r.name.startswith(prefix)), None)


def _summary(r: SensorReport) -> str:
    """Two or three sentences on what the numbers show."""
    van, ds = _find(r.rows, "Vanilla"), _find(r.rows, "Depth Scaling")
    if van is None or ds is None:
        return ""
    out = []
    if van.mean_md is not None and ds.mean_md is not None:
        out.append(f"Depth scaling moves the mean Mahalanobis distance from {van.mean_md:.3g} "
                   f"to {ds.mean_md:.3g} (calibrated: {EXPECTED_MD:.3f}) and the regression "
                   f"NLL from {tables.number(van.reg_nll)} to {tables.number(ds.reg_nll)}.")
    out.append(f"Classification: ECE {van.ece:.4f} → {ds.ece:.4f}, class NLL "
               f"{van.cls_nll:.4f} → {ds.cls_nll:.4f}, mAP {van.mean_ap:.3f} → "
               f"{ds.mean_ap:.3f} (calibration re-scores, so mAP moves only through the "
               f"ranking across classes).")
    sampling = [row for row in r.rows if row.name.startswith(("MCD", "DE", "DSE"))
                and row.mean_md is not None]
    if sampling:
        best = min(sampling, key=lambda row: row.mean_md or float("inf"))
        out.append(f"The sampling row with the lowest mean MD ({best.name}) reaches "
                   f"{best.mean_md:.3g} on {best.n_used} of its {best.n_tp} TPs (the others "
                   f"have a singular cluster covariance), at "
                   f"{best.forward_ms / max(van.forward_ms, 1e-9):.1f}× the vanilla forward "
                   f"time.")
    return " ".join(out)


def _attention_verdict(rows: Sequence[Row]) -> str:
    by = {row.name: row for row in rows}
    a, b = by.get("attention spread + cell²/12 + DS"), by.get("layer spread + DS")
    z = by.get("Σ = 0 + DS (distance only)")
    if a is None or b is None or a.reg_nll is None or b.reg_nll is None:
        return ""
    better = "better than" if a.reg_nll < b.reg_nll else "worse than"
    text = (f"After depth scaling, the attention-spread covariance gives a regression NLL of "
            f"{a.reg_nll:.4g}, {better} the layer spread's {b.reg_nll:.4g}")
    if a.mean_md is not None and a.mean_md < EXPECTED_MD:
        text += (f" (its mean MD {a.mean_md:.3g} is below E[χ₂] = {EXPECTED_MD:.3f}: the raw "
                 f"attention covariance is already too wide, and depth scaling can only add "
                 f"variance, k ≥ 0)")
    if z is not None and z.reg_nll is not None:
        text += (f"; depth scaling from Σ = 0 (distance alone) gives {z.reg_nll:.4g}, the "
                 f"reference either source has to beat to show it carries information")
    return text + "."


def readme(reports: Sequence[SensorReport], command: str, seconds: float,
           options: ReportOptions) -> str:
    """`docs/report/README.md`: the command, the sections, the DE/DSE training commands."""
    head = [
        "# detcal report: calibration vs sampling baselines on the bundled detectors",
        f"Generated by `{command}` (total {seconds / 60:.1f} min on this machine, "
        f"{options.threads} torch thread(s); forward passes cached in `{options.cache}`, so "
        f"a re-run only recomputes what changed). Do not edit by hand: re-run the command.",
        "Rows follow the thesis's Figs. 5-2/5-5/5-7 (seed 002): Vanilla = the report's model "
        "(the shipped one; for lidar `lidar_de0.pt`, the v1 detector its ensembles were "
        "trained with) "
        "with the spread of the box across its 3 decoder layers as covariance; MCD N = N "
        "passes with dropout on, merged by query index (IoU > 0.5 with the top-scoring "
        "member, thesis Algorithm 1) and, for one N, by class-wise DBSCAN on 1 − BEV IoU "
        "(Algorithm 2), covariance = sample covariance of the cluster; TS = temperature "
        "scaling; Mod = logits modulation (Eq. 4-1) with T = 1; TS+Mod; Depth Scaling = the "
        "better classification setting plus Σ' = Σ + k_c·d·I. Everything is fit on val and "
        "measured on test. Regression metrics are over (x, y) of the true positives; a TP "
        "whose covariance is singular (e.g. every 2-pass MC-dropout cluster: 2 samples span "
        "one direction in 2-D) has no density and is left out, as the notes column says.",
    ]
    cached = [f"{r.sensor} {c}" for r in reports for c in r.from_cache]
    head[1] += (" Forward passes read from the cache in this run: "
                + (", ".join(cached) if cached else "none (cold run)") + ".")
    body = [r.markdown for r in reports]
    tail = ["## Deep ensembles and sub-ensembles", DE_COMMANDS]
    return "\n\n".join(head + [_overview(reports), _honest_overview(reports),
                               _discussion(reports)] + body + tail) + "\n"


def _honest_overview(reports: Sequence[SensorReport]) -> str:
    """One line per sensor: what detcal's default profile buys over global TS and Gaussian
    ellipses (class-wise ECE over classes with >= 500 test TPs)."""
    levels = " / ".join(f"{q:.0%}" for q in LEVELS)
    lines = ["## Honest uncertainty: detcal's default profile",
             f"| sensor | chosen stages | ECE TS → default | worst class ECE TS → default "
             f"| served coverage at {levels}: thesis DS → default | mean MD DS → shrinkage "
             f"(E = {EXPECTED_MD:.3f}) | mAP raw → default |",
             "|---|---|---|---|---|---|---|"]
    for r in reports:
        h = r.honest
        if h is None or h.default_row is None or h.ts_row is None:
            continue
        big = [c for c in h.classes if c.n_tp >= 500]
        worst = (max((c.ece_ts or 0.0) for c in big), max((c.ece_auto or 0.0) for c in big)
                 ) if big else (None, None)
        shrink, ds = _find(h.rows, "Shrinkage"), _find(r.rows, "Depth Scaling")
        thesis, default = h.regions[0], h.regions[-1]
        cells = [r.sensor, " + ".join(h.chosen),
                 f"{h.ts_row.ece:.4f} → {h.default_row.ece:.4f}",
                 f"{tables.number(worst[0])} → {tables.number(worst[1])}",
                 f"{_levels(thesis.coverage)} → {_levels(default.coverage)}",
                 f"{tables.number(None if ds is None else ds.mean_md)} → "
                 f"{tables.number(None if shrink is None else shrink.mean_md)}",
                 f"{_find(r.rows, 'Vanilla').mean_ap:.3f} → {h.default_row.mean_ap:.3f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n" + CELLS_LINK


#: Where the per-cell figures on held-out scenes are (written by `bench/bench_cells.py`).
CELLS_LINK = ("Per class × distance cell, with sampling intervals, on 3,000 scenes of the "
              "`holdout` split that no fit or choice used: [cells.md](cells.md), written by "
              "`bench/bench_cells.py --label` (the commands are in its docstring). Its "
              "sections `cross <sensor> holdout` set the default cross-fitted radii (every "
              "val frame calibrates) against split-conformal ones over four "
              "calibration-split seeds (`bench/bench_cross_regions.py --label`), and its "
              "sections `null <sensor> holdout` show what an exactly calibrated method "
              "leaves under the same criterion (`bench/bench_cells_null.py --label`).")


def _levels(values: Sequence[float]) -> str:
    return " / ".join(f"{v:.3f}" for v in values)


def _overview(reports: Sequence[SensorReport]) -> str:
    """One line per sensor: what depth scaling and the best sampling row buy."""
    lines = ["## Overview",
             f"| sensor | mAP | MD vanilla → DS (E = {EXPECTED_MD:.3f}) | reg. NLL vanilla → DS "
             f"| ECE vanilla → DS | lowest-MD sampling row: MD, cost |",
             "|---|---:|---|---|---|---|"]
    for r in reports:
        van, ds = _find(r.rows, "Vanilla"), _find(r.rows, "Depth Scaling")
        if van is None or ds is None:
            lines.append(f"| {r.sensor} | no shipped weights yet | | | | |")
            continue
        sampling = [row for row in r.rows if row.name.startswith(("MCD", "DE", "DSE"))
                    and row.mean_md is not None]
        best = min(sampling, key=lambda row: row.mean_md or float("inf"), default=None)
        cost = "-" if best is None else (
            f"{best.name}: {tables.number(best.mean_md)}, "
            f"{best.forward_ms / max(van.forward_ms, 1e-9):.1f}× forward")
        lines.append(
            f"| {r.sensor} | {van.mean_ap:.3f} | {tables.number(van.mean_md)} → "
            f"{tables.number(ds.mean_md)} | {tables.number(van.reg_nll)} → "
            f"{tables.number(ds.reg_nll)} | {van.ece:.4f} → {ds.ece:.4f} | {cost} |")
    return "\n".join(lines)


def _discussion(reports: Sequence[SensorReport]) -> str:
    """What the numbers show across sensors, written from the rows (never by hand)."""
    done = [(r, _find(r.rows, "Vanilla"), _find(r.rows, "Depth Scaling")) for r in reports]
    done = [(r, v, d) for r, v, d in done if v is not None and d is not None]
    if not done:
        return ""
    out = ["## Discussion (generated from the rows above)"]
    mds = [d.mean_md for _, _, d in done if d.mean_md is not None]
    posts = [d.post_ms for _, _, d in done]
    if mds:
        out.append(f"- **Depth scaling** brings the mean Mahalanobis distance to "
                   f"{min(mds):.3g}–{max(mds):.3g} on every sensor (a calibrated 2-D Gaussian "
                   f"gives {EXPECTED_MD:.3f}) for at most {max(posts):.2f} ms of "
                   f"post-processing per frame and no extra forward pass.")
    sampling = [(r.sensor, row, v) for r, v, _ in done for row in r.rows
                if row.name.startswith(("MCD", "DE", "DSE")) and row.mean_md is not None]
    if sampling:
        sensor, best, van = min(sampling, key=lambda t: t[1].mean_md or float("inf"))
        out.append(f"- **Sampling baselines** stay over-confident: the closest to calibrated "
                   f"of all of them is {best.name} on {sensor} with a mean MD of "
                   f"{best.mean_md:.3g} at {best.forward_ms / max(van.forward_ms, 1e-9):.1f}× "
                   f"the forward time; their regression NLL is "
                   f"{_range([row.reg_nll for _, row, _ in sampling])}, against "
                   f"{_range([d.reg_nll for _, _, d in done])} after depth scaling.")
    eces = [(v.ece, d.ece) for _, v, d in done]
    mod = max(abs(_row(r, "Mod").ece - v.ece) for r, v, _ in done)
    ts_mod = max(abs(_row(r, "TS+Mod").ece - _row(r, "TS").ece) for r, _, _ in done)
    out.append(f"- **Classification**: temperature scaling takes ECE from "
               f"{_range([a for a, _ in eces])} to {_range([b for _, b in eces])}; logits "
               f"modulation alone changes it by at most {mod:.3f}, and TS+Mod is within "
               f"{ts_mod:.3f} of TS alone.")
    for r, v, _ in done:
        de = _find(r.rows, "DE N=4")
        if de is not None:
            out.append(f"- **Deep ensemble** ({r.sensor}, N = 4, DBSCAN merge): mAP "
                       f"{de.mean_ap:.3f} against {v.mean_ap:.3f} for the single model, ECE "
                       f"{de.ece:.4f} against {v.ece:.4f}, at "
                       f"{de.forward_ms / max(v.forward_ms, 1e-9):.1f}× the forward time.")
    order = sorted(done, key=lambda t: -t[1].mean_ap)
    out.append("- **Sensors** by mAP: " + " > ".join(f"{r.sensor} ({v.mean_ap:.3f})"
                                                    for r, v, _ in order) + ".")
    return "\n".join(out)


def _row(r: SensorReport, name: str) -> Row:
    return next(row for row in r.rows if row.name == name)


def _range(values: Sequence[float | None]) -> str:
    vals = [v for v in values if v is not None]
    if not vals:
        return "-"
    lo, hi = tables.number(min(vals)), tables.number(max(vals))
    return lo if lo == hi else f"{lo}–{hi}"
