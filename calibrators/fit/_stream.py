"""Fit a calibration profile from a Parquet dataset in bounded memory (docs/science.md,
"Streamed fit"), in this process or on Dask workers.

`fit_profile_stream(path, options)` gives the profile `fit_profile(load_parquet(path),
options)` gives, T and every k to 1e-6 relative, holding one part of the dataset at a time:

1. the hold-out frames are drawn as `fit_profile` draws them (`held_out_frames`, same seed);
2. a light pass over the logits alone: the fit rows (whether score tables hold rows or
   cells) and, sigmoid, the range of the predicted logits, the grid `TemperatureScaler` bins
   them on;
3. first pass, per part (`stream_chunks.first_pass`): the `min_score` filter, matching of the
   part's fit frames, row counts, the `SigmoidBins` of the predicted logits on that grid
   (small fits: the logits themselves), and the depth-scaling `BinSums` of the true
   positives per covariance source; the sums over the parts are the statistics
   `TemperatureScaler` and `DepthScaler` bin in memory, so T and k come from the same Brent
   searches;
4. softmax temperature, which has no finite statistic: one pass over the parts' logits per
   evaluation of Brent's root finder on the NLL's derivative (the parts' sums add up; the
   first pass returned every fit row's target column, 2 bytes a row, so these passes
   neither match nor read boxes), started where the same seeded subsample (gathered from
   the parts) puts T;
5. covariance and regions (`_stream_stages`): the fit frames are split into a
   training and a calibration part as `fit_profile` splits them (`held_out_frames` of the
   fit frames' tokens with `calibration` and seed + 1, so the same frames whatever the
   partitioning); depth and shrinkage (`s·Σ + k·d·I`) are fit on the training part's
   summed depth statistics (plus the `near_zero_q` sums shrinkage needs), `auto` choosing by
   the regression NLL of the calibration part's true positives (kept by the first pass: a
   residual, a raw Σ per source and two numbers each), whose Mahalanobis scores under the
   fitted Σ' give the conformal radii, exactly as in memory (with `region_calibration`
   'cross', a second pass scores the training part's true positives: `_stream_cross`);
6. the profile is assembled as `fit_profile` assembles it; its report summarises a seeded
   sample of at most `report_detections` detections of whole fit (and held-out) frames,
   all of them when they fit (the report then equals the in-memory one), and says so.

The per-class score calibrators and the choice among score candidates (`_stream_scores`)
are fit on the `ScoreTable`s the first pass returns for the training and calibration parts
(summed as they arrive, then dropped): the rows themselves up to `EXACT_ROWS` fit detections
(the in-memory stage), cell counts above. `check_stream_options` refuses with an
`OptionError` naming the option the one combination without a per-part statistic:
`score_method='auto'` on softmax scores with a calibration part.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np

from calibrators.core.errors import OptionError
from calibrators.core.vocab import COV_SOURCES
from calibrators.covariance import (
    resolve_cov_source,
)
from calibrators.data import canonical_order, concat_frames, held_out_frames
from calibrators.evaluation import ProfileReport, summarize
from calibrators.fit._chunks import (
    Chunk,
    FirstPass,
    first_pass,
    frames_of,
    sigmoid_range,
    softmax_rows,
    softmax_sums,
)
from calibrators.fit._distributed import Mapper
from calibrators.fit._options import FitOptions
from calibrators.fit._pipeline import (
    base_profile,
    check_fit_input,
    resolve_options,
    selection_of,
    source_stage,
    versioned,
)
from calibrators.fit._region_stage import (
    CovarianceFit,
    RegionFit,
)
from calibrators.fit._score_stage import ScoreFit, candidate_names
from calibrators.fit._stream_cross import stream_cross_regions
from calibrators.fit._stream_scores import ScoreTables, stream_scores
from calibrators.fit._stream_stages import (
    calibration_frames,
    refit_covariance,
    stream_covariance,
    stream_regions,
)
from calibrators.io.parquet import ParquetDataset, open_parquet
from calibrators.profile import CalibrationProfile, make_provenance
from calibrators.scores import (
    EXACT_ROWS,
    SIGMOID_BINS,
    SUBSAMPLE_MIN,
    SigmoidBins,
    TemperatureScaler,
    sigmoid_nll,
    softmax_mean,
    subsample_rows,
    subsample_start,
)

#: Detections of whole frames the report summarises at most (per part: fit, held out).
REPORT_DETECTIONS = 500_000

Progress = Callable[[str, float], None]


def check_stream_options(options: FitOptions, n_fit_frames: int | None = None,
                         score_mode: str | None = None) -> None:
    """Raise `OptionError` naming the option when a streamed fit cannot give what
    `fit_profile` gives with `options` on a dataset of `score_mode` (None: not known yet):
    choosing `score_method='auto'` among candidates on softmax scores, where the global
    temperature's candidate needs every row's softmax at the training part's T (`auto` with
    no calibration part, `calibration=0` or fewer than 2 fit frames, `n_fit_frames`, means
    the temperature alone)."""
    no_calibration = options.calibration <= 0 or (n_fit_frames is not None and n_fit_frames < 2)
    if options.score_method == "auto" and score_mode == "softmax" and not no_calibration:
        raise OptionError("score_method", "the streamed fit cannot reproduce "
                          "score_method='auto' on softmax scores: its temperature candidate "
                          "is fit on the training part alone, one pass over the data per "
                          "step; name a score method (e.g. 'platt') or use calibration=0")


def fit_profile_stream(path: Any, options: FitOptions | None = None, *, client: Any = None,
                       progress: Progress | None = None,
                       report_detections: int = REPORT_DETECTIONS,
                       exact_rows: int = EXACT_ROWS, **overrides: Any) -> CalibrationProfile:
    """Fit a profile from the Parquet dataset at `path` (module docstring).

    options / overrides: as `fit_profile`. client: a `distributed.Client` to run the
    per-part work on (None: in this process). progress: `progress(stage, fraction)`.
    exact_rows: the fit detections up to which the score stage's tables hold the rows
    themselves (the in-memory stage, 28 bytes a detection), cell counts above.
    Raises `OptionError` for options a streamed fit cannot reproduce, `FieldError` for a bad
    dataset, ValueError for data that cannot be fit (the messages of `fit_profile`).
    """
    opts = resolve_options(options, overrides)
    report_progress = progress if progress is not None else (lambda stage, fraction: None)
    ds = open_parquet(path)
    empty = ds.empty_dump()
    source = check_fit_input(empty, opts)
    held = held_out_frames(ds.frames()[0], opts.holdout, opts.seed)
    check_stream_options(opts, ds.n_frames - int(held.sum()), ds.score_mode)
    report_progress("prepare", 0.0)
    calib = calibration_frames(ds.frames()[0], held, opts)
    sources = (source, *_other_sources(empty, source, opts))
    mapper = Mapper(client)

    report_progress("match", 0.1)
    chunks, firsts, n_fit, n_tp, sums = _first_passes(ds, held, calib, opts, sources, mapper,
                                                      exact_rows)

    report_progress("scores", 0.25)
    temperature = _temperature(ds, opts, chunks, firsts, n_fit, mapper, sums.sigmoid)
    scores = ScoreFit(method="temperature", temperature=temperature, params=None)
    if sums.tables is not None:
        scores = stream_scores(opts, sums.tables, temperature, lambda: _sigmoid_temperature(
            sums.sigmoid_train, _width(ds, opts)))
    report_progress("covariance", 0.4)
    tps = None if calib is None else [f.calib for f in firsts]
    covs = {s: stream_covariance(ds.classes, s, firsts, tps, opts) for s in sources}
    report_progress("regions", 0.5)
    if opts.region_calibration == "cross" and tps is not None and opts.region_method != \
            "gaussian":   # radii on every fit true positive: a second pass (_stream_cross)
        on_calib, on_all = ({s: refit_covariance(ds.classes, s, firsts, tps, opts,
                                                 covs[s].method, whole) for s in sources}
                            for whole in (False, True))
        covs, regions = stream_cross_regions(ds.classes, opts, covs, on_calib, on_all, tps,
                                             chunks, mapper)
    else:
        regions = stream_regions(ds.classes, opts, covs, tps)
    provenance = make_provenance(
        dump_sha256=ds.source_sha256, n_frames=ds.n_frames, n_detections=ds.n_detections,
        n_ground_truth=ds.n_ground_truth, n_fit_frames=ds.n_frames - int(held.sum()),
        n_fit_detections=n_fit, n_holdout_frames=int(held.sum()), n_matched=n_tp,
        holdout=opts.holdout, seed=int(opts.seed),
        n_calibration_frames=0 if calib is None else int(calib.sum()),
        options=opts.to_dict())
    profile = _assembled(empty, opts, scores, covs, sources, regions, provenance)

    report_progress("report", 0.6)
    report = _report(profile, opts, chunks, firsts, held, report_detections, mapper,
                     selection_of(scores, covs[source], regions[source], tuple(ds.classes)),
                     report_progress)
    report_progress("done", 1.0)
    return replace(profile, report=report)


def _light_pass(ds: ParquetDataset, chunks: list[Chunk], mapper: Mapper, per_class: bool
                ) -> tuple[int, tuple[float, float] | None]:
    """The fit rows, from the logits alone, and the range of the predicted logits the
    sigmoid bins span (None for softmax or when the fit rows are few enough to keep: module
    docstring, step 2); no pass (0, None) for softmax without per-class score tables, which
    need neither."""
    if ds.score_mode != "sigmoid" and not per_class:
        return 0, None
    ranges = mapper.map(sigmoid_range, chunks)
    n_rows = sum(r[0] for r in ranges)
    if ds.score_mode == "sigmoid" and n_rows > SIGMOID_BINS:
        return n_rows, (min(r[1] for r in ranges), max(r[2] for r in ranges))
    return n_rows, None


SigmoidStats = SigmoidBins | list[tuple[np.ndarray, np.ndarray]] | None


class _Sums(NamedTuple):
    """What the first passes return summed over the parts as they arrive (each part's own
    copy dropped): the score tables (None: no per-class score method to fit), and the sigmoid
    temperature statistics of all fit rows and of the training part's (`SigmoidBins`
    summed, or the parts' predicted logits and labels for small fits; None: softmax)."""

    tables: ScoreTables | None = None
    sigmoid: SigmoidStats = None
    sigmoid_train: SigmoidStats = None


