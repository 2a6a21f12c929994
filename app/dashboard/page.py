"""Assemble the dashboard HTML: health and request rates, profiles, the before/after table,
plots from the active profile's report, and a simulated bird's-eye frame before and after.

The plots (matplotlib) and the bundled detectors (torch) are imported when a page first
draws them, so importing the service loads neither.
"""

from __future__ import annotations

import html
import threading
import time
from typing import Any

import numpy as np

from app.calibrate.cache import LoadedProfile
from app.dashboard.intervals import MIN_TPS, RULE, proportion_interval, too_small
from app.store import JobRecord, NameSummary
from calibrators import ProfileReport, Summary
from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from calibrators.evaluation import Pair

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:0;background:#f6f7f9;color:#222}
header{background:#1f2d3d;color:#fff;padding:12px 24px}header h1{margin:0;font-size:20px}
header p{margin:4px 0 0;color:#c9d3de;font-size:13px}
main{padding:16px 24px;display:grid;gap:16px}
section{background:#fff;border:1px solid #dde2e8;border-radius:6px;padding:12px 16px}
h2{font-size:15px;margin:0 0 8px}table{border-collapse:collapse;font-size:12px}
td,th{border-bottom:1px solid #e5e8ec;padding:3px 10px;text-align:right}
th:first-child,td:first-child{text-align:left}.ok{color:#1a7f37}.bad{color:#c62828}
.note{color:#666;font-size:12px}.plots{display:flex;flex-wrap:wrap;gap:12px;align-items:flex-start}
svg.plot{max-width:100%;height:auto}.better{color:#1a7f37}.worse{color:#c62828}
code{background:#eef1f4;padding:1px 4px;border-radius:3px}
td.small{color:#9aa3ad;background:#f3f4f6}.ci{color:#888;font-size:10px}
"""


def _e(value: Any) -> str:
    return html.escape(str(value))


def _num(value: Any, digits: int = 4) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return _e(value)


def _pair_row(name: str, pair: Pair | None, lower_is_better: bool = True) -> str:
    b, a = (None, None) if pair is None else (pair.before, pair.after)
    cls = ""
    if isinstance(b, int | float) and isinstance(a, int | float):
        cls = "better" if (a < b) == lower_is_better else "worse"
    return f"<tr><td>{_e(name)}</td><td>{_num(b)}</td><td class='{cls}'>{_num(a)}</td></tr>"


def before_after_table(summary: Summary) -> str:
    """The before/after metrics table of one report part (classification and regression)."""
    c, r = summary.classification, summary.regression
    rows = [_pair_row(label, c.get(key)) for key, label in
            (("ece", "ECE"), ("mce", "MCE"), ("dece", "D-ECE"), ("nll", "class NLL"),
             ("brier", "Brier"))]
    rows.append(_pair_row("regression NLL", r.nll))
    rows.append(f"<tr><td>mean Mahalanobis distance (ideal {_num(r.expected_md)})</td>"
                f"<td>{_num(r.mean_md.before)}</td><td>{_num(r.mean_md.after)}</td></tr>")
    cov, tps = r.coverage, summary.counts.tp
    for i, radius in enumerate(cov.radii):
        before = None if cov.before is None else cov.before[i]
        after = None if cov.after is None else cov.after[i]
        rows.append(f"<tr><td>coverage within {radius:g}σ (nominal {_num(cov.nominal[i], 3)})"
                    f"</td>{_share_cell(before, tps)}{_share_cell(after, tps)}</tr>")
    for axis, pair in r.miscalibration_area.items():
        rows.append(_pair_row(f"miscalibration area {axis}", pair))
    caption = ", ".join(f"{k} {v}" for k, v in summary.counts.to_dict().items())
    return (f"<table class='metrics'><caption class='note'>{_e(caption)}</caption>"
            "<tr><th>metric</th><th>before</th><th>after</th></tr>" + "".join(rows) +
            "</table>")


def per_class_table(summary: Summary) -> str:
    """Per-class k, matches and ECE/NLL before and after."""
    rows = []
    for row in summary.per_class:
        fb = " (pooled)" if row.fallback else ""
        small = " class='small'" if too_small(row.tp) else ""
        rows.append(f"<tr><td>{_e(row.name)}</td><td>{_num(row.n)}</td>"
                    f"<td>{_num(row.tp)}</td><td>{_num(row.k)}{fb}</td>"
                    + "".join(f"<td{small}>{_num(v)}</td>" for v in (
                        row.ece_before, row.ece_after, row.nll_before, row.nll_after))
                    + "</tr>")
    return (f"<p class='note'>{_e(RULE.split('. ')[0])}.</p>"
            "<table class='per-class'><tr><th>class</th><th>detections</th><th>TP</th>"
            "<th>k [m²/m]</th><th>ECE before</th><th>ECE after</th><th>reg. NLL before</th>"
            "<th>reg. NLL after</th></tr>" + "".join(rows) + "</table>")


def _share_cell(value: float | None, n: int | None, mark: bool = False) -> str:
    """A table cell with a share seen over `n` true positives and its sampling interval;
    grey when `n` is too small to judge, red when `mark`."""
    if value is None or not n:
        return f"<td class='small'>{_num(value, 3)}</td>"
    lo, hi = proportion_interval(value, n)
    cls = "small" if too_small(n) else ("worse" if mark else "")
    return (f"<td class='{cls}'>{_num(value, 3)} <span class='ci'>[{lo:.2f}, {hi:.2f}]"
            "</span></td>")


#: A served level whose coverage misses it by more than this is marked (the service's own
#: tolerance for a class × range cell), in cells with at least `COVERAGE_MIN_TPS` true
#: positives: smaller cells are too noisy to judge (their counts are shown).
COVERAGE_TOLERANCE = 0.04
COVERAGE_MIN_TPS = 100


def region_table(summary: Summary, part: str) -> str:
    """Coverage of the served ellipses per level, overall and per class × distance bin, with
    the mean ellipse area; cells more than 4 pp off their level are marked."""
    regions = summary.regions
    if not regions or not regions.get("coverage"):
        return ("<p class='note'>This profile's report has no served-region coverage (a "
                "profile fit before detcal measured it, or no x, y dims).</p>")
    levels = regions["levels"]
    cov = regions["coverage"]

    def cells(values: list[float | None], count: int) -> str:
        out = []
        for q, v in zip(levels, values, strict=True):
            off = (v is not None and count >= COVERAGE_MIN_TPS
                   and abs(v - q) > COVERAGE_TOLERANCE)
            out.append(_share_cell(v, count, off))
        return "".join(out)

    def span(rng: list) -> str:
        lo, hi = rng
        return f"{lo:g}+ m" if hi is None else f"{lo:g}–{hi:g} m"

    head = "".join(f"<th>{q:.0%}</th>" for q in levels)
    rows = [f"<tr><td><b>all</b></td><td></td><td>{cov['count']}</td>"
            f"{cells(cov['overall'], cov['count'])}</tr>"]
    rows += [f"<tr><td>{_e(r['class'])}</td><td>{span(r['distance_range'])}</td>"
             f"<td>{r['count']}</td>{cells(r['coverage'], r['count'])}</tr>"
             for r in cov["rows"]]
    area = " / ".join(_num(a, 3) for a in regions["mean_area"])
    gauss = " / ".join(_num(g, 3) for g in regions["gaussian_coverage"])
    return (f"<p class='note'>{_e(part)}: share of true centres inside the served "
            f"{_e(regions['method'])} ellipse at each level; mean area {area} m²; Gaussian χ² "
            f"radii on the same Σ' would cover {gauss}. Cells with ≥ {COVERAGE_MIN_TPS} TPs "
            f"more than {COVERAGE_TOLERANCE:.0%} off their level are red. {_e(RULE)}</p>"
            f"<table class='coverage'><tr><th>class</th>"
            f"<th>range</th><th>TPs</th>{head}</tr>" + "".join(rows) + "</table>")


class DashboardRenderer:
    """Renders the page; the plots of a profile version are drawn once and cached."""

    def __init__(self) -> None:
        self._plots: dict[str, str] = {}
        self._bev: dict[str, str] = {}
        self._lock = threading.Lock()

    def report_plots(self, loaded: LoadedProfile) -> str:
        """The report plots of a profile version (cached by version id)."""
        key = loaded.record.ref + loaded.record.sha256
        with self._lock:
            if key in self._plots:
                return self._plots[key]
        report = ProfileReport.from_dict(loaded.profile.report)
        data = {} if report is None else report.fit.plots
        if not data:
            out = "<p class='note'>This profile's report has no plot data.</p>"
        else:
            from app.dashboard import plots

            out = ("<div class='plots'>" + plots.reliability(data) + plots.calibration_curves(data)
                   + plots.residual_plot(data) + "</div><h2>Reliability per class</h2>"
                   "<p class='note'>Fit part; each title gives the class's true positives, and "
                   f"a panel with fewer than {MIN_TPS} is grey: too few to judge.</p>"
                   + plots.reliability_per_class(
                       data, {row.name: row.tp for row in report.fit.per_class}))
        with self._lock:
            self._plots[key] = out
        return out

    def panels_2d(self, loaded: LoadedProfile) -> str:
        """The panels of a 2-D profile version (`app.dashboard.panels2d`, cached by version
        id)."""
        key = "boxes2d" + loaded.record.ref + loaded.record.sha256
        with self._lock:
            if key in self._plots:
                return self._plots[key]
        from app.dashboard.panels2d import report_panels

        out = report_panels(loaded)
        with self._lock:
            self._plots[key] = out
        return out

    def bev(self, loaded: LoadedProfile, detectors: Any, sensor: str, seed: int) -> str:
        """The BEV frame before/after calibration (cached), or a note saying why not."""
        key = f"{loaded.record.ref}{loaded.record.sha256}{sensor}{seed}"
        with self._lock:
            if key in self._bev:
                return self._bev[key]
        out = _bev_section(loaded, detectors, sensor, seed)
        with self._lock:
            self._bev[key] = out
        return out


def _bev_section(loaded: LoadedProfile, detectors: Any, sensor: str, seed: int) -> str:
    from app.bundled_detectors import DetectorUnavailable, detections_of
    from app.calibrate.documents import calibrate_frames
    from app.dashboard import plots
    from app.http.errors import RequestError
    from app.schemas.calibrate import FrameIn
    from calibrators.covariance import layer_spread
    from calibrators.regions import ellipse

    reason = detectors.available()
    if reason is not None:
        return f"<p class='note'>No bird's-eye view: {_e(reason)}.</p>"
    try:
        out = detectors.run(sensor, seed, None, min_score=0.3)
        frame = FrameIn.model_construct(frame_id="bev", ego_translation=None,
                                        detections=detections_of(out, loaded))
        rows = calibrate_frames(loaded, [frame], ELLIPSE_CONFIDENCE)[0]
    except (DetectorUnavailable, RequestError, ValueError, OSError) as exc:
        msg = exc.msg if isinstance(exc, RequestError) else str(exc)
        return f"<p class='note'>No bird's-eye view for profile {_e(loaded.record.ref)}: " \
               f"{_e(msg)}</p>"
    boxes = out.layer_boxes[:, -1] if len(out.layer_boxes) else np.zeros((0, 9))
    raw_el = None
    if len(boxes) and out.layer_boxes.shape[1] >= 2:
        e = ellipse(layer_spread(out.layer_boxes, ("x", "y")), ELLIPSE_CONFIDENCE)
        raw_el = (e.semi_major, e.semi_minor, e.angle)
    cal_el = None
    if rows and rows[0]["ellipse"] is not None:
        cal_el = tuple(np.array([r["ellipse"][k] for r in rows])  # type: ignore[index]
                       for k in ("semi_major", "semi_minor", "angle"))
    raw_scores = [r["score_raw"] for r in rows]
    cal_scores = [r["score"] for r in rows]
    svg = plots.bev(out.points, out.gt_boxes, [
        {"title": "before: raw scores, layer-spread Σ", "boxes": boxes, "scores": raw_scores,
         "ellipses": raw_el, "color": plots.BEFORE},
        {"title": f"after: {loaded.record.ref}", "boxes": boxes, "scores": cal_scores,
         "ellipses": cal_el, "color": plots.AFTER},
    ], title="Bird's-eye view")
    sizes = " and ".join(f"{name} {float(np.median(el[0])):.2f} m" for name, el in
                         (("before", raw_el), ("after", cal_el)) if el is not None and len(el[0]))
    return (f"<p class='note'>Simulated {_e(sensor)} frame, seed {seed}, zoomed to its objects: "
            f"points (grey), ground truth (green), {len(rows)} detections with raw score ≥ 0.3, "
            f"their scores and their 95% ellipses (filled; median semi-major axis {sizes})."
            f"</p>" + svg)


def render_page(*, version: str, status: dict[str, str], uptime_s: float,
                requests: dict[str, float], names: list[NameSummary], default_name: str,
                loaded: LoadedProfile | None, versions_html: str, report_html: str,
                bev_html: str, jobs: list[JobRecord], health_html: str = "",
                profile_note: str | None = None) -> str:
    """The whole dashboard document; `profile_note` (HTML) stands for the active profile's
    panel when it is not a 3-D profile (`app.dashboard.panels2d.profile_summary`)."""
    total = sum(requests.values())
    rate = total / max(uptime_s, 1e-9)
    status_cells = "".join(
        f"<tr><td>{_e(k)}</td><td class='{'ok' if v in ('ok', 'ready') else 'bad'}'>{_e(v)}"
        "</td></tr>" for k, v in status.items())
    req_rows = "".join(f"<tr><td><code>{_e(route)}</code></td><td>{int(n)}</td>"
                       f"<td>{n / max(uptime_s, 1e-9):.3f}</td></tr>"
                       for route, n in sorted(requests.items(), key=lambda kv: -kv[1]))
    name_rows = "".join(
        f"<tr><td>{_e(n.name)}</td><td>{_num(n.active_version)}</td><td>{n.n_versions}</td>"
        f"<td>{n.latest_version}</td></tr>" for n in names)
    job_rows = "".join(
        f"<tr><td><code>{_e(j.id[:8])}</code></td><td>{_e(j.name)}</td><td>{_e(j.state)}</td>"
        f"<td>{j.progress:.0%}</td><td>{_num(j.profile_version)}</td>"
        f"<td>{_e(j.error or '')}</td></tr>" for j in jobs)
    if profile_note is not None:
        profile_html = profile_note
    elif loaded is None:
        profile_html = (f"<p class='note'>No active profile named {_e(default_name)!s} yet: "
                        "upload a validation dump to <code>POST /v1/fit</code>.</p>")
    else:
        p = loaded.profile
        ks = ", ".join(f"{_e(c)} {p.depth_k.get(c, p.pooled_k):.4g}" for c in p.classes)
        profile_html = (
            f"<p><b>{_e(loaded.record.ref)}</b> · {_e(p.score_mode)} · scores "
            f"{_e(p.score_method)} · covariance {_e(p.cov_method)} · regions "
            f"{_e(p.region_method)} · T = {p.temperature:.4g}"
            f" · cov_source {_e(p.cov_source)} over {_e(', '.join(p.cov_dims))} · pooled k = "
            f"{p.pooled_k:.4g} · created {_e(p.provenance.get('created_at', '?'))} · dump "
            f"<code>{_e(str(p.provenance.get('dump_sha256', ''))[:12])}</code></p>"
            f"<p class='note'>k per class: {ks}</p>" + versions_html)
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>detcal dashboard</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="data:,">
<style>{_CSS}</style>
</head><body>
<header><h1>detcal — calibration service</h1>
<p>version {_e(version)} · up {uptime_s:.0f} s · {int(total)} requests ({rate:.3f}/s)</p></header>
<main>
<section id="health"><h2>Health</h2><table>{status_cells}</table></section>
<section id="requests"><h2>Requests</h2><table><tr><th>route</th><th>count</th>
<th>per second</th></tr>{req_rows}</table></section>
<section id="profiles"><h2>Profiles</h2><table><tr><th>name</th><th>active</th><th>versions</th>
<th>latest</th></tr>{name_rows}</table></section>
<section id="active"><h2>Active profile ({_e(default_name)})</h2>{profile_html}</section>
<section id="calibration-health"><h2>Calibration health (labelled feedback)</h2>{health_html or
"<p class='note'>No active profile.</p>"}</section>
<section id="report"><h2>Before / after calibration</h2>{report_html}</section>
<section id="bev"><h2>Bird's-eye view</h2>{bev_html}</section>
<section id="jobs"><h2>Recent fit jobs</h2><table><tr><th>job</th><th>name</th><th>state</th>
<th>progress</th><th>version</th><th>error</th></tr>{job_rows}</table></section>
</main></body></html>"""


def versions_table(records: list[Any]) -> str:
    """The versions of the active profile's name."""
    rows = "".join(
        f"<tr><td>{r.version}</td><td>{'active' if r.active else ''}</td>"
        f"<td>{_e(r.created_at.strftime('%Y-%m-%d %H:%M:%S'))}</td><td><code>{_e(r.sha256[:12])}"
        f"</code></td></tr>" for r in records)
    return ("<table><tr><th>version</th><th></th><th>created (UTC)</th><th>sha256</th></tr>"
            + rows + "</table>")


def uptime(started: float) -> float:
    """Seconds since `started` (time.time())."""
    return time.time() - started
