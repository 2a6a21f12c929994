"""The dashboard's panels of a 2-D profile (`kind: boxes2d`), from its fit report's held-out
part (`calibrators.boxes2d`, docs/boxes2d.md "Dashboard"): scores raw against calibrated,
reliability per category, the calibration over the image position, the box regions' coverage
per category × size, and one held-out image with its boxes.

A report written before detcal kept a panel's data lacks its key: that panel says so and the
others still draw. Matplotlib is imported when a figure is drawn (`plots`), never here.
"""

from __future__ import annotations

import html
from typing import Any

from app.calibrate.cache import LoadedProfile
from app.dashboard.image_plane import FP, TP, TRUTH, position_heatmap, sample_canvas
from app.dashboard.intervals import MIN_TPS, RULE, too_small
from app.dashboard.page import COVERAGE_MIN_TPS, COVERAGE_TOLERANCE

#: The most categories drawn as reliability panels (those with the most held-out TPs).
MAX_CLASS_PANELS = 20


def _e(value: Any) -> str:
    return html.escape(str(value))


def _num(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    return f"{value:.{digits}g}" if isinstance(value, float) else _e(value)


def _missing(what: str) -> str:
    return (f"<p class='note missing'>This profile's report has no {_e(what)} (it was fit "
            "before detcal kept it): not drawn.</p>")


def profile_summary(loaded: LoadedProfile, versions_html: str) -> str:
    """The active 2-D profile: what it serves, how it was chosen, its versions."""
    p, rec = loaded.profile, loaded.record
    size = "various" if p.image_size is None else f"{p.image_size[0]} × {p.image_size[1]} px"
    selection = (p.report.get("selection") or {}).get("score") or {}
    nll = " · ".join(f"{_e(name)} {c['nll']:.4g}"
                     for name, c in (selection.get("candidates") or {}).items())
    return (f"<p><b>{_e(rec.ref)}</b> · 2-D boxes (<code>boxes2d</code>) · scores "
            f"{_e(p.score_method)} · regions {_e(p.region_score or 'none')} · COCO IoU ≥ "
            f"{p.matching['iou_threshold']:g} · {len(p.category_ids)} categories · images "
            f"{size} · created {_e(p.provenance.get('created_at', '?'))}</p>"
            + (f"<p class='note'>Score calibrators by NLL on the calibration images: {nll}; "
               f"chosen {_e(selection.get('chosen'))}.</p>" if nll else "") + versions_html)


def report_panels(loaded: LoadedProfile) -> str:
    """Every panel of the active 2-D profile's held-out report, or a note saying why none."""
    held = loaded.profile.report.get("holdout")
    if not isinstance(held, dict):
        return ("<p class='note'>This 2-D profile has no held-out report (it was fit with "
                "<code>holdout</code> = 0): nothing to draw.</p>")
    from app.dashboard import plots

    parts = ["<div class='plots'><div><h3>held-out images</h3>", scores_table(held),
             "</div><div><h3>Per category</h3>", per_class_table(held), "</div></div>",
             "<h3 id='reliability-2d'>Reliability per category</h3>"]
    rel = held.get("reliability")
    if rel and rel.get("overall"):
        parts += ["<p class='note'>Held-out images; <i>before</i> is the detector's raw score, "
                  "<i>after</i> the calibrated one. Each title gives the category's true "
                  f"positives, and a panel with fewer than {MIN_TPS} is grey: too few to judge."
                  "</p><div class='plots'>",
                  plots.reliability({"reliability": _before_after(rel["overall"])},
                                    "Reliability (all categories)"),
                  plots.reliability_per_class(*_class_panels(held, rel)), "</div>"]
    else:
        parts.append(_missing("reliability diagrams"))
    parts.append("<h3 id='position-2d'>Calibration over the image position</h3>")
    pos = held.get("position")
    if pos:
        size = loaded.profile.image_size
        parts += [f"<p class='note'>D-ECE of the held-out detections in each cell of their box "
                  f"centre (the image split {len(pos['count'][0])} × {len(pos['count'])}, the "
                  "D-ECE's own position bins, drawn as in the image: left to right, top to "
                  "bottom); a figure is the cell's D-ECE and <i>n</i> its detections. On a few "
                  "dozen detections a cell's D-ECE stays above 0 even for calibrated scores "
                  f"(binning noise). Cells with fewer than {MIN_TPS} detections are grey: too "
                  "few to judge.</p>",
                  position_heatmap(pos, size[0] / size[1] if size else 4 / 3)]
    else:
        parts.append(_missing("calibration over position"))
    parts += ["<h3 id='coverage-2d'>Box regions: coverage per category × size</h3>",
              coverage_table(held), "<h3 id='sample-2d'>A held-out image</h3>",
              sample_section(held)]
    return "".join(parts)


def _before_after(pair: dict[str, Any] | None) -> dict[str, Any]:
    """A raw / calibrated pair under the keys `plots` reads (before / after)."""
    pair = pair or {}
    return {"before": pair.get("raw"), "after": pair.get("calibrated")}


def _class_panels(held: dict[str, Any], rel: dict[str, Any]
                  ) -> tuple[dict[str, Any], dict[str, int]]:
    tps = {name: row["true_positives"] for name, row in held.get("per_class", {}).items()}
    drawn = sorted((name for name, pair in rel["per_class"].items() if pair),
                   key=lambda name: -tps.get(name, 0))[:MAX_CLASS_PANELS]
    return ({"reliability_per_class": {n: _before_after(rel["per_class"][n]) for n in drawn}},
            {n: tps[n] for n in drawn if n in tps})


def _pair_row(name: str, pair: dict[str, Any] | None) -> str:
    raw, cal = (pair or {}).get("raw"), (pair or {}).get("calibrated")
    cls = "" if raw is None or cal is None else ("better" if cal < raw else "worse")
    return f"<tr><td>{_e(name)}</td><td>{_num(raw)}</td><td class='{cls}'>{_num(cal)}</td></tr>"


def scores_table(held: dict[str, Any]) -> str:
    """ECE, D-ECE (confidence × box centre) and LaECE_0 of the raw and calibrated scores."""
    caption = (f"{held['n_images']} images, {held['n_detections']} detections, "
               f"{held['n_true_positives']} true positives")
    return (f"<table class='scores-2d'><caption class='note'>{_e(caption)}</caption>"
            "<tr><th>metric</th><th>raw</th><th>calibrated</th></tr>"
            + _pair_row("ECE", held.get("ece")) + _pair_row("D-ECE (confidence × centre)",
                                                            held.get("d_ece"))
            + _pair_row("LaECE₀", held.get("laece")) + "</table>")


def per_class_table(held: dict[str, Any]) -> str:
    """Per category: detections, true positives, ECE raw and calibrated (grey when too few)."""
    rows = []
    for name, row in held.get("per_class", {}).items():
        small = " class='small'" if too_small(row["true_positives"]) else ""
        rows.append(f"<tr><td>{_e(name)}</td><td>{row['n']}</td><td>{row['true_positives']}"
                    f"</td><td{small}>{_num(row['ece_raw'])}</td>"
                    f"<td{small}>{_num(row['ece_calibrated'])}</td></tr>")
    return ("<table class='per-class-2d'><tr><th>category</th><th>detections</th><th>TP</th>"
            "<th>ECE raw</th><th>ECE calibrated</th></tr>" + "".join(rows) + "</table>")


def _share(shares: dict[str, Any], j: int, level: float) -> str:
    """One level's coverage cell: share and interval; grey when too few TPs, red when a
    judgeable cell misses its level by more than the tolerance."""
    n, value, (lo, hi) = shares["count"], shares["coverage"][j], shares["interval"][j]
    off = n >= COVERAGE_MIN_TPS and abs(value - level) > COVERAGE_TOLERANCE
    cls = "small" if too_small(n) else ("worse" if off else "")
    return (f"<td class='{cls}'>{_num(value, 3)} <span class='ci'>[{lo:.2f}, {hi:.2f}]</span>"
            "</td>")


def coverage_table(held: dict[str, Any]) -> str:
    """Coverage of the box regions per level, overall and per category × size cell, with the
    intervals and the guarantee of each cell's regions at 90 %."""
    regions = held.get("regions")
    if not regions:
        return ("<p class='note'>This profile serves no box regions (no calibration part), or "
                "its held-out images have no true positive.</p>")
    table = regions.get("per_class_size")
    if not table:
        return _missing("coverage per category × size")
    levels = table["levels"]
    j90 = levels.index(0.9) if 0.9 in levels else len(levels) - 1

    def size(rng: list) -> str:
        lo, hi = rng
        return f"{lo:g}+ px" if hi is None else f"{lo:g}–{hi:g} px"

    def cells(shares: dict[str, Any]) -> str:
        return "".join(_share(shares, j, q) for j, q in enumerate(levels))

    head = "".join(f"<th>{q:.0%}</th>" for q in levels)
    rows = [f"<tr><td><b>all</b></td><td></td><td>{table['overall']['count']}</td>"
            f"{cells(table['overall'])}<td></td></tr>"]
    for r in table["rows"]:
        kind = (r.get("guarantee") or {}).get(str(levels[j90]), "—")
        rows.append(f"<tr><td>{_e(r['class'])}</td><td>{size(r['size_range'])}</td>"
                    f"<td>{r['count']}</td>{cells(r)}<td>{_e(kind)} "
                    f"({_num(r.get('calibration_count'))})</td></tr>")
    return (f"<p class='note'>Held-out true positives whose true box lies between the inner and "
            f"the outer box at each level (all four edges), per category × size of the detected "
            f"box (√(w·h)). Cells with ≥ {COVERAGE_MIN_TPS} TPs more than "
            f"{COVERAGE_TOLERANCE:.0%} off their level are red. The last column says what the "
            f"cell's regions guarantee at {levels[j90]:.0%} and its calibration TPs. {_e(RULE)}"
            "</p><table class='coverage coverage-2d'><tr><th>category</th><th>size</th>"
            f"<th>TPs</th>{head}<th>guarantee</th></tr>" + "".join(rows) + "</table>")


def sample_section(held: dict[str, Any]) -> str:
    """The held-out sample image with a caption and a legend."""
    if "sample" not in held:
        return _missing("sample image")
    sample = held["sample"]
    if not sample:
        return "<p class='note'>No held-out image has a detection.</p>"
    level = sample.get("level")
    band = ("" if level is None else f", the {level:.0%} region of each detection (shaded "
            "band: the true box's edges lie between its inner and outer box)")
    swatch = "<span style='color:{}'>■</span> {}"
    legend = " ".join(swatch.format(c, t) for c, t in ((TRUTH, "ground truth"),
                                                      (TP, "true positive"),
                                                      (FP, "false positive")))
    return (f"<p class='note'>Image {_e(sample['image_id'])} ({sample['width']:g} × "
            f"{sample['height']:g} px; a profile keeps no pixels): its ground truth, its "
            f"{len(sample['detections'])} of {sample['n_detections']} detections with a "
            f"calibrated score ≥ {sample['min_score']:g}, labelled with category and "
            f"calibrated score{band}. {legend}</p>" + sample_canvas(sample))