def _first_passes(ds: ParquetDataset, held: np.ndarray, calib: np.ndarray | None,
                  opts: FitOptions, sources: tuple[str, ...], mapper: Mapper, exact_rows: int
                  ) -> tuple[list[Chunk], list[FirstPass], int, int, _Sums]:
    """The parts (each with the offset of its first fit row), their first passes (module
    docstring, step 3) with their additive statistics summed as they come (`_Sums`), the fit
    rows and the true positives; the ValueErrors of `fit_profile` when nothing is left to
    fit on or nothing matched."""
    chunks = _chunks(ds, held, calib, opts)
    per_class = candidate_names(opts.score_method, calib is not None) != ["temperature"]
    n_rows, span = _light_pass(ds, chunks, mapper, per_class)
    if per_class:
        mode = "exact" if n_rows <= exact_rows else "grid"
        chunks = [replace(c, score_table=mode) for c in chunks]
    firsts: list[FirstPass] = []
    sums = _Sums()
    for first in mapper.imap(first_pass, chunks, sources=sources, span=span):
        sums = _Sums(sums.tables if first.scores is None else first.scores
                     if sums.tables is None else sums.tables + first.scores,
                     _fold(sums.sigmoid, first.sigmoid),
                     _fold(sums.sigmoid_train, first.sigmoid_train))
        firsts.append(replace(first, scores=None, sigmoid=None, sigmoid_train=None))
    counts = np.array([f.n_fit_detections for f in firsts])
    if sum(int(f.fit_per_frame.sum() + f.held_per_frame.sum()) for f in firsts) == 0:
        raise ValueError(f"min_score={opts.min_score} leaves no detection to fit on")
    n_tp = sum(f.n_tp for f in firsts)
    if n_tp == 0:
        raise ValueError(f"no detection matched ground truth within {opts.threshold} m "
                         f"(threshold); check the dump's coordinates and classes")
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    chunks = [replace(c, offset=int(o)) for c, o in zip(chunks, offsets, strict=True)]
    return chunks, firsts, int(counts.sum()), n_tp, sums


