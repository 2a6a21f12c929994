"""Before/after calibration summary of a set of detections (a `Dump`): `summarize` -> `Summary`.

*Before* is the raw detector: temperature 1 and the raw covariance of the profile's source
(`given` det_cov, `layers` spread, `none`: no covariance, so regression metrics are null).
*After* applies a `CalibrationProfile` (fitted T, optional logits modulation from the
per-layer logits, and Σ' = Σ + k·d·I); without a profile every `after` is null. Labels
are the nuScenes matching of the final-layer detections at `threshold` m (no range filter);
both sides keep the raw detector's labels. Regression metrics use the TPs' residuals
(matched GT − final box) over the profile's dims; a metric is null when its covariances are
missing or singular (the density is undefined), and `regression.note_before` /
`note_after` say why.

`Summary` is a typed, frozen result; `Summary.to_dict()` is the stable JSON form a profile's
report stores (and `Summary.from_dict` reads it back). `ProfileReport` is a profile's
`report`: the summary of the fit part and of the held-out part. Keys of the dict form
(stable; every float may be null):

    schema: 1, threshold: float, score_mode: str, cov_source: str, dims: [D] str,
    temperature: float | null
    counts: {frames, detections, ground_truth, tp, fp, fn}
    classification: {ece, mce, dece, nll, brier: {before, after}}
        ECE/MCE over the predicted-class score vs TP; D-ECE over score × ego-relative box
        (x, y) with (10, 5, 5) bins; NLL and Brier: binary (score vs TP) in sigmoid mode,
        categorical over the C + 1 columns (target: label if TP else no-object) in softmax mode.
    regression: {n, nll, mean_md: {before, after}, expected_md: float,
                 coverage: {radii: [1, 2, 3], nominal: [3], before: [3] | null, after: [3] | null},
                 miscalibration_area: {x, y: {before, after}}, note_before, note_after}
        expected_md = E[MD] of a calibrated Gaussian = sqrt(2)·Γ((D+1)/2)/Γ(D/2) (χ_D mean).
    per_class: [{class, n, tp, k, fallback, ece_before, ece_after, nll_before, nll_after}]
    plots: {reliability: {before, after}, reliability_per_class: {class: {before, after}},
            calibration_curve: {x, y: {before, after}},
            residuals: {n_total, before, after}}
        reliability: {bin_edges, confidence, accuracy, count}; calibration_curve: {expected,
        observed} (50 points); residuals: {residual_norm, sigma, within_1sigma, within_3sigma}
        on at most `max_points` TPs (seeded sample).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import stats
from scipy.special import log_softmax

from calibrators import metrics
from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.json_safe import to_jsonable
from calibrators.core.vocab import check_dims
from calibrators.covariance import raw_covariances, resolve_cov_source
from calibrators.data import Dump
from calibrators.evaluation._dump_match import match_dump, tp_residuals
from calibrators.evaluation._matching import MatchResult
from calibrators.evaluation._reports import ProfileReport, Summary
from calibrators.metrics import expected_mahalanobis
from calibrators.profile import (
    CalibratedDetections,
    CalibrationProfile,
    apply_profile,
    check_profile_fits,
)
from calibrators.regions import DEFAULT_DISTANCE_EDGES, gaussian_radius, xy_mahalanobis
from calibrators.scores import modulate_logits

__all__ = ["ProfileReport", "Summary", "format_table", "summarize"]

#: The served levels whose coverage a summary measures.
SUMMARY_LEVELS = (0.5, 0.9, 0.95, 0.99)
_CURVE_POINTS = 50
_CLASS_METRICS = ("ece", "mce", "dece", "nll", "brier")


def summarize(dump: Dump, profile: CalibrationProfile | None = None, *,
              threshold: float = MATCH_THRESHOLD, dims: str | Sequence[str] = ("x", "y"),
              cov_source: str = "auto", match: MatchResult | None = None,
              max_points: int = 2000, seed: int = 0,
              levels: Sequence[float] = SUMMARY_LEVELS) -> Summary:
    """Before/after metrics of `dump`'s final-layer detections (keys: module docstring).

    With a `profile`, its dims and covariance source are used (`dims` / `cov_source` are
    ignored) and the dump must provide what it needs. `match` reuses a matching already done
    at `threshold`. `levels`: the served region levels whose coverage is measured.
    """
    if profile is not None:
        dims, source = tuple(profile.cov_dims), profile.cov_source
        check_profile_fits(dump, profile)
    else:
        dims = check_dims(dims)
        source = resolve_cov_source(dump, cov_source, dims)
    m = match if match is not None else match_dump(dump, threshold)
    tp = np.asarray(m.tp, dtype=bool)
    cov_raw = raw_covariances(dump, source, dims)
    before = _State(dump.det_scores, _full_probs(dump, 1.0), cov_raw)
    after, served = (None, None) if profile is None else _calibrated(dump, profile, levels)
    if after is not None and profile.score_method != "temperature":
        before.probs = after.probs = None   # a per-class score stage: binary metrics on both
    res = tp_residuals(dump, m, dims)
    rng = np.random.default_rng(seed)
    sample = np.sort(rng.permutation(len(res))[:max_points])
    n_tp = int(tp.sum())
    return Summary.from_dict({
        "schema": 1,
        "threshold": float(threshold),
        "score_mode": dump.score_mode,
        "cov_source": source,
        "dims": list(dims),
        "temperature": None if profile is None else float(profile.temperature),
        "counts": {"frames": dump.n_frames, "detections": dump.n_detections,
                   "ground_truth": int(len(dump.gt_labels)), "tp": n_tp,
                   "fp": dump.n_detections - n_tp, "fn": int(len(dump.gt_labels)) - n_tp},
        "classification": _pairs(_classification(dump, tp, before),
                                 None if after is None else _classification(dump, tp, after)),
        "regression": _regression_section(res, tp, dims, before, after),
        "per_class": _per_class(dump, tp, res, profile, before, after),
        "plots": _plots(dump, tp, res, dims, before, after, sample),
        "regions": None if served is None else _regions(dump, profile, tp, res, served),
    })


class _State:
    """One side of the comparison: scores `[N]`, full probabilities, covariances `[N, D, D]`."""

    def __init__(self, scores: np.ndarray, probs: np.ndarray, cov: np.ndarray | None) -> None:
        self.scores = np.clip(np.asarray(scores, dtype=np.float64), 0.0, 1.0)
        self.probs = probs        # softmax: [N, C + 1]; sigmoid: unused (scores suffice)
        self.cov = cov


def _full_probs(dump: Dump, temperature: float, modulation: bool = False) -> np.ndarray:
    z = modulate_logits(dump.det_logits) if modulation else dump.det_logits[:, -1]
    if dump.score_mode == "softmax":
        return np.exp(log_softmax(z / temperature, axis=1))
    return np.zeros((len(z), 0))


def _calibrated(dump: Dump, profile: CalibrationProfile, levels: Sequence[float]
                ) -> tuple[_State, CalibratedDetections | None]:
    n, dim = dump.n_detections, len(profile.cov_dims)
    probs = _full_probs(dump, profile.temperature, profile.modulation)
    if n == 0:
        return _State(np.zeros(0), probs, np.zeros((0, dim, dim))), None
    out = apply_profile(dump, profile, levels=levels)
    return _State(out.scores, probs, out.covariances), out


def _regions(dump: Dump, profile: CalibrationProfile, tp: np.ndarray, res: np.ndarray,
             out: CalibratedDetections) -> dict[str, Any] | None:
    """Coverage of the served ellipses per level, overall and per class × distance bin, their
    mean area, and the coverage the Gaussian χ²₂ radii would give on the same Σ'."""
    if not out.region_radii or "x" not in profile.cov_dims or "y" not in profile.cov_dims:
        return None
    levels = list(out.region_radii)
    dims = tuple(profile.cov_dims)
    radii = np.stack([out.region_radii[q][tp] for q in levels], axis=1)
    cov = out.covariances[tp]
    md = xy_mahalanobis(res, cov, dims)
    ix, iy = dims.index("x"), dims.index("y")
    block = cov[:, [ix, iy]][:, :, [ix, iy]]
    conformal = profile.source_stages[out.cov_source].conformal
    edges = DEFAULT_DISTANCE_EDGES if conformal is None else tuple(conformal.edges_)
    if len(md) == 0:
        return {"method": out.region_method, "levels": levels, "coverage": None,
                "mean_area": None, "gaussian_coverage": None}
    names = np.asarray(dump.classes)[dump.det_labels[tp]]
    table = metrics.coverage_table(md, radii, levels, names, out.distances[tp], edges)
    gauss = np.array([gaussian_radius(q) for q in levels])
    return {"method": out.region_method, "levels": levels, "coverage": table.to_dict(),
            # an unbounded level (beyond its conformal groups' points) has no finite area
            "mean_area": [None if np.isinf(a) else a
                          for a in metrics.mean_ellipse_area(block, radii).tolist()],
            "gaussian_coverage": (md[:, None] <= gauss[None, :]).mean(axis=0).tolist()}


