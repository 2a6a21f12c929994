"""Sampling intervals of the dashboard's proportions and the rule that greys out a cell too
small to judge."""

from __future__ import annotations

from scipy import stats

#: Confidence of the intervals the tables print.
CONFIDENCE = 0.95
#: A cell with fewer true positives than this is shown grey: its figures are too noisy to
#: judge (at 30 TPs a 95 % interval of a proportion near 0.9 is already about ±0.12 wide).
MIN_TPS = 30


def proportion_interval(value: float, n: int, confidence: float = CONFIDENCE
                        ) -> tuple[float, float]:
    """Clopper-Pearson (exact binomial) interval of a proportion `value` seen in `n` trials."""
    hits = round(value * n)
    a = (1.0 - confidence) / 2.0
    lo = float(stats.beta.ppf(a, hits, n - hits + 1)) if hits > 0 else 0.0
    hi = float(stats.beta.ppf(1 - a, hits + 1, n - hits)) if hits < n else 1.0
    return lo, hi


def too_small(tps: int | None) -> bool:
    """Whether a cell of `tps` true positives is too small to judge."""
    return tps is None or tps < MIN_TPS


RULE = (f"Grey cells rest on fewer than {MIN_TPS} true positives: too few to judge. Brackets "
        f"are {CONFIDENCE:.0%} Clopper-Pearson intervals of the share.")
