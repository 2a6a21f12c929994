"""Calibration health from labelled feedback: per-frame evidence, running sums, and the figures.

Feedback is a `Dump` (detections plus the ground truth of the same frames) calibrated by the
profile version that served it. `collect_evidence` matches it with the library's matcher
(`match_dump`, no range filter: the same labels as `summarize`), calibrates it with the
profile (through the covariance stage `feedback_source` picks: the primary one, as
`apply_profile`, when the dump provides it) and keeps, per frame, the sufficient statistics of

- the scores: per class × equal-width confidence bin, the count, the sum of calibrated scores
  and the number of true positives (ECE and class-wise ECE are exact functions of them, the
  same numbers `summarize` / `detcal evaluate` give on the same frames);
- the served regions: per class × distance bin (the profile's conformal edges, else
  `DEFAULT_DISTANCE_EDGES`), the true positives and how many of their centres the served
  ellipse of each level contains (`coverage_table` on the same frames).

`HealthCounts` is such a sum over any set of frames; sums add and subtract, so a store keeps
cumulative sums and gets a window or "since activation" as a difference. `health_figures`
turns a sum into the figures with their confidence bounds (Clopper-Pearson for coverage; for
ECE, the per-bin gaps shrunk / widened by their accuracy interval). The drift test lives in
`_drift`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from calibrators.core.bins import bin_index
from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.errors import FieldError
from calibrators.covariance import source_arrays
from calibrators.data import Dump
from calibrators.evaluation import SUMMARY_LEVELS, match_dump, tp_residuals
from calibrators.metrics import INTERVAL_CONFIDENCE, proportion_bounds
from calibrators.profile import CalibratedDetections, CalibrationProfile
from calibrators.regions import DEFAULT_DISTANCE_EDGES, check_levels, distance_bins, xy_mahalanobis

__all__ = ["HEALTH_LEVELS", "FrameEvidence", "HealthCounts", "RegionGroups", "collect_evidence",
           "feedback_source", "health_figures", "profile_edges", "region_groups"]

#: The served levels whose coverage feedback tracks (the summary's levels).
HEALTH_LEVELS: tuple[float, ...] = SUMMARY_LEVELS
#: Equal-width confidence bins of the ECE.
N_SCORE_BINS = 10
#: Two-sided confidence of the bounds in `health_figures`.
BOUND_CONFIDENCE = INTERVAL_CONFIDENCE


@dataclass(frozen=True)
class HealthCounts:
    """Sums over a set of feedback frames (C classes, B score bins, K distance bins, Q levels).

    frames, detections, tp, gt: ints; score_count, score_sum, hit_sum: [C, B];
    region_count: [C, K] true positives; region_hits: [C, K, Q] of them inside the ellipse.
    """

    frames: int
    detections: int
    tp: int
    gt: int
    score_count: np.ndarray
    score_sum: np.ndarray
    hit_sum: np.ndarray
    region_count: np.ndarray
    region_hits: np.ndarray

    @classmethod
    def zeros(cls, n_classes: int, n_bins: int, n_distance_bins: int, n_levels: int
              ) -> HealthCounts:
        """The empty sum."""
        cb, ck = (n_classes, n_bins), (n_classes, n_distance_bins)
        return cls(0, 0, 0, 0, np.zeros(cb), np.zeros(cb), np.zeros(cb), np.zeros(ck),
                   np.zeros((*ck, n_levels)))

    def _combine(self, other: HealthCounts, sign: int) -> HealthCounts:
        return HealthCounts(*(getattr(self, f.name) + sign * getattr(other, f.name)
                              for f in fields(self)))

    def __add__(self, other: HealthCounts) -> HealthCounts:
        return self._combine(other, 1)

    def __sub__(self, other: HealthCounts) -> HealthCounts:
        return self._combine(other, -1)

    def ece(self) -> float | None:
        """ECE of all classes' scores (None without detections)."""
        return _ece(self.score_count.sum(axis=0), self.score_sum.sum(axis=0),
                    self.hit_sum.sum(axis=0))["value"]

    def coverage(self) -> list[float | None]:
        """Coverage of every level over all cells (None without true positives)."""
        n = self.region_count.sum()
        return [None if n <= 0 else float(h / n) for h in self.region_hits.sum(axis=(0, 1))]

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON (lists of numbers)."""
        return {f.name: (v.tolist() if isinstance(v := getattr(self, f.name), np.ndarray)
                         else int(v)) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HealthCounts:
        """The inverse of `to_dict`."""
        return cls(**{f.name: (int(data[f.name]) if f.type == "int"
                               else np.asarray(data[f.name], dtype=np.float64))
                      for f in fields(cls)})


@dataclass(frozen=True)
class RegionGroups:
    """The units a profile's region guarantee holds for: its conformal groups (a class ×
    distance-bin cell, or cells pooled because they were too small), or, for Gaussian
    regions, every class × distance bin. `names [G]` (`car 15-30 m`), `n [G]` calibration
    points (inf for Gaussian regions)."""

    names: tuple[str, ...]
    n: tuple[float, ...]


@dataclass(frozen=True)
class FrameEvidence:
    """Per-frame sums of F feedback frames (fields of `HealthCounts` with a leading F axis),
    the true positives and covered centres per region group `[F, G]`, `[F, G, Q]`, and, for
    the drift test, every detection's frame `[N]`, class × score-bin cell `[N]`
    (`label · B + bin`), calibrated score `[N]` and TP flag `[N]`."""

    groups: RegionGroups
    group_count: np.ndarray
    group_hits: np.ndarray
    classes: tuple[str, ...]
    levels: np.ndarray
    distance_edges: np.ndarray
    n_bins: int
    detections: np.ndarray
    tp: np.ndarray
    gt: np.ndarray
    score_count: np.ndarray
    score_sum: np.ndarray
    hit_sum: np.ndarray
    region_count: np.ndarray
    region_hits: np.ndarray
    det_frame: np.ndarray
    det_cell: np.ndarray
    det_score: np.ndarray
    det_hit: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.detections.shape[0])

    def counts(self, start: int = 0, stop: int | None = None) -> HealthCounts:
        """The sum over frames `start:stop`."""
        sl = slice(start, stop)
        return HealthCounts(
            frames=len(range(*sl.indices(self.n_frames))),
            detections=int(self.detections[sl].sum()), tp=int(self.tp[sl].sum()),
            gt=int(self.gt[sl].sum()), score_count=self.score_count[sl].sum(axis=0),
            score_sum=self.score_sum[sl].sum(axis=0), hit_sum=self.hit_sum[sl].sum(axis=0),
            region_count=self.region_count[sl].sum(axis=0),
            region_hits=self.region_hits[sl].sum(axis=0))


def feedback_source(dump: Dump, profile: CalibrationProfile) -> str:
    """The covariance source whose stage scores `dump`: the profile's primary source if the dump
    provides it (what `apply_profile`, `summarize` and `detcal evaluate` use), else the first
    of its other sources the dump provides, in the order the service prefers them (`given`
    covariances, the `hypotheses` spread, the `layers` spread, `none`); a FieldError
    (`dump`) if none."""
    if tuple(profile.classes) != tuple(dump.classes) or profile.score_mode != dump.score_mode:
        raise FieldError("dump", f"profile is for {profile.score_mode} classes "
                                 f"{list(profile.classes)} but the feedback has "
                                 f"{dump.score_mode} classes {list(dump.classes)}")
    provides = {"given": dump.det_cov is not None and dump.cov_dims == tuple(profile.cov_dims),
                "hypotheses": dump.n_hypotheses > 0, "layers": dump.n_layers >= 2,
                "none": True}
    served = profile.served_sources
    for source in (profile.cov_source, *provides):
        if source in served and provides[source]:
            return source
    raise FieldError("dump", f"the profile scores covariances from {list(served)}; "
                             f"the feedback provides none of them (covariances over "
                             f"{list(profile.cov_dims)}, box hypotheses, or at least 2 "
                             f"decoder layers)")


def region_groups(profile: CalibrationProfile, source: str | None = None) -> RegionGroups:
    """The region groups of `profile`'s stage for covariance `source` (default: its primary
    source); see `RegionGroups`."""
    conformal = profile.source_stages[source or profile.cov_source].conformal
    if conformal is None:
        edges = profile_edges(profile, source)
        names = [f"{c} {_range_text(edges[b], edges[b + 1])}" for c in profile.classes
                 for b in range(edges.size - 1)]
        return RegionGroups(tuple(names), (float("inf"),) * len(names))
    return RegionGroups(tuple(conformal.group_name(g, profile.classes) for g in conformal.groups_),
                        tuple(float(g.n) for g in conformal.groups_))


def _range_text(lo: float, hi: float) -> str:
    return f"{lo:g}+ m" if not np.isfinite(hi) else f"{lo:g}-{hi:g} m"


def _group_index(profile: CalibrationProfile, source: str, labels: np.ndarray,
                 distances: np.ndarray) -> np.ndarray:
    """`[M]` region group of each detection."""
    conformal = profile.source_stages[source].conformal
    if conformal is None:
        edges = profile_edges(profile, source)
        return labels * (edges.size - 1) + distance_bins(distances, edges)
    return conformal.group_index(labels, distances)


def profile_edges(profile: CalibrationProfile, source: str | None = None) -> np.ndarray:
    """Distance bin edges of the profile's served regions for covariance `source` (default:
    the primary one): its conformal edges, else the default ones."""
    conformal = profile.source_stages[source or profile.cov_source].conformal
    return np.asarray(DEFAULT_DISTANCE_EDGES if conformal is None else conformal.edges_,
                      dtype=np.float64)


def collect_evidence(dump: Dump, profile: CalibrationProfile, *,
                     levels: Sequence[float] = HEALTH_LEVELS, threshold: float = MATCH_THRESHOLD,
                     n_bins: int = N_SCORE_BINS) -> FrameEvidence:
    """Match `dump` to its ground truth, calibrate it with `profile` and sum, per frame, what
    health needs (module docstring). Levels a region group cannot serve count as covered
    (their radius is infinite); a profile without x, y regions yields no region sums."""
    q = check_levels(levels)
    source = feedback_source(dump, profile)
    m = match_dump(dump, threshold)
    tp = np.asarray(m.tp, dtype=bool)
    n_frames, n_classes = dump.n_frames, len(dump.classes)
    edges = profile_edges(profile, source)
    n_dist = edges.size - 1
    out = _served(dump, profile, source, q) if dump.n_detections else None
    scores = np.zeros(0) if out is None else np.clip(
        np.asarray(out.scores, dtype=np.float64), 0.0, 1.0)
    cell = dump.det_labels * n_bins + bin_index(scores, np.linspace(0.0, 1.0, n_bins + 1))
    flat = dump.det_frame * (n_classes * n_bins) + cell
    size = n_frames * n_classes * n_bins
    shape = (n_frames, n_classes, n_bins)

    def per_frame(weights: np.ndarray | None) -> np.ndarray:
        return np.bincount(flat, weights=weights, minlength=size).reshape(shape).astype(float)

    groups = region_groups(profile, source)
    n_groups = len(groups.names)
    region_count = np.zeros((n_frames, n_classes, n_dist))
    region_hits = np.zeros((n_frames, n_classes, n_dist, q.size))
    group_count = np.zeros((n_frames, n_groups))
    group_hits = np.zeros((n_frames, n_groups, q.size))
    if out is not None and out.region_radii and tp.any():
        dims = tuple(profile.cov_dims)
        md = xy_mahalanobis(tp_residuals(dump, m, dims), out.covariances[tp], dims)
        radii = np.stack([out.region_radii[float(level)][tp] for level in q], axis=1)
        covered = (md[:, None] <= radii).astype(np.float64)
        rcell = (dump.det_frame[tp] * n_classes + dump.det_labels[tp]) * n_dist + \
            distance_bins(out.distances[tp], edges)
        rsize = n_frames * n_classes * n_dist
        region_count = np.bincount(rcell, minlength=rsize).reshape(
            n_frames, n_classes, n_dist).astype(float)
        region_hits = np.stack([np.bincount(rcell, weights=covered[:, j], minlength=rsize)
                                for j in range(q.size)], axis=1).reshape(
            n_frames, n_classes, n_dist, q.size)
        gcell = dump.det_frame[tp] * n_groups + _group_index(
            profile, source, dump.det_labels[tp], out.distances[tp])
        gsize = n_frames * n_groups
        group_count = np.bincount(gcell, minlength=gsize).reshape(n_frames, n_groups)
        group_hits = np.stack([np.bincount(gcell, weights=covered[:, j], minlength=gsize)
                               for j in range(q.size)], axis=1).reshape(
            n_frames, n_groups, q.size)
    return FrameEvidence(
        groups=groups, group_count=group_count.astype(float), group_hits=group_hits,
        classes=tuple(dump.classes), levels=q, distance_edges=edges, n_bins=n_bins,
        detections=np.bincount(dump.det_frame, minlength=n_frames),
        tp=np.bincount(dump.det_frame[tp], minlength=n_frames),
        gt=np.bincount(dump.gt_frame, minlength=n_frames),
        score_count=per_frame(None), score_sum=per_frame(scores),
        hit_sum=per_frame(tp.astype(np.float64)), region_count=region_count,
        region_hits=region_hits, det_frame=dump.det_frame.copy(), det_cell=cell,
        det_score=scores, det_hit=tp)


def _served(dump: Dump, profile: CalibrationProfile, source: str, levels: np.ndarray
            ) -> CalibratedDetections:
    """The dump's final-layer detections calibrated through the `source` stage, with regions
    at `levels`; a level some region group cannot serve (too few calibration points) gets an
    infinite radius (it covers everything) rather than failing the whole feedback."""
    def calibrate(at: list[float] | None) -> CalibratedDetections:
        return profile.calibrate(
            layer_logits=dump.det_logits, labels=dump.det_label, boxes=dump.final_boxes,
            **source_arrays(dump, source), ego_xy=dump.ego_xy(dump.det_frame), levels=at)

    try:
        return calibrate(levels.tolist())
    except FieldError as exc:
        if exc.field != "levels":
            raise
    radii = {}
    for level in levels.tolist():
        try:
            radii[level] = calibrate([level]).region_radii[level]
        except FieldError:
            radii[level] = np.full(dump.n_detections, np.inf)
    return replace(calibrate(None), region_radii=radii)


def _ece(count: np.ndarray, conf: np.ndarray, hit: np.ndarray) -> dict[str, float | None]:
    """ECE over bins `[B]` from their sums, with bounds from each bin's accuracy interval."""
    n = count.sum()
    if n <= 0:
        return {"value": None, "lower": None, "upper": None}
    lo, hi = proportion_bounds(hit, count)
    safe = np.maximum(count, 1)
    mean_conf = conf / safe
    gap = np.abs(hit - conf) / safe
    # the smallest and largest |acc - conf| the accuracy interval allows, per bin
    gap_lo = np.where(count > 0, np.maximum(0.0, np.maximum(lo - mean_conf, mean_conf - hi)), 0)
    gap_hi = np.where(count > 0, np.maximum(np.abs(hi - mean_conf), np.abs(lo - mean_conf)), 0)
    w = count / n
    return {"value": float(np.sum(w * gap)), "lower": float(np.sum(w * gap_lo)),
            "upper": float(np.sum(w * gap_hi))}


