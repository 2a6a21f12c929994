"""The logarithmic grid of `a = λ/d` that depth scaling bins its NLL terms on: bins from the
float64 bits of `a` (`log_bin`), no logarithm taken."""

from __future__ import annotations

import numpy as np

MANTISSA_BITS = 9  # bins of a = λ/d per octave: 2**9, a relative width <= 2e-3
OCTAVES = 64  # octaves of a below its maximum that the grid covers
GRID_BINS = OCTAVES << MANTISSA_BITS  # bins per class


def bin_key(a: np.ndarray, low: int, n_bins: int, plain: bool, out: np.ndarray
             ) -> np.ndarray:
    """The bins of `a >= 0` on the grid `(low, B, plain)` of `_key_grid` into `out` (int64,
    the shape of `a`), as `log_bin_low` gives them: `1 + raw key - low` floored at 1, 0 for
    `a = 0`; only the raw key where `plain` (the caller adds `1 - low`)."""
    if not n_bins:
        out.fill(0)
        return out
    bits = a.view(np.int64)
    np.right_shift(bits, 52 - MANTISSA_BITS, out=out)
    if plain:
        return out
    out -= low - 1
    np.maximum(out, 1, out=out)
    # a = 0 has bits 0, so this sets its bin to 0; for a > 0 (bits >= 1) the bin is <= bits
    np.minimum(out, bits, out=out)
    return out


def log_bin(a: np.ndarray) -> tuple[np.ndarray, int]:
    """Bins of the floats `a >= 0` (any shape): `(bin [same shape], B)` with bins `1 .. B` for
    `a > 0` (increasing with `a`, B <= `GRID_BINS`) and bin 0 for `a == 0`; no logarithm taken.

    The bits of a positive float64 read as an int64 grow with its value: dropping all but the
    top `MANTISSA_BITS` mantissa bits splits every octave into `2**MANTISSA_BITS` equal
    bins (relative width <= 2**-MANTISSA_BITS). The grid spans the observed `a`, at most
    `OCTAVES` octaves below the largest; anything smaller shares the lowest bin (such `a` are
    below 1e-19 of the largest, negligible next to any k Brent tries).
    """
    key, n_bins, _ = log_bin_low(a)
    return key, n_bins


def log_bin_low(a: np.ndarray) -> tuple[np.ndarray, int, int]:
    """`log_bin(a)` and the raw key (`raw_key`) of bin 1 (0 when no `a > 0`)."""
    key = raw_key(a)
    positive = a > 0
    if not positive.any():
        return np.zeros(a.shape, dtype=np.int64), 0, 0
    top = int(key.max())
    low = max(int(key[positive].min()), top - GRID_BINS + 1)
    key -= low - 1
    np.maximum(key, 1, out=key)
    key[~positive] = 0
    return key, top - low + 1, low


def raw_key(a: np.ndarray) -> np.ndarray:
    """The float64 bits of `a` without the low mantissa bits: increasing with `a > 0`."""
    return a.view(np.int64) >> (52 - MANTISSA_BITS)
