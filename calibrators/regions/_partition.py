"""The partition of class × distance-bin cells into conformal groups (`ConformalRegions`):
within a class, a bin with fewer than `min_group` scores is merged with its smaller adjacent
neighbour until every run of bins holds `min_group`; classes too small as a whole are pooled
per run of bins the same way, or served by all scores together."""

from __future__ import annotations

import numpy as np


def partition(counts: np.ndarray, min_group: int) -> tuple[list[list[tuple]], list[list[str]]]:
    """Group key and reason of every cell of `counts [C, B]`: a partition (module docstring).
    Keys: ("class", c, lo, hi) for bins lo..hi of class c; ("pool", lo, hi) for bins lo..hi
    of the classes too small on their own; ("all", 0, B - 1) for all scores."""
    n_classes, n_bins = counts.shape
    keys: list[list[tuple]] = [[] for _ in range(n_classes)]
    reasons: list[list[str]] = [[] for _ in range(n_classes)]
    small = [c for c in range(n_classes) if counts[c].sum() < min_group]
    for c in range(n_classes):
        if c in small:
            continue
        for lo, hi in runs_of(counts[c], min_group):
            keys[c] += [("class", c, lo, hi)] * (hi - lo + 1)
            reasons[c] += ["own" if lo == hi else "merged_bins"] * (hi - lo + 1)
    pooled = counts[small].sum(axis=0) if small else np.zeros(n_bins, dtype=np.int64)
    enough = pooled.sum() >= min_group
    runs = runs_of(pooled, min_group) if enough else [(0, n_bins - 1)]
    for c in small:
        for lo, hi in runs:
            keys[c] += [("pool" if enough else "all", lo, hi)] * (hi - lo + 1)
            reasons[c] += ["pooled_classes" if enough else "global"] * (hi - lo + 1)
    return keys, reasons


def runs_of(row: np.ndarray, min_group: int) -> list[tuple[int, int]]:
    """Contiguous runs (lo, hi) of bins covering `row [B]`, each holding >= `min_group`
    (the smallest run merged into its smaller neighbour until all do; needs
    `row.sum() >= min_group`, else one run)."""
    runs = [(b, b) for b in range(row.size)]

    def total(run: tuple[int, int]) -> int:
        return int(row[run[0]:run[1] + 1].sum())

    while len(runs) > 1:
        i = min(range(len(runs)), key=lambda j: (total(runs[j]), j))
        if total(runs[i]) >= min_group:
            break
        left = total(runs[i - 1]) if i > 0 else None
        right = total(runs[i + 1]) if i < len(runs) - 1 else None
        j = i - 1 if right is None or (left is not None and left <= right) else i + 1
        lo, hi = min(i, j), max(i, j)
        runs[lo:hi + 1] = [(runs[lo][0], runs[hi][1])]
    return runs
