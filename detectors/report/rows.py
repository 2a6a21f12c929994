"""One function per row of the report's tables; every row is measured the same way.

`measure(name, dump, scores, covariances)` scores N final-layer detections of a test dump:

- matching: nuScenes rule at 2 m on the dump's labels and raw scores (calibration re-scores,
  it never relabels, so TP/FP is the same for every row built on one dump);
- classification: ECE, D-ECE (score × ego-relative box x, y; (10, 5, 5) bins) and binary NLL
  of the row's `scores [N]` against TP;
- regression over (x, y): residual r = matched GT − box of the M TPs; Gaussian NLL, mean
  Mahalanobis distance (next to E[χ_2] = 1.2533) and coverage of the 1/2/3σ Mahalanobis
  balls under the row's `covariances [N, 2, 2]`. A density needs a positive-definite Σ: TPs
  whose Σ is singular (a two-sample or one-member cluster covariance, rank < 2) are left
  out of the regression metrics and the row says how many were used (`n_used` of `n_tp`);
- mAP: `calibrators.evaluate` (nuScenes devkit definitions) with the row's scores.

Rows (fit on val, measured on test): `vanilla_row`, `sampling_row` (MCD / DE / DSE after
merging), `profile_row` (TS, Mod, TS+Mod with the raw covariance; Depth Scaling with the
calibrated one), built from `fit_profiles`. `class_rows` gives the class-wise table.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from calibrators import (
    CalibrationProfile,
    Dump,
    MatchResult,
    apply_profile,
    evaluate,
    fit_profile,
    layer_spread,
    match_dump,
    metrics,
    raw_covariances,
    tp_residuals,
)

DIMS = ("x", "y")
RADII = (1.0, 2.0, 3.0)
EXPECTED_MD = metrics.expected_mahalanobis(len(DIMS))   # E[χ_2] = 1.2533


@dataclass(frozen=True)
class Row:
    """One table row. Metrics are None where undefined; coverage [3] at 1/2/3σ."""

    name: str
    reg_nll: float | None
    mean_md: float | None
    cls_nll: float
    ece: float
    dece: float
    mean_ap: float
    forward_ms: float
    post_ms: float
    coverage: tuple[float | None, ...]
    n_tp: int
    n_used: int
    note: str = ""


@dataclass(frozen=True)
class ClassRow:
    """Class-wise metrics of one class: n detections, n TPs, regression over its TPs."""

    name: str
    n: int
    n_tp: int
    reg_nll: float | None
    mean_md: float | None
    cls_nll: float | None
    ece: float | None


@dataclass(frozen=True)
class Profiles:
    """The profiles fit on val: TS, Mod (T = 1), TS+Mod and the best of TS / TS+Mod by val
    class NLL (`best`, the Depth Scaling row; every fit profile carries its depth k)."""

    ts: CalibrationProfile
    mod: CalibrationProfile
    ts_mod: CalibrationProfile
    best: CalibrationProfile
    best_name: str


def positive_definite(cov: np.ndarray) -> np.ndarray:
    """`[N]` bool: Σ `[N, D, D]` has a smallest eigenvalue > 1e-12 of its largest entry."""
    if len(cov) == 0:
        return np.zeros(0, dtype=bool)
    scale = np.maximum(np.abs(cov).max(axis=(1, 2)), np.finfo(np.float64).tiny)
    return np.linalg.eigvalsh(cov)[:, 0] > 1e-12 * scale


def measure(name: str, dump: Dump, scores: np.ndarray, covariances: np.ndarray,
            forward_ms: float, post_ms: float = 0.0, m: MatchResult | None = None,
            note: str = "") -> Row:
    """Score a row (module docstring): `scores [N]`, `covariances [N, 2, 2]` of `dump`."""
    m = match_dump(dump) if m is None else m
    tp = np.asarray(m.tp, dtype=bool)
    conf = np.clip(np.asarray(scores, dtype=np.float64), 0.0, 1.0)
    feats = dump.final_boxes[:, :2] - dump.ego_xy(dump.det_frame)
    res = tp_residuals(dump, m, DIMS)
    reg = _regression(res, np.asarray(covariances, dtype=np.float64)[tp])
    if reg.n_used < len(res):
        extra = f"Σ singular for {len(res) - reg.n_used} of {len(res)} TPs (left out)"
        note = f"{note}; {extra}" if note else extra
    return Row(name=name, reg_nll=reg.nll, mean_md=reg.md,
               cls_nll=metrics.classification_nll(conf, tp),
               ece=metrics.expected_calibration_error(conf, tp),
               dece=metrics.detection_ece(conf, tp, feats),
               mean_ap=float(evaluate(dump, scores=conf).mean_ap),
               forward_ms=float(forward_ms), post_ms=float(post_ms), coverage=reg.coverage,
               n_tp=len(res), n_used=reg.n_used, note=note)


@dataclass(frozen=True)
class _Regression:
    nll: float | None
    md: float | None
    coverage: tuple[float | None, ...]
    n_used: int


def _regression(res: np.ndarray, cov: np.ndarray) -> _Regression:
    """Regression metrics on the TPs `res [M, 2]` whose `cov [M, 2, 2]` is PD."""
    ok = positive_definite(cov)
    if not ok.any():
        return _Regression(None, None, (None,) * len(RADII), 0)
    r, c = res[ok], cov[ok]
    cover = metrics.coverage(r, c, radii=RADII).observed
    return _Regression(metrics.regression_nll(r, c), float(np.mean(metrics.mahalanobis(r, c))),
                       tuple(float(v) for v in cover), int(ok.sum()))


def class_rows(dump: Dump, scores: np.ndarray, covariances: np.ndarray,
               m: MatchResult | None = None) -> list[ClassRow]:
    """Class-wise regression NLL / MD (PD TPs of the class) and class NLL / ECE."""
    m = match_dump(dump) if m is None else m
    tp = np.asarray(m.tp, dtype=bool)
    conf = np.clip(np.asarray(scores, dtype=np.float64), 0.0, 1.0)
    res, cov = tp_residuals(dump, m, DIMS), np.asarray(covariances, dtype=np.float64)[tp]
    tp_labels = dump.det_labels[tp]
    out = []
    for c, name in enumerate(dump.classes):
        det = dump.det_labels == c
        reg = _regression(res[tp_labels == c], cov[tp_labels == c])
        out.append(ClassRow(
            name=name, n=int(det.sum()), n_tp=int((tp_labels == c).sum()),
            reg_nll=reg.nll, mean_md=reg.md,
            cls_nll=metrics.classification_nll(conf[det], tp[det]) if det.any() else None,
            ece=metrics.expected_calibration_error(conf[det], tp[det]) if det.any() else None))
    return out


def fit_profiles(val: Dump) -> Profiles:
    """Fit TS and TS+Mod (each with depth scaling on the layer spread) on `val`."""
    thesis = {"cov_source": "layers", "score_method": "temperature", "cov_method": "depth",
              "region_method": "gaussian", "calibration": 0.0, "other_sources": False}
    ts = fit_profile(val, **thesis)
    ts_mod = fit_profile(val, modulation=True, **thesis)
    mod = CalibrationProfile(classes=val.classes, score_mode=val.score_mode, temperature=1.0,
                             modulation=True, cov_source="layers")
    nll = {name: p.report["fit"]["classification"]["nll"]["after"]
           for name, p in (("TS", ts), ("TS+Mod", ts_mod))}
    best_name = min(nll, key=lambda k: np.inf if nll[k] is None else nll[k])
    return Profiles(ts=ts, mod=mod, ts_mod=ts_mod, best=ts if best_name == "TS" else ts_mod,
                    best_name=best_name)


def vanilla_row(test: Dump, forward_ms: float, m: MatchResult | None = None) -> Row:
    """Raw scores, covariance = spread of the box across decoder layers."""
    return measure("Vanilla", test, test.det_scores, layer_spread(test.det_boxes, DIMS),
                   forward_ms, m=m)


def sampling_row(name: str, merged: Dump, forward_ms: float, merge_ms: float) -> Row:
    """A merged sampling method: its mean scores and cluster sample covariance."""
    return measure(name, merged, merged.det_scores, merged.det_cov, forward_ms, merge_ms)


def profile_row(name: str, test: Dump, profile: CalibrationProfile, forward_ms: float,
                regression: bool, m: MatchResult | None = None, note: str = "") -> Row:
    """Scores of `profile` on `test`; covariance = the profile's calibrated Σ' if
    `regression` (Depth Scaling), else the raw covariance of its source."""
    start = time.perf_counter()
    out = apply_profile(test, profile)
    post_ms = 1000.0 * (time.perf_counter() - start) / max(test.n_frames, 1)
    cov = out.covariances if regression else raw_covariance(test, profile)
    return measure(name, test, out.scores, cov, forward_ms, post_ms, m=m, note=note)


def raw_covariance(dump: Dump, profile: CalibrationProfile) -> np.ndarray:
    """`[N, 2, 2]` Σ before depth scaling from the profile's source (zeros for "none")."""
    cov = raw_covariances(dump, profile.cov_source, DIMS)
    return np.zeros((dump.n_detections, 2, 2)) if cov is None else cov
