"""The covariance and region stages of a fit.

Covariance: the candidates `Σ + k_c·d·I` (depth, the thesis) and `s_c·Σ + k_c·d·I`
(shrinkage) are fit by Brent on the Gaussian NLL of the training part's true-positive
residuals and scored by the regression NLL on the calibration part; `auto` picks the lower.
Regions: split conformal (`ConformalRegions`) on the Mahalanobis distance of the calibration
part's true positives under the fitted `Σ'` (x, y block, the one the ellipses are drawn
from), grouped by class × distance bin; those frames were not used to fit `Σ'`, so the
radii keep their finite-sample guarantee. `gaussian` keeps the χ²₂ radii.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from calibrators import metrics
from calibrators.core.json_safe import to_jsonable
from calibrators.core.selection import choose_lowest_nll
from calibrators.core.vocab import COV_METHODS
from calibrators.covariance import DepthScaler, ShrinkageDepthScaler, raw_covariances
from calibrators.data import Dump
from calibrators.evaluation import SUMMARY_LEVELS, MatchResult, tp_residuals
from calibrators.regions import ConformalRegions, xy_mahalanobis

__all__ = ["SCALE_BOUNDS", "CovarianceFit", "RegionFit", "conformal_region_fit",
           "covariance_fit", "fit_covariance_stage", "fit_region_stage", "make_scaler",
           "region_fit_of_scores", "regression_nll_or_none", "tp_scores"]

#: Shrinkage factors searched (a layer spread of mm² may need s in the thousands).
SCALE_BOUNDS = (1e-3, 1e4)


@dataclass(frozen=True)
class CovarianceFit:
    """The fitted covariance stage: `method`, k per class (and pooled), s per class (and
    pooled; 1 for depth), the classes on the pooled pair, each candidate's held-out NLL."""

    method: str
    depth_k: dict[str, float]
    pooled_k: float
    scale: dict[str, float]
    pooled_scale: float
    fallback_classes: tuple[str, ...]
    candidates: dict[str, dict[str, float | None]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types (tuples as lists; a candidate without an NLL holds None)."""
        return to_jsonable(asdict(self))


@dataclass(frozen=True)
class RegionFit:
    """The fitted region stage: `method`, the conformal radii's dict form (None: gaussian),
    the calibration true positives it was fit on, per class × distance cell what the
    conformal regions guarantee at the summary's levels (`ConformalRegions.guarantees`, classes
    by index; None: gaussian), and what the radii were calibrated on (`split`: the calibration
    part; `cross`: every fit true positive, `calibrators.fit._cross`)."""

    method: str
    conformal: dict[str, Any] | None
    n_calibration: int
    cells: list[dict[str, Any]] | None = None
    calibration: str = "split"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types (`conformal` is already `ConformalRegions.to_dict()`)."""
        return to_jsonable(asdict(self))


