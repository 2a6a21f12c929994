"""Choosing among fitted candidates by their held-out score: the rule every "auto" option of
a fit follows (score calibrators, covariance scalers, in 3-D and 2-D).

Each candidate, in the order given, is fit on the training part and scored on the
calibration part; the lowest held-out NLL is chosen, ties going to the earlier candidate (the
simpler one: candidate lists start with the thesis' method), and a candidate whose NLL
cannot be computed (None: a singular Σ') is never chosen over one whose NLL can.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["choose_lowest_nll"]


def choose_lowest_nll(names: Sequence[str], score: Callable[[str], dict[str, Any]]
                      ) -> tuple[str, dict[str, dict[str, Any]]]:
    """`(chosen, {name: score(name)})`: every candidate of `names` (at least one) scored by
    `score(name)`, a dict with at least `"nll"` (a float, or None when it cannot be
    computed), and the one of lowest NLL chosen (module docstring)."""
    candidates = {name: score(name) for name in names}
    chosen = min(names, key=lambda n: math.inf if candidates[n]["nll"] is None
                 else candidates[n]["nll"])
    return chosen, candidates
