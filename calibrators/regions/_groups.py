"""A conformal group: the order statistics of its calibration scores and the radius they give
at a level.

- Split-conformal (`delta` None): for `n` exchangeable scores the radius at level `q` is the
  `⌈(n+1)·q⌉`-th smallest; a new point of the group falls within it with probability >= q,
  averaged over calibration draws (marginal).
- Training-conditional (`delta` in (0, 1), Vovk 2012): the `k`-th smallest, `k` the smallest
  rank with `P(Binomial(n, q) <= k - 1) >= 1 - delta`. The coverage of the `k`-th order
  statistic is Beta(k, n + 1 - k) distributed over calibration draws, so with probability
  >= 1 - delta over the draw, the served radius covers at least q of the group.
- A cell floor (`base`): a class × distance cell served by a larger group keeps its own scores
  too. Where they show that the group's radius covers less than q of the cell — more of them
  lie beyond it than a cell covered at q gives with probability `FLOOR_ALPHA` (a binomial
  test) — the cell is served the larger of its own radius and the group's: its own radius
  carries the guarantee above for the cell itself (`guarantee` "cell"); a cell too small for
  the level (its rank exceeds n) gets the group's radius scaled by how much wider its scores
  are than the group's at the highest anchor level it can certify ("scaled"). Elsewhere the
  group's radius is served as it is ("pooled"): a floor on every cell would be the largest of
  a handful of scores in a small cell and over-cover it.
- Cell ceilings (`ceiling`): the other side of the same test. Where a cell's scores show that
  its group's radius covers more than q of it — fewer of them lie beyond it than a cell
  covered at q leaves with probability `FLOOR_ALPHA` — and the cell holds enough scores for
  its own split-conformal radius, the cell is served its own radius ("cell"): a narrow cell
  pooled with wide ones (far buses with near ones) is otherwise covered far above q.
- Tail floors (`floor_delta`): at levels >= `TAIL_FROM` a cell floor is served whatever the
  test says: the larger of its group's radius and its own training-conditional radius at
  `floor_delta` (or the group's radius widened as above where the cell is too small for that
  rank). A cell's own scores are too few for the test to see a wider tail, and a tail level is
  the bound a planner reads: there the cell keeps its own guarantee with probability
  >= 1 - floor_delta over the calibration draw. Below `TAIL_FROM` the test decides, as above.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable
from typing import Any

import numpy as np
from scipy.stats import binom

from calibrators.core.checks import as_float_array

_TAIL_STEP, _BULK_STEP = 0.03, 0.004  # rank spacing: of the tail mass above, of n
#: Levels at which a cell too small for a served level compares its width with its group's.
ANCHOR_LEVELS = np.array([0.5, 0.8, 0.9, 0.95])
GUARANTEES = ("cell", "scaled", "pooled", "marginal", "none")
#: The lowest level at which a tail floor (`floor_delta`) serves every cell floor.
TAIL_FROM = 0.8
#: The binomial test's level: a cell whose scores beyond its group's radius are this improbable
#: for a cell covered at q is served its floor.
FLOOR_ALPHA = 0.05


def conformal_rank(n: int, levels: np.ndarray, delta: float | None = None) -> np.ndarray:
    """`[Q]` 1-based rank of the order statistic served at `levels [Q]` among `n` scores (may
    exceed n: no finite radius): `⌈(n+1)·q⌉` (to 1e-9), or with `delta` the smallest `k`
    with `P(Binomial(n, q) <= k - 1) >= 1 - delta`."""
    if delta is None:
        return np.ceil(np.round((n + 1) * levels, 9)).astype(np.int64)
    if n == 0:
        return np.ones(levels.shape, dtype=np.int64)
    return binom.ppf(1.0 - delta, n, levels).astype(np.int64) + 1


@dataclasses.dataclass(frozen=True)
class ConformalGroup:
    """The scores of one group: `label` (None = all classes), distance `bins` (lo, hi)
    inclusive, `n` scores, and their order statistics `values [R]` at `ranks [R]`
    (1-based, increasing, always including n). `delta`: the PAC level (None: marginal).
    `base`: for a cell floor, the group that served the cell before; `floor_delta`: its tail
    floor's PAC level (None: no tail floor); `ceiling`: whether the cell also takes its own
    radius where the group's over-covers it (module docstring)."""

    label: Hashable | None
    bins: tuple[int, int]
    n: int
    ranks: np.ndarray
    values: np.ndarray
    delta: float | None = None
    base: ConformalGroup | None = None
    floor_delta: float | None = None
    ceiling: bool = False

    def own_radius(self, levels: np.ndarray, delta: float | None = None) -> np.ndarray:
        """Radii `[Q]` of this group's own scores at checked `levels [Q]`: the stored order
        statistic at the first stored rank >= the served rank, inf beyond rank n."""
        rank = conformal_rank(self.n, levels, delta)
        idx = np.searchsorted(self.ranks, rank, side="left")
        out = np.full(levels.shape, np.inf)
        ok = rank <= self.n
        out[ok] = self.values[idx[ok]]
        return out

    def radius(self, levels: np.ndarray) -> np.ndarray:
        """Served radii `[Q]` at checked `levels [Q]` (a cell floor: module docstring)."""
        own = self.own_radius(levels, self.delta)
        if self.base is None:
            return own
        pooled = self.base.radius(levels)
        capped = self._capped(levels, pooled, own)
        served = np.where(self._floored(levels, pooled), self._floor(own, pooled),
                          np.where(capped, own, pooled))
        if self.floor_delta is None:
            return served
        tail_own = self._tail_own(levels)
        tail = np.where(capped & np.isfinite(tail_own), np.maximum(tail_own, own),
                        self._floor(tail_own, pooled))
        return np.where(levels >= TAIL_FROM, tail, served)

    def _floor(self, own: np.ndarray, pooled: np.ndarray) -> np.ndarray:
        """The larger of the cell's `own` and its group's `pooled` radii `[Q]`; where its own
        is infinite (too few scores), the group's widened by the cell's width."""
        return np.where(np.isfinite(own), np.maximum(own, pooled), pooled * self._width())

    def _tail_own(self, levels: np.ndarray) -> np.ndarray:
        """The cell's own radii `[Q]` at the tail floor's PAC level (the stricter of it and
        `delta`)."""
        assert self.floor_delta is not None
        return self.own_radius(levels, min(self.floor_delta, self.delta or 1.0))

    def guarantee(self, levels: np.ndarray, kind: str = "cell") -> tuple[list[str], list[int]]:
        """What holds for the cell this group serves at each of `levels [Q]`, and the
        calibration scores behind it: a cell floor serves "cell" (its own radius, its own n)
        or "scaled" (its group's radius widened, the group's n) where floored, elsewhere what
        its group gives; a plain group gives `kind` ("cell" for a single class × bin,
        "pooled" for merged bins or pooled classes, "marginal" for all scores) with its n."""
        if self.base is None:
            return [kind] * levels.size, [self.n] * levels.size
        pooled = self.base.radius(levels)
        own_radius = self.own_radius(levels, self.delta)
        floored = self._floored(levels, pooled) | self._capped(levels, pooled, own_radius)
        own = np.isfinite(own_radius)
        if self.floor_delta is not None:
            tail = levels >= TAIL_FROM
            floored, own = floored | tail, np.where(tail, np.isfinite(self._tail_own(levels)), own)
        wider = self._width() > 1.0
        names = [("cell" if o else "scaled" if wider else kind) if f else kind
                 for o, f in zip(own.tolist(), floored.tolist(), strict=True)]
        return names, [self.n if g == "cell" else self.base.n for g in names]

    def _floored(self, levels: np.ndarray, pooled: np.ndarray) -> np.ndarray:
        """`[Q]` bool: the cell is served its floor at `levels`: its scores show the group's
        radius too small there, or at any anchor level (where a small cell has the counts to
        show that it is wider than its group)."""
        assert self.base is not None
        wide = bool(self._misses(ANCHOR_LEVELS, self.base.radius(ANCHOR_LEVELS)).any())
        return self._misses(levels, pooled) | wide

    def _misses(self, levels: np.ndarray, pooled: np.ndarray) -> np.ndarray:
        """`[Q]` bool: this cell's scores beyond the `pooled` radii are too many for a cell
        covered at `levels` (P(Binomial(n, 1 - q) >= beyond) < FLOOR_ALPHA)."""
        beyond = self._beyond(pooled)
        return (beyond > 0) & (binom.sf(beyond - 1, self.n, 1.0 - levels) < FLOOR_ALPHA)

    def _capped(self, levels: np.ndarray, pooled: np.ndarray, own: np.ndarray) -> np.ndarray:
        """`[Q]` bool: with `ceiling`, this cell's scores beyond the `pooled` radii are too few
        for a cell covered at `levels` (P(Binomial(n, 1 - q) <= beyond) < FLOOR_ALPHA) and its
        `own` radius is finite."""
        if not self.ceiling:
            return np.zeros(levels.shape, dtype=bool)
        return np.isfinite(own) & (binom.cdf(self._beyond(pooled), self.n, 1.0 - levels)
                                   < FLOOR_ALPHA)

    def _beyond(self, radii: np.ndarray) -> np.ndarray:
        """`[Q]` how many of this cell's scores lie beyond `radii [Q]`, counted from the stored
        order statistics: exact up to `n_exact` scores, else at least as many (so a floor may
        come sooner, a ceiling only later, than the exact count gives)."""
        idx = np.searchsorted(self.values, radii, side="right")
        within = np.where(idx > 0, self.ranks[np.maximum(idx - 1, 0)], 0)
        return self.n - within

    def _width(self) -> float:
        """How much wider this cell's scores are than its base group's (>= 1), at the highest
        anchor level the cell can certify; 1 when it can certify none."""
        own = self.own_radius(ANCHOR_LEVELS)
        ok = np.flatnonzero(np.isfinite(own))
        if self.base is None or ok.size == 0:
            return 1.0
        j = int(ok[-1])
        pooled = float(self.base.radius(ANCHOR_LEVELS[j:j + 1])[0])
        return max(1.0, float(own[j]) / pooled) if pooled > 0 else 1.0