def _fold(acc: SigmoidStats, part: SigmoidBins | tuple[np.ndarray, np.ndarray] | None
          ) -> SigmoidStats:
    """`acc` with a part's sigmoid statistics added (bins summed, logits listed)."""
    if part is None:
        return acc
    if isinstance(part, SigmoidBins):
        return part if acc is None else acc + part   # type: ignore[operator]
    return [*(acc or []), part]   # type: ignore[misc]


def _assembled(empty: Any, opts: FitOptions, scores: ScoreFit, covs: dict[str, CovarianceFit],
               sources: tuple[str, ...], regions: dict[str, RegionFit | None],
               provenance: dict) -> CalibrationProfile:
    """The profile as `fit_profile` assembles it (no report yet)."""
    source = sources[0]
    profile = base_profile(empty, opts, scores, covs[source], source, provenance)
    profile = replace(profile, regions=source_stage(covs[source], regions[source])["regions"])
    if opts.other_sources:
        profile = replace(profile, sources={s: source_stage(covs[s], regions[s])
                                            for s in sources[1:]} or None)
    return versioned(profile)


def _other_sources(empty: Any, source: str, opts: FitOptions) -> tuple[str, ...]:
    """The covariance sources besides `source` the dataset allows (with `other_sources`)."""
    if not opts.other_sources:
        return ()
    out = []
    for other in COV_SOURCES:
        if other == source:
            continue
        try:
            resolve_cov_source(empty, other, opts.dims)
        except OptionError:
            continue
        out.append(other)
    return tuple(out)


