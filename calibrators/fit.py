"""Fit a calibration profile (temperature + per-class depth k) on a validation dump.

`fit_profile(dump, ...)` runs the whole pipeline:

1. optional `min_score` filter on the raw final-layer scores (the report states it);
2. optional hold-out: a seeded random fraction of the *frames* is kept aside for the report;
3. nuScenes matching of the final-layer detections to the ground truth at `threshold` m.
   No class range filter is applied: the nuScenes ranges (30-50 m) are an evaluation
   convention, while a profile must calibrate every detection the detector emits, and the far
   detections carry most of the depth signal. Filter the dump beforehand to fit on a range;
4. temperature scaling on the final-layer logits with TP labels (`matched.ts_labels`:
   sigmoid 0/1 of the predicted class; softmax target column = matched class or no-object);
   with `modulation=True` the final-layer logits are first modulated from all decoder layers
   (Eq. 4-1, `calibrators.modulation`) and T is fit on the modulated logits. Matching and
   labels stay those of the raw detector (modulation re-scores, it does not relabel);
5. residuals (matched ground truth − final box) of the TPs over `dims` (yaw wrapped) and the
   raw covariance from `cov_source` (`given` det_cov, `layers` spread across decoder layers,
   `none`), then `DepthScaler` per predicted class with BEV distance from the ego;
6. the before/after summary (`calibrators.summary`) on the fit part and the held-out part.

Every option is a field of `FitOptions` (calibrators/options.py), validated there once.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from calibrators.depth import DepthScaler
from calibrators.dump import Dump
from calibrators.matched import (
    match_dump,
    raw_covariances,
    resolve_cov_source,
    select_detections,
    split_frames,
    tp_residuals,
    ts_labels,
    ts_logits,
)
from calibrators.matching import MatchResult
from calibrators.options import FitOptions, OptionError
from calibrators.profile import CalibrationProfile, make_provenance
from calibrators.summary import summarize
from calibrators.summary_types import ProfileReport
from calibrators.temperature import TemperatureScaler

Progress = Callable[[str, float], None]


def fit_profile(dump: Dump, options: FitOptions | None = None, *,
                dump_sha256: str | None = None, progress: Progress | None = None,
                **overrides: Any) -> CalibrationProfile:
    """Fit temperature and per-class depth k on `dump`; see the module docstring.

    options: a `FitOptions` (default: all defaults); keyword `overrides` replace single
    options, e.g. `fit_profile(dump, holdout=0.3)`. dump_sha256: the dump file's hash for
    provenance (None: a hash of the arrays). progress: called as `progress(stage, fraction)`
    once the options are valid, with stages prepare, match, temperature, depth, report,
    holdout report (if any), done and fractions rising from 0 to 1.
    Raises ValueError naming the option (an `OptionError`) for bad options, or a ValueError
    for a dump that cannot be fit.
    """
    opts = options if options is not None else FitOptions()
    if not isinstance(opts, FitOptions):
        raise OptionError("options", f"options must be a FitOptions, got {type(opts).__name__}")
    if overrides:
        opts = FitOptions.from_dict({**opts.to_dict(), **overrides})
    report_progress = progress if progress is not None else _no_progress
    threshold, dims, holdout = opts.threshold, opts.dims, opts.holdout
    min_score, min_samples, seed = opts.min_score, opts.min_samples, opts.seed
    source = check_fit_input(dump, opts)
    modulation = opts.modulation
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
    depth = _fit_depth(fit_part, matched, dims, source, min_samples)
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
    fit_summary = summarize(fit_part, profile, threshold=threshold, match=matched)
    held_summary = None
    if held_part is not None:
        report_progress("holdout report", 0.8)
        held_summary = summarize(held_part, profile, threshold=threshold)
    report = ProfileReport(fit=fit_summary, holdout=held_summary, min_score=min_score,
                           threshold=threshold)
    profile = replace(profile, report=report.to_dict())
    report_progress("done", 1.0)
    return profile


def check_fit_input(dump: Dump, options: FitOptions) -> str:
    """Raise `OptionError` naming the option if `dump` cannot be fit with `options` (logits
    modulation without 2 decoder layers, a covariance source the dump lacks); returns the
    resolved covariance source. Front ends call it to refuse an upload before queueing a fit.
    """
    if options.modulation and dump.n_layers < 2:
        raise OptionError("modulation", f"modulation=True needs the logits of at least 2 "
                                        f"decoder layers, the dump has {dump.n_layers}")
    return resolve_cov_source(dump, options.cov_source, options.dims)


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


def _fit_depth(dump: Dump, matched: MatchResult, dims: tuple[str, ...], source: str,
               min_samples: int) -> DepthScaler:
    """DepthScaler fit on the TPs' residuals `[M, D]`, raw covariance, distance and class."""
    tp = matched.tp
    residuals = tp_residuals(dump, matched, dims)
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


def _no_progress(stage: str, fraction: float) -> None:
    """Default progress callback: does nothing."""
