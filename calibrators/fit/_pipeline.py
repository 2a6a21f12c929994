"""Fit a calibration profile (score, covariance and region stages) on a validation dump.

`fit_profile(dump, ...)` runs the whole pipeline:

1. optional `min_score` filter on the raw final-layer scores (the report states it);
2. optional hold-out: a seeded random fraction of the *frames* is kept aside for the report;
3. nuScenes matching of the final-layer detections to the ground truth at `threshold` m.
   No class range filter is applied: the nuScenes ranges (30-50 m) are an evaluation
   convention, while a profile must calibrate every detection the detector emits, and the far
   detections carry most of the depth signal. Filter the dump beforehand to fit on a range;
4. a seeded `calibration` fraction of the fit part's frames is kept apart (when an `auto`
   method has to be chosen or conformal radii fit): the *training* part fits, the
   *calibration* part chooses and calibrates;
5. score stage (`calibrators.fit._score_stage`): temperature scaling on the final-layer logits with
   TP labels (`matched.ts_labels`: sigmoid 0/1 of the predicted class; softmax target column
   = matched class or no-object) and the per-class calibrators, the best by held-out NLL;
   with `modulation=True` the final-layer logits are first modulated from all decoder layers
   (Eq. 4-1, `calibrators.scores`). Matching and labels stay those of the raw detector;
6. covariance stage (`calibrators.fit._region_stage`): residuals (matched ground truth − final box)
   of the TPs over `dims` (yaw wrapped), the raw covariance from `cov_source` (`given`
   det_cov, `layers` spread across decoder layers, `hypotheses` group-score-weighted spread
   of the det_hyp_boxes, `none`), then `Σ + k_c·d·I` or
   `s_c·Σ + k_c·d·I` per predicted class with BEV distance from the ego;
7. region stage: split-conformal radii per class × distance bin on the calibration part
   (its frames were not used for Σ'), or the Gaussian χ²₂ radii; with
   `region_calibration='cross'`, on every fit true positive, each part scored under the Σ'
   fit on the other, served with the Σ' fit on the whole fit part (`_cross`);
8. the before/after summary (`calibrators.evaluation`) on the fit part and the held-out part,
   with every candidate's held-out score in the report's `selection`.

With the thesis methods (temperature, depth, gaussian) the profile is written as version 1.

Every option is a field of `FitOptions` (calibrators/fit/_options.py), validated there once.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from calibrators.core.errors import OptionError
from calibrators.core.vocab import COV_SOURCES
from calibrators.covariance import resolve_cov_source
from calibrators.data import Dump, canonical_order, select_detections, split_frames
from calibrators.evaluation import (
    MatchResult,
    ProfileReport,
    match_dump,
    summarize,
)
from calibrators.fit._cross import cross_fit_regions, with_covariance
from calibrators.fit._options import FitOptions
from calibrators.fit._region_stage import (
    CovarianceFit,
    RegionFit,
    fit_covariance_stage,
    fit_region_stage,
)
from calibrators.fit._score_stage import ScoreFit, fit_score_stage
from calibrators.profile import CalibrationProfile, apply_profile, make_provenance

Progress = Callable[[str, float], None]


def fit_profile(dump: Dump, options: FitOptions | None = None, *,
                dump_sha256: str | None = None, progress: Progress | None = None,
                **overrides: Any) -> CalibrationProfile:
    """Fit a calibration profile (scores, covariance, regions) on `dump`; see the module docstring.

    options: a `FitOptions` (default: all defaults); keyword `overrides` replace single
    options, e.g. `fit_profile(dump, holdout=0.3)`. dump_sha256: the dump file's hash for
    provenance (None: a hash of the arrays). progress: called as `progress(stage, fraction)`
    once the options are valid, with stages prepare, match, scores, covariance, regions,
    other sources (if any), report, holdout report (if any), done and fractions rising from
    0 to 1.
    Raises ValueError naming the option (an `OptionError`) for bad options, or a ValueError
    for a dump that cannot be fit.
    """
    opts = resolve_options(options, overrides)
    report_progress = progress if progress is not None else _no_progress
    source = check_fit_input(dump, opts)
    report_progress("prepare", 0.0)
    if dump_sha256 is None:
        dump_sha256 = dump_digest(dump)
    fit_part, held_part = _fit_and_held(dump, opts)

    report_progress("match", 0.1)
    matched = _matched(fit_part, opts.threshold)
    train, calib = _calibration_split(fit_part, matched, opts)

    report_progress("scores", 0.25)
    scores = fit_score_stage(fit_part, matched.tp, train[0], train[1].tp,
                             None if calib is None else calib[0],
                             None if calib is None else calib[1].tp,
                             opts.score_method, opts.modulation, opts.min_samples,
                             opts.score_shrink)

    report_progress("covariance", 0.4)
    conformal = calib is not None and opts.region_method != "gaussian"
    cov = fit_covariance_stage(train if conformal else (fit_part, matched), train, calib,
                               opts.dims, source, opts.cov_method, opts.min_samples)
    profile = base_profile(dump, opts, scores, cov, source, _provenance(
        dump, fit_part, held_part, calib, matched.tp, dump_sha256, opts))

    report_progress("regions", 0.5)
    profile, cov, region = _with_regions(profile, fit_part, matched, train, calib, opts,
                                         conformal, cov, report_progress)
    profile = versioned(profile)
    report = _report(profile, fit_part, held_part, matched, opts,
                     selection_of(scores, cov, region, tuple(dump.classes)), report_progress)
    profile = replace(profile, report=report)
    report_progress("done", 1.0)
    return profile


def resolve_options(options: FitOptions | None, overrides: dict[str, Any]) -> FitOptions:
    """`options` (default: all defaults) with the keyword `overrides` applied; `OptionError`
    when `options` is not a `FitOptions`."""
    opts = options if options is not None else FitOptions()
    if not isinstance(opts, FitOptions):
        raise OptionError("options", f"options must be a FitOptions, got {type(opts).__name__}")
    if overrides:
        opts = FitOptions.from_dict({**opts.to_dict(), **overrides})
    return opts


def _fit_and_held(dump: Dump, opts: FitOptions) -> tuple[Dump, Dump | None]:
    """The fit part and the held-out part (None without one) of `dump`, in canonical order
    (the same profile whatever the order of frames and boxes) and after `min_score`."""
    work = canonical_order(dump)
    if opts.min_score is not None:
        work = select_detections(work, work.det_scores >= opts.min_score)
    if work.n_detections == 0:
        raise ValueError(f"min_score={opts.min_score} leaves no detection to fit on")
    return split_frames(work, opts.holdout, opts.seed)


def _matched(fit_part: Dump, threshold: float) -> MatchResult:
    """The fit part's matching; ValueError when no detection matches."""
    matched = match_dump(fit_part, threshold)
    if not matched.tp.any():
        raise ValueError(f"no detection matched ground truth within {threshold} m (threshold); "
                         f"check the dump's coordinates and classes")
    return matched


