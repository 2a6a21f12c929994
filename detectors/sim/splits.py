"""Fixed, disjoint scene-seed ranges of the train / val / test splits."""

from __future__ import annotations

from detectors.vocab import SPLIT_NAMES

# Seed ranges in SPLIT_NAMES order: train, val, test, holdout.
SPLITS: dict[str, range] = dict(zip(SPLIT_NAMES, (
    range(0, 100_000),
    range(100_000, 101_000),
    range(200_000, 201_000),
    range(300_000, 310_000),
), strict=True))


def split_seeds(split: str, n: int | None = None) -> range:
    """The first `n` seeds of `split` (all of them when `n` is None)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {tuple(SPLITS)}, got {split!r}")
    seeds = SPLITS[split]
    if n is None:
        return seeds
    if n < 0 or n > len(seeds):
        raise ValueError(f"n must be in [0, {len(seeds)}] for split {split!r}, got {n}")
    return seeds[:n]