def _nan_none(values: np.ndarray) -> list[float | None]:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(values).ravel()]


def health_figures(counts: HealthCounts, classes: Sequence[str], levels: Sequence[float],
                   distance_edges: Sequence[float]) -> dict[str, Any]:
    """The figures of one sum: counts, ECE and class-wise ECE with bounds, and the served
    ellipses' coverage per level overall and per class × distance bin with bounds (plain
    JSON; an inf edge is None)."""
    edges = np.asarray(distance_edges, dtype=np.float64)
    q = np.asarray(levels, dtype=np.float64)
    c = counts
    overall_n = c.region_count.sum()
    overall_hits = c.region_hits.sum(axis=(0, 1))
    lo, hi = proportion_bounds(overall_hits, np.full(q.size, overall_n))
    overall = [{"level": float(level), "n": int(overall_n),
                "coverage": None if overall_n == 0 else float(overall_hits[j] / overall_n),
                "lower": _nan_none(lo[j:j + 1])[0], "upper": _nan_none(hi[j:j + 1])[0]}
               for j, level in enumerate(q)]
    cells = []
    for ci, name in enumerate(classes):
        for b in range(edges.size - 1):
            n = c.region_count[ci, b]
            if n <= 0:
                continue
            hits = c.region_hits[ci, b]
            clo, chi = proportion_bounds(hits, np.full(q.size, n))
            cells.append({"class": name, "distance_range": _nan_none(edges[b:b + 2]),
                          "n": int(n), "coverage": (hits / n).tolist(),
                          "lower": _nan_none(clo), "upper": _nan_none(chi)})
    return {
        "frames": c.frames, "detections": c.detections, "tp": c.tp, "gt": c.gt,
        "ece": _ece(c.score_count.sum(axis=0), c.score_sum.sum(axis=0), c.hit_sum.sum(axis=0)),
        "classwise_ece": {name: _ece(c.score_count[i], c.score_sum[i], c.hit_sum[i])["value"]
                          for i, name in enumerate(classes)},
        "coverage": {"levels": q.tolist(), "overall": overall, "cells": cells},
    }


def check_feedback(dump: Dump, profile: CalibrationProfile) -> None:
    """Raise `FieldError` (field `dump`) unless `dump` holds feedback `profile` can score:
    at least one frame and one detection."""
    if dump.n_frames == 0 or dump.n_detections == 0:
        raise FieldError("dump", "feedback needs at least one frame with detections")