def _with_regions(profile: CalibrationProfile, fit_part: Dump, matched: MatchResult,
                  train: tuple[Dump, MatchResult], calib: tuple[Dump, MatchResult] | None,
                  opts: FitOptions, conformal: bool, cov: CovarianceFit,
                  report_progress: Progress
                  ) -> tuple[CalibrationProfile, CovarianceFit, RegionFit | None]:
    """The profile with its region stage and (with `other_sources`) the other covariance
    sources' stages, the primary covariance stage it serves and the primary region fit."""
    cov, region = _source_regions(profile, cov, (fit_part, matched), train, calib, opts,
                                  conformal)
    profile = replace(with_covariance(profile, cov), regions=_regions(region))
    if opts.other_sources:   # serve whatever covariance evidence a request carries
        report_progress("other sources", 0.55)
        others = _other_sources(profile, fit_part, matched, train, calib, opts, conformal)
        profile = replace(profile, sources=others or None)
    return profile, cov, region


def _source_regions(profile: CalibrationProfile, cov: CovarianceFit,
                    fit_all: tuple[Dump, MatchResult], train: tuple[Dump, MatchResult],
                    calib: tuple[Dump, MatchResult] | None, opts: FitOptions, conformal: bool
                    ) -> tuple[CovarianceFit, RegionFit | None]:
    """The covariance stage served and the region stage of `profile`'s own covariance source,
    whose `Σ'` is `cov` (fit on `train` when `conformal`): split conformal on `calib`, or
    with `region_calibration='cross'` cross-fitted on every fit true positive and served with
    the `Σ'` fit on `fit_all` (`calibrators.fit._cross`)."""
    method = opts.region_method if conformal else "gaussian"
    if (conformal and opts.region_calibration == "cross" and calib is not None
            and "x" in opts.dims and "y" in opts.dims):
        return cross_fit_regions(profile, cov, fit_all, train, calib, opts, method)
    return cov, fit_region_stage(
        calib, None if calib is None else apply_profile(calib[0], profile).covariances,
        opts.dims, method, opts.min_group, opts.distance_edges, **opts.conformal_options())