def _pairs(before: dict[str, Any], after: dict[str, Any] | None) -> dict[str, dict]:
    return {key: {"before": before[key], "after": None if after is None else after[key]}
            for key in before}


def _classification(dump: Dump, tp: np.ndarray, state: _State) -> dict[str, float | None]:
    if dump.n_detections == 0:
        return dict.fromkeys(_CLASS_METRICS)
    conf = state.scores
    feats = dump.final_boxes[:, :2] - dump.ego_xy(dump.det_frame)
    if dump.score_mode == "softmax" and state.probs is not None:
        target = np.where(tp, dump.det_labels, len(dump.classes))
        nll = metrics.classification_nll(state.probs, target)
        brier = metrics.brier_score(state.probs, target)
    else:
        nll = metrics.classification_nll(conf, tp)
        brier = metrics.brier_score(conf, tp)
    return {"ece": metrics.expected_calibration_error(conf, tp),
            "mce": metrics.max_calibration_error(conf, tp),
            "dece": metrics.detection_ece(conf, tp, feats),
            "nll": _finite(nll), "brier": _finite(brier)}


def _usable(cov: np.ndarray | None, n: int) -> str | None:
    """Why the TPs' covariances `[M, D, D]` cannot give a density, or None if they can."""
    if n == 0:
        return "no true positives"
    if cov is None:
        return "no covariance (cov_source 'none'): regression NLL is undefined"
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return "some covariances are singular: regression NLL is undefined"
    return None