def _chunks(ds: ParquetDataset, held: np.ndarray, calib: np.ndarray | None, opts: FitOptions
            ) -> list[Chunk]:
    ids, ego = ds.frames()
    return [Chunk(dataset=ds, index=i, held=held[p.first:p.stop],
                  frame_ids=ids[p.first:p.stop], ego=None if ego is None else ego[p.first:p.stop],
                  threshold=opts.threshold, min_score=opts.min_score,
                  modulation=opts.modulation, dims=opts.dims,
                  calib=None if calib is None else calib[p.first:p.stop])
            for i, p in enumerate(ds.parts)]


def _temperature(ds: ParquetDataset, opts: FitOptions, chunks: list[Chunk],
                 firsts: list[FirstPass], n: int, mapper: Mapper, sigmoid: SigmoidStats
                 ) -> float:
    """T as `TemperatureScaler.fit` finds it on all fit rows (module docstring, step 3):
    sigmoid from the summed statistics `sigmoid`."""
    scaler = TemperatureScaler(mode=ds.score_mode)
    width = _width(ds, opts)
    if ds.score_mode == "sigmoid":
        return _sigmoid_temperature(sigmoid, width)

    labels = [f.softmax_labels for f in firsts]

    def value_grad(log_t: float) -> tuple[float, float]:
        inv_t = float(np.exp(-log_t))
        sums = mapper.map(softmax_sums, chunks, labels, inv_t=inv_t)
        return softmax_mean(n, inv_t, *(sum(s[i] for s in sums) for i in range(3)))

    start = None
    if n >= SUBSAMPLE_MIN:
        rows = subsample_rows(n)
        local = [rows[(rows >= c.offset) & (rows < c.offset + f.n_fit_detections)] - c.offset
                 for c, f in zip(chunks, firsts, strict=True)]
        got = mapper.map(softmax_rows, chunks, local, labels)
        start = subsample_start(np.concatenate([g[0] for g in got]),
                                np.concatenate([g[1] for g in got]), scaler.log_bounds())
    scaler.fit_gradient(value_grad, n, width, start)
    return float(scaler.temperature_)


