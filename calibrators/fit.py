"""Fit a calibration profile (temperature + per-class depth k) on a validation dump.

`fit_profile(dump, ...)` runs the whole pipeline:

1. optional `min_score` filter on the raw final-layer scores (the report states it);
2. optional hold-out: a seeded random fraction of the *frames* is kept aside for the report;
3. nuScenes matching of the final-layer detections to the ground truth at `threshold` m.
   No class range filter is applied: the nuScenes ranges (30-50 m) are an evaluation
   convention, while a profile must calibrate every detection the detector emits, and the far
   detections carry most of the depth signal. Filter the dump beforehand to fit on a range;
4. temperature scaling on the final-layer logits with TP labels (`_fitdata.ts_labels`:
   sigmoid 0/1 of the predicted class; softmax target column = matched class or no-object);
   with `modulation=True` the final-layer logits are first modulated from all decoder layers
   (Eq. 4-1, `calibrators.modulation`) and T is fit on the modulated logits. Matching and
   labels stay those of the raw detector (modulation re-scores, it does not relabel);
5. residuals (matched ground truth − final box) of the TPs over `dims` (yaw wrapped) and the
   raw covariance from `cov_source` (`given` det_cov, `layers` spread across decoder layers,
   `none`), then `DepthScaler` per predicted class with BEV distance from the ego;
6. the before/after report (`calibrators.report`) on the fit part and the held-out part.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from calibrators._fitdata import (
    check_dims,
    match_dump,
    raw_covariances,
    resolve_cov_source,
    select_detections,
    split_frames,
    tp_residuals,
    ts_labels,
    ts_logits,
)
from calibrators.depth import DepthScaler
from calibrators.dump import Dump
from calibrators.profile import CalibrationProfile, make_provenance
from calibrators.report import calibration_report
from calibrators.temperature import TemperatureScaler

Progress = Callable[[str, float], None]


def fit_profile(dump: Dump, threshold: float = 2.0, dims: str | Sequence[str] = ("x", "y"),
                cov_source: str = "auto", holdout: float = 0.0, min_score: float | None = None,
                min_samples: int = 50, seed: int = 0, dump_sha256: str | None = None,
                progress: Progress | None = None, modulation: bool = False
                ) -> CalibrationProfile:
    """Fit temperature and per-class depth k on `dump`; see the module docstring.

    threshold: matching distance in m (> 0). dims: regression box fields (`("x", "y")` or
    `"x,y"`). cov_source: `auto` | `given` | `layers` | `none` (`auto`: given if the dump has
    det_cov over `dims`, else layers if L >= 2, else none). holdout: fraction of frames in
    [0, 1) kept for the report. min_score: drop detections with a raw score below it (None:
    all queries). min_samples: matches a class needs for its own k (else the pooled k).
    dump_sha256: the dump file's hash for provenance (None: a hash of the arrays).
    modulation: apply logits modulation before temperature scaling (needs L >= 2 layers);
    recorded in the profile, whose `calibrate` then needs `layer_logits`.
    progress: called as `progress(stage, fraction)` once the options are valid, with stages
    prepare, match, temperature, depth, report, holdout report (if any), done and fractions
    rising from 0 to 1.
    Raises ValueError naming the option for bad options or a dump that cannot be fit.
    """
    report_progress = progress if progress is not None else _no_progress
    threshold = _check_threshold(threshold)
    dims = check_dims(dims)
    holdout = _check_holdout(holdout)
    min_score = _check_min_score(min_score)
    min_samples = _check_min_samples(min_samples)
    modulation = _check_modulation(modulation, dump)
    source = resolve_cov_source(dump, cov_source, dims)
    report_progress("prepare", 0.0)
    if dump_sha256 is None:
        dump_sha256 = dump_digest(dump)

    work = dump if min_score is None else select_detections(dump, dump.det_scores >= min_score)
    if work.n_detections == 0:
        raise ValueError(f"min_score={min_score} leaves no detection to fit on")
    fit_part, held_part = split_frames(work, holdout, seed)

    report_progress("match", 0.1)
    matched = match_dump(fit_part, threshold)
    if not matched.tp.any():
        raise ValueError(f"no detection matched ground truth within {threshold} m (threshold); "
                         f"check the dump's coordinates and classes")

    report_progress("temperature", 0.25)
    scaler = TemperatureScaler(mode=fit_part.score_mode)
    scaler.fit(ts_logits(fit_part, modulation), ts_labels(fit_part, matched.tp))

    report_progress("depth", 0.4)
    depth = _fit_depth(fit_part, matched.gt_index, matched.tp, dims, source, min_samples)
    fallbacks = [c for c in fit_part.classes if c not in depth.k_ or c in
                 {str(f) for f in depth.fallback_classes_}]
    profile = CalibrationProfile(
        classes=tuple(dump.classes), score_mode=dump.score_mode,
        temperature=float(scaler.temperature_), modulation=modulation, cov_dims=dims,
        cov_source=source,
        depth_k={c: float(depth.k_.get(c, depth.pooled_k_)) for c in dump.classes},
        pooled_k=float(depth.pooled_k_), fallback_classes=tuple(fallbacks),
        matching={"rule": "center_distance", "threshold": threshold},
        min_score=min_score, report={},
        provenance=_provenance(dump, fit_part, held_part, matched.tp, dump_sha256, holdout,
                               seed),
    )

    report_progress("report", 0.6)
    fit_report = calibration_report(fit_part, profile, threshold=threshold, match=matched)
    held_report = None
    if held_part is not None:
        report_progress("holdout report", 0.8)
        held_report = calibration_report(held_part, profile, threshold=threshold)
    profile = replace(profile, report={"fit": fit_report, "holdout": held_report,
                                       "min_score": min_score, "threshold": threshold})
    report_progress("done", 1.0)
    return profile


def dump_digest(dump: Dump) -> str:
    """sha256 over the dump's classes, score mode and arrays (for dumps without a file)."""
    h = hashlib.sha256()
    h.update("\n".join((*dump.classes, dump.score_mode, *dump.cov_dims)).encode())
    for arr in (dump.frame_ids.astype(str), dump.det_frame, dump.det_logits, dump.det_boxes,
                dump.gt_frame, dump.gt_labels, dump.gt_boxes, dump.ego_translation,
                dump.det_cov):
        if arr is None:
            h.update(b"none")
        else:
            h.update(str(arr.shape).encode())
            h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def _fit_depth(dump: Dump, gt_index: np.ndarray, tp: np.ndarray, dims: tuple[str, ...],
               source: str, min_samples: int) -> DepthScaler:
    """DepthScaler fit on the TPs' residuals `[M, D]`, raw covariance, distance and class."""
    residuals = tp_residuals(dump, gt_index, tp, dims)
    cov = raw_covariances(dump, source, dims)
    classes = np.asarray(dump.classes)[dump.det_labels[tp]]
    try:
        return DepthScaler(min_samples=min_samples).fit(
            residuals, None if cov is None else cov[tp], dump.det_distance[tp], classes)
    except ValueError as exc:
        raise ValueError(f"depth scaling failed with cov_source={source!r}: {exc}") from exc