def _regression(res: np.ndarray, cov: np.ndarray | None, dims: tuple[str, ...]
                ) -> tuple[dict[str, Any], str | None]:
    note = _usable(cov, len(res))
    area: dict[str, float | None] = {"x": None, "y": None}
    if note is not None:
        return {"nll": None, "mean_md": None, "coverage": None, "area": area}, note
    for axis in ("x", "y"):
        if axis in dims:
            j = dims.index(axis)
            area[axis] = metrics.miscalibration_area(res[:, j], np.sqrt(cov[:, j, j]),
                                                     n_bins=_CURVE_POINTS)
    cov_obj = metrics.coverage(res, cov, radii=(1, 2, 3))
    return {"nll": metrics.regression_nll(res, cov),
            "mean_md": float(np.mean(metrics.mahalanobis(res, cov))),
            "coverage": [float(v) for v in cov_obj.observed], "area": area}, None


def _regression_section(res: np.ndarray, tp: np.ndarray, dims: tuple[str, ...],
                        before: _State, after: _State | None) -> dict[str, Any]:
    b, note_b = _regression(res, _tp_cov(before, tp), dims)
    a, note_a = ({"nll": None, "mean_md": None, "coverage": None, "area": {"x": None, "y": None}},
                 "no profile") if after is None else _regression(res, _tp_cov(after, tp), dims)
    radii = [1.0, 2.0, 3.0]
    return {
        "n": int(len(res)),
        "nll": {"before": _finite(b["nll"]), "after": _finite(a["nll"])},
        "mean_md": {"before": _finite(b["mean_md"]), "after": _finite(a["mean_md"])},
        "expected_md": expected_mahalanobis(len(dims)),
        "coverage": {"radii": radii,
                     "nominal": [float(v) for v in stats.chi2(len(dims)).cdf(np.square(radii))],
                     "before": b["coverage"], "after": a["coverage"]},
        "miscalibration_area": {axis: {"before": _finite(b["area"][axis]),
                                       "after": _finite(a["area"][axis])} for axis in ("x", "y")},
        "note_before": note_b,
        "note_after": note_a,
    }


