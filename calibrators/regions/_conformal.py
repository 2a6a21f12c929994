"""Split-conformal radii for the Mahalanobis distance, per class × distance bin (Mondrian).

On a calibration part of the val dump disjoint from what `Σ'` was fit on, each true positive
has a score `m = sqrt(rᵀ Σ'⁻¹ r)`. For a group of `n` exchangeable scores, the radius at
level `q` is the `⌈(n+1)·q⌉`-th smallest score (inf when that rank exceeds n), and a new
point of the group falls within it with probability >= q (and < q + 1/(n+1) without ties).

Groups: a partition of the class × distance-bin cells (`_levels`), so that every
calibration score belongs to exactly the group that serves its cell (what the guarantee
needs: a group's radius is calibrated on the very cells it serves). Within a class, a bin
with fewer than `min_group` scores is merged with its smaller adjacent neighbour (repeatedly)
until every contiguous run of bins holds `min_group`; a class too small as a whole joins the
other small classes, pooled per run of bins the same way; if even their total is below
`min_group` they are served by the group of all scores (no per-group guarantee for them).
Each cell records why ("own", "merged_bins", "pooled_classes", "global"). A class unknown
at fit is served by the group of all scores too.

Each group stores its order statistics at a set of ranks: all of them for `n <= n_exact`,
else at most `max_ranks`, every rank in the top tail and then spaced by at most 3 % of the
tail mass above and 0.4 % of n. A level whose exact rank is not stored is served by the next
stored rank above (conservative: never a smaller radius, at most that spacing more coverage).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Sequence
from typing import Any

import numpy as np

from calibrators.core.bins import check_n_bins, check_nonempty
from calibrators.core.checks import (
    as_float_array,
    check_distances,
    check_fitted,
    check_length,
    class_codes,
)
from calibrators.core.errors import FieldError
from calibrators.core.json_safe import to_jsonable
from calibrators.regions._groups import (
    ConformalGroup,
    group_from_dict,
    group_to_dict,
    stored_ranks,
)
from calibrators.regions._levels import (
    DEFAULT_DISTANCE_EDGES,
    check_distance_edges,
    check_levels,
    distance_bins,
)
from calibrators.regions._partition import partition

REASONS = ("own", "merged_bins", "pooled_classes", "global")




class ConformalRegions:
    """Split-conformal Mahalanobis radii per class × distance bin (module docstring).

    Parameters
    ----------
    distance_edges : increasing bin edges in m (>= 0; the last may be inf).
    min_group : scores a group needs (>= 1); 99 make the 0.99 radius finite.
    n_exact : groups with at most this many scores store every order statistic
        (<= max_ranks).
    max_ranks : the most order statistics a larger group stores (>= 100).
    delta : None (split-conformal: coverage >= q on average over calibration draws) or, in
        (0, 1), the training-conditional radii: every group's (and cell floor's) coverage is
        >= q with probability >= 1 - delta over the draw (`_groups`).
    cell_floor : a cell served by a larger group (merged bins, pooled classes) also gets its
        own scores as a floor: the larger of its own radius and the group's (`_groups`).
    floor_delta : None, or in (0, 1): with `cell_floor`, at levels >= 0.8 every cell floor
        serves at least the cell's own training-conditional radius at this δ (`_groups`).
    cell_ceiling : with `cell_floor`, a cell whose own scores show its group's radius
        over-covering it is served its own radius instead (`_groups`).

    Attributes set by `fit`: `classes_` (list), `edges_ [B + 1]`, `counts_ [C, B]` (scores
    per cell), `groups_` (list of `ConformalGroup`), `serving_ [C + 1, B]` (group index per
    cell; the last row serves unseen classes), `reasons_` (list [C + 1] of lists [B]).
    """

    def __init__(self, distance_edges: Sequence[float] = DEFAULT_DISTANCE_EDGES,
                 min_group: int = 100, n_exact: int = 500, max_ranks: int = 600,
                 delta: float | None = None, cell_floor: bool = False,
                 floor_delta: float | None = None, cell_ceiling: bool = False) -> None:
        self.distance_edges = distance_edges
        self.min_group = min_group
        self.n_exact = n_exact
        self.max_ranks = max_ranks
        self.delta = delta
        self.cell_floor = cell_floor
        self.floor_delta = floor_delta
        self.cell_ceiling = cell_ceiling

    def fit(self, scores: np.ndarray, classes: np.ndarray, distances: np.ndarray,
            all_classes: Sequence[Hashable] | None = None) -> ConformalRegions:
        """Fit on `scores [M]` (Mahalanobis distances >= 0 of calibration true positives),
        `classes [M]` (labels, e.g. ints or names), `distances [M]` (m); `all_classes`
        lists every class to serve (default: those in `classes`). Returns self."""
        edges = check_distance_edges(self.distance_edges)
        min_group = check_n_bins("min_group", self.min_group, minimum=1)
        n_exact = check_n_bins("n_exact", self.n_exact, minimum=1)
        max_ranks = check_n_bins("max_ranks", self.max_ranks, minimum=100)
        if n_exact > max_ranks:
            raise FieldError("n_exact", f"n_exact ({n_exact}) must be <= max_ranks ({max_ranks})")
        delta = _check_delta(self.delta)
        floor_delta = _check_delta(self.floor_delta, "floor_delta")
        s = as_float_array("scores", scores, ndim=1)
        check_nonempty("scores", s)
        if (s < 0).any():
            i = int(np.argmax(s < 0))
            raise FieldError("scores", f"scores[{i}] = {s[i]} is negative (a Mahalanobis "
                             "distance)", row=i)
        d = check_distances(distances, None)
        check_length("distances", d, s.shape[0], "scores")
        keys, codes = class_codes(classes, s.shape[0])
        known = keys if all_classes is None else _all_classes(all_classes, keys)
        position = {key: i for i, key in enumerate(known)}
        cls = np.array([position[key] for key in keys], dtype=np.int64)[codes]
        bins = distance_bins(d, edges)
        n_bins = edges.size - 1
        counts = np.zeros((len(known), n_bins), dtype=np.int64)
        np.add.at(counts, (cls, bins), 1)

        keys, reasons = partition(counts, min_group)
        index: dict[tuple, int] = {}
        self.__dict__.pop("_tables", None)   # radius and guarantee tables of the previous fit
        self.groups_: list[ConformalGroup] = []
        serving = np.zeros((len(known) + 1, n_bins), dtype=np.int64)  # last row: unknown
        small = [c for c in range(len(known)) if keys[c][0][0] == "pool"]
        for c, row in enumerate([*keys, [("all", 0, n_bins - 1)] * n_bins]):
            for b, key in enumerate(row):
                if key not in index:
                    index[key] = len(self.groups_)
                    self.groups_.append(_group(key, known, s, cls, bins, small, n_exact,
                                               max_ranks, delta))
                serving[c, b] = index[key]
        if self.cell_floor:
            self._add_cell_floors(keys, counts, (known, s, cls, bins), serving,
                                  (n_exact, max_ranks, delta), floor_delta)
        self.reasons_ = [*reasons, ["global"] * n_bins]
        self.classes_, self.edges_, self.counts_, self.serving_ = known, edges, counts, serving
        return self

    def _add_cell_floors(self, keys: list[list[tuple]], counts: np.ndarray, data: tuple,
                         serving: np.ndarray, storage: tuple, floor_delta: float | None
                         ) -> None:
        """Every cell with scores (`counts [C, B]`) that a larger group serves gets its own
        group with that group as its `base`, and serves from it (`_groups`). `data`: the
        fit's (classes, scores, class codes, bins); `storage`: (n_exact, max_ranks, delta)."""
        for c, row in enumerate(keys):
            for b, key in enumerate(row):
                if key == ("class", c, b, b) or counts[c, b] == 0:
                    continue
                own = _group(("class", c, b, b), *data, [], *storage)
                self.groups_.append(dataclasses.replace(own, base=self.groups_[serving[c, b]],
                                                        floor_delta=floor_delta,
                                                        ceiling=bool(self.cell_ceiling)))
                serving[c, b] = len(self.groups_) - 1

    def guarantees(self, levels: Sequence[float]) -> list[dict[str, Any]]:
        """One row per class × bin: the calibration scores of the cell and of the group
        serving it, and what holds at each of `levels` (`guarantee_table`)."""
        check_fitted(self, "serving_")
        q = check_levels(levels)
        names, _ = self.guarantee_table(q)
        return [{"class": label, "bin": b, "count": int(self.counts_[c, b]),
                 "group_n": group.n if group.base is None else group.base.n,
                 "guarantee": dict(zip(map(str, q.tolist()), names[g].tolist(), strict=True))}
                for c, label in enumerate(self.classes_) for b in range(self.edges_.size - 1)
                for g in [int(self.serving_[c, b])] for group in [self.groups_[g]]]

    def guarantee_table(self, levels: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """What each group's radius guarantees at `levels [Q]` for the cells it serves, `[G, Q]`
        ("cell": the cell's own scores certify it; "pooled": a group of merged bins or pooled
        classes does; "marginal": only all scores together; "scaled": a cell floor's widened
        group radius, no finite-sample guarantee of its own), and the calibration scores
        behind it `[G, Q]` (int). A group serves one kind of cell, so this is per group."""
        def build(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            kinds = self._kinds()
            rows = [g.guarantee(q, kinds[i]) for i, g in enumerate(self.groups_)]
            return (np.array([r[0] for r in rows], dtype=object).reshape(len(rows), q.size),
                    np.array([r[1] for r in rows], dtype=np.int64).reshape(len(rows), q.size))

        return self._per_levels("guarantees", levels, build)

    def _kinds(self) -> list[str]:
        """Per group, the guarantee its own radius gives the cells it serves (a cell floor:
        its base group's), from why those cells are served by it (`reasons_`)."""
        kind = {"own": "cell", "merged_bins": "pooled", "pooled_classes": "pooled",
                "global": "marginal"}
        out = ["marginal"] * len(self.groups_)   # a base whose cells all have floors
        for c, row in enumerate(self.reasons_):
            for b, reason in enumerate(row):
                out[int(self.serving_[c, b])] = kind[reason]
        return out

    def radii(self, levels: Sequence[float], classes: np.ndarray, distances: np.ndarray
              ) -> np.ndarray:
        """Radii `[N, Q]` at `levels [Q]` for detections of `classes [N]` at `distances [N]`."""
        return self.radius_table(levels)[self.group_index(classes, distances)]

    def radius_table(self, levels: Sequence[float]) -> np.ndarray:
        """Radii `[G, Q]` of every group (rows of `groups_`) at `levels [Q]`; `radii` is its
        rows at `group_index`. Kept per level set (a server asks for the same few)."""
        def build(q: np.ndarray) -> np.ndarray:
            table = np.stack([g.radius(q) for g in self.groups_])
            table.setflags(write=False)
            return table

        return self._per_levels("radii", levels, build)

    def _per_levels(self, kind: str, levels: Sequence[float], build: Any) -> Any:
        """`build(q)` of the checked `levels`, kept per kind and level set (a server asks for
        the same few; at most 64 each; emptied by `fit`)."""
        check_fitted(self, "serving_")
        q = check_levels(levels)
        tables = self.__dict__.setdefault("_tables", {}).setdefault(kind, {})
        hit = tables.get(q.tobytes())
        if hit is None:
            hit = build(q)
            if len(tables) < 64:
                tables[q.tobytes()] = hit
        return hit

    def radius(self, level: float, classes: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """Radii `[N]` at one `level` in (0, 1)."""
        q = check_levels(level, "level")
        if q.size != 1:
            raise FieldError("level", f"level must be one number in (0, 1), got {q.size} of them")
        return self.radii(q, classes, distances)[:, 0]

    def group_index(self, classes: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """`[N]` index into `groups_` of the group serving each detection."""
        check_fitted(self, "serving_")
        return self._group_of(classes, distances)

    def groups(self, classes: np.ndarray, distances: np.ndarray) -> list[dict[str, Any]]:
        """The group serving each detection `[N]` as `{"class", "bins", "n", "reason"}`."""
        check_fitted(self, "serving_")
        cls, bins = self._cells(classes, distances)
        return [{**self._describe(int(self.serving_[c, b])), "reason": self.reasons_[c][b]}
                for c, b in zip(cls.tolist(), bins.tolist(), strict=True)]

    def group_name(self, group: ConformalGroup, class_names: Sequence[str]) -> str:
        """`car 15-30 m`, `pooled classes 30+ m`, ... of one of `groups_` (classes fit by
        index, named by `class_names`)."""
        who = "pooled classes" if group.label is None else class_names[int(group.label)]
        lo, hi = self.edges_[min(group.bins)], self.edges_[max(group.bins) + 1]
        return f"{who} {lo:g}+ m" if not np.isfinite(hi) else f"{who} {lo:g}-{hi:g} m"

    def serving_table(self) -> list[dict[str, Any]]:
        """One row per class × bin: scores in the cell, the serving group and why (plain JSON
        types; an inf distance edge is None)."""
        check_fitted(self, "serving_")
        return to_jsonable([
            {"class": label, "bin": b, "distance_range": self.edges_[b:b + 2].tolist(),
             "count": int(self.counts_[c, b]), "reason": self.reasons_[c][b],
             **self._describe(int(self.serving_[c, b]), prefix="group_")}
            for c, label in enumerate(self.classes_) for b in range(self.edges_.size - 1)])

    def to_dict(self) -> dict[str, Any]:
        """Strict-JSON-able plain dict (an inf edge is None); `from_dict` serves identically."""
        check_fitted(self, "serving_")
        hyper = {"distance_edges": list(self.distance_edges), "min_group": self.min_group,
                 "n_exact": self.n_exact, "max_ranks": self.max_ranks}
        # written only when set: regions fit without them keep their earlier JSON
        hyper.update({k: v for k, v in (("delta", self.delta), ("cell_floor", self.cell_floor),
                                        ("floor_delta", self.floor_delta),
                                        ("cell_ceiling", self.cell_ceiling)) if v})
        index = {id(g): i for i, g in enumerate(self.groups_)}
        return to_jsonable({
            "hyper": hyper,
            "classes": self.classes_, "distance_edges": self.edges_, "counts": self.counts_,
            "groups": [group_to_dict(g, index) for g in self.groups_],
            "serving": self.serving_, "reasons": self.reasons_,
        })

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ConformalRegions:
        """The fitted regions `to_dict` wrote; ValueError naming a missing or bad key."""
        if not isinstance(data, dict):
            raise ValueError(f"conformal regions must be a dict, got {type(data).__name__}")
        missing = [k for k in ("hyper", "classes", "distance_edges", "counts", "groups",
                               "serving", "reasons") if k not in data]
        if missing:
            raise ValueError(f"conformal regions dict lacks {missing[0]!r}")
        hyper = dict(data["hyper"])
        hyper["distance_edges"] = tuple(_inf(v) for v in hyper.get("distance_edges", ()))
        try:
            self = cls(**hyper)
        except TypeError as exc:
            raise ValueError(f"hyper has a bad key: {exc}") from None
        self.classes_ = list(data["classes"])
        self.edges_ = check_distance_edges([_inf(v) for v in data["distance_edges"]])
        self.counts_ = np.asarray(data["counts"], dtype=np.int64).reshape(
            len(self.classes_), self.edges_.size - 1)
        self.groups_, delta = [], _check_delta(self.delta)
        floor_delta = _check_delta(self.floor_delta, "floor_delta")
        for i, g in enumerate(data["groups"]):
            self.groups_.append(group_from_dict(i, g, self.groups_, delta, floor_delta,
                                                bool(self.cell_ceiling)))
        self.serving_ = np.asarray(data["serving"], dtype=np.int64)
        if (self.serving_.shape != (len(self.classes_) + 1, self.edges_.size - 1)
                or (self.serving_ < 0).any() or (self.serving_ >= len(self.groups_)).any()):
            raise ValueError("serving must be [C + 1, B] indices of groups")
        self.reasons_ = [list(r) for r in data["reasons"]]
        if any(r not in REASONS for row in self.reasons_ for r in row):
            raise ValueError(f"reasons must be among {list(REASONS)}")
        return self

    # -- helpers -------------------------------------------------------------------------------
    def _cells(self, classes: np.ndarray, distances: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        d = check_distances(distances, None)
        keys, codes = class_codes(classes, d.shape[0])
        position = {key: i for i, key in enumerate(self.classes_)}
        unseen = len(self.classes_)
        cls = np.array([position.get(key, unseen) for key in keys], dtype=np.int64)
        return (cls[codes] if d.size else np.zeros(0, dtype=np.int64)), distance_bins(
            d, self.edges_)

    def _group_of(self, classes: np.ndarray, distances: np.ndarray) -> np.ndarray:
        cls, bins = self._cells(classes, distances)
        return self.serving_[cls, bins]

    def _describe(self, g: int, prefix: str = "") -> dict[str, Any]:
        group = self.groups_[g]
        return {f"{prefix}class": group.label, f"{prefix}bins": list(group.bins),
                f"{prefix}n": group.n}


def _group(key: tuple, known: list, s: np.ndarray, cls: np.ndarray, bins: np.ndarray,
           small: list[int], n_exact: int, max_ranks: int, delta: float | None = None
           ) -> ConformalGroup:
    """The stored table of the group `key` (see `partition`)."""
    lo, hi = key[-2:]
    mask = (bins >= lo) & (bins <= hi)
    if key[0] == "class":
        mask &= cls == key[1]
    elif key[0] == "pool":
        mask &= np.isin(cls, small)
    values = np.sort(s[mask])
    ranks = stored_ranks(values.size, n_exact, max_ranks)
    label = known[key[1]] if key[0] == "class" else None
    return ConformalGroup(label, (int(lo), int(hi)), int(values.size), ranks,
                          values[ranks - 1] if values.size else values, delta)


def _check_delta(delta: Any, name: str = "delta") -> float | None:
    """`delta` as a float in (0, 1), or None; FieldError naming `name` otherwise."""
    if delta is None:
        return None
    if isinstance(delta, bool) or not isinstance(delta, int | float) \
            or not 0.0 < float(delta) < 1.0:
        raise FieldError(name, f"{name} must be a number in (0, 1) or None, got {delta!r}")
    return float(delta)




def _all_classes(all_classes: Sequence[Hashable], seen: list) -> list:
    known = list(all_classes.tolist() if isinstance(all_classes, np.ndarray) else all_classes)
    if len(set(known)) != len(known):
        raise FieldError("all_classes", "all_classes must list each class once")
    missing = [key for key in seen if key not in set(known)]
    if missing:
        raise FieldError("classes", f"classes holds {missing[0]!r}, which is not in all_classes")
    return known




def _inf(value: Any) -> float:
    return float("inf") if value is None else float(value)
