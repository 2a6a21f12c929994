"""How a served region is indexed: its coverage levels and the distance bins of its group.

A level `q` in (0, 1) is the fraction of true centres a served ellipse should contain. A
request names at most `MAX_LEVELS` distinct levels. Distance bins are `[e_j, e_{j+1})` of
increasing edges `e [B + 1]` (the last may be inf); a distance below the first edge falls in
bin 0 and one at or above the last in bin B - 1, so only the inner edges decide a bin.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats

from calibrators.core.errors import FieldError
from calibrators.regions._ellipse import chi2_2_quantile

#: The most levels one request, fit or metric may name.
MAX_LEVELS = 20
#: Default distance bins (m from the ego): near, mid, far.
DEFAULT_DISTANCE_EDGES: tuple[float, ...] = (0.0, 15.0, 30.0, float("inf"))


def check_levels(levels: object, name: str = "levels") -> np.ndarray:
    """`levels` as float64 `[Q]`: 1 <= Q <= `MAX_LEVELS`, each finite in (0, 1), distinct.

    A scalar is one level. Raises ValueError naming `name` and the offending entry.
    """
    try:
        arr = np.atleast_1d(np.asarray(levels, dtype=np.float64))
    except (TypeError, ValueError):
        raise FieldError(name, f"{name} must be numbers in (0, 1), got {levels!r}") from None
    if arr.ndim != 1 or arr.size == 0:
        raise FieldError(name, f"{name} must be a non-empty list of numbers, got shape {arr.shape}")
    if arr.size > MAX_LEVELS:
        raise FieldError(name, f"{name} has {arr.size} entries; at most {MAX_LEVELS} are allowed")
    bad = ~((arr > 0.0) & (arr < 1.0))  # NaN fails both comparisons
    if bad.any():
        i = int(np.argmax(bad))
        raise FieldError(name, f"{name}[{i}] = {arr[i]} is not a level in (0, 1)", row=i)
    order = np.argsort(arr, kind="stable")
    repeats = order[1:][arr[order][1:] == arr[order][:-1]]  # later occurrences of a value
    if repeats.size:
        i = int(repeats.min())
        first = int(np.flatnonzero(arr == arr[i])[0])
        raise FieldError(name, f"{name}[{i}] = {arr[i]} repeats {name}[{first}]", row=i)
    return arr


def gaussian_radius(level: float, dim: int = 2) -> float:
    """Mahalanobis radius `sqrt(χ²_dim(q))` of the Gaussian region holding a fraction `level`.

    `dim = 2` uses the closed form of `_ellipse.chi2_2_quantile`.
    """
    q = float(check_levels(level, "level")[0])
    if isinstance(dim, bool) or not isinstance(dim, int | np.integer) or dim < 1:
        raise FieldError("dim", f"dim must be an integer >= 1, got {dim!r}")
    quantile = chi2_2_quantile(q) if dim == 2 else float(stats.chi2.ppf(q, int(dim)))
    return float(np.sqrt(quantile))


def check_distance_edges(edges: Sequence[float], name: str = "distance_edges") -> np.ndarray:
    """Edges `[B + 1]` (B >= 1) as float64: strictly increasing, the first finite and >= 0,
    only the last may be inf."""
    try:
        arr = np.asarray(edges, dtype=np.float64)
    except (TypeError, ValueError):
        raise FieldError(name, f"{name} must be numbers, got {edges!r}") from None
    if arr.ndim != 1 or arr.size < 2:
        raise FieldError(name, f"{name} must list at least 2 edges (one bin), got {edges!r}")
    if np.isnan(arr).any() or not np.isfinite(arr[:-1]).all() or arr[-1] == -np.inf:
        raise FieldError(name, f"{name} must be finite (only the last edge may be inf), got "
                         f"{arr.tolist()}")
    if arr[0] < 0 or (np.diff(arr) <= 0).any():
        raise FieldError(name, f"{name} must be >= 0 and strictly increasing, got {arr.tolist()}")
    return arr


def distance_bins(distances: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin `[N]` (int64 in [0, B)) of each distance `[N]` under checked `edges [B + 1]`."""
    return np.searchsorted(edges[1:-1], distances, side="right").astype(np.int64)