def _tp_cov(state: _State, tp: np.ndarray) -> np.ndarray | None:
    return None if state.cov is None else state.cov[tp]


def _per_class(dump: Dump, tp: np.ndarray, res: np.ndarray, profile: CalibrationProfile | None,
               before: _State, after: _State | None) -> list[dict[str, Any]]:
    rows = []
    tp_labels = dump.det_labels[tp]
    cov_b, cov_a = _tp_cov(before, tp), None if after is None else _tp_cov(after, tp)
    for c, name in enumerate(dump.classes):
        det = dump.det_labels == c
        tp_c = tp_labels == c
        rows.append({
            "class": name, "n": int(det.sum()), "tp": int(tp_c.sum()),
            "k": None if profile is None else _finite(profile.depth_k.get(name)),
            "fallback": None if profile is None else name in profile.fallback_classes,
            "ece_before": _ece(before, tp, det),
            "ece_after": None if after is None else _ece(after, tp, det),
            "nll_before": _class_nll(res, cov_b, tp_c),
            "nll_after": None if after is None else _class_nll(res, cov_a, tp_c),
        })
    return rows


def _ece(state: _State, tp: np.ndarray, det: np.ndarray) -> float | None:
    if not det.any():
        return None
    return _finite(metrics.expected_calibration_error(state.scores[det], tp[det]))


def _class_nll(res: np.ndarray, cov: np.ndarray | None, rows: np.ndarray) -> float | None:
    if cov is None or _usable(cov[rows], int(rows.sum())) is not None:
        return None
    return _finite(metrics.regression_nll(res[rows], cov[rows]))


def _plots(dump: Dump, tp: np.ndarray, res: np.ndarray, dims: tuple[str, ...], before: _State,
           after: _State | None, sample: np.ndarray) -> dict[str, Any]:
    def reliability(state: _State | None, rows: np.ndarray) -> dict | None:
        if state is None or not rows.any():
            return None
        return metrics.reliability_diagram(state.scores[rows], tp[rows]).to_dict()

    def curve(state: _State | None, axis: str) -> dict | None:
        cov = None if state is None else _tp_cov(state, tp)
        if axis not in dims or _usable(cov, len(res)) is not None:
            return None
        j = dims.index(axis)
        return metrics.average_calibration_curve(res[:, j], np.sqrt(cov[:, j, j]),
                                                 n_bins=_CURVE_POINTS).to_dict()

    def residuals(state: _State | None) -> dict | None:
        cov = None if state is None else _tp_cov(state, tp)
        if cov is None or len(sample) == 0:
            return None
        return metrics.residual_uncertainty(res[sample], cov[sample]).to_dict()

    every = np.ones(dump.n_detections, dtype=bool)
    return {
        "reliability": {"before": reliability(before, every), "after": reliability(after, every)},
        "reliability_per_class": {
            name: {"before": reliability(before, dump.det_labels == c),
                   "after": reliability(after, dump.det_labels == c)}
            for c, name in enumerate(dump.classes)},
        "calibration_curve": {axis: {"before": curve(before, axis), "after": curve(after, axis)}
                              for axis in ("x", "y")},
        "residuals": {"n_total": int(len(res)), "before": residuals(before),
                      "after": residuals(after)},
    }