def _report(profile: CalibrationProfile, fit_part: Dump, held_part: Dump | None,
            matched: MatchResult, opts: FitOptions, selection: dict[str, Any],
            report_progress: Progress) -> dict[str, Any]:
    """The profile's report: the before/after summaries of the fit and held-out parts."""
    report_progress("report", 0.6)
    fit_summary = summarize(fit_part, profile, threshold=opts.threshold, match=matched)
    held_summary = None
    if held_part is not None:
        report_progress("holdout report", 0.8)
        held_summary = summarize(held_part, profile, threshold=opts.threshold)
    report = ProfileReport(fit=fit_summary, holdout=held_summary, min_score=opts.min_score,
                           threshold=opts.threshold, selection=selection)
    return report.to_dict()


def base_profile(dump: Dump, opts: FitOptions, scores: ScoreFit, cov: CovarianceFit,
                 source: str, provenance: dict) -> CalibrationProfile:
    """The profile of the fitted score and covariance stages (no regions, sources or report
    yet); `dump` gives the classes and the score mode."""
    return CalibrationProfile(
        classes=tuple(dump.classes), score_mode=dump.score_mode,
        temperature=scores.temperature, modulation=opts.modulation, cov_dims=opts.dims,
        cov_source=source, depth_k=cov.depth_k, pooled_k=cov.pooled_k,
        fallback_classes=cov.fallback_classes,
        matching={"rule": "center_distance", "threshold": opts.threshold},
        min_score=opts.min_score, report={}, provenance=provenance,
        score_calibration={"method": scores.method, "params": scores.params},
        covariance_scaling={"method": cov.method, "scale": cov.scale,
                            "pooled_scale": cov.pooled_scale})


def source_stage(cov: CovarianceFit, region: RegionFit | None) -> dict[str, Any]:
    """One entry of `CalibrationProfile.sources`: the covariance and region stages of a
    covariance source other than the profile's own."""
    return {"depth_k": cov.depth_k, "pooled_k": cov.pooled_k,
            "fallback_classes": list(cov.fallback_classes),
            "covariance_scaling": {"method": cov.method, "scale": cov.scale,
                                   "pooled_scale": cov.pooled_scale},
            "regions": _regions(region)}


