"""Cross-fitted conformal radii in a streamed fit (`region_calibration='cross'`), as the
in-memory fit computes them (`calibrators.fit._cross`), part by part:

1. the covariance stage of each source is chosen and fit on the training part as before
   (`stream_covariance`); the calibration part's true positives are scored under it (their
   residuals and raw Σ came with the first pass);
2. the same method is fit on the calibration part's true positives alone (their summed depth
   statistics, `_calibration_sums`), and one second pass over the parts scores each part's
   training true positives under it, every source at once (`training_scores`: 14 bytes a
   true positive and source come back);
3. `ConformalRegions` is fit on the pooled scores, and the Σ' served is the one fit on the
   training and the calibration statistics summed (the whole fit part).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibrators.covariance import add_depth_term, raw_covariances
from calibrators.evaluation import tp_residuals
from calibrators.fit._chunks import CalibrationTPs, Chunk, prepare
from calibrators.fit._distributed import Mapper
from calibrators.fit._options import FitOptions
from calibrators.fit._region_stage import CovarianceFit, RegionFit, region_fit_of_scores
from calibrators.regions import xy_mahalanobis

__all__ = ["calibration_scores", "served_covariances", "stream_cross_regions",
           "training_scores"]

Scores = tuple[np.ndarray, np.ndarray, np.ndarray]


def served_covariances(part: CalibrationTPs, source: str, cov: CovarianceFit,
                       classes: tuple[str, ...], dims: tuple[str, ...]) -> np.ndarray:
    """Σ' `[M, D, D]` of a part's true positives `part`, as a served call scales it:
    `Σ + k·d·I`, or `s·Σ + k·d·I` with shrinkage (Σ = 0 for source none)."""
    n, dim = len(part.labels), len(dims)
    raw = part.covariances[source]
    base = np.zeros((n, dim, dim)) if raw is None else raw
    if cov.method == "shrinkage":
        base = base * np.array([cov.scale[c] for c in classes])[part.labels][:, None, None]
    k = np.array([cov.depth_k[c] for c in classes])[part.labels]
    return add_depth_term(base, part.distances, k)


def calibration_scores(tps: list[CalibrationTPs], source: str, cov: CovarianceFit,
                       classes: tuple[str, ...], dims: tuple[str, ...]) -> Scores:
    """The Mahalanobis scores (x, y block), class indices and distances `[M]` of the
    calibration true positives `tps` (per part, joined in order) under `cov`'s Σ' of
    `source`, computed part by part."""
    return (np.concatenate([xy_mahalanobis(p.residuals, served_covariances(
                p, source, cov, classes, dims), dims) for p in tps]),
            np.concatenate([p.labels for p in tps]), np.concatenate([p.distances for p in tps]))


def training_scores(chunk: Chunk, covs: dict[str, CovarianceFit], classes: tuple[str, ...]
                    ) -> dict[str, Scores]:
    """Per covariance source of `covs`, the Mahalanobis scores (x, y block), class indices and
    distances `[M]` of the part's training-part true positives (fit frames outside the
    calibration part) under its Σ' (the part is read and matched once for all sources)."""
    _, fit, matched = prepare(chunk)
    tp = np.asarray(matched.tp, dtype=bool)
    assert chunk.calib is not None
    train = ~chunk.calib[~chunk.held][fit.det_frame][tp]      # [TPs]
    residuals = tp_residuals(fit, matched, chunk.dims)[train]
    labels, distances = fit.det_labels[tp][train], fit.det_distance[tp][train]
    out = {}
    for source, cov in covs.items():
        raw = raw_covariances(fit, source, chunk.dims)
        part = CalibrationTPs(residuals, {source: None if raw is None else raw[tp][train]},
                              distances, labels)
        out[source] = (xy_mahalanobis(residuals, served_covariances(
            part, source, cov, classes, chunk.dims), chunk.dims), labels, distances)
    return out


def stream_cross_regions(classes: tuple[str, ...], opts: FitOptions,
                         covs: dict[str, CovarianceFit], on_calib: dict[str, CovarianceFit],
                         served: dict[str, CovarianceFit], tps: list[CalibrationTPs],
                         chunks: list[Chunk], mapper: Mapper
                         ) -> tuple[dict[str, CovarianceFit], dict[str, RegionFit | None]]:
    """Per covariance source, the Σ' served (`served`, with `covs`' candidates) and the
    cross-fitted region stage (module docstring): the calibration true positives `tps` (per
    part) under `covs`, the training ones under `on_calib` (a second pass over `chunks`)."""
    if "x" not in opts.dims or "y" not in opts.dims:   # no ellipse to serve
        return dict(covs), dict.fromkeys(covs)
    train = list(mapper.imap(training_scores, chunks, covs=on_calib, classes=classes))
    out_covs, out_regions = {}, {}
    for source, cov in covs.items():
        calib = calibration_scores(tps, source, cov, classes, opts.dims)
        pooled = tuple(np.concatenate(arrays) for arrays in zip(
            calib, *(part[source] for part in train), strict=True))
        out_regions[source] = region_fit_of_scores(
            pooled, len(classes), opts.region_method, opts.min_group, opts.distance_edges,
            **opts.conformal_options(), calibration="cross")
        out_covs[source] = replace(served[source], candidates=cov.candidates)
    return out_covs, out_regions