def _sigmoid_temperature(stats: SigmoidStats, width: int) -> float:
    """The sigmoid T of summed `SigmoidBins` or of the parts' predicted logits and labels."""
    scaler = TemperatureScaler(mode="sigmoid")
    if isinstance(stats, SigmoidBins):
        scaler.fit_bins(stats, width)
    else:
        assert stats is not None
        s, y = (np.concatenate([part[i] for part in stats]) for i in (0, 1))
        scaler.fit_objective(sigmoid_nll(s, y), len(s), width)
    return float(scaler.temperature_)


def _width(ds: ParquetDataset, opts: FitOptions) -> int:
    """The columns the temperature is fit over (what `n_columns_` records)."""
    return 1 if opts.modulation and ds.score_mode == "sigmoid" else ds.n_columns


def _report(profile: CalibrationProfile, opts: FitOptions, chunks: list[Chunk],
            firsts: list[FirstPass], held: np.ndarray, budget: int, mapper: Mapper,
            selection: dict[str, Any], report_progress: Progress) -> dict[str, Any]:
    """The profile's report on seeded samples of whole fit and held-out frames (module
    docstring, step 4); `sample` records what was summarised when not everything was."""
    fit_counts = np.concatenate([f.fit_per_frame for f in firsts])
    held_counts = np.concatenate([f.held_per_frame for f in firsts])
    rng = np.random.default_rng(opts.seed)
    fit_keep, fit_note = _sample(~held, fit_counts, budget, rng)
    fit_summary = summarize(_gather(chunks, fit_keep, mapper), profile,
                            threshold=opts.threshold)
    held_summary, held_note = None, None
    if held.any():
        report_progress("holdout report", 0.8)
        held_keep, held_note = _sample(held, held_counts, budget, rng)
        held_summary = summarize(_gather(chunks, held_keep, mapper), profile,
                                 threshold=opts.threshold)
    out = ProfileReport(fit=fit_summary, holdout=held_summary, min_score=opts.min_score,
                        threshold=opts.threshold, selection=selection).to_dict()
    if fit_note or held_note:
        out["sample"] = {"fit": fit_note, "holdout": held_note, "seed": int(opts.seed),
                         "max_detections": int(budget)}
    return out


def _sample(frames: np.ndarray, counts: np.ndarray, budget: int, rng: np.random.Generator
            ) -> tuple[np.ndarray, dict[str, int] | None]:
    """`[F]` mask of whole frames among `frames` holding at most `budget` detections (at
    least one frame; all when they fit, then no note), and the note of what was kept."""
    index = np.flatnonzero(frames)
    if counts[index].sum() <= budget:
        return frames.copy(), None
    order = rng.permutation(index)
    n_keep = max(1, int(np.searchsorted(np.cumsum(counts[order]), budget, side="right")))
    keep = np.zeros_like(frames)
    keep[order[:n_keep]] = True
    return keep, {"frames": n_keep, "of_frames": len(index),
                  "detections": int(counts[keep].sum()), "of_detections": int(counts[index].sum())}


def _gather(chunks: list[Chunk], keep: np.ndarray, mapper: Mapper) -> Any:
    masks = [keep[c.dataset.parts[c.index].first:c.dataset.parts[c.index].stop] for c in chunks]
    todo = [(c, m) for c, m in zip(chunks, masks, strict=True) if m.any()]
    parts = mapper.map(frames_of, [c for c, _ in todo], [m for _, m in todo])
    return canonical_order(concat_frames([p for p in parts if p is not None]))  # as fit_profile