def selection_of(scores: ScoreFit, cov: CovarianceFit, region: RegionFit | None,
                 classes: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The report's `selection`: the chosen method of each stage and its candidates' scores,
    and per conformal cell what its regions guarantee (`classes` name the cells)."""
    return {"score": {"chosen": scores.method, "candidates": scores.candidates,
                      "shrink": scores.shrink, "shrink_candidates": scores.shrink_candidates},
            "covariance": {"chosen": cov.method, "candidates": cov.candidates},
            "regions": None if region is None else {
                "chosen": region.method, "calibration_tps": region.n_calibration,
                "cells": _cell_guarantees(region, classes),
                **({"calibration": "cross"} if region.calibration == "cross" else {})}}


def _cell_guarantees(region: RegionFit, classes: tuple[str, ...] | None
                     ) -> list[dict[str, Any]] | None:
    """The region stage's per-cell guarantees, the class by name when `classes` are given."""
    if region.cells is None:
        return None
    return [{**r, "class": classes[r["class"]]} if classes else r for r in region.cells]


def _regions(region: RegionFit | None) -> dict[str, Any] | None:
    """A profile's `regions` stage; cross-fitted radii say so (`calibration`: cross)."""
    if region is None:
        return None
    cross = {"calibration": "cross"} if region.calibration == "cross" else {}
    return {"method": region.method, "conformal": region.conformal, **cross}


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


def has_calibration_part(opts: FitOptions, n_fit_frames: int) -> bool:
    """Whether a fit with `opts` on `n_fit_frames` keeps a calibration part: something needs
    it (an `auto` method to choose or conformal radii to fit), `calibration > 0` and at least
    2 frames; an `OptionError` when `region_method='conformal'` needs one it cannot have."""
    needed = "auto" in (opts.score_method, opts.cov_method) or opts.region_method != "gaussian"
    if opts.calibration <= 0 or not needed or n_fit_frames < 2:
        if opts.region_method == "conformal":
            raise OptionError("calibration", "region_method='conformal' needs a calibration "
                                             "part: calibration > 0 and at least 2 frames")
        return False
    return True


def _calibration_split(fit_part: Dump, matched: MatchResult, opts: FitOptions
                       ) -> tuple[tuple[Dump, MatchResult], tuple[Dump, MatchResult] | None]:
    """(training part, calibration part or None), each with its matching: a seeded
    `opts.calibration` fraction of the fit part's frames, when something needs it (an `auto`
    method to choose or conformal radii to fit). A part keeps its frames' matching."""
    if not has_calibration_part(opts, fit_part.n_frames):
        return (fit_part, matched), None
    train, calib = split_frames(fit_part, opts.calibration, opts.seed + 1)
    return (train, match_dump(train, opts.threshold)), (calib, match_dump(calib,
                                                                          opts.threshold))


def _other_sources(profile: CalibrationProfile, fit_part: Dump, matched: MatchResult,
                   train: tuple[Dump, MatchResult], calib: tuple[Dump, MatchResult] | None,
                   opts: FitOptions, conformal: bool) -> dict[str, dict]:
    """The covariance and region stages for every covariance source the dump allows besides
    the profile's own (`CalibrationProfile.sources`), fit exactly like the primary one."""
    out = {}
    for source in COV_SOURCES:
        if source == profile.cov_source:
            continue
        try:
            resolve_cov_source(fit_part, source, opts.dims)
        except OptionError:
            continue                      # the dump cannot provide this source
        cov = fit_covariance_stage(train if conformal else (fit_part, matched), train, calib,
                                   opts.dims, source, opts.cov_method, opts.min_samples)
        as_primary = replace(with_covariance(profile, cov), cov_source=source, regions=None,
                             sources=None)
        out[source] = source_stage(*_source_regions(as_primary, cov, (fit_part, matched),
                                                    train, calib, opts, conformal))
    return out


def versioned(profile: CalibrationProfile) -> CalibrationProfile:
    """The profile as version 1 when its stages are the thesis methods (temperature, depth,
    gaussian): older readers load it and it serves exactly as version 1."""
    if (profile.score_method, profile.cov_method, profile.region_method) == (
            "temperature", "depth", "gaussian") and profile.sources is None:
        return replace(profile, score_calibration=None, covariance_scaling=None, regions=None,
                       schema_version=1)
    return profile


def _provenance(dump: Dump, fit_part: Dump, held_part: Dump | None,
                calib: tuple[Dump, MatchResult] | None, tp: np.ndarray, sha256: str,
                opts: FitOptions) -> dict:
    return make_provenance(
        dump_sha256=sha256,
        n_frames=dump.n_frames,
        n_detections=dump.n_detections,
        n_ground_truth=len(dump.gt_labels),
        n_fit_frames=fit_part.n_frames,
        n_fit_detections=fit_part.n_detections,
        n_holdout_frames=0 if held_part is None else held_part.n_frames,
        n_matched=int(np.count_nonzero(tp)),
        holdout=opts.holdout,
        seed=int(opts.seed),
        n_calibration_frames=0 if calib is None else calib[0].n_frames,
        options=opts.to_dict(),
    )


def _no_progress(stage: str, fraction: float) -> None:
    """Default progress callback: does nothing."""