def _tp_data(dump: Dump, matched: MatchResult, dims: tuple[str, ...], source: str
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """Residuals `[M, D]`, raw Σ `[M, D, D]` (None for source none), distances and class
    names `[M]` of the TPs."""
    tp = np.asarray(matched.tp, dtype=bool)
    cov = raw_covariances(dump, source, dims)
    names = np.asarray(dump.classes)[dump.det_labels[tp]]
    return (tp_residuals(dump, matched, dims), None if cov is None else cov[tp],
            dump.det_distance[tp], names)


def make_scaler(method: str, min_samples: int) -> Any:
    """The unfitted covariance scaler of `method` (depth or shrinkage) as the fit uses it."""
    if method == "depth":
        return DepthScaler(min_samples=min_samples)
    return ShrinkageDepthScaler(min_samples=min_samples, scale_bounds=SCALE_BOUNDS)


def fit_covariance_stage(fit_on: tuple[Dump, MatchResult], train: tuple[Dump, MatchResult],
                         calib: tuple[Dump, MatchResult] | None, dims: tuple[str, ...],
                         source: str, method: str, min_samples: int) -> CovarianceFit:
    """Choose on (`train`, `calib`) when `method` is auto, then fit the chosen scaler on
    `fit_on` (the training part when conformal radii follow, else the whole fit part)."""
    names = list(COV_METHODS) if method == "auto" else [method]
    if source == "none" or (method == "auto" and calib is None):
        names = ["depth"] if method == "auto" else names   # no Σ to shrink / nothing to choose
    candidates: dict[str, dict[str, float | None]] = {}
    if calib is not None and len(names) > 1:
        res, cov, dist, cls = _tp_data(*train, dims, source)
        c_res, c_cov, c_dist, c_cls = _tp_data(*calib, dims, source)
        chosen, candidates = choose_lowest_nll(names, lambda name: {
            "nll": regression_nll_or_none(c_res, _fit_scaler(
                name, min_samples, res, cov, dist, cls, source).transform(c_cov, c_dist,
                                                                          c_cls))})
    else:
        chosen = names[0]
    scaler = _fit_scaler(chosen, min_samples, *_tp_data(*fit_on, dims, source), source)
    return covariance_fit(scaler, fit_on[0].classes, chosen, candidates)


def covariance_fit(scaler: Any, classes: tuple[str, ...], method: str,
                   candidates: dict[str, dict[str, float | None]] | None = None
                   ) -> CovarianceFit:
    """The `CovarianceFit` of a fitted depth or shrinkage `scaler` (classes by name): every
    class of `classes` gets its own k, or the pooled one when it had too few (or no)
    matches."""
    chosen = method
    fallback = {str(c) for c in scaler.fallback_classes_}
    s = getattr(scaler, "s_", {})
    pooled_s = float(getattr(scaler, "pooled_s_", 1.0))
    return CovarianceFit(
        method=chosen,
        depth_k={c: float(scaler.k_.get(c, scaler.pooled_k_)) for c in classes},
        pooled_k=float(scaler.pooled_k_),
        scale={c: float(s.get(c, pooled_s)) for c in classes} if chosen == "shrinkage" else {},
        pooled_scale=pooled_s,
        fallback_classes=tuple(c for c in classes if c not in scaler.k_ or c in fallback),
        candidates=candidates or {})


def _fit_scaler(name: str, min_samples: int, res: np.ndarray, cov: np.ndarray | None,
                dist: np.ndarray, cls: np.ndarray, source: str) -> Any:
    try:
        with warnings.catch_warnings():   # s at a bound: Σ carries no (or all) information
            warnings.filterwarnings("ignore", "shrinkage s for class", RuntimeWarning)
            return make_scaler(name, min_samples).fit(res, cov, dist, cls)
    except ValueError as exc:
        raise ValueError(f"{name} covariance scaling failed with cov_source={source!r}: {exc}"
                         ) from exc


def regression_nll_or_none(res: np.ndarray, cov: np.ndarray) -> float | None:
    """Regression NLL, or None when a Σ' is singular (the density is undefined)."""
    if len(res) == 0:
        return None
    try:
        return float(metrics.regression_nll(res, cov))
    except ValueError:
        return None




def fit_region_stage(calib: tuple[Dump, MatchResult] | None, covariances: np.ndarray | None,
                     dims: tuple[str, ...], method: str, min_group: int,
                     distance_edges: tuple[float, ...], *, cell_floor: bool = False,
                     delta: float | None = None, floor_delta: float | None = None,
                     cell_ceiling: bool = False) -> RegionFit | None:
    """The region stage from the calibration part and `covariances [N, D, D]`, the fitted
    Σ' of its detections (None when there is no calibration part). None when `dims` lack
    x or y (no ellipse to serve). `cell_floor`, `delta`, `floor_delta`, `cell_ceiling`: of
    `ConformalRegions` (`FitOptions.conformal_options()`)."""
    if "x" not in dims or "y" not in dims:
        return None
    scores = None if calib is None or covariances is None else tp_scores(calib, covariances,
                                                                           dims)
    return region_fit_of_scores(scores, 0 if calib is None else len(calib[0].classes), method,
                                min_group, distance_edges, cell_floor=cell_floor, delta=delta,
                                floor_delta=floor_delta, cell_ceiling=cell_ceiling)


def tp_scores(part: tuple[Dump, MatchResult], covariances: np.ndarray, dims: tuple[str, ...]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Mahalanobis distances (x, y block), class indices and distances `[M]` of the true
    positives of `part` under `covariances [N, D, D]`, the Σ' of its N detections."""
    dump, matched = part
    tp = np.asarray(matched.tp, dtype=bool)
    scores = xy_mahalanobis(tp_residuals(dump, matched, dims), covariances[tp], dims)
    return scores, dump.det_labels[tp], dump.det_distance[tp]


def region_fit_of_scores(scores: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
                         n_classes: int, method: str, min_group: int,
                         distance_edges: tuple[float, ...], *, cell_floor: bool = False,
                         delta: float | None = None, floor_delta: float | None = None,
                         cell_ceiling: bool = False, calibration: str = "split") -> RegionFit:
    """The region stage of calibration true positives' (scores, class indices, distances)
    `[M]` (None: no calibration part): gaussian when `method` says so or, with `auto`, below
    `min_group` of them; else conformal (`conformal_region_fit`), recording `calibration`."""
    n_tp = 0 if scores is None else int(scores[0].shape[0])
    if method == "gaussian" or (method == "auto" and n_tp < min_group):
        return RegionFit("gaussian", None, n_tp)
    if scores is None or n_tp == 0:
        raise ValueError("region_method='conformal' needs a calibration part with true "
                         "positives (calibration > 0)")
    fit = conformal_region_fit(*scores, n_classes, min_group, distance_edges,
                               cell_floor=cell_floor, delta=delta, floor_delta=floor_delta,
                               cell_ceiling=cell_ceiling)
    return replace(fit, calibration=calibration)


def conformal_region_fit(scores: np.ndarray, labels: np.ndarray, distances: np.ndarray,
                         n_classes: int, min_group: int, distance_edges: tuple[float, ...], *,
                         cell_floor: bool = False, delta: float | None = None,
                         floor_delta: float | None = None, cell_ceiling: bool = False
                         ) -> RegionFit:
    """The conformal `RegionFit` of the calibration true positives' Mahalanobis `scores [M]`,
    class indices `labels [M]` and `distances [M]` (m), over classes 0..n_classes-1 (the
    in-memory and the streamed fit share it)."""
    regions = ConformalRegions(distance_edges=(0.0, *distance_edges, float("inf")),
                               min_group=min_group, cell_floor=cell_floor, delta=delta,
                               floor_delta=floor_delta if cell_floor else None,
                               cell_ceiling=cell_ceiling and cell_floor)
    regions.fit(scores, labels, distances, all_classes=list(range(n_classes)))
    return RegionFit("conformal", regions.to_dict(), int(scores.shape[0]),
                     regions.guarantees(SUMMARY_LEVELS))
