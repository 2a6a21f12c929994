"""Measure the drift alarm's false-alarm rate and detection delay over seeded runs.

Each run fits a profile on a fresh synthetic validation dump (300 frames, 30 % held out for
the conformal radii), then feeds the same `DriftMonitor` rule

- `--frames` in-distribution feedback frames (a new seed): any alarm is a false alarm;
- feedback from a shifted world (the same simulator with `--shift` times the position noise
  variance per metre, `depth_k`) to a fresh monitor: the frame of the first alarm.

    python -m tests.calibrators.drift_rate --runs 100      # the figures in docs/production.md
    python -m tests.calibrators.drift_rate --runs 30 --frames 10 --shift 2 --shifted-frames 400

`tests/calibrators/monitoring/test_drift.py` runs a few of these runs.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from calibrators import FitOptions, fit_profile
from calibrators.data import DEFAULT_DEPTH_K, synthetic_dump
from calibrators.monitoring import AlarmRule, DriftMonitor, collect_evidence


@dataclass(frozen=True)
class RunResult:
    """One run: whether in-distribution feedback raised an alarm (and at which frame), and
    the first alarm's frame under the shift (None: none within the shifted frames)."""

    false_alarm_frame: int | None
    detection_frame: int | None


def one_run(seed: int, frames: int = 2000, shift: float = 4.0, shifted_frames: int = 200,
            rule: AlarmRule | None = None) -> RunResult:
    """Run `seed` (module docstring)."""
    rule = rule or AlarmRule()
    profile = fit_profile(synthetic_dump(n_frames=300, seed=10_000 + seed), FitOptions(holdout=0.3))
    good = collect_evidence(synthetic_dump(n_frames=frames, seed=20_000 + seed), profile)
    mon = DriftMonitor.for_evidence(good, rule)
    alarms = mon.update(good)
    bad_dump = synthetic_dump(n_frames=shifted_frames, seed=30_000 + seed,
                              depth_k={k: shift * v for k, v in DEFAULT_DEPTH_K.items()})
    bad = collect_evidence(bad_dump, profile)
    raised = DriftMonitor.for_evidence(bad, rule).update(bad)
    return RunResult(min((a["frame"] for a in alarms), default=None),
                     min((a["frame"] for a in raised), default=None))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--shift", type=float, default=4.0)
    parser.add_argument("--shifted-frames", type=int, default=200)
    args = parser.parse_args()
    start = time.monotonic()
    results = [one_run(seed, args.frames, args.shift, args.shifted_frames)
               for seed in range(args.runs)]
    false = [r for r in results if r.false_alarm_frame is not None]
    delays = np.array([r.detection_frame if r.detection_frame is not None else np.inf
                       for r in results])
    print(f"{args.runs} runs, {args.frames} in-distribution frames each: {len(false)} with a "
          f"false alarm (rate {len(false) / args.runs:.3f}); frames of false alarms: "
          f"{[r.false_alarm_frame for r in false]}")
    print(f"shift x{args.shift:g} (position noise variance per metre): first alarm at frame "
          f"median {np.median(delays):g}, 90th percentile {np.percentile(delays, 90):g}, max "
          f"{delays.max():g}; {int(np.isinf(delays).sum())} runs without an alarm in "
          f"{args.shifted_frames} frames")
    print(f"({time.monotonic() - start:.0f} s)")


if __name__ == "__main__":
    main()