def _provenance(dump: Dump, fit_part: Dump, held_part: Dump | None, tp: np.ndarray,
                sha256: str, holdout: float, seed: int) -> dict:
    return make_provenance(
        dump_sha256=sha256,
        n_frames=dump.n_frames,
        n_detections=dump.n_detections,
        n_ground_truth=len(dump.gt_labels),
        n_fit_frames=fit_part.n_frames,
        n_fit_detections=fit_part.n_detections,
        n_holdout_frames=0 if held_part is None else held_part.n_frames,
        n_matched=int(np.count_nonzero(tp)),
        holdout=holdout,
        seed=int(seed),
    )


def _check_threshold(threshold: float) -> float:
    t = float(threshold)
    if not np.isfinite(t) or t <= 0:
        raise ValueError(f"threshold must be a finite distance > 0 m, got {threshold}")
    return t


def _check_holdout(holdout: float) -> float:
    h = float(holdout)
    if not (0.0 <= h < 1.0):
        raise ValueError(f"holdout must be a fraction of frames in [0, 1), got {holdout}")
    return h


def _check_min_score(min_score: float | None) -> float | None:
    if min_score is None:
        return None
    s = float(min_score)
    if not (0.0 <= s <= 1.0):
        raise ValueError(f"min_score must be a probability in [0, 1], got {min_score}")
    return s


def _check_min_samples(min_samples: int) -> int:
    if isinstance(min_samples, bool) or int(min_samples) != min_samples or min_samples < 1:
        raise ValueError(f"min_samples must be an integer >= 1, got {min_samples}")
    return int(min_samples)


def _check_modulation(modulation: bool, dump: Dump) -> bool:
    if not isinstance(modulation, bool | np.bool_):
        raise ValueError(f"modulation must be True or False, got {modulation!r}")
    if modulation and dump.n_layers < 2:
        raise ValueError(f"modulation=True needs the logits of at least 2 decoder layers, the "
                         f"dump has {dump.n_layers}")
    return bool(modulation)


def _no_progress(stage: str, fraction: float) -> None:
    """Default progress callback: does nothing."""
