"""Drift alarms: sequential tests that a served guarantee still holds, on feedback frames.

Two families of tests, each an e-detector (Shiryaev-Roberts statistic of a mixture of
betting martingales) updated once per feedback frame:

- **scores**, per class × confidence bin, both sides: H0 says a detection's chance of being a
  true positive is within `score_tolerance` of its calibrated score. A detection with score
  `p` and outcome `X` (1 = TP) bets `1 + λ (X − p − tol)` (too few TPs: `1 + λ (p − tol − X)`).
- **regions**, per region group (the unit the profile's guarantee is for: a conformal group,
  i.e. a class × distance bin or the cells pooled with it; for Gaussian regions every class ×
  distance bin) × served level `q`: H0 says the served level-q ellipse misses the true centre
  at most `a = 1 − q + max(coverage_tolerance, z·sqrt(q(1 − q)/(n + 1)))` of the time, where
  `n` is the group's calibration points and `z = calibration_sigmas`: split-conformal coverage
  holds on average over calibration sets, and one finite calibration set leaves a group's
  coverage off by about `sqrt(q(1 − q)/(n + 1))`, which is no drift. A true positive bets
  `1 + λ (miss − a)`.

Each factor has expectation ≤ 1 under H0, so for each betting fraction `λ` (a small grid,
mixed with equal weights) the Shiryaev-Roberts statistic `R_t = (1 + R_{t−1}) · L_t` (`L_t` the
product of a frame's factors; a frame without observations leaves a test alone) satisfies
`E[R_t] ≤ t`, and by Doob's inequality P(max over the first T frames ≥ A) ≤ T / A. An alarm
is raised when a test's mixed statistic reaches `A = n_tests · horizon_frames / false_alarm`:
with the union over tests, at most `false_alarm` probability of any false alarm within
`horizon_frames` frames of in-distribution feedback (a bound; docs/production.md states
the measured rate). Under drift the statistic grows geometrically, so the alarm comes after
about `log A / (expected log-bet per observation)` observations of a drifted cell.
Unlike a test since the start, the Shiryaev-Roberts form forgets a good past: drift after a
long healthy period is caught as fast as at the start.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.special import logsumexp

from calibrators.monitoring._health import FrameEvidence

__all__ = ["AlarmRule", "DriftMonitor"]

#: Betting fractions of the score tests (|λ| < 1 / (1 + tol) keeps every factor positive).
SCORE_LAMBDAS = (0.05, 0.1, 0.2, 0.4, 0.8)
#: Betting fractions of the region tests, as fractions of 1 / a.
REGION_FRACTIONS = (0.1, 0.25, 0.5, 0.75, 0.9)


@dataclass(frozen=True)
class AlarmRule:
    """The drift alarm's parameters (module docstring); `min_frames`: fewer feedback frames
    since activation (and no alarm) is `insufficient` evidence."""

    score_tolerance: float = 0.05
    coverage_tolerance: float = 0.05
    calibration_sigmas: float = 2.5
    false_alarm: float = 0.01
    horizon_frames: int = 2000
    min_frames: int = 20

    def __post_init__(self) -> None:
        for name in ("score_tolerance", "coverage_tolerance", "false_alarm"):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {value}")
        if not 0.0 <= self.calibration_sigmas < 100.0:
            raise ValueError(f"calibration_sigmas must be in [0, 100), got "
                             f"{self.calibration_sigmas}")
        for name in ("horizon_frames", "min_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")

    def log_threshold(self, n_tests: int) -> float:
        """log A for `n_tests` tests."""
        return float(np.log(max(n_tests, 1) * self.horizon_frames / self.false_alarm))

    def to_dict(self) -> dict[str, Any]:
        return {"score_tolerance": self.score_tolerance,
                "coverage_tolerance": self.coverage_tolerance,
                "calibration_sigmas": self.calibration_sigmas,
                "false_alarm": self.false_alarm, "horizon_frames": self.horizon_frames,
                "min_frames": self.min_frames}


@dataclass
class DriftMonitor:
    """The tests' state for one profile version: log R per test and betting fraction.

    classes [C], levels [Q], distance_edges [K + 1] (of the figures), groups [G] and group_n
    [G] (region groups and their calibration points), n_bins B;
    score_log_r: [C, B, 2, J] (side 0: too many TPs for the score, 1: too few);
    region_log_r: [G, Q, J]; frames: frames seen; alarms: tests that reached the threshold
    (first frame, the statistic then), kept once raised.
    """

    classes: tuple[str, ...]
    levels: tuple[float, ...]
    distance_edges: tuple[float, ...]
    groups: tuple[str, ...]
    group_n: tuple[float, ...]
    n_bins: int
    rule: AlarmRule = field(default_factory=AlarmRule)
    score_log_r: np.ndarray | None = None
    region_log_r: np.ndarray | None = None
    frames: int = 0
    alarms: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        c, g, q = len(self.classes), len(self.groups), len(self.levels)
        if self.score_log_r is None:
            self.score_log_r = np.full((c, self.n_bins, 2, len(SCORE_LAMBDAS)), -np.inf)
        if self.region_log_r is None:
            self.region_log_r = np.full((g, q, len(REGION_FRACTIONS)), -np.inf)

    @classmethod
    def for_evidence(cls, ev: FrameEvidence, rule: AlarmRule | None = None) -> DriftMonitor:
        """A fresh monitor for the classes, levels and region groups of `ev`."""
        return cls(ev.classes, tuple(ev.levels.tolist()), tuple(ev.distance_edges.tolist()),
                   ev.groups.names, ev.groups.n, ev.n_bins, rule or AlarmRule())

    def miss_limits(self) -> np.ndarray:
        """`a [G, Q]`: the miss rate each region test tolerates."""
        q = np.asarray(self.levels)[None, :]
        n = np.asarray(self.group_n, dtype=np.float64)[:, None]
        slack = self.rule.calibration_sigmas * np.sqrt(q * (1.0 - q) / (n + 1.0))
        return np.minimum(1.0 - q + np.maximum(self.rule.coverage_tolerance, slack), 1 - 1e-6)

    @property
    def n_tests(self) -> int:
        return int(np.prod(self.score_log_r.shape[:3]) + np.prod(self.region_log_r.shape[:3]))

    @property
    def log_threshold(self) -> float:
        return self.rule.log_threshold(self.n_tests)

    def update(self, ev: FrameEvidence) -> list[dict[str, Any]]:
        """Feed the frames of `ev` in order; the alarms newly raised."""
        if ev.classes != self.classes or ev.n_bins != self.n_bins or \
                tuple(ev.levels.tolist()) != self.levels or ev.groups.names != self.groups:
            raise ValueError("evidence does not match this monitor's classes, bins, levels "
                             "and region groups")
        score_l, score_seen = self._score_bets(ev)
        region_l, region_seen = self._region_bets(ev)
        new: list[dict[str, Any]] = []
        for f in range(ev.n_frames):
            self.frames += 1
            for log_r, bets, seen in ((self.score_log_r, score_l, score_seen),
                                      (self.region_log_r, region_l, region_seen)):
                s = seen[f]
                if s.any():
                    log_r[s] = np.logaddexp(0.0, log_r[s]) + bets[f][s]
            new += self._check()
        return new

    def _score_bets(self, ev: FrameEvidence) -> tuple[np.ndarray, np.ndarray]:
        """log L per frame `[F, C, B, 2, J]` and which tests saw data `[F, C, B, 2]`."""
        c, b, j = len(self.classes), self.n_bins, len(SCORE_LAMBDAS)
        lam = np.asarray(SCORE_LAMBDAS)
        tol = self.rule.score_tolerance
        x = ev.det_hit.astype(np.float64)[:, None]
        p = ev.det_score[:, None]
        logs = np.stack([np.log1p(lam * (x - p - tol)), np.log1p(lam * (p - tol - x))], axis=1)
        out = np.zeros((ev.n_frames * c * b, 2, j))
        np.add.at(out, ev.det_frame * (c * b) + ev.det_cell, logs)
        seen = (ev.score_count > 0)[..., None].repeat(2, axis=-1)
        return out.reshape(ev.n_frames, c, b, 2, j), seen

    def _region_bets(self, ev: FrameEvidence) -> tuple[np.ndarray, np.ndarray]:
        """log L per frame `[F, G, Q, J]` and which tests saw data `[F, G, Q]`."""
        a = self.miss_limits()[..., None]                                        # [G, Q, 1]
        lam = np.asarray(REGION_FRACTIONS) / a                                   # [G, Q, J]
        n = ev.group_count[..., None]                                            # [F, G, 1]
        miss = n - ev.group_hits                                                 # [F, G, Q]
        bets = (miss[..., None] * np.log1p(lam * (1.0 - a))
                + (n - miss)[..., None] * np.log1p(-lam * a))
        return bets, np.broadcast_to(n > 0, miss.shape)

    def statistic(self) -> tuple[np.ndarray, np.ndarray]:
        """log of the mixed statistic per test: scores `[C, B, 2]`, regions `[C, K, Q]`."""
        j_s, j_r = self.score_log_r.shape[-1], self.region_log_r.shape[-1]
        return (logsumexp(self.score_log_r, axis=-1) - np.log(j_s),
                logsumexp(self.region_log_r, axis=-1) - np.log(j_r))

    def _check(self) -> list[dict[str, Any]]:
        score, region = self.statistic()
        limit = self.log_threshold
        known = {a["test"] for a in self.alarms}
        new = []
        for ci, b, side in zip(*np.nonzero(score >= limit), strict=True):
            test = f"score:{self.classes[ci]}:{b}:{side}"
            if test in known:
                continue
            lo, hi = b / self.n_bins, (b + 1) / self.n_bins
            new.append({"test": test, "kind": "score", "subject": self.classes[ci],
                        "frame": self.frames, "log_statistic": float(score[ci, b, side]),
                        "reason": f"{self.classes[ci]} scores in [{lo:.1f}, {hi:.1f}) are "
                                  f"{'over' if side == 1 else 'under'}confident by more than "
                                  f"{self.rule.score_tolerance:g}"})
        limits = self.miss_limits()
        for gi, qi in zip(*np.nonzero(region >= limit), strict=True):
            q, group = self.levels[qi], self.groups[gi]
            test = f"region:{group}:{q:g}"
            if test in known:
                continue
            new.append({"test": test, "kind": "region", "subject": group,
                        "frame": self.frames, "log_statistic": float(region[gi, qi]),
                        "reason": f"{group}: the {q:g} ellipses miss more than "
                                  f"{limits[gi, qi]:.3g} of true centres"})
        self.alarms += new
        return new

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON state (-inf as None)."""
        def arr(a: np.ndarray) -> list:
            return np.where(np.isfinite(a), a, np.nan).round(6).tolist()

        return {"classes": list(self.classes), "levels": list(self.levels),
                "distance_edges": [None if not np.isfinite(e) else e
                                   for e in self.distance_edges],
                "groups": list(self.groups),
                "group_n": [None if not np.isfinite(n) else n for n in self.group_n],
                "n_bins": self.n_bins, "rule": self.rule.to_dict(),
                "score_log_r": _nan_to_none(arr(self.score_log_r)),
                "region_log_r": _nan_to_none(arr(self.region_log_r)),
                "frames": self.frames, "alarms": self.alarms}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DriftMonitor:
        """The inverse of `to_dict`."""
        def arr(v: Any) -> np.ndarray:
            a = np.asarray(v, dtype=np.float64)   # None -> nan
            return np.where(np.isnan(a), -np.inf, a)

        return cls(classes=tuple(data["classes"]), levels=tuple(data["levels"]),
                   distance_edges=tuple(np.inf if e is None else float(e)
                                        for e in data["distance_edges"]),
                   groups=tuple(data["groups"]),
                   group_n=tuple(np.inf if n is None else float(n) for n in data["group_n"]),
                   n_bins=int(data["n_bins"]), rule=AlarmRule(**data["rule"]),
                   score_log_r=arr(data["score_log_r"]), region_log_r=arr(data["region_log_r"]),
                   frames=int(data["frames"]), alarms=list(data["alarms"]))


def _nan_to_none(value: Any) -> Any:
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    return None if isinstance(value, float) and np.isnan(value) else value
