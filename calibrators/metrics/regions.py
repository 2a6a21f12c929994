"""Served regions: coverage of ellipses at their levels (overall and per class × distance
bin), their sharpness (mean area), and the class-wise ECE of calibrated scores.

A true centre lies in a detection's level-q ellipse iff its Mahalanobis distance `m` under
the served `Σ'` is at most the served radius `r_q` (`sqrt(χ²₂(q))` for a Gaussian region, a
conformal radius otherwise); its area is `π · r_q² · sqrt(det Σ')`. Radii may be inf (a
conformal level beyond what its group can certify): such an ellipse covers everything.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

from calibrators.core import checks
from calibrators.core.bins import ResultMixin, as_binary, check_nonempty
from calibrators.core.checks import check_distances, class_codes
from calibrators.core.errors import FieldError
from calibrators.metrics.classification import expected_calibration_error
from calibrators.regions import (
    DEFAULT_DISTANCE_EDGES,
    check_distance_edges,
    check_levels,
    distance_bins,
)


@dataclass(frozen=True)
class EllipseCoverage(ResultMixin):
    """levels: [Q]; coverage: [Q] fraction of centres within the radius; count: M."""

    levels: np.ndarray
    coverage: np.ndarray
    count: int


@dataclass(frozen=True)
class CoverageTable(ResultMixin):
    """Coverage per level overall and per class × distance bin.

    levels: [Q]; overall: [Q]; count: M; distance_edges: [B + 1] (inf becomes None in
    `to_dict`); rows: one dict per non-empty cell, sorted by class then bin, with `class`,
    `bin`, `distance_range` [lo, hi], `count` and `coverage` [Q].
    """

    levels: np.ndarray
    overall: np.ndarray
    count: int
    distance_edges: np.ndarray
    rows: list


def ellipse_coverage(mahalanobis: np.ndarray, radii: np.ndarray, levels: Sequence[float]
                     ) -> EllipseCoverage:
    """Fraction of `mahalanobis [M]` distances within the served `radii [M, Q]` at each of
    `levels [Q]` (the level each column was served for)."""
    q, m, r = _inputs(mahalanobis, radii, levels)
    return EllipseCoverage(q, _covered(m, r).mean(axis=0), int(m.shape[0]))


def coverage_table(mahalanobis: np.ndarray, radii: np.ndarray, levels: Sequence[float],
                   classes: np.ndarray, distances: np.ndarray,
                   distance_edges: Sequence[float] = DEFAULT_DISTANCE_EDGES) -> CoverageTable:
    """`ellipse_coverage` overall and per class × distance bin.

    mahalanobis: [M]; radii: [M, Q]; levels: [Q]; classes: [M] labels (ints or names);
    distances: [M] m from the ego; distance_edges: increasing bin edges (the last may be inf).
    """
    q, m, r = _inputs(mahalanobis, radii, levels)
    edges = check_distance_edges(distance_edges)
    d = check_distances(distances, None)
    checks.check_length("distances", d, m.shape[0], "mahalanobis")
    keys, codes = class_codes(classes, m.shape[0])
    covered = _covered(m, r)
    cell = codes * (edges.size - 1) + distance_bins(d, edges)
    n_cells = len(keys) * (edges.size - 1)
    count = np.bincount(cell, minlength=n_cells)
    hits = np.stack([np.bincount(cell, weights=covered[:, j], minlength=n_cells)
                     for j in range(q.size)], axis=1)
    rows = []
    for i in np.flatnonzero(count):
        c, b = divmod(int(i), edges.size - 1)
        rows.append({"class": keys[c], "bin": b, "distance_range": edges[b:b + 2].tolist(),
                     "count": int(count[i]), "coverage": (hits[i] / count[i]).tolist()})
    return CoverageTable(q, covered.mean(axis=0), int(m.shape[0]), edges, rows)


def mean_ellipse_area(covariances: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Mean area `[Q]` of the ellipses `π r² sqrt(det Σ)` of `covariances [M, 2, 2]` (the
    served `x, y` block) at `radii [M, Q]`; inf if any radius of that level is."""
    cov = checks.as_float_array("covariances", covariances, ndim=3)
    check_nonempty("covariances", cov)
    checks.check_covariances("covariances", cov, dim=2)
    r = _radii(radii, cov.shape[0], "covariances")
    det = np.maximum(cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0], 0.0)
    with np.errstate(invalid="ignore"):
        area = np.pi * r**2 * np.sqrt(det)[:, None]
    return np.where(np.isinf(r), np.inf, area).mean(axis=0)


def classwise_ece(scores: np.ndarray, tp: np.ndarray, labels: np.ndarray,
                  classes: Sequence[Hashable], n_bins: int = 10) -> dict[Hashable, float | None]:
    """ECE (`expected_calibration_error`) of the detections of each class.

    scores: [N] calibrated probabilities of the labelled class; tp: [N] bool or 0/1;
    labels: [N] index into `classes` (names, in logit column order). A class with no
    detection maps to None.
    """
    s = checks.as_float_array("scores", scores, ndim=1)
    checks.check_probabilities("scores", s)
    hit = as_binary("tp", tp, s.shape[0], "scores")
    y = checks.as_int_array("labels", labels)
    checks.check_length("labels", y, s.shape[0], "scores")
    names = list(classes)
    checks.check_index("labels", y, len(names), "classes")
    out: dict[Hashable, float | None] = {}
    for k, name in enumerate(names):
        rows = y == k
        out[name] = (float(expected_calibration_error(s[rows], hit[rows], n_bins))
                     if rows.any() else None)
    return out


def _inputs(mahalanobis: object, radii: object, levels: object
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q = check_levels(levels)
    m = checks.as_float_array("mahalanobis", mahalanobis, ndim=1)
    check_nonempty("mahalanobis", m)
    if (m < 0).any():
        i = int(np.argmax(m < 0))
        raise FieldError("mahalanobis", f"mahalanobis[{i}] = {m[i]} is negative", row=i)
    r = _radii(radii, m.shape[0], "mahalanobis")
    if r.shape[1] != q.size:
        raise FieldError("radii", f"radii has {r.shape[1]} columns but levels has {q.size} entries")
    return q, m, r


def _radii(radii: object, n: int, other: str) -> np.ndarray:
    """Radii `[n, Q]` >= 0 (`n` the rows of `other`), +inf allowed (an uncertified level),
    NaN not."""
    try:
        r = np.asarray(radii, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FieldError("radii", f"radii must be numeric: {exc}") from None
    if r.ndim != 2:
        raise FieldError("radii", f"radii must have 2 dimensions [M, Q], got shape {r.shape}")
    checks.check_length("radii", r, n, other)
    bad = np.isnan(r) | (r < 0)
    if bad.any():
        i, j = (int(v) for v in np.argwhere(bad)[0])
        raise FieldError("radii", f"radii[{i}, {j}] = {r[i, j]} is not a radius >= 0", row=i)
    return r


def _covered(m: np.ndarray, r: np.ndarray) -> np.ndarray:
    """`[M, Q]` float 1.0 where the centre is inside (m <= r), else 0.0."""
    return (m[:, None] <= r).astype(np.float64)