def stored_ranks(n: int, n_exact: int, max_ranks: int) -> np.ndarray:
    """Ranks `[R]` (1-based, increasing) to store for n scores: all for n <= n_exact; else
    walking down from n in steps of max(1, min(t·u, b·n)) with u the ranks above, t and b
    widened by 1.25x until at most `max_ranks` remain."""
    if n <= n_exact:
        return np.arange(1, n + 1, dtype=np.int64)
    tail, bulk = _TAIL_STEP, _BULK_STEP
    while True:
        above, out = 0, []
        while above < n and len(out) <= max_ranks:
            out.append(n - above)
            above += max(1, int(min(tail * above, bulk * n)))
        if out[-1] != 1:
            out.append(1)
        if len(out) <= max_ranks:
            return np.array(out[::-1], dtype=np.int64)
        tail, bulk = tail * 1.25, bulk * 1.25


def group_to_dict(g: ConformalGroup, index: dict[int, int]) -> dict[str, Any]:
    """The JSON form of `g`; `index` maps `id()` of a group to its position (for `base`)."""
    out = {"class": g.label, "bins": list(g.bins), "n": g.n, "ranks": g.ranks,
           "values": g.values}
    if g.base is not None:
        out["base"] = index[id(g.base)]
    return out


def group_from_dict(i: int, g: dict[str, Any], groups: list[ConformalGroup],
                    delta: float | None = None, floor_delta: float | None = None,
                    ceiling: bool = False) -> ConformalGroup:
    """Group `i` from its JSON form; `groups` are the groups before it (a `base` is one); a
    cell floor gets `floor_delta` and `ceiling`."""
    ranks = np.asarray(g["ranks"], dtype=np.int64)
    values = as_float_array(f"groups[{i}].values", g["values"], ndim=1)
    n = int(g["n"])
    if ranks.shape != values.shape or (n and (ranks[-1] != n or (np.diff(ranks) <= 0).any())):
        raise ValueError(f"groups[{i}] must have increasing ranks ending at n, one value each")
    base = g.get("base")
    if base is not None and not (isinstance(base, int) and 0 <= base < len(groups)):
        raise ValueError(f"groups[{i}].base must index a group before it, got {base!r}")
    return ConformalGroup(g["class"], (int(g["bins"][0]), int(g["bins"][1])), n, ranks, values,
                          delta, None if base is None else groups[base],
                          None if base is None else floor_delta, base is not None and ceiling)
