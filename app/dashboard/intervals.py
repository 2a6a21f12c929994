"""Sampling intervals of the dashboard's proportions and the rule that greys out a cell too
small to judge."""

from __future__ import annotations

from calibrators.metrics import INTERVAL_CONFIDENCE as CONFIDENCE
from calibrators.metrics import proportion_bounds

#: A cell with fewer true positives than this is shown grey: its figures are too noisy to
#: judge (at 30 TPs a 95 % interval of a proportion near 0.9 is already about ±0.12 wide).
MIN_TPS = 30


def proportion_interval(value: float, n: int, confidence: float = CONFIDENCE
                        ) -> tuple[float, float]:
    """Clopper-Pearson (exact binomial) interval of a proportion `value` seen in `n` trials."""
    lo, hi = proportion_bounds(round(value * n), n, confidence)
    return float(lo), float(hi)


def too_small(tps: int | None) -> bool:
    """Whether a cell of `tps` true positives is too small to judge."""
    return tps is None or tps < MIN_TPS


RULE = (f"Grey cells rest on fewer than {MIN_TPS} true positives: too few to judge. Brackets "
        f"are {CONFIDENCE:.0%} Clopper-Pearson intervals of the share.")