def _finite(value: float | None) -> float | None:
    """`value` as a float, None for None or a non-finite number (`to_jsonable`)."""
    return None if value is None else to_jsonable(float(value))


def format_table(summary: Summary | ProfileReport) -> str:
    """A plain-text before/after table of a `Summary`, or of a `ProfileReport` (one table per
    part: the fit part and, if any, the held-out part)."""
    if isinstance(summary, ProfileReport):
        parts = [("fit part", summary.fit)]
        if summary.holdout is not None:
            parts.append(("held-out part", summary.holdout))
        head = "detections taking part: " + ("all queries" if summary.min_score is None
                                               else f"raw score >= {summary.min_score:g}")
        return "\n\n".join([head] + [f"== {name} ==\n{format_table(r)}" for name, r in parts])
    c, reg, t = summary.counts, summary.regression, summary.temperature
    lines = [f"{c.detections} detections, {c.ground_truth} ground truth, {c.tp} TP at "
             f"{summary.threshold:g} m; T = {'-' if t is None else f'{t:.4g}'}, covariance "
             f"{summary.cov_source} over {','.join(summary.dims)}",
             f"{'metric':<32}{'before':>12}{'after':>12}", "classification"]
    names = {"ece": "ECE", "mce": "MCE", "dece": "D-ECE", "nll": "NLL", "brier": "Brier"}
    for key, label in names.items():
        pair = summary.classification[key]
        lines.append(_row(label, pair.before, pair.after))
    lines.append(f"regression ({reg.n} TPs)")
    lines.append(_row("NLL", reg.nll.before, reg.nll.after))
    lines.append(_row(f"mean MD (E = {reg.expected_md:.3f})", reg.mean_md.before,
                      reg.mean_md.after))
    cov = reg.coverage
    for i, (r, nominal) in enumerate(zip(cov.radii, cov.nominal, strict=True)):
        lines.append(_row(f"coverage {r:g}σ (nominal {nominal:.3f})",
                          None if cov.before is None else cov.before[i],
                          None if cov.after is None else cov.after[i]))
    for axis, pair in reg.miscalibration_area.items():
        lines.append(_row(f"miscalibration area {axis}", pair.before, pair.after))
    for side, note in (("before", reg.note_before), ("after", reg.note_after)):
        if note and note != "no profile":
            lines.append(f"  ({side}: {note})")
    lines += ["", f"{'class':<22}{'n':>7}{'TP':>7}{'k':>10}{'NLL before':>12}{'NLL after':>12}"]
    for row in summary.per_class:
        k = "-" if row.k is None else f"{row.k:.4g}" + ("*" if row.fallback else "")
        lines.append(f"{row.name:<22}{row.n:>7}{row.tp:>7}{k:>10}"
                     f"{_cell(row.nll_before)}{_cell(row.nll_after)}")
    if any(row.fallback for row in summary.per_class):
        lines.append("* too few matches: pooled k")
    return "\n".join(lines)


def _row(label: str, before: float | None, after: float | None) -> str:
    return f"  {label:<30}{_cell(before)}{_cell(after)}"


def _cell(value: float | None) -> str:
    """A 12-wide right-aligned number: fixed point, or scientific when it would not fit."""
    if value is None:
        return f"{'-':>12}"
    text = f"{value:.4f}"
    return f" {text:>11}" if len(text) <= 11 else f" {value:>11.4g}"
