"""How the bundled detectors' raw scores are miscalibrated, and what their profile does.

For each validation dump given (default: the shipped `detectors/data/lidar_val.npz`): fit a
profile on the first 70 % of its frames as `make run` does (decoder-layer spread, 30 % of
those held out to choose stages), then on the last 30 % print, for detections with a raw
score >= 0.3 (the ones a user sees): mean raw and calibrated score against the share that are
true positives (2 m) and the signed gap (positive: under-confident), the same for the
detections below 0.3, and the ECE of all detections before and after (library `summarize`).

    .venv/bin/python docs/shipped_calibration.py [DUMP.npz ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from calibrators import FitOptions, apply_profile, fit_profile, load_dump, match_dump, summarize

SHIPPED = Path(__file__).resolve().parents[1] / "detectors" / "data" / "lidar_val.npz"


def measure(path: Path) -> str:
    """One line of figures for the dump at `path`."""
    dump = load_dump(path)
    cut = int(round(0.7 * dump.n_frames))
    frames = np.arange(dump.n_frames)
    fit_part, test = dump.select_frames(frames < cut), dump.select_frames(frames >= cut)
    profile = fit_profile(fit_part, FitOptions(holdout=0.3), cov_source="layers")
    tp = match_dump(test).tp
    raw, cal = test.det_scores, apply_profile(test, profile).scores
    shown = raw >= 0.3
    ece = summarize(test, profile).classification["ece"]
    precision = tp[shown].mean()
    low = ~shown
    return (f"{path.name}: {dump.n_frames} frames ({test.n_frames} test), "
            f"{int(shown.sum())} detections with raw score >= 0.3, precision {precision:.3f}; "
            f"mean score raw {raw[shown].mean():.3f} (gap {precision - raw[shown].mean():+.3f})"
            f" -> calibrated {cal[shown].mean():.3f} (gap {precision - cal[shown].mean():+.3f}); "
            f"below 0.3: precision {tp[low].mean():.3f}, mean score raw {raw[low].mean():.3f} -> "
            f"calibrated {cal[low].mean():.3f}; ECE of all {test.n_detections} detections "
            f"{ece.before:.4f} -> {ece.after:.4f}; "
            f"T = {profile.temperature:.3f}, scores {profile.score_method}")


if __name__ == "__main__":
    for arg in sys.argv[1:] or [str(SHIPPED)]:
        print(measure(Path(arg)), flush=True)
