"""The per-part work of a streamed fit (`calibrators.fit._stream`): plain functions of a
`Chunk` (one part of a Parquet dataset and what the fit needs to know about it) that return
small, additive statistics. They run in the calling process or on Dask workers alike.

Every function first `prepare`s the part exactly as `fit_profile` treats those frames:
the `min_score` filter, the hold-out frames dropped, nuScenes matching of what remains
(matching never crosses frames, so a part matches as it would within the whole dump), the
temperature-scaling logits and labels (`ts_logits`, `ts_labels`) and the true positives'
depth-scaling terms per covariance source. With a calibration part (conformal regions), the
depth terms are those of the training part's true positives, and the calibration part's true
positives are kept (`CalibrationTPs`: residuals, raw Σ per source, distances, classes; a few
numbers each) for the region stage, as `fit_profile` splits the fit frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.covariance import BinSums, fit_inputs, near_zero_q, raw_covariances
from calibrators.data import Dump, select_detections
from calibrators.evaluation import MatchResult, match_dump, tp_residuals, ts_labels, ts_logits
from calibrators.fit._score_stage import score_table
from calibrators.fit._stream_scores import ScoreTables
from calibrators.io.parquet import ParquetDataset
from calibrators.scores import SigmoidBins, SoftmaxSums, row_max


@dataclass(frozen=True)
class Chunk:
    """One part of `dataset` and the fit's settings: `held [frames of the part]` the hold-out
    frames, the part's `frame_ids` / `ego` rows, matching `threshold`, `min_score`,
    `modulation`, regression `dims`, `offset`, the index of the part's first fit detection
    among all fit detections (set after the first pass), and `calib [frames of the part]`,
    the frames of the calibration part (None: no calibration part), and `score_table`:
    whether the first pass tabulates the labelled logits for per-class score calibrators
    (`""`: no; `"exact"`: the rows themselves; `"grid"`: the counts of `ScoreTable`'s cells).
    """

    dataset: ParquetDataset
    index: int
    held: np.ndarray
    frame_ids: np.ndarray
    ego: np.ndarray | None
    threshold: float
    min_score: float | None
    modulation: bool
    dims: tuple[str, ...]
    offset: int = 0
    calib: np.ndarray | None = None
    score_table: str = ""


@dataclass(frozen=True)
class FirstPass:
    """The first full pass over a part: row counts, the fit detections per frame `[frames of
    the part]` (0 for held-out frames), the held-out detections per frame, the
    temperature-scaling statistics (sigmoid: `SigmoidBins` on the grid given, or the
    predicted logits and labels themselves for small fits; softmax: the target column of
    every fit row, in the smallest integer type, so that the passes of the softmax search
    read logits alone), the depth-scaling `BinSums` of the (training part's) true positives
    per covariance source (groups = class index) with their `near_zero_q` sums `[C]` (the
    shrinkage fit's), the calibration part's true positives, and with `Chunk.score_table`
    the `ScoreTable`s of the training and calibration parts' detections (`scores`) and the
    training part's own temperature statistics (`sigmoid_train`, sigmoid with a calibration
    part: the global temperature candidate is fit on them)."""

    n_detections: int
    n_ground_truth: int
    n_fit_detections: int
    n_tp: int
    fit_per_frame: np.ndarray
    held_per_frame: np.ndarray
    sigmoid: SigmoidBins | tuple[np.ndarray, np.ndarray] | None
    softmax_labels: np.ndarray | None
    bins: dict[str, BinSums]
    calib: CalibrationTPs | None = None
    near_q: dict[str, np.ndarray] | None = None
    scores: ScoreTables | None = None
    sigmoid_train: SigmoidBins | tuple[np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True)
class CalibrationTPs:
    """The true positives of a part's calibration frames: residuals `[M, D]`, raw Σ
    `[M, D, D]` per covariance source (None for `none`), distances `[M]` (m), class indices
    `[M]` (the stream's covariance and region stages read them part by part)."""

    residuals: np.ndarray
    covariances: dict[str, np.ndarray | None]
    distances: np.ndarray
    labels: np.ndarray


def _work(chunk: Chunk, logits_only: bool = False) -> Dump:
    """The part after the `min_score` filter."""
    part = chunk.dataset.read_part(chunk.index, (chunk.frame_ids, chunk.ego), logits_only)
    if chunk.min_score is None:
        return part
    return select_detections(part, part.det_scores >= chunk.min_score)


def _fit_frames(work: Dump, held: np.ndarray) -> Dump:
    return work.select_frames(~held) if held.any() else work


def prepare(chunk: Chunk) -> tuple[Dump, Dump, MatchResult]:
    """`(whole part after min_score, its fit frames, their matching)`."""
    work = _work(chunk)
    fit = _fit_frames(work, chunk.held)
    return work, fit, match_dump(fit, chunk.threshold)


def sigmoid_range(chunk: Chunk) -> tuple[int, float, float]:
    """`(fit rows, min, max)` of the part's predicted (sigmoid) logits, from its logits alone
    (no matching): the grid of the `SigmoidBins` the first pass fills (softmax: the fit rows
    alone, min and max infinite)."""
    fit = _fit_frames(_work(chunk, logits_only=True), chunk.held)
    if fit.score_mode != "sigmoid":
        return fit.n_detections, np.inf, -np.inf
    s = row_max(ts_logits(fit, chunk.modulation))
    if not len(s):
        return 0, np.inf, -np.inf
    return len(s), float(s.min()), float(s.max())


def first_pass(chunk: Chunk, sources: tuple[str, ...],
               span: tuple[float, float] | None = None) -> FirstPass:
    """Counts, temperature and depth statistics of one part (see `FirstPass`); sigmoid
    logits are binned on `span` when given, else returned as they are."""
    work, fit, matched = prepare(chunk)
    tp = np.asarray(matched.tp, dtype=bool)
    sigmoid: SigmoidBins | tuple[np.ndarray, np.ndarray] | None = None
    labels = ts_labels(fit, tp)
    row_calib = (None if chunk.calib is None   # [fit rows] in the calibration part
                 else chunk.calib[~chunk.held][fit.det_frame])
    sigmoid_train = None
    if fit.score_mode == "sigmoid":
        s = row_max(ts_logits(fit, chunk.modulation))
        sigmoid = (s, labels) if span is None else SigmoidBins.from_logits(s, labels, span=span)
        if chunk.score_table and row_calib is not None:
            s, y = s[~row_calib], labels[~row_calib]
            sigmoid_train = (s, y) if span is None else SigmoidBins.from_logits(s, y,
                                                                                span=span)
    scores = None if not chunk.score_table else _score_tables(fit, tp, row_calib, chunk)
    bins, raw, near_q = {}, {}, {}
    in_calib = (np.zeros(int(tp.sum()), dtype=bool) if row_calib is None   # [TPs]
                else row_calib[tp])
    train = ~in_calib   # of the true positives: their depth terms fit k
    res, codes = tp_residuals(fit, matched, chunk.dims), fit.det_labels[tp]
    for source in sources:
        cov = raw_covariances(fit, source, chunk.dims)
        raw[source] = None if cov is None else cov[tp][in_calib]
        if not train.any():
            bins[source] = BinSums.build_empty(len(chunk.dims), len(fit.classes))
            near_q[source] = np.zeros(len(fit.classes))
            continue
        try:
            terms = fit_inputs(res[train], None if cov is None else cov[tp][train],
                               fit.det_distance[tp][train], codes[train])[5]
        except ValueError as exc:
            raise ValueError(f"depth covariance scaling failed with cov_source={source!r}: "
                             f"part {chunk.dataset.parts[chunk.index].name}: {exc}") from exc
        bins[source] = BinSums.build(terms, codes[train], len(fit.classes))
        near_q[source] = near_zero_q(terms, codes[train], len(fit.classes))
    per_frame = np.bincount(work.det_frame, minlength=work.n_frames)
    return FirstPass(
        n_detections=chunk.dataset.parts[chunk.index].n_detections,
        n_ground_truth=len(work.gt_labels), n_fit_detections=fit.n_detections,
        n_tp=int(tp.sum()), fit_per_frame=np.where(chunk.held, 0, per_frame),
        held_per_frame=np.where(chunk.held, per_frame, 0), sigmoid=sigmoid,
        softmax_labels=labels.astype(np.min_scalar_type(len(fit.classes)))
        if fit.score_mode == "softmax" else None,
        bins=bins, calib=None if chunk.calib is None else CalibrationTPs(
            res[in_calib], raw, fit.det_distance[tp][in_calib], codes[in_calib]),
        near_q=near_q, scores=scores, sigmoid_train=sigmoid_train)


def _score_tables(fit: Dump, tp: np.ndarray, row_calib: np.ndarray | None, chunk: Chunk
                  ) -> ScoreTables:
    """The `ScoreTable`s of the part's training and calibration rows (None: no calibration
    part), as the in-memory score stage tabulates them."""
    exact = chunk.score_table == "exact"
    if row_calib is None:
        return ScoreTables(score_table(fit, tp, chunk.modulation, exact), None)
    return ScoreTables(score_table(fit, tp, chunk.modulation, exact, ~row_calib),
                       score_table(fit, tp, chunk.modulation, exact, row_calib))


def _softmax_logits(chunk: Chunk) -> np.ndarray:
    """The temperature-scaling logits `[n, C']` of the part's fit rows, read from the logits
    alone (the same rows, in the same order, as `prepare`)."""
    return ts_logits(_fit_frames(_work(chunk, logits_only=True), chunk.held), chunk.modulation)


def softmax_rows(chunk: Chunk, rows: np.ndarray, labels: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Logits `[len(rows), C']` and target columns of the part's fit rows `rows` (indices
    within the part, with repeats); `labels`: the part's `FirstPass.softmax_labels`."""
    return _softmax_logits(chunk)[rows], labels[rows].astype(np.int64)


def softmax_sums(chunk: Chunk, labels: np.ndarray, inv_t: float
                 ) -> tuple[float, float, float]:
    """`(Σ logsumexp(z/T), Σ Σ_j p_j z_j, Σ z_y)` over the part's fit rows at `1/T`
    (`SoftmaxSums`; additive over parts)."""
    z = np.ascontiguousarray(_softmax_logits(chunk), dtype=np.float64)
    if not len(z):
        return 0.0, 0.0, 0.0
    sums = SoftmaxSums(z, labels.astype(np.int64))
    log_sum, expected = sums.at(inv_t)
    return log_sum, expected, sums.target


def frames_of(chunk: Chunk, keep: np.ndarray) -> Dump | None:
    """The part (after `min_score`) with only the frames where `keep [frames]`; None if none."""
    if not keep.any():
        return None
    work = _work(chunk)
    return work if keep.all() else work.select_frames(keep)
